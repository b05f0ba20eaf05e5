"""Monte Carlo consistency of the filter on synthetic scenes: NEES and NIS against their chi-square bands.

A filter is consistent when its errors are as large as its covariance says (Bar-Shalom, Li and
Kirubarajan 2001, ch. 5.4). Over R independent runs on the same scene:

* pose NEES at step k: xi^T P^-1 xi with xi = log(mu^-1 T_true), the right perturbation of the
  filter (T = mu exp(xi^)), P = the 6x6 pose block of the covariance. For a consistent filter it
  is chi2(6), so the average over R runs times R is chi2(6R): the two-sided 95 % band of the
  average is [chi2.ppf(0.025, 6R) / R, chi2.ppf(0.975, 6R) / R]. About 95 % of the steps should
  lie in it (the first ``skip`` steps, where the pose is still at its near-zero prior, are left out).
  A run's error persists over many steps, so the share of steps in the band moves in large jumps:
  one run whose error stays large for a while lifts the average over every step of it. Each run's
  time average is one independent sample, so the Student-t interval of their mean
  (:func:`run_mean_interval`) says, without counting the steps as independent, whether 6 is what
  the runs give. (E1)
* landmark NEES: e^T C^-1 e (3 dof) for every mapped landmark of every run, with the band of the
  average of that many chi2(3) values. Landmarks of one run share the pose errors they were seen
  with, so they are not independent: the band is then too narrow and only a guide.            (E2)
* NIS: the EKF's r_i^T S_ii^-1 r_i per used stereo observation (4 dof) with the band of the
  average over all used observations. The observations that pass the chi-square gate (and the
  1-point RANSAC) are a truncated sample, so a consistent filter gives a little less than 4.    (E3)

One run against ground truth (:func:`trajectory_nees`; real data has one run, so each step's NEES is
one sample): estimate and truth are matched by nearest stamp (``metrics.associate_indices``, evo)
and expressed relative to their first matched pose (estimate ``mu_0^-1 mu_k``, truth ``T_0^-1 T_k``:
the filter's world is its first pose, the truth's world any frame). Per step, with P the 6x6
covariance of the right perturbation ``xi = [rho; phi]``:

* position NEES (3 dof): e^T P_rho^-1 e with e = R_mu^T (p_true - p_mu) (= rho to first order) and
  P_rho the top-left 3x3 block (:func:`position_nees`);
* pose NEES (6 dof): xi^T P^-1 xi with xi = log(mu^-1 T_true) (:func:`pose_nees`).

Each is chi2(dof) for a consistent filter: mean dof, 95 % of the steps inside the 95 % ellipsoid
NEES <= chi2.ppf(0.95, dof) (7.815 for 3 dof, 12.59 for 6). The leading steps whose covariance is
numerically zero (every variance <= :data:`ZERO_POSE_VARIANCE`: the first pose is the world frame)
are skipped and counted apart, and so is always the first matched step, whose relative error is
zero by construction; a later singular covariance gives NEES inf, counted.                      (E4)

The scenes come from a *scene factory*: ``factory(noise_seed, gyro_bias=None)`` returns a scene
with ``sequence``, ``world_T_imu_true`` (N,4,4) and ``landmark_positions`` (K,3) by track id, whose
geometry is the factory's and whose noise (pixels, track cuts, outliers, IMU) is that of the
noise seed (``synth.scene.SceneFactory`` is one). Run i uses the noise seed ``seed0 + i``; its
gyro bias is drawn from the filter's own prior (:func:`run_one`), since a constant bias shared by
every run is not a sample of the assumed error.

The runner takes any ``concurrent.futures.Executor``-like object (``submit`` returning futures
with ``result()``); by default a process pool over every core. :func:`run_one` is a top-level
function, so any process-based executor can run it with a picklable factory.
"""

from __future__ import annotations

import concurrent.futures
import os
import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable, Optional, Protocol

import numpy as np
from threadpoolctl import threadpool_limits

from .. import chi2
from ..config import Config, Mode
from ..data.sequence import Sequence
from ..errors import ConfigError, HealthWarning, VislamError
from ..geometry import se3
from ..run.runner import run_sequence
from .metrics import associate_indices


class Scene(Protocol):
    """What a Monte Carlo run needs of a scene."""

    sequence: Sequence
    world_T_imu_true: np.ndarray  # (N,4,4)
    landmark_positions: np.ndarray  # (K,3), row = track id


#: ``factory(noise_seed, gyro_bias (3,) or None) -> Scene`` (module docstring)
SceneFactory = Callable[[int, Optional[np.ndarray]], Scene]

#: Steps left out of the band statistics (the pose starts at its near-zero prior covariance).
SKIP_STEPS = 10
BAND_PROBABILITY = 0.95
#: Random stream (of the noise seed) of the per-run gyro bias, apart from synth's streams.
GYRO_BIAS_STREAM = 9001
#: A pose covariance whose every variance (m^2, rad^2) is at most this is numerically zero (the first
#: pose, the world frame: noise.initial_pose_sigma = 1e-6 gives 1e-12; one step of prediction > 1e-6).
ZERO_POSE_VARIANCE = 1e-10
#: The probability of the chi-square ellipsoid a step's NEES is counted inside of (E4)
INSIDE_PROBABILITY = 0.95


# ---------------------------------------------------------------------------------------- NEES


def pose_nees(mu: np.ndarray, P_pose: np.ndarray, T_true: np.ndarray) -> float:
    """xi^T P^-1 xi with xi = log(mu^-1 T_true) (6 dof; right perturbation T = mu exp(xi^)).

    inf when ``P_pose`` is singular.
    """
    xi = se3.log_se3(se3.inverse(mu) @ T_true)
    try:
        L = np.linalg.cholesky(np.asarray(P_pose, dtype=float))
    except np.linalg.LinAlgError:
        return float("inf")
    w = np.linalg.solve(L, xi)
    return float(w @ w)


def position_nees(mu: np.ndarray, P_pose: np.ndarray, T_true: np.ndarray) -> float:
    """e^T P_rho^-1 e with e = R_mu^T (p_true - p_mu) (3 dof; ``rho`` of T = mu exp(xi^) to first order).

    Parameters
    ----------
    mu, T_true : (4, 4) arrays, the estimate and the true pose
    P_pose : (6, 6) array, covariance of xi = [rho; phi]; its top-left 3x3 block is used

    Returns
    -------
    float, inf when that block is singular
    """
    mu = np.asarray(mu, dtype=float)
    e = mu[:3, :3].T @ (np.asarray(T_true, dtype=float)[:3, 3] - mu[:3, 3])
    try:
        L = np.linalg.cholesky(np.asarray(P_pose, dtype=float)[:3, :3])
    except np.linalg.LinAlgError:
        return float("inf")
    w = np.linalg.solve(L, e)
    return float(w @ w)


def landmark_nees(positions: np.ndarray, covariances: np.ndarray, true_positions: np.ndarray) -> np.ndarray:
    """e_j^T C_j^-1 e_j (3 dof) for estimates (K,3) with covariances (K,3,3) against the truth (K,3)."""
    e = np.asarray(positions, dtype=float) - np.asarray(true_positions, dtype=float)
    C = np.asarray(covariances, dtype=float)
    if e.shape[0] == 0:
        return np.zeros(0)
    try:
        return np.einsum("ki,ki->k", e, np.linalg.solve(C, e[:, :, None])[:, :, 0])
    except np.linalg.LinAlgError:  # some covariance singular: those get inf
        out = np.full(e.shape[0], np.inf)
        for i in range(e.shape[0]):
            try:
                out[i] = e[i] @ np.linalg.solve(C[i], e[i])
            except np.linalg.LinAlgError:
                pass
        return out


def average_band(dof: int, count: int, probability: float = BAND_PROBABILITY) -> tuple[float, float]:
    """Two-sided band of the average of ``count`` independent chi2(``dof``) values."""
    if count <= 0:
        return (float("nan"), float("nan"))
    tail = 0.5 * (1.0 - probability)
    return (chi2.quantile(dof * count, tail) / count, chi2.quantile(dof * count, 1.0 - tail) / count)


def chi2_quantile(dof: int, probability: float = INSIDE_PROBABILITY) -> float:
    """chi2.ppf(probability, dof): 7.815 for 3 dof and 12.59 for 6 at 0.95 (``backend.chi2``)."""
    return chi2.quantile(dof, probability)


# ---------------------------------------------------------------------------------------- one trajectory, NEES


@dataclass
class NeesSummary:
    """NEES of the counted steps of one run against chi2(``dof``) (module docstring, E4)."""

    dof: int
    mean: float  # over the counted steps (inf when one is inf; expectation dof); nan without steps
    median: float
    share_inside_95: float  # share of the counted steps with NEES <= quantile_95 (expectation 0.95)
    quantile_95: float  # chi2.ppf(0.95, dof)
    steps: int  # counted
    skipped: int  # leading steps not counted (numerically zero covariance, the first matched step)
    infinite: int  # counted steps whose covariance is singular (NEES inf)

    @property
    def expected(self) -> float:
        return float(self.dof)

    def as_dict(self) -> dict[str, Any]:
        return {"dof": self.dof, "expected": self.expected, "mean": self.mean, "median": self.median,
                "share_inside_95": self.share_inside_95, "quantile_95": self.quantile_95, "steps": self.steps,
                "skipped_steps": self.skipped, "infinite_steps": self.infinite}


def summarize_nees(values: np.ndarray, dof: int, skipped: int = 0) -> NeesSummary:
    """Mean, median and share inside the 95 % ellipsoid of the counted steps' NEES ``values`` (M,)."""
    v = np.asarray(values, dtype=float).reshape(-1)
    quantile = chi2_quantile(dof)
    if v.size == 0:
        return NeesSummary(dof, float("nan"), float("nan"), float("nan"), quantile, 0, int(skipped), 0)
    return NeesSummary(dof=dof, mean=float(np.mean(v)), median=float(np.median(v)),
                       share_inside_95=float(np.mean(v <= quantile)), quantile_95=quantile, steps=int(v.size),
                       skipped=int(skipped), infinite=int(np.sum(np.isinf(v))))


@dataclass
class TrajectoryNees:
    """Per-step NEES of a run's pose covariance against ground truth (module docstring, E4)."""

    time_stamps: np.ndarray  # (M,) s, the estimate's stamps of the steps matched to the ground truth
    estimate_index: np.ndarray  # (M,) int, those steps' indices into the estimate
    position_nees: np.ndarray  # (M,) 3 dof; nan at the skipped steps
    pose_nees: np.ndarray  # (M,) 6 dof; nan at the skipped steps
    position: NeesSummary
    pose: NeesSummary

    @property
    def skipped(self) -> int:
        return self.position.skipped

    def as_dict(self) -> dict[str, Any]:
        """The summaries (not the per-step values)."""
        return {"matched_steps": int(self.time_stamps.shape[0]), "skipped_steps": self.skipped,
                "position": self.position.as_dict(), "pose": self.pose.as_dict()}


def yaw_alignment(world_T_imu: np.ndarray, true_world_T_imu: np.ndarray) -> np.ndarray:
    """The rotation about z and translation A (4,4) that move the pose ``world_T_imu`` onto
    ``true_world_T_imu`` except for roll and pitch: the rotation error of A world_T_imu against the
    truth, R_true (A R)^T = exp(phi^), has phi_z = 0 (a world-frame error, as the filters' invariant
    errors; the yaw of a tilted body axis would leave phi_z of order tilt x tan(pitch)) and the
    positions agree."""
    R, R_true = world_T_imu[:3, :3], true_world_T_imu[:3, :3]
    yaw = 0.0
    for _ in range(20):
        c, s = np.cos(yaw), np.sin(yaw)
        Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        step = se3.log_so3(R_true @ (Rz @ R).T)[2]
        yaw += step
        if abs(step) < 1e-15:
            break
    A = np.eye(4)
    A[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    A[:3, 3] = true_world_T_imu[:3, 3] - A[:3, :3] @ world_T_imu[:3, 3]
    return A


def trajectory_nees(est_t: Any, world_T_imu: Any, pose_covariance: Any, gt_t: Any, gt_world_T_imu: Any, *,
                    max_diff: float = 0.01, gravity_aligned: bool = False) -> TrajectoryNees:
    """Position and pose NEES of each step of one run against ground truth (module docstring, E4).

    Parameters
    ----------
    est_t : (N,) array, seconds, strictly increasing
    world_T_imu : (N, 4, 4) array, the estimate
    pose_covariance : (N, 6, 6) array, covariance of the right perturbation xi = [rho; phi] of each pose
    gt_t : (G,) array, seconds, strictly increasing
    gt_world_T_imu : (G, 4, 4) array, the ground truth (any world frame)
    max_diff : float
        Largest stamp difference (s) of a matched pair (nearest stamp, ``metrics.associate_indices``).
    gravity_aligned : bool
        Both world frames have z up (an inertial filter's, a gravity-aligned ground truth's): then
        roll and pitch are absolute and only the unobservable yaw and position of the first matched
        pose are removed (the estimate moved by a rotation about z and a translation onto the truth's
        first pose); else both trajectories are taken relative to their first pose.

    Returns
    -------
    TrajectoryNees
        Raises ``InputError`` when fewer than 3 steps match.
    """
    t = np.asarray(est_t, dtype=float)
    mu = np.asarray(world_T_imu, dtype=float)
    P = np.asarray(pose_covariance, dtype=float)
    truth = np.asarray(gt_world_T_imu, dtype=float)
    if mu.ndim != 3 or mu.shape[1:] != (4, 4) or t.shape != (mu.shape[0],):
        raise ValueError(f"estimate: stamps (N,) and poses (N, 4, 4) expected, got {t.shape} and {mu.shape}")
    if P.shape != (mu.shape[0], 6, 6):
        raise ValueError(f"pose_covariance must have shape ({mu.shape[0]}, 6, 6), got {P.shape}")
    if truth.ndim != 3 or truth.shape[1:] != (4, 4) or np.shape(gt_t) != (truth.shape[0],):
        raise ValueError(f"ground truth: stamps (G,) and poses (G, 4, 4) expected, got {np.shape(gt_t)} and "
                         f"{truth.shape}")
    for what, a in (("estimate", mu), ("pose_covariance", P), ("ground truth", truth)):
        if not np.isfinite(a).all():
            index = int(np.flatnonzero(~np.isfinite(a).all(axis=(1, 2)))[0])
            raise ValueError(f"{what}: non-finite value at index {index}")
    i, j = associate_indices(t, gt_t, max_diff)
    if gravity_aligned:
        A = yaw_alignment(mu[i[0]], truth[j[0]])
        mu_rel, true_rel = A @ mu[i], truth[j]
    else:
        mu_rel = se3.inverse(mu[i[0]]) @ mu[i]
        true_rel = se3.inverse(truth[j[0]]) @ truth[j]
    P = P[i]
    zero = np.all(np.diagonal(P, axis1=1, axis2=2) <= ZERO_POSE_VARIANCE, axis=1)
    skipped = max(1, int(np.argmin(zero)) if not zero.all() else zero.size)
    position = np.full(i.size, np.nan)
    pose = np.full(i.size, np.nan)
    for k in range(skipped, i.size):
        position[k] = position_nees(mu_rel[k], P[k], true_rel[k])
        pose[k] = pose_nees(mu_rel[k], P[k], true_rel[k])
    return TrajectoryNees(time_stamps=t[i], estimate_index=i, position_nees=position, pose_nees=pose,
                          position=summarize_nees(position[skipped:], 3, skipped),
                          pose=summarize_nees(pose[skipped:], 6, skipped))


# ---------------------------------------------------------------------------------------- one run


@dataclass
class RunTrace:
    """What one Monte Carlo run measured (small: travels back from a worker process)."""

    noise_seed: int
    pose_nees: np.ndarray  # (N,) per step, 6 dof
    nis_sum: np.ndarray  # (N,) per step, sum over the used observations (4 dof each; a window's feature 4n - 3)
    nis_count: np.ndarray  # (N,) int, used observations per step
    landmark_nees: np.ndarray  # (K,) mapped landmarks (3 dof each), in id order
    # Final-trajectory position RMSE against the truth WITHOUT alignment (m): the truth and both
    # estimates start at the identity, so the raw error is the drift the filter reports against.
    ate_estimate: float
    ate_dead_reckoning: float
    observations_gated: int = 0
    conventions: str = ""  # decided by backend.run.decisions.decide, e.g. "flip=no,velocity=this"
    health_messages: list = field(default_factory=list)
    wall_seconds: float = 0.0
    nis_dof: np.ndarray | None = None  # (N,) int, the degrees of freedom of nis_sum (None: 4 an observation)

    @property
    def steps(self) -> int:
        return int(self.pose_nees.shape[0])

    @property
    def mean_nis(self) -> float:
        used = int(self.nis_count.sum())
        return float(self.nis_sum.sum() / used) if used else float("nan")

    @property
    def dof(self) -> int:
        """The degrees of freedom of every NIS summed: the expectation of ``nis_sum.sum()``."""
        return int(self.nis_dof.sum()) if self.nis_dof is not None else 4 * int(self.nis_count.sum())


def _position_rmse(estimate: np.ndarray, truth: np.ndarray) -> float:
    d = estimate[:, :3, 3] - truth[:, :3, 3]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def run_one(scene_factory: SceneFactory, filter_config: Config, noise_seed: int,
            sample_gyro_bias: bool = True) -> RunTrace:
    """One run: build the scene of ``noise_seed``, run the filter over it
    (``backend.run.runner.run_sequence``) and record the NEES and NIS through its observer hook.

    ``sample_gyro_bias``: the scene's constant gyro bias is replaced by a draw from the filter's
    prior N(0, gyro_bias_sigma0^2 I) (stream ``GYRO_BIAS_STREAM`` of the noise seed), so that the
    bias error is a sample of what the filter assumes.

    BLAS threads follow ``execution.blas_threads`` (1) and the filter's health warnings are kept in
    the trace instead of being printed (safe under a thread pool too: see :func:`monte_carlo`).
    """
    t0 = time.perf_counter()
    seed = int(noise_seed)
    config = filter_config.validate()
    bias = None
    inertial = getattr(scene_factory, "sampled_bias", "gyroscope") == "accelerometer"
    if sample_gyro_bias and inertial:  # the accelerometer bias from the initialization's prior (Z4, M4)
        from ..run.initialization import RestOptions

        bias = np.random.default_rng([seed, GYRO_BIAS_STREAM]).normal(0.0, RestOptions().accel_bias_sigma0, 3)
    elif sample_gyro_bias and config.estimator.estimate_gyro_bias:
        # the initial error is drawn from the filter's prior, as a consistency test requires
        bias = np.random.default_rng([seed, GYRO_BIAS_STREAM]).normal(0.0, config.noise.gyro_bias_sigma0, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", HealthWarning)  # kept in the trace (health_messages)
        scene = scene_factory(seed, bias)
        truth = scene.world_T_imu_true
        n = scene.sequence.num_steps
        nees = np.empty(n)
        nis_sum = np.zeros(n)
        nis_count = np.zeros(n, dtype=np.int64)
        nis_dof = np.zeros(n, dtype=np.int64)

        align = [np.eye(4)]  # an inertial run's world is the truth's up to yaw and position (E5)

        aligned = scene.sequence.inertial  # a real IMU: a gravity-aligned world of its own

        def record(k, ekf, step_stats) -> None:
            if k == 0 and aligned:
                align[0] = yaw_alignment(ekf.world_T_imu, truth[0])
            nees[k] = pose_nees(align[0] @ ekf.world_T_imu, ekf.pose_covariance, truth[k])
            if step_stats is not None:
                nis_sum[k] = step_stats.nis_sum
                nis_count[k] = step_stats.used
                nis_dof[k] = step_stats.nis_dof

        result = run_sequence(scene.sequence, config, observer=record)  # one BLAS thread by config
        A = align[0]
        positions = result.map_positions @ A[:3, :3].T + A[:3, 3]
        covariances = A[:3, :3] @ result.map_covariances @ A[:3, :3].T
        # scene.landmark_ids is arange(K): an id is its row of landmark_positions
        lm_nees = landmark_nees(positions, covariances, scene.landmark_positions[result.map_ids])
        estimate = A @ result.world_T_imu
        dead_reckoning = A @ result.dead_reckoning
    if result.inertial:
        decided = f"start={result.decisions.initialization.how}"
    else:
        conventions = result.decisions.conventions
        decided = f"flip={'yes' if conventions.imu_flip else 'no'},velocity={conventions.velocity_index}"
    return RunTrace(
        noise_seed=seed,
        pose_nees=nees,
        nis_sum=nis_sum,
        nis_count=nis_count,
        nis_dof=nis_dof,
        landmark_nees=lm_nees,
        ate_estimate=_position_rmse(estimate, truth),
        ate_dead_reckoning=_position_rmse(dead_reckoning, truth),
        observations_gated=result.stats.observations_gated,
        conventions=decided,
        health_messages=list(result.stats.health_messages),
        wall_seconds=time.perf_counter() - t0,
    )


# ---------------------------------------------------------------------------------------- many runs


@dataclass
class ConsistencyResult:
    """NEES and NIS over R runs against their 95 % chi-square bands (module docstring)."""

    runs: int
    steps: int
    skip: int  # first steps left out of the band share and the time averages
    pose_nees_mean: np.ndarray  # (N,) average over the runs at each step
    pose_nees_band: tuple  # band of the average of R chi2(6)
    pose_nees_in_band: float  # share of steps >= skip whose average lies in the band
    pose_nees_time_average: float  # mean over steps >= skip of pose_nees_mean (expectation 6)
    landmark_nees_mean: float  # over every mapped landmark of every run (expectation 3)
    landmark_count: int
    landmark_nees_band: tuple  # of the mean of every landmark's NEES as if independent (they are not: a run's share errors)
    nis_mean: float  # per used observation over every run (expectation nis_expected, a little less after gating)
    nis_count: int
    nis_band: tuple
    nis_per_step: np.ndarray  # (N,) NIS per used observation at each step over the runs (nan: none used)
    ate_estimate: np.ndarray  # (R,) m, unaligned position RMSE (RunTrace)
    ate_dead_reckoning: np.ndarray  # (R,)
    noise_seeds: list
    per_run_pose_nees: np.ndarray  # (R,) time average of each run's pose NEES (steps >= skip)
    per_run_nis: np.ndarray  # (R,) each run's NIS per observation
    per_run_landmark_nees: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (R,) nan: no landmark
    observations_gated: int = 0
    conventions: dict = field(default_factory=dict)  # decision -> number of runs
    health_messages: dict = field(default_factory=dict)  # noise seed -> messages (runs with any)
    wall_seconds: float = 0.0
    scene: dict = field(default_factory=dict)
    filter: dict = field(default_factory=dict)
    nis_expected: float = 4.0  # NIS per observation expected: 4; a window's features 4 - 3 / n each (W5)

    def as_dict(self) -> dict[str, Any]:
        return {
            "runs": self.runs,
            "steps": self.steps,
            "skip_steps": self.skip,
            "band_probability": BAND_PROBABILITY,
            "pose_nees": {
                "dof": 6,
                "time_average": self.pose_nees_time_average,
                "band_of_run_average": list(self.pose_nees_band),
                "share_of_steps_in_band": self.pose_nees_in_band,
                "mean_per_step": self.pose_nees_mean,
                "per_run_time_average": self.per_run_pose_nees,
                "interval_of_run_mean": list(run_mean_interval(self.per_run_pose_nees)),
            },
            "landmark_nees": {
                "dof": 3,
                "mean": self.landmark_nees_mean,
                "count": self.landmark_count,
                "band": list(self.landmark_nees_band),
                "per_run": self.per_run_landmark_nees,
                "interval_of_run_mean": list(run_mean_interval(self.per_run_landmark_nees)),
            },
            "nis": {
                "dof": 4,
                "expected_per_observation": self.nis_expected,
                "mean_per_observation": self.nis_mean,
                "count": self.nis_count,
                "band": list(self.nis_band),
                "observations_gated": self.observations_gated,
                "mean_per_step": self.nis_per_step,
                "per_run": self.per_run_nis,
                "interval_of_run_mean": list(run_mean_interval(self.per_run_nis)),
            },
            "ate_unaligned_m": {
                "estimate_mean": float(np.mean(self.ate_estimate)) if self.runs else None,
                "dead_reckoning_mean": float(np.mean(self.ate_dead_reckoning)) if self.runs else None,
                "estimate": self.ate_estimate,
                "dead_reckoning": self.ate_dead_reckoning,
            },
            "noise_seeds": self.noise_seeds,
            "conventions": self.conventions,
            "health_messages": self.health_messages,
            "wall_seconds": self.wall_seconds,
            "scene": self.scene,
            "filter": self.filter,
        }

    def summary_lines(self) -> list[str]:
        """Pose NEES against its 95 % band and, as landmark NEES and NIS, against the interval of
        the runs' mean (:func:`consistency_verdict`); then a warning line for each distinct health
        message of the runs (how many runs had it)."""
        lo, hi = self.pose_nees_band
        return self._metric_lines(lo, hi) + self._health_lines()

    def pose_nees_verdict(self) -> str:
        """The runs' time averages of the pose NEES against 6 (E1): :func:`consistency_verdict`."""
        return consistency_verdict(6.0, self.per_run_pose_nees, "the pose covariances")

    def _health_lines(self) -> list[str]:
        counts: dict[str, int] = {}
        for messages in self.health_messages.values():
            for message in dict.fromkeys(m.split(": ", 1)[1] if m.startswith("step ") else m for m in messages):
                counts[message] = counts.get(message, 0) + 1
        return [f"warning ({n} of {self.runs} runs): {message}" for message, n in counts.items()]

    def _metric_lines(self, lo, hi) -> list[str]:
        return [
            f"pose NEES (6 dof): {100 * self.pose_nees_in_band:.0f} % of steps {self.skip}..{self.steps - 1} in the "
            f"95 % band [{lo:.2f}, {hi:.2f}] of the {self.runs}-run average; time average {self.pose_nees_time_average:.2f}; "
            + self.pose_nees_verdict(),
            f"landmark NEES (3 dof): mean {self.landmark_nees_mean:.2f} over {self.landmark_count} landmarks; "
            + consistency_verdict(3.0, self.per_run_landmark_nees, "the map's covariances"),
            f"NIS (4 dof): mean {self.nis_mean:.3f} per observation over {self.nis_count}"
            + ("; " if self.nis_expected == 4.0 else f" (expected {self.nis_expected:.3f}: a window's feature seen n "
                                                     "times has 4n - 3 dof); ")
            + consistency_verdict(round(self.nis_expected, 3), self.per_run_nis, "the innovations' covariances"),
        ]


def run_mean_interval(values: Any, probability: float = BAND_PROBABILITY) -> tuple[float, float]:
    """The ``probability`` interval (Student t) of the mean of per-run values (R,), nan ignored.

    Runs are independent; the landmarks or observations of one run are not (they share its pose
    errors), so a band built as if every landmark were an independent chi-square sample is far too
    narrow: the spread of the runs' own means says how well the mean is known. (nan, nan) with
    fewer than two runs."""
    from scipy.stats import t as student

    x = np.asarray(values, dtype=float)
    x = x[np.isfinite(x)]
    if x.size < 2:
        return float("nan"), float("nan")
    half = float(student.ppf(0.5 + probability / 2, x.size - 1) * x.std(ddof=1) / np.sqrt(x.size))
    return float(x.mean() - half), float(x.mean() + half)


def consistency_verdict(expected: float, per_run: Any, what: str) -> str:
    """The runs' mean of a NEES or NIS against its ``expected`` value, in words: the interval of
    :func:`run_mean_interval` and whether it holds ``expected``, else by how much and which way."""
    lo, hi = run_mean_interval(per_run)
    if not np.isfinite(lo):
        return "one run: no interval of the mean"
    mean = 0.5 * (lo + hi)
    runs = int(np.isfinite(np.asarray(per_run, dtype=float)).sum())
    where = f"95 % interval of the {runs} runs' mean [{lo:.3f}, {hi:.3f}]"
    if lo <= expected <= hi:
        return f"{where}: consistent with {expected:g}"
    off = 100.0 * abs(mean / expected - 1.0)
    if hi < expected:
        return f"{where}: {off:.0f} % below {expected:g}, {what} are larger than the errors (pessimistic)"
    return f"{where}: {off:.0f} % above {expected:g}, {what} are smaller than the errors (overconfident)"


def summarize(traces: list[RunTrace], skip: int = SKIP_STEPS) -> ConsistencyResult:
    """Combine the runs' traces (all of the same length) into a :class:`ConsistencyResult`."""
    if not traces:
        raise ValueError("no runs to summarize")
    steps = traces[0].steps
    if any(t.steps != steps for t in traces):
        raise ValueError("runs of different lengths")
    R = len(traces)
    nees = np.stack([t.pose_nees for t in traces])  # (R,N)
    mean = nees.mean(axis=0)
    band = average_band(6, R)
    tail = mean[skip:] if steps > skip else mean
    in_band = float(np.mean((tail >= band[0]) & (tail <= band[1]))) if tail.size else float("nan")
    lm = np.concatenate([t.landmark_nees for t in traces])
    nis_sum = np.stack([t.nis_sum for t in traces]).sum(axis=0)
    nis_cnt = np.stack([t.nis_count for t in traces]).sum(axis=0)
    total = int(nis_cnt.sum())
    with np.errstate(invalid="ignore", divide="ignore"):
        nis_step = np.where(nis_cnt > 0, nis_sum / np.maximum(nis_cnt, 1), np.nan)
    conventions: dict[str, int] = {}
    for t in traces:
        conventions[t.conventions] = conventions.get(t.conventions, 0) + 1
    return ConsistencyResult(
        runs=R,
        steps=steps,
        skip=min(skip, steps),
        pose_nees_mean=mean,
        pose_nees_band=band,
        pose_nees_in_band=in_band,
        pose_nees_time_average=float(tail.mean()) if tail.size else float("nan"),
        landmark_nees_mean=float(lm.mean()) if lm.size else float("nan"),
        landmark_count=int(lm.size),
        landmark_nees_band=average_band(3, int(lm.size)),
        nis_mean=float(nis_sum.sum() / total) if total else float("nan"),
        nis_expected=float(sum(t.dof for t in traces) / total) if total else 4.0,
        nis_count=total,
        nis_band=average_band(4, total),
        nis_per_step=nis_step,
        ate_estimate=np.array([t.ate_estimate for t in traces]),
        ate_dead_reckoning=np.array([t.ate_dead_reckoning for t in traces]),
        noise_seeds=[t.noise_seed for t in traces],
        per_run_pose_nees=np.array([(t.pose_nees[skip:] if steps > skip else t.pose_nees).mean() for t in traces]),
        per_run_nis=np.array([t.mean_nis for t in traces]),
        per_run_landmark_nees=np.array([t.landmark_nees.mean() if t.landmark_nees.size else np.nan for t in traces]),
        observations_gated=int(sum(t.observations_gated for t in traces)),
        conventions=conventions,
        health_messages={str(t.noise_seed): t.health_messages for t in traces if t.health_messages},
    )


def _finished(futures: list):
    """The futures as they finish (concurrent.futures ones), else in submission order."""
    if all(isinstance(f, concurrent.futures.Future) for f in futures):
        return concurrent.futures.as_completed(futures)
    return iter(futures)


def monte_carlo(
    scene_factory: SceneFactory,
    filter_config: Config,
    runs: int,
    seed0: int = 0,
    executor: Optional[concurrent.futures.Executor] = None,
    progress: Optional[Callable[[int], None]] = None,
    skip: int = SKIP_STEPS,
) -> ConsistencyResult:
    """``runs`` runs of :func:`run_one` with the noise seeds ``seed0 .. seed0 + runs - 1`` (the geometry
    stays the factory's), summarized.

    ``executor``: any object with the ``concurrent.futures.Executor`` interface (``submit``); it is
    used as is and not shut down. Default: a ``ProcessPoolExecutor`` over ``os.cpu_count()``
    workers, created and shut down here. ``progress(finished)`` is called with the number of runs
    finished so far, once per run.

    BLAS thread limits and warning filters are process-wide; they are set here too (one BLAS
    thread, health warnings off) so that the runs' own nested settings, which a thread pool
    interleaves, save and restore only these values and leave the caller's as they were.
    """
    if runs < 1:
        raise ConfigError(f"monte carlo: runs must be >= 1, got {runs!r}")
    if filter_config.validate().estimator.mode != Mode.SLAM:
        raise ConfigError("monte carlo consistency needs estimator.mode 'slam' (the pose covariance), got "
                          f"{filter_config.estimator.mode.value!r}")
    seeds = [int(seed0) + i for i in range(int(runs))]
    own = executor is None
    if own:
        executor = concurrent.futures.ProcessPoolExecutor(max_workers=min(os.cpu_count() or 1, len(seeds)))
    t0 = time.perf_counter()
    traces: list[RunTrace] = []
    completed = False
    try:
        with threadpool_limits(limits=1), warnings.catch_warnings():
            warnings.simplefilter("ignore", HealthWarning)  # kept in the traces
            futures = [executor.submit(run_one, scene_factory, filter_config, s) for s in seeds]
            seed_of = {id(f): s for f, s in zip(futures, seeds)}
            try:
                for fut in _finished(futures):
                    try:
                        traces.append(fut.result())
                    except VislamError:  # the scene or the filter refused its settings: that says it all
                        raise
                    except Exception as exc:
                        raise RuntimeError(f"monte carlo run with noise seed {seed_of[id(fut)]} failed: {exc}") from exc
                    if progress is not None:
                        progress(len(traces))
            except BaseException:
                for f in futures:
                    f.cancel()
                raise
        completed = True
    finally:
        if own:
            executor.shutdown(wait=True, cancel_futures=not completed)
    traces.sort(key=lambda t: t.noise_seed)
    result = summarize(traces, skip)
    result.wall_seconds = time.perf_counter() - t0
    result.scene = scene_factory.as_dict() if hasattr(scene_factory, "as_dict") else {}
    result.filter = filter_config.as_dict()
    return result
