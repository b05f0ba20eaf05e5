"""`run_sequence`: a whole sequence through the EKF, as a loop over the online API.

Decides the data conventions and the IMU noise first (both recorded), then steps
:class:`~backend.ekf.VisualInertialEKF` once per time stamp, timing prediction and update.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
from threadpoolctl import threadpool_limits

from backend import kernels, se3
from backend.camera import StereoCamera
from backend.config import FilterConfig
from backend.conventions import ConventionDecision, decide_conventions
from backend.ekf import ImuNoise, StepStats, VisualInertialEKF
from backend.errors import InputError
from backend.imu import VELOCITY_INDEX_OFFSET, NoiseDecision, compose_steps, decide_imu_noise
from backend.sequence import SYNTHETIC_TRACKER, VISLAM_TRACKER, Sequence
from backend.timing import repeats_previous


@dataclass
class RunStats:
    """Counts and timings of one run (all go to summary.json)."""

    steps: int = 0
    observations: int = 0  # valid observations in the input
    observations_used: int = 0  # in joint updates
    observations_gated: int = 0
    observations_dropped_input: dict = field(default_factory=dict)  # dropped by the loader, by reason
    repeated_frames: int = 0  # steps whose pixels repeat the previous step's exactly (vision skipped)
    landmarks_initialized: int = 0
    landmarks_dropped: int = 0  # removed after repeated gating
    landmarks_reanchored: int = 0  # re-triangulated after reanchor_observations (tracker drift)
    track_drift: str = ""  # the decision and why (decide_track_drift)
    landmarks_mapped: int = 0
    active_landmarks_mean: float = 0.0
    active_landmarks_max: int = 0
    mean_nis: float = float("nan")  # per used observation; expectation 4 (a little less after gating)
    wall_seconds: float = 0.0  # the filter loop
    setup_seconds: float = 0.0  # convention checks and noise estimation (and loading, from `vislam run`)
    kernel_seconds: float = 0.0  # compiling (first run after an install) or loading the compiled kernels; apart, as imports
    sequence_seconds: float = 0.0
    seconds_predict: float = 0.0
    seconds_update: float = 0.0  # the joint updates (gate, RANSAC, update), without bookkeeping
    seconds_bookkeeping: float = 0.0  # ended tracks marginalized to the map, new landmarks initialized
    step_ms_median: float = 0.0  # latency of one step (predict + update), what a live user waits
    step_ms_p99: float = 0.0
    step_ms_max: float = 0.0
    health_messages: list = field(default_factory=list)

    @property
    def gated_share(self) -> float:
        total = self.observations_used + self.observations_gated
        return self.observations_gated / total if total else 0.0

    @property
    def real_time_factor(self) -> float:
        """Sequence duration / (setup + loop)."""
        return self.sequence_seconds / max(self.wall_seconds + self.setup_seconds, 1e-9)

    def as_dict(self) -> dict:
        out = dict(self.__dict__)
        out["gated_share"] = self.gated_share
        out["real_time_factor"] = self.real_time_factor
        return out


@dataclass
class RunResult:
    time_stamps: np.ndarray  # (N,)
    world_T_imu: np.ndarray  # (N,4,4) the estimate
    dead_reckoning: np.ndarray  # (N,4,4) IMU only, same conventions
    map_ids: np.ndarray  # (K,)
    map_positions: np.ndarray  # (K,3) world frame
    map_covariances: np.ndarray  # (K,3,3)
    gyro_bias: np.ndarray  # (3,) final estimate
    stats: RunStats
    step_seconds: np.ndarray  # (N,) wall seconds of each step (predict + update)
    conventions: ConventionDecision
    imu_noise: NoiseDecision
    config: FilterConfig


def prepare(seq: Sequence, config: FilterConfig) -> tuple[ConventionDecision, NoiseDecision]:
    """Decide the extrinsic, the velocity timing and the IMU noise for this sequence."""
    conventions = decide_conventions(seq, config.imu_flip, config.velocity_index, config.convention_horizon)
    noise = imu_noise(config, seq.linear_velocity, seq.angular_velocity, seq.num_observations / max(seq.num_steps, 1))
    return conventions, noise


def imu_noise(config: FilterConfig, linear_velocity: np.ndarray, angular_velocity: np.ndarray,
              observations_per_step: float) -> NoiseDecision:
    """The IMU noise and gyro-bias decision of ``config`` for these velocities (backend.imu)."""
    return decide_imu_noise(
        linear_velocity,
        angular_velocity,
        config.linear_velocity_sigma,
        config.angular_velocity_sigma,
        config.linear_velocity_sigma_floor,
        config.angular_velocity_sigma_floor,
        config.estimate_gyro_bias,
        observations_per_step,
        config.gyro_bias_min_observations,
    )


def decide_track_drift(config: FilterConfig, tracker: str) -> tuple[FilterConfig, str]:
    """Resolve ``track_drift = "auto"`` for tracks made by ``tracker`` (``Sequence.tracker``).

    Tracks from another front end (the course files) drift with their age (BENCHMARKS.md,
    finding 9), so their landmarks random-walk (``landmark_random_walk``) and are re-anchored
    (backend.ekf); vislam's own tracker aligns every patch to its track's first patch and
    synthetic tracks are exact projections: there the drift model only discards information.
    Returns the config with ``track_drift`` "yes" or "no" and one line saying why.
    """
    if config.track_drift == "auto":
        exact = tracker in (VISLAM_TRACKER, SYNTHETIC_TRACKER)
        config = dataclasses.replace(config, track_drift="no" if exact else "yes")
        source = "auto: " + (f"tracks from the {tracker} tracker, which do not drift" if exact
                             else "tracks from another tracker, which drift with age")
    else:
        source = "configured"
    if config.track_drift == "no":
        return config, f"track drift: not modelled ({source})"
    walk = f"landmark random walk {config.landmark_random_walk:g} m/sqrt(s)"
    if config.full_state:
        return config, f"track drift: {walk}, no re-anchoring (--full-state keeps every landmark) ({source})"
    return config, (f"track drift: {walk}; re-anchoring after {config.reanchor_observations} observations "
                    f"({config.reanchor_far_observations} when anchored below {config.reanchor_far_disparity:g} px "
                    f"disparity; 0: never) ({source})")


class OnlineRun:
    """The filter over a stream, one call of :meth:`step` per time stamp; :func:`run_sequence` and the
    one-pass image path (tools/track.py) are loops over it.

    ``step(t, v, w, ids, pixels)`` takes the IMU sample stamped t and the stereo observations of
    the frame at t. It applies the velocity timing of ``conventions`` (the sample stamped k
    ("this") or k+1 ("next") drives the step k -> k+1: both are known once step k+1 arrives), the
    repeated-frame policy (backend.timing), records dead reckoning alongside, and collects the run
    statistics. :meth:`result` marginalizes what is left and returns the :class:`RunResult`.
    ``tracker`` names what made the tracks (``Sequence.tracker``; "" unknown) for
    ``track_drift = "auto"`` (:func:`decide_track_drift`).
    """

    def __init__(
        self,
        camera: StereoCamera,
        conventions: ConventionDecision,
        noise: NoiseDecision,
        config: FilterConfig,
        expected_landmarks: int | None = None,
        observer: Optional[Callable[[int, VisualInertialEKF, Optional[StepStats]], None]] = None,
        tracker: str = "",
    ) -> None:
        config.validate()
        if noise.gyro_bias != config.estimate_gyro_bias:
            config = dataclasses.replace(config, estimate_gyro_bias=noise.gyro_bias)
        config, track_drift = decide_track_drift(config, tracker)
        self.config = config
        self.conventions = conventions
        self.noise = noise
        self.ekf = VisualInertialEKF(camera, conventions.imu_T_cam, config,
                                     ImuNoise(noise.linear_sigma, noise.angular_sigma),
                                     expected_landmarks=expected_landmarks)
        self.observer = observer
        self.stats = RunStats(track_drift=track_drift, kernel_seconds=self.ekf.kernel_seconds)
        self._next = VELOCITY_INDEX_OFFSET[conventions.velocity_index] == 1
        self._t: list[float] = []
        self._poses: list[np.ndarray] = []
        self._dr_twists: list[np.ndarray] = []  # dead reckoning, composed in result()
        self._prev_sample = None  # (t, v, w) of the previous step
        self._prev_frame = None  # (ids, pixels) of the last step that was not a repeat
        self._active_sum = 0
        self._nis_sum = 0.0
        self._wall = 0.0
        self._step_seconds: list[float] = []

    @property
    def num_steps(self) -> int:
        return len(self._t)

    def step(self, t: float, linear_velocity, angular_velocity, ids, pixels) -> Optional[StepStats]:
        """Predict into t (from the second call on), then use the observations (ids (n,), pixels (n,4))."""
        t0 = time.perf_counter()
        v = np.asarray(linear_velocity, dtype=float)
        w = np.asarray(angular_velocity, dtype=float)
        k = len(self._t)
        if k:
            t_prev, v_prev, w_prev = self._prev_sample
            dt = float(t) - t_prev
            if not dt > 0:
                raise InputError(f"step {k}: time stamp {t!r} does not increase (previous {t_prev!r})")
            v_step, w_step = (v, w) if self._next else (v_prev, w_prev)
            self.ekf.predict(dt, v_step, w_step)
            self._dr_twists.append(dt * np.concatenate([v_step, w_step]))
        t1 = time.perf_counter()
        self._prev_sample = (float(t), v, w)
        step_stats = self._observe(np.asarray(ids, dtype=np.int64), np.asarray(pixels, dtype=float).reshape(-1, 4))
        if self.observer is not None:
            self.observer(k, self.ekf, step_stats)
        self._t.append(float(t))
        self._poses.append(self.ekf.world_T_imu.copy())
        t2 = time.perf_counter()
        self.stats.seconds_predict += t1 - t0
        self.stats.seconds_update += t2 - t1
        self._wall += t2 - t0
        self._step_seconds.append(t2 - t0)
        return step_stats

    def _observe(self, ids: np.ndarray, pixels: np.ndarray) -> Optional[StepStats]:
        """Use a frame's observations as the repeated-frame policy says (backend.timing)."""
        stats = self.stats
        stats.observations += ids.size
        repeated = self._prev_frame is not None and repeats_previous(ids, pixels, *self._prev_frame)
        if repeated:
            stats.repeated_frames += 1
        else:
            self._prev_frame = (ids, pixels)
        policy = self.config.repeated_frames
        if repeated and policy != "use":
            if policy == "cut":
                self.ekf.finish()  # no track bridges a stalled camera
            return None
        step_stats = self.ekf.update(ids, pixels)
        stats.observations_used += step_stats.used
        stats.observations_gated += step_stats.gated
        stats.landmarks_initialized += step_stats.initialized
        stats.landmarks_dropped += step_stats.dropped
        stats.landmarks_reanchored += step_stats.reanchored
        stats.active_landmarks_max = max(stats.active_landmarks_max, step_stats.active)
        self._active_sum += step_stats.active
        self._nis_sum += step_stats.nis_sum
        return step_stats

    def result(self, setup_seconds: float = 0.0) -> RunResult:
        """Marginalize the active landmarks into the map; the run's trajectory, map and statistics."""
        if not self._t:
            raise InputError("no steps: nothing to estimate")
        t0 = time.perf_counter()
        self.ekf.finish()
        stats = self.stats
        stats.steps = len(self._t)
        stats.wall_seconds = self._wall + time.perf_counter() - t0
        stats.setup_seconds = setup_seconds
        stats.sequence_seconds = self._t[-1] - self._t[0]
        stats.active_landmarks_mean = self._active_sum / stats.steps
        stats.mean_nis = self._nis_sum / stats.observations_used if stats.observations_used else float("nan")
        stats.health_messages = list(self.ekf.health.messages)
        stats.seconds_bookkeeping = self.ekf.seconds_bookkeeping
        stats.seconds_update -= self.ekf.seconds_bookkeeping
        step_ms = 1e3 * np.array(self._step_seconds)
        stats.step_ms_median, stats.step_ms_p99 = (float(x) for x in np.percentile(step_ms, [50, 99]))
        stats.step_ms_max = float(step_ms.max())
        map_ids, map_pos, map_cov = self.ekf.landmark_map()
        stats.landmarks_mapped = int(map_ids.size)
        return RunResult(
            time_stamps=np.array(self._t),
            world_T_imu=np.array(self._poses),
            dead_reckoning=compose_steps(se3.exp_se3_batch(np.array(self._dr_twists).reshape(-1, 6))),
            map_ids=map_ids,
            map_positions=map_pos,
            map_covariances=map_cov,
            gyro_bias=self.ekf.gyro_bias.copy(),
            stats=stats,
            step_seconds=step_ms / 1e3,
            conventions=self.conventions,
            imu_noise=self.noise,
            config=self.config,
        )


def run_sequence(
    seq: Sequence,
    config: FilterConfig,
    progress: Optional[Callable[[int], None]] = None,
    decisions: tuple[ConventionDecision, NoiseDecision] | None = None,
    observer: Optional[Callable[[int, VisualInertialEKF, Optional[StepStats]], None]] = None,
) -> RunResult:
    """Run the filter over every step and every observation of ``seq`` (a loop over :class:`OnlineRun`).

    ``progress(k)`` is called after each step; ``observer(k, ekf, step_stats)`` too, with the
    filter itself (step_stats is None where the step's observations were not used);
    ``decisions`` skips :func:`prepare`.
    """
    config.validate()
    if seq.num_steps < 2:
        raise InputError(f"{seq.source}: key 'time_stamps': need at least 2 steps, got {seq.num_steps}")
    with threadpool_limits(limits=config.blas_threads):
        kernels.warm_up()  # the convention test calls the triangulation kernel: load them apart from setup
        t_setup = time.perf_counter()
        conventions, noise = decisions if decisions is not None else prepare(seq, config)
        setup_seconds = time.perf_counter() - t_setup
        run = OnlineRun(StereoCamera(seq.K, seq.baseline), conventions, noise, config,
                        expected_landmarks=seq.num_features, observer=observer, tracker=seq.tracker)
        for k in range(seq.num_steps):
            run.step(seq.time_stamps[k], seq.linear_velocity[k], seq.angular_velocity[k], *seq.observations(k))
            if progress:
                progress(k)
        result = run.result(setup_seconds)
    result.stats.observations_dropped_input = dict(seq.dropped)
    return result
