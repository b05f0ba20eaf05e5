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

from backend.camera import StereoCamera
from backend.config import FilterConfig
from backend.conventions import ConventionDecision, decide_conventions
from backend.ekf import ImuNoise, StepStats, VisualInertialEKF
from backend.errors import InputError
from backend.imu import NoiseDecision, dead_reckoning, decide_imu_noise, step_velocities
from backend.sequence import Sequence
from backend.timing import repeated_steps


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
    landmarks_mapped: int = 0
    active_landmarks_mean: float = 0.0
    active_landmarks_max: int = 0
    mean_nis: float = float("nan")  # per used observation; expectation 4 (a little less after gating)
    wall_seconds: float = 0.0  # the filter loop
    setup_seconds: float = 0.0  # convention checks and noise estimation
    sequence_seconds: float = 0.0
    real_time_factor: float = 0.0  # sequence duration / (setup + loop)
    seconds_predict: float = 0.0
    seconds_update: float = 0.0
    health_messages: list = field(default_factory=list)

    @property
    def gated_share(self) -> float:
        total = self.observations_used + self.observations_gated
        return self.observations_gated / total if total else 0.0

    def as_dict(self) -> dict:
        out = dict(self.__dict__)
        out["gated_share"] = self.gated_share
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
    conventions: ConventionDecision
    imu_noise: NoiseDecision
    config: FilterConfig


def prepare(seq: Sequence, config: FilterConfig) -> tuple[ConventionDecision, NoiseDecision]:
    """Decide the extrinsic, the velocity timing and the IMU noise for this sequence."""
    conventions = decide_conventions(seq, config.imu_flip, config.velocity_index, config.convention_horizon)
    noise = decide_imu_noise(
        seq.linear_velocity,
        seq.angular_velocity,
        config.linear_velocity_sigma,
        config.angular_velocity_sigma,
        config.linear_velocity_sigma_floor,
        config.angular_velocity_sigma_floor,
        config.estimate_gyro_bias,
        seq.num_observations / max(seq.num_steps, 1),
        config.gyro_bias_min_observations,
    )
    return conventions, noise


def run_sequence(
    seq: Sequence,
    config: FilterConfig,
    progress: Optional[Callable[[int], None]] = None,
    decisions: tuple[ConventionDecision, NoiseDecision] | None = None,
    observer: Optional[Callable[[int, VisualInertialEKF, Optional[StepStats]], None]] = None,
) -> RunResult:
    """Run the filter over every step and every observation of ``seq``.

    ``progress(k)`` is called after each step; ``observer(k, ekf, step_stats)`` too, with the
    filter itself (step_stats is None where the step's observations were not used);
    ``decisions`` skips :func:`prepare`.
    """
    config.validate()
    if seq.num_steps < 2:
        raise InputError(f"{seq.source}: key 'time_stamps': need at least 2 steps, got {seq.num_steps}")
    with threadpool_limits(limits=config.blas_threads):
        t_setup = time.perf_counter()
        conventions, noise = decisions if decisions is not None else prepare(seq, config)
        setup_seconds = time.perf_counter() - t_setup

        ekf = VisualInertialEKF(
            StereoCamera(seq.K, seq.baseline),
            conventions.imu_T_cam,
            config if noise.gyro_bias == config.estimate_gyro_bias else dataclasses.replace(config, estimate_gyro_bias=noise.gyro_bias),
            ImuNoise(noise.linear_sigma, noise.angular_sigma),
            expected_landmarks=seq.num_features,
        )
        v_steps, w_steps = step_velocities(seq.linear_velocity, seq.angular_velocity, conventions.velocity_index)
        poses = np.empty((seq.num_steps, 4, 4))
        stats = RunStats(steps=seq.num_steps, observations=seq.num_observations,
                         observations_dropped_input=dict(seq.dropped))
        active_sum = 0
        nis_sum = 0.0
        t_predict = t_update = 0.0

        def absorb(step_stats) -> None:
            nonlocal active_sum, nis_sum
            stats.observations_used += step_stats.used
            stats.observations_gated += step_stats.gated
            stats.landmarks_initialized += step_stats.initialized
            stats.landmarks_dropped += step_stats.dropped
            stats.active_landmarks_max = max(stats.active_landmarks_max, step_stats.active)
            active_sum += step_stats.active
            nis_sum += step_stats.nis_sum

        repeated = repeated_steps(seq)
        stats.repeated_frames = int(repeated.sum())
        policy = config.repeated_frames
        dts = np.diff(seq.time_stamps)

        def step(k: int) -> None:
            """Use the observations of step k as the repeated-frame policy says (backend.timing)."""
            step_stats = None
            if not repeated[k] or policy == "use":
                step_stats = ekf.update(*seq.observations(k))
                absorb(step_stats)
            elif policy == "cut":
                ekf.finish()  # no track bridges a stalled camera
            if observer is not None:
                observer(k, ekf, step_stats)

        t_loop = time.perf_counter()
        step(0)
        poses[0] = ekf.world_T_imu
        if progress:
            progress(0)
        for k in range(seq.num_steps - 1):
            t0 = time.perf_counter()
            ekf.predict(dts[k], v_steps[k], w_steps[k])
            t1 = time.perf_counter()
            step(k + 1)
            t_update += time.perf_counter() - t1
            t_predict += t1 - t0
            poses[k + 1] = ekf.world_T_imu
            if progress:
                progress(k + 1)
        ekf.finish()
        stats.wall_seconds = time.perf_counter() - t_loop

    stats.setup_seconds = setup_seconds
    stats.seconds_predict = t_predict
    stats.seconds_update = t_update
    stats.sequence_seconds = float(seq.time_stamps[-1] - seq.time_stamps[0])
    stats.real_time_factor = stats.sequence_seconds / max(stats.wall_seconds + setup_seconds, 1e-9)
    stats.active_landmarks_mean = active_sum / seq.num_steps
    stats.mean_nis = nis_sum / stats.observations_used if stats.observations_used else float("nan")
    stats.health_messages = list(ekf.health.messages)
    map_ids, map_pos, map_cov = ekf.landmark_map()
    stats.landmarks_mapped = int(map_ids.size)
    dr = dead_reckoning(seq.time_stamps, seq.linear_velocity, seq.angular_velocity, conventions.velocity_index)
    return RunResult(
        time_stamps=seq.time_stamps.copy(),
        world_T_imu=poses,
        dead_reckoning=dr,
        map_ids=map_ids,
        map_positions=map_pos,
        map_covariances=map_cov,
        gyro_bias=ekf.gyro_bias.copy(),
        stats=stats,
        conventions=conventions,
        imu_noise=noise,
        config=config,
    )
