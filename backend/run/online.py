"""The filter over a stream of time stamps: the online API, with what a run decided applied.

:class:`OnlineRun` steps :class:`~vislam.backend.estimator.ekf.VisualInertialEKF` once per time
stamp with a run's :class:`~vislam.backend.run.decisions.Decisions` (extrinsic, velocity timing,
the IMU velocity correction, the stereo disparity offset, noise, track drift, repeated frames),
keeps dead reckoning alongside and collects the run's statistics and every step's pose
covariance; :meth:`OnlineRun.result` returns the :class:`RunResult`. The loop over a stream is
``backend.run.runner``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Optional

import numpy as np

from ..config import Config, Mode, RepeatedFrames
from ..errors import InputError
from ..estimator.ekf import ImuNoise, StepStats, VisualInertialEKF
from ..estimator.health import ScaleCheck, scale_check, vision_check
from ..estimator.lever_arm import LeverArmEstimate
from ..estimator.offset import OffsetEstimate
from ..estimator.propagation import VELOCITY_INDEX_OFFSET, compose_steps
from ..geometry import se3
from ..geometry.camera import StereoCamera
from .decisions import Decisions

if TYPE_CHECKING:
    from .inertial import InertialDecisions
from .timing import MotionPrior, repeats_previous


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
    tracks_rejected: int = 0  # rejected by the per-track test (R4, drift.track_test_probability)
    landmarks_reanchored: int = 0  # re-triangulated after reanchor_observations (tracker drift)
    frozen_steps: int = 0  # repeated frames carried through with their landmarks (repeated_frames = freeze)
    still_frames: int = 0  # a real IMU's frames at which the rig stood still: v = 0 measured (Z9)
    landmarks_mapped: int = 0
    active_landmarks_mean: float = 0.0
    active_landmarks_max: int = 0
    mean_nis: float = float("nan")  # per used observation; expectation nis_expected (a little less after gating)
    nis_expected: float = 4.0  # 4 per used observation; a window's feature seen n times has 4n - 3 dof (W5)
    filter_seconds: float = 0.0  # the filter loop (predict and update of every step)
    load_seconds: float = 0.0  # reading the input (`vislam run`)
    input_seconds: float = 0.0  # producing the steps while the run goes (an image stream: decoding and tracking)
    setup_seconds: float = 0.0  # convention checks and noise estimation
    kernel_seconds: float = 0.0  # compiling (first run after an install) or loading the compiled kernels; apart, as imports
    sequence_seconds: float = 0.0
    seconds_predict: float = 0.0
    seconds_update: float = 0.0  # the joint updates (gate, RANSAC, update), without bookkeeping
    seconds_bookkeeping: float = 0.0  # ended tracks marginalized to the map, new landmarks initialized
    step_ms_median: float = 0.0  # latency of one step (predict + update), what a live user waits
    step_ms_p99: float = 0.0
    step_ms_max: float = 0.0
    health_messages: list = field(default_factory=list)
    scale: Optional[ScaleCheck] = None  # H4: the filter's scale against the IMU's (SLAM runs with velocities)

    @property
    def gated_share(self) -> float:
        total = self.observations_used + self.observations_gated
        return self.observations_gated / total if total else 0.0

    @property
    def real_time_factor(self) -> float:
        """Sequence duration / (loading + setup + producing the steps (tracking) + loop)."""
        return self.sequence_seconds / max(self.total_seconds, 1e-9)

    @property
    def total_seconds(self) -> float:
        """Wall seconds of the whole run: loading, setup, producing the steps (tracking), the loop."""
        return self.filter_seconds + self.setup_seconds + self.load_seconds + self.input_seconds

    def as_dict(self) -> dict:
        out = dict(self.__dict__)
        out["scale"] = None if self.scale is None else self.scale.as_dict()
        out["gated_share"] = self.gated_share
        out["real_time_factor"] = self.real_time_factor
        return out


class RunBook:
    """The statistics of one run as its steps go (``RunStats``), shared by every kind of run: what each
    update used, the step times, and at the end the map, the health check (H3) and the timings."""

    def __init__(self, ekf: VisualInertialEKF) -> None:
        self.ekf = ekf
        self.stats = RunStats(kernel_seconds=ekf.kernel_seconds)
        self.times: list[float] = []
        self.step_seconds: list[float] = []
        self._active_sum = 0
        self._nis_sum = 0.0
        self._nis_dof = 0

    def add_update(self, step_stats: StepStats) -> None:
        """Count one update's observations and landmarks."""
        stats = self.stats
        stats.observations_used += step_stats.used
        stats.observations_gated += step_stats.gated
        stats.landmarks_initialized += step_stats.initialized
        stats.landmarks_dropped += step_stats.dropped
        stats.tracks_rejected += step_stats.rejected
        stats.landmarks_reanchored += step_stats.reanchored
        stats.still_frames += step_stats.still
        stats.active_landmarks_max = max(stats.active_landmarks_max, step_stats.active)
        self._active_sum += step_stats.active
        self._nis_sum += step_stats.nis_sum
        self._nis_dof += step_stats.nis_dof

    def add_step(self, t: float, predict_seconds: float, update_seconds: float) -> None:
        """One time stamp done, with the seconds of its prediction and its update."""
        self.times.append(float(t))
        self.stats.seconds_predict += predict_seconds
        self.stats.seconds_update += update_seconds
        self.step_seconds.append(predict_seconds + update_seconds)

    def close(self, mode: Mode, setup_seconds: float, load_seconds: float, input_seconds: float):
        """Marginalize the active landmarks into the map, check that vision did something (H3), fill
        the statistics; returns (map ids (K,), positions (K,3), covariances (K,3,3), step seconds (N,))."""
        if not self.times:
            raise InputError("no steps: nothing to estimate")
        t0 = time.perf_counter()
        self.ekf.finish()
        stats = self.stats
        stats.steps = len(self.times)
        stats.filter_seconds = sum(self.step_seconds) + time.perf_counter() - t0
        stats.setup_seconds = setup_seconds
        stats.load_seconds = load_seconds
        stats.input_seconds = input_seconds
        stats.sequence_seconds = self.times[-1] - self.times[0]
        stats.active_landmarks_mean = self._active_sum / stats.steps
        stats.mean_nis = self._nis_sum / stats.observations_used if stats.observations_used else float("nan")
        stats.nis_expected = self._nis_dof / stats.observations_used if stats.observations_used else 4.0
        if mode != Mode.DEAD_RECKONING:  # H3: a run meant to see that did not
            message = vision_check(stats.observations, stats.observations_used, stats.observations_gated,
                                   slam=mode == Mode.SLAM)
            if message is not None:
                self.ekf.health.report(message)
        stats.health_messages = list(self.ekf.health.messages)
        stats.seconds_bookkeeping = self.ekf.seconds_bookkeeping
        stats.seconds_update -= self.ekf.seconds_bookkeeping
        step_ms = 1e3 * np.array(self.step_seconds)
        stats.step_ms_median, stats.step_ms_p99 = (float(x) for x in np.percentile(step_ms, [50, 99]))
        stats.step_ms_max = float(step_ms.max())
        map_ids, map_pos, map_cov = self.ekf.landmark_map()
        stats.landmarks_mapped = int(map_ids.size)
        return map_ids, map_pos, map_cov, step_ms / 1e3


@dataclass
class RunResult:
    time_stamps: np.ndarray  # (N,)
    world_T_imu: np.ndarray  # (N,4,4) the estimate
    pose_covariance: np.ndarray  # (N,6,6) of the right perturbation world_T_imu = mu exp(xi^), xi = [rho; phi]
    dead_reckoning: np.ndarray  # (N,4,4) IMU only, same conventions
    map_ids: np.ndarray  # (K,)
    map_positions: np.ndarray  # (K,3) world frame
    map_covariances: np.ndarray  # (K,3,3)
    gyro_bias: np.ndarray  # (3,) final estimate
    stats: RunStats
    step_seconds: np.ndarray  # (N,) wall seconds of each step (predict + update)
    decisions: "Decisions | InertialDecisions"  # what the run decided from the data
    config: Config  # the configuration with the decided values (Decisions.config_for)
    velocity: np.ndarray | None = None  # (N,3) m/s in the world frame: an inertial run's (``backend.run.inertial``)
    gyro_biases: np.ndarray | None = None  # (N,3) rad/s at every step: an inertial run's
    accel_biases: np.ndarray | None = None  # (N,3) m/s^2 at every step: an inertial run's
    disparity_offset: OffsetEstimate | None = None  # the residual disparity offset in the filter at the end (O1)
    lever_arm: LeverArmEstimate | None = None  # the residual lever arm of the IMU's velocities at the end (V1)

    @property
    def inertial(self) -> bool:
        """A real IMU's run (velocity and biases per step), not a velocity run."""
        return self.velocity is not None

    @property
    def conventions(self):
        """The extrinsic and velocity timing decided (``decisions.conventions``)."""
        return self.decisions.conventions


class OnlineRun:
    """The filter over a stream, one call of :meth:`step` per time stamp (``backend.run.runner`` loops
    over it for files, image streams and the API alike).

    ``step(t, v, w, ids, pixels)`` takes the IMU sample stamped t and the stereo observations of
    the frame at t, and applies the ``decisions``: the IMU velocity correction (N3), the velocity
    timing (the sample stamped k ("this") or k+1 ("next") drives the step k -> k+1: both are known
    once step k+1 arrives), the stereo disparity offset (D1), the repeated-frame policy
    (``backend.run.timing``: with "freeze" a repeated frame's step is predicted by
    ``VisualInertialEKF.predict_frozen`` with the motion prior T2), and the decided noise and drift
    through the filter's configuration (:meth:`Decisions.config_for`). It records dead reckoning
    alongside and collects the run statistics; :meth:`result` marginalizes what is left and
    returns the :class:`RunResult`.
    """

    def __init__(
        self,
        camera: StereoCamera,
        decisions: Decisions,
        config: Config,
        expected_landmarks: int | None = None,
        observer: Optional[Callable[[int, VisualInertialEKF, Optional[StepStats]], None]] = None,
    ) -> None:
        config = decisions.config_for(config.validate())
        self.config = config
        self.decisions = decisions
        imu = decisions.imu
        self.ekf = VisualInertialEKF(camera, decisions.imu_T_cam, config, ImuNoise(imu.linear_sigma, imu.angular_sigma),
                                     expected_landmarks=expected_landmarks,
                                     lever_prior=decisions.lever_covariance_for(config))
        self.observer = observer
        self.book = RunBook(self.ekf)
        self.stats = self.book.stats
        self._next = VELOCITY_INDEX_OFFSET[decisions.conventions.velocity_index] == 1
        self._offset = decisions.stereo_offset
        self._velocity = decisions.velocity
        self._R_cam_imu = np.asarray(decisions.imu_T_cam, dtype=float)[:3, :3].T
        self._policy = config.conventions.repeated_frames
        self._motion = MotionPrior(np.concatenate([imu.linear_sigma, imu.angular_sigma]))
        self._t = self.book.times
        self._poses: list[np.ndarray] = []
        self._pose_covariances: list[np.ndarray] = []
        self._dr_twists: list[np.ndarray] = []  # dead reckoning, composed in result()
        self._prev_sample = None  # (t, v, w) of the previous step
        self._prev_frame = None  # (ids, pixels) of the last step that was not a repeat, as given

    @property
    def num_steps(self) -> int:
        return len(self._t)

    def step(self, t: float, linear_velocity, angular_velocity, ids, pixels) -> Optional[StepStats]:
        """Predict into t (from the second call on), then use the observations (ids (n,), pixels (n,4))."""
        t0 = time.perf_counter()
        w = np.asarray(angular_velocity, dtype=float)
        v = self._velocity.correct(np.asarray(linear_velocity, dtype=float), w)
        ids = np.asarray(ids, dtype=np.int64)
        pixels = np.asarray(pixels, dtype=float).reshape(-1, 4)
        k = len(self._t)
        repeated = self._prev_frame is not None and repeats_previous(ids, pixels, *self._prev_frame)
        if not repeated:
            self._prev_frame = (ids, pixels)
        if k:
            t_prev, v_prev, w_prev = self._prev_sample
            dt = float(t) - t_prev
            if not dt > 0:
                raise InputError(f"step {k}: time stamp {t!r} does not increase (previous {t_prev!r})")
            v_step, w_step = (v, w) if self._next else (v_prev, w_prev)
            if repeated and self._policy == RepeatedFrames.FREEZE and self.ekf.use_vision:
                prior = self._motion.predict(dt) if self.ekf.estimate_pose else None
                self.ekf.predict_frozen(dt, v_step, w_step, prior)
                self.stats.frozen_steps += 1
            else:
                self.ekf.predict(dt, v_step, w_step)
            self._dr_twists.append(dt * np.concatenate([v_step, w_step]))
            imu_velocity = np.concatenate([v_step, w_step - self.ekf.gyro_bias])
        t1 = time.perf_counter()
        self._prev_sample = (float(t), v, w)
        if self._offset.active:  # D1: the stereo pair's disparity offset at this step's rate
            pixels = self._offset.correct(pixels, float(self._R_cam_imu[1] @ w))
        step_stats = self._observe(ids, pixels, repeated)
        if self.observer is not None:
            self.observer(k, self.ekf, step_stats)
        if k:
            self._motion.add(self._poses[-1], self.ekf.world_T_imu, float(t) - self._t[-1], imu_velocity, repeated)
        self._poses.append(self.ekf.world_T_imu.copy())
        self._pose_covariances.append(self.ekf.pose_covariance)
        self.book.add_step(t, t1 - t0, time.perf_counter() - t1)
        return step_stats

    def _observe(self, ids: np.ndarray, pixels: np.ndarray, repeated: bool) -> Optional[StepStats]:
        """Use a frame's observations as the repeated-frame policy says (``backend.run.timing``)."""
        stats = self.stats
        stats.observations += ids.size
        if repeated:
            stats.repeated_frames += 1
            if self._policy != RepeatedFrames.USE:
                if self._policy == RepeatedFrames.CUT:
                    self.ekf.finish()  # no track bridges a stalled camera
                return None
        step_stats = self.ekf.update(ids, pixels)
        self.book.add_update(step_stats)
        return step_stats

    def _imu_steps(self) -> np.ndarray:
        """(N-1,4,4) what the IMU moved over each step, exp(tau [v; omega]^) (dead reckoning's steps)."""
        return se3.exp_se3_batch(np.array(self._dr_twists).reshape(-1, 6))

    def scale_check(self, imu_steps: np.ndarray | None = None) -> ScaleCheck:
        """H4 over the steps so far: the IMU's displacement per step against the filter's."""
        imu_steps = self._imu_steps() if imu_steps is None else imu_steps
        return scale_check(np.array(self._poses), imu_steps[:, :3, 3])

    def result(self, setup_seconds: float = 0.0, load_seconds: float = 0.0, input_seconds: float = 0.0) -> RunResult:
        """Marginalize the active landmarks into the map; the run's trajectory, map and statistics; a
        SLAM run's scale checked against the IMU's (H4)."""
        imu_steps = self._imu_steps()
        if self.config.estimator.mode == Mode.SLAM and self._poses:
            self.stats.scale = self.scale_check(imu_steps)
            if (message := self.stats.scale.message()) is not None:
                self.ekf.health.report(message)
        map_ids, map_pos, map_cov, step_seconds = self.book.close(self.config.estimator.mode, setup_seconds,
                                                                  load_seconds, input_seconds)
        return RunResult(
            time_stamps=np.array(self._t),
            world_T_imu=np.array(self._poses),
            pose_covariance=np.array(self._pose_covariances),
            dead_reckoning=compose_steps(imu_steps),
            map_ids=map_ids,
            map_positions=map_pos,
            map_covariances=map_cov,
            gyro_bias=self.ekf.gyro_bias.copy(),
            disparity_offset=self.ekf.disparity_offset,
            lever_arm=self.ekf.lever_arm,
            stats=self.stats,
            step_seconds=step_seconds,
            decisions=self.decisions,
            config=self.config,
        )
