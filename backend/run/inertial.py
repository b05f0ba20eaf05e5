"""A run with a real IMU: what is decided from the data, and the filter over an inertial sequence.

:func:`decide_inertial` makes one frozen :class:`InertialDecisions` from an inertial
:class:`~vislam.backend.data.sequence.Sequence` (``sequence.imu`` holds the samples):

- the start (``backend.run.initialization``): the IMU at rest over the first second after the
  first frame gives gravity, the gyro bias and the samples' noise with the rig's vibration (Z1-Z5);
  else, in motion, vision's poses of the first second against the IMU give the gyro bias, gravity
  and the velocity (M1-M4); a start neither can make is refused;
- the IMU's noise densities: for each sensor the larger of the file's (a Kalibr-style datasheet
  value) and the one measured (at rest; started in motion, the white noise of the whole record from
  second differences, N1 of ``backend.run.noise``: 3.1e-3 and 8.3e-2 on EuRoC V1_01), since a
  running rig's vibration is in the samples but not in a datasheet (EuRoC V1_01: datasheet 1.7e-4 rad/s/sqrt(Hz) and 2.0e-3 m/s^2/sqrt(Hz), at rest
  3.5e-3 and 4.6e-2; 1 s of propagation from the ground truth misses by 2.3 cm, NEES 298 with the
  datasheet's, 0.75 with the measured ones: ``benchmarks/inertial.py``); the random walks from the
  file, else the ADIS16448's, said so;
- the pixel noise: the configured value, else the RMS of two-view fit residuals of consecutive
  frame pairs (N2 of ``backend.run.noise``; the stereo rows where no pair has enough points).

:class:`InertialRun` steps :class:`~vislam.backend.estimator.ekf.VisualInertialEKF` with the
inertial state frame by frame (every IMU sample between two frames, then the frame's
observations), keeps the IMU-only propagation alongside as dead reckoning, and returns the same
:class:`~vislam.backend.run.online.RunResult` as a velocity run, with the velocity and the biases
of every frame (each as the filter had it at the frame). With a sliding window of clones, the
trajectory and its covariances are each frame's as the window settled it (W8 of
``backend.estimator.window``). :func:`run_inertial` is that over a whole sequence.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
from threadpoolctl import threadpool_limits

from ..compiled import warm_up
from ..config import Choice, Config
from ..data.inertial import ADIS16448, ImuNoiseDensities, ImuSamples
from ..data.sequence import Sequence
from ..errors import InputError
from ..estimator.ekf import StepStats, VisualInertialEKF
from ..estimator.inertial import STANDARD_GRAVITY, InertialStart, propagate
from ..estimator.window import settled_trajectory, window_in_use, window_text
from ..geometry.camera import StereoCamera
from .initialization import (Initialization, RestOptions, initialize_at_rest, initialize_in_motion, rest_test,
                             vision_motion)
from .decisions import NOISE_MIN_POINTS, PAIRS_GAP1
from .noise import estimate_white_noise, gap_statistics, pixel_noise
from .two_view import fit_pairs
from .online import RunBook, RunResult

__all__ = ["InertialDecisions", "decide_inertial", "InertialRun", "run_inertial"]


@dataclass(frozen=True)
class InertialDecisions:
    """What an inertial run decided from its data (module docstring), with the numbers behind it."""

    initialization: Initialization
    noise: ImuNoiseDensities  # used
    noise_reason: str
    pixel_sigma: float
    pixel_reason: str
    gravity: np.ndarray  # (3,) m/s^2 in the world frame
    imu_T_cam: np.ndarray  # (4,4) as given
    steps: int

    def config_for(self, config: Config) -> Config:
        """``config`` with the decided pixel noise (configured values win) and no track drift model
        unless configured (the drift test needs velocities: not run on inertial inputs)."""
        values = {"noise.pixel_sigma": self.pixel_sigma}
        if config.drift.track_drift == Choice.AUTO:
            values["drift.track_drift"] = Choice.NO
        return config.with_values(values)

    def describe(self, config: Config | None = None) -> str:
        n = self.noise
        return "\n".join([
            "IMU: a real IMU's samples (the inertial state: attitude, velocity, position, gyro and accelerometer "
            "biases)",
            self.initialization.describe(),
            f"IMU noise densities: gyroscope {n.gyroscope_noise_density:.3g} rad/s/sqrt(Hz), accelerometer "
            f"{n.accelerometer_noise_density:.3g} m/s^2/sqrt(Hz); random walks {n.gyroscope_random_walk:.3g} "
            f"rad/s^2/sqrt(Hz), {n.accelerometer_random_walk:.3g} m/s^3/sqrt(Hz) ({self.noise_reason})",
            f"pixel noise: {self.pixel_sigma:.3g} px ({self.pixel_reason})",
            "extrinsic: as given; stereo offset, velocity timing and drift tests: not run on inertial inputs",
        ])

    def as_dict(self) -> dict:
        return {"imu": "inertial", "initialization": self.initialization.as_dict(), "noise": self.noise.as_dict(),
                "noise_reason": self.noise_reason, "pixel_sigma": self.pixel_sigma, "pixel_reason": self.pixel_reason,
                "gravity": self.gravity.tolist(), "steps": self.steps}


def _noise(imu: ImuSamples, init: Initialization) -> tuple[ImuNoiseDensities, str]:
    """The densities used (module docstring) and where each came from."""
    file = imu.noise
    m = init.measured
    if init.at_rest:
        g_rest, a_rest, where = m["gyroscope_density_at_rest"], m["accelerometer_density_at_rest"], "measured at rest"
    else:  # (N1) the white noise of the whole record, from second differences
        root_dt = np.sqrt(float(np.median(np.diff(imu.time_stamps))))
        g_rest = float(np.sqrt(np.mean(estimate_white_noise(imu.angular_velocity) ** 2))) * root_dt
        a_rest = float(np.sqrt(np.mean(estimate_white_noise(imu.linear_acceleration) ** 2))) * root_dt
        where = "the samples' white noise (N1)"
    walks = file if file is not None else ADIS16448
    g_file = file.gyroscope_noise_density if file is not None else 0.0
    a_file = file.accelerometer_noise_density if file is not None else 0.0
    gyro, accel = max(g_file, g_rest), max(a_file, a_rest)
    said = []
    for name, used, given, rest in (("gyroscope", gyro, g_file, g_rest), ("accelerometer", accel, a_file, a_rest)):
        if file is None:
            said.append(f"{name} {where}")
        elif used == given:
            said.append(f"{name} from the file ({where} {rest:.3g})")
        else:
            said.append(f"{name} {where}, {rest / given:.1f}x the file's {given:.3g}")
    said.append("random walks from the file" if file is not None else f"random walks: {ADIS16448.source}, none given")
    return (ImuNoiseDensities(accel, walks.accelerometer_random_walk, gyro, walks.gyroscope_random_walk,
                              source="decided"), "; ".join(said))


def decide_inertial(seq: Sequence, config: Config) -> InertialDecisions:
    """(module docstring) from the inertial sequence ``seq``; InputError when it can start neither at rest nor in
    motion."""
    if seq.imu is None:
        raise ValueError("decide_inertial needs an inertial sequence (sequence.imu)")
    gravity = np.array([0.0, 0.0, -STANDARD_GRAVITY])
    rest = RestOptions()
    t0 = float(seq.time_stamps[0])
    still = rest_test(seq.imu, t0, rest.window)
    seen = vision_motion(seq, rest.window, still.get("gyro_mean", np.zeros(3)))
    init = initialize_at_rest(seq.imu, t0, gravity, seq.imu.noise, rest, seen)
    if not init.ok:
        rest = init.reason
        init = initialize_in_motion(seq, gravity, seq.imu.noise)
        if not init.ok:
            raise InputError(f"{seq.source}: key 'features': the inertial state cannot start: not at rest after the "
                             f"first frame ({rest}), and in motion {init.reason}")
    noise, reason = _noise(seq.imu, init)
    configured = config.noise.pixel_sigma is not None  # then the fits would feed nothing
    fits = {} if configured else {1: fit_pairs(seq, 1, PAIRS_GAP1, offset=True, min_points=NOISE_MIN_POINTS)}
    pixels = pixel_noise(seq, gap_statistics(fits), 1, config.noise.pixel_sigma)
    sigma, why = pixels.sigma, pixels.source
    if pixels.source == "two-view fits":
        why = (f"the RMS of two-view fit residuals of {len(fits[1])} consecutive frame pairs (N2); stereo rows "
               f"{pixels.rows_px:.3g} px")
    return InertialDecisions(init, noise, reason, sigma, why, gravity, np.array(seq.imu_T_cam, dtype=float),
                             seq.num_steps)


class InertialRun:
    """The filter over the frames of an inertial sequence, one :meth:`step` per frame (module docstring)."""

    def __init__(self, camera: StereoCamera, decisions: InertialDecisions, config: Config, imu: ImuSamples,
                 expected_landmarks: int | None = None,
                 observer: Optional[Callable[[int, VisualInertialEKF, Optional[StepStats]], None]] = None) -> None:
        config = decisions.config_for(config.validate())
        self.config, self.decisions, self.imu, self.observer = config, decisions, imu, observer
        init = decisions.initialization
        self.start = InertialStart(init.mean, init.covariance, decisions.noise, decisions.gravity)
        self.ekf = VisualInertialEKF(camera, decisions.imu_T_cam, config, None, expected_landmarks=expected_landmarks,
                                     inertial=self.start)
        self.book = RunBook(self.ekf)
        self.stats = self.book.stats
        self._dr = init.mean.copy()
        self._t = self.book.times
        self._rows: dict[str, list] = {k: [] for k in ("pose", "cov", "dr", "v", "bg", "ba")}

    def step(self, t: float, ids, pixels) -> Optional[StepStats]:
        """Propagate from the previous frame to t by every IMU sample between, then use the frame's
        observations (ids (n,), pixels (n,4))."""
        t0 = time.perf_counter()
        t = float(t)
        k = len(self._t)
        if k:
            t_prev = self._t[-1]
            if not t > t_prev:
                raise InputError(f"step {k}: time stamp {t!r} does not increase (previous {t_prev!r})")
            self.ekf.propagate(self.imu, t_prev, t)
            self._dr, _ = propagate(self._dr, self.imu, t_prev, t, None, self.decisions.gravity)  # the mean alone
        t1 = time.perf_counter()
        ids = np.asarray(ids, dtype=np.int64)
        pixels = np.asarray(pixels, dtype=float).reshape(-1, 4)
        self.stats.observations += ids.size
        step_stats = self.ekf.update(ids, pixels)
        self.book.add_update(step_stats)
        if self.observer is not None:
            self.observer(k, self.ekf, step_stats)
        ekf, rows = self.ekf, self._rows
        if ekf.window is None:  # a window's poses and covariances are the settled ones (W8), read at the end
            rows["pose"].append(ekf.world_T_imu.copy())
            rows["cov"].append(ekf.pose_covariance)
        rows["dr"].append(self._dr.world_T_imu.copy())
        rows["v"].append(ekf.velocity.copy())
        rows["bg"].append(ekf.gyro_bias.copy())
        rows["ba"].append(ekf.accel_bias.copy())
        self.book.add_step(t, t1 - t0, time.perf_counter() - t1)
        return step_stats

    def result(self, setup_seconds: float = 0.0, load_seconds: float = 0.0) -> RunResult:
        """Marginalize the active landmarks into the map; the run's trajectory, states, map and statistics."""
        map_ids, map_pos, map_cov, step_seconds = self.book.close(self.config.estimator.mode, setup_seconds,
                                                                  load_seconds, 0.0)
        rows = {k: np.array(v) for k, v in self._rows.items()}
        if self.ekf.window is not None:  # (W8) each frame's pose as the window settled it
            rows["pose"], rows["cov"] = settled_trajectory(self.ekf.window.settled, len(self._t))
        return RunResult(
            time_stamps=np.array(self._t), world_T_imu=rows["pose"], pose_covariance=rows["cov"],
            dead_reckoning=rows["dr"], map_ids=map_ids, map_positions=map_pos, map_covariances=map_cov,
            gyro_bias=self.ekf.gyro_bias.copy(), stats=self.stats, step_seconds=step_seconds, decisions=self.decisions,
            config=self.config, velocity=rows["v"], gyro_biases=rows["bg"], accel_biases=rows["ba"])


def run_inertial(seq: Sequence, config: Config | None = None, *, decisions: InertialDecisions | None = None,
                 load_seconds: float = 0.0, progress: Optional[Callable[[int], None]] = None,
                 observer: Optional[Callable[[int, VisualInertialEKF, Optional[StepStats]], None]] = None,
                 say: Callable[[str], None] = lambda _: None) -> RunResult:
    """The filter over every frame and observation of the inertial sequence ``seq``:
    :func:`decide_inertial` (unless ``decisions`` are given), then :class:`InertialRun` frame by frame."""
    config = (config if config is not None else Config()).validate()
    with threadpool_limits(limits=config.execution.blas_threads):
        warm_up(inertial=True, window=window_in_use(config, inertial=True))
        t0 = time.perf_counter()
        if decisions is None:
            decisions = decide_inertial(seq, config)
        setup = time.perf_counter() - t0
        say(decisions.describe())
        if text := window_text(config, inertial=True):
            say(text)
        run = InertialRun(StereoCamera(seq.K, seq.baseline), decisions, config, seq.imu,
                          expected_landmarks=seq.num_features, observer=observer)
        for k in range(seq.num_steps):
            run.step(seq.time_stamps[k], *seq.observations(k))
            if progress is not None:
                progress(k)
        result = run.result(setup, load_seconds)
    result.stats.observations_dropped_input = dict(seq.dropped)
    return result
