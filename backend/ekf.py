"""The visual-inertial EKF on SE(3): one object, stepped one time step at a time.

State (right perturbation, ECE276A / Barfoot ch. 7-9):

    world_T_imu = mu exp(xi^),   xi in R^6 = [rho, theta]          (pose, 6)
    b_g                                                             (gyro bias, 3)
    theta_1 .. theta_n  (backend.landmarks)                         (active landmarks, 3 each)

with one dense covariance ``P`` over ``[xi, b_g, theta_1 .. theta_n]``. World-xyz landmarks take a
small random walk (``landmark_random_walk``, m/sqrt s: P_mm += q^2 tau I at each prediction):
the point a tracker follows drifts with the track's age. Only landmarks whose track is
live are in the state; when a track ends its landmark is marginalized (rows and columns
dropped, exact for a Gaussian) and moves to the map with its mean and 3x3 covariance.

Prediction, for the body twist u = [v, omega - b_g] over tau = t_{k+1} - t_k:

    mu    <- mu exp(tau u^)                                         (course eq. for the mean)
    xi    <- exp(-tau u-curlyhat) xi - tau J_r(tau u) [0; I] delta_b + w,   w ~ N(0, W)
    P_xx  <- F P_xx F^T + Q,  P_x,L <- F P_x,L,   F = [[exp(-tau u-curlyhat), -tau J_r E], [0, I]]

Observation of landmark j in the stereo pair (course eq. z = Ks pi(cam_T_imu T^-1 m)), with the
landmark as a homogeneous point w = A (e + B theta) (backend.landmarks: world xyz, or anchored
inverse depth, the default):

    s = mu^-1 w,   q = cam_T_imu s,   z = Ks pi(q)
    dz/dxi    = -Ks dpi/dq cam_T_imu s^odot     (T^-1 w = exp(-xi^) mu^-1 w ~ s - xi^ s)
    dz/dtheta =  Ks dpi/dq cam_T_imu mu^-1 A B

Update: every observed landmark jointly, in three rows per observation (U1). The pixel noise is
white (sigma^2 I) and on rectified pairs the rows of H for vL and vR are equal, so the orthogonal
change of rows  [uL, vL, uR, vR] -> [uL, (vL + vR)/sqrt 2, uR | (vL - vR)/sqrt 2]  leaves the noise
sigma^2 I and puts all the state information in the first three rows; the last has H = 0 and only
adds d^2 / sigma^2 to the NIS. The update from 3 rows is identical to the one from 4 (and the
NIS, gate and RANSAC errors are computed over all 4), at (3/4)^2 of the dense work.
Each 3-row block of H touches 6 pose and 3 landmark columns. Per step: chi-square gate (4 dof)
on the prior innovation blocks; 1-point RANSAC (Civera et al. 2010), every observation a
hypothesis; a rescue test of the rest against the inliers' update (U3); then, with S = L L^T
over the kept rows (all of it one compiled call, ``kernels.select_and_update_inplace``),

    A = L^-1 H P,   w = L^-1 r,   dx = A^T w,   P <- P - A^T A                               (U2)

the symmetric form of P - K S K^T (equal to the Joseph form for the optimal gain), one triangle
by BLAS syrk and mirrored, so P stays exactly symmetric; its positive definiteness is checked
every 100 steps.

Re-anchoring (tracker drift). Feature tracks drift with their age: on the real drives the image
motion of a track older than ~10 frames is 5-10 % shorter than the true motion (BENCHMARKS.md),
which biases both the scale and the rotation a long-lived landmark tells the filter. So a
landmark lives for at most ``reanchor_observations`` observations (``reanchor_far_observations``
when it was anchored with a disparity below ``reanchor_far_disparity``: distant points drift
little and hold the rotation): then it is marginalized to the map and the same track starts a
new landmark from its current stereo observation, which is used once, for the initialization.
Marginalization is exact and the new landmark's cross covariance comes from the augmentation
below, so nothing is counted twice. The first segment of each track is shortened by
``id mod limit`` observations, so that landmarks born together are not all re-anchored at once.
Off with ``track_drift = "no"`` (as the landmark random walk) and in full-state mode; vislam's
own tracker aligns every patch to its track's first patch, so its tracks do not drift
(``backend.pipeline.decide_track_drift``).

Landmark initialization (EKF-SLAM state augmentation) from the first stereo observation:
theta = g(z, mu) with Jacobians J_z and J_xi (backend.landmarks.initialize), and

    P_mm = J_xi P_xixi J_xi^T + J_z R J_z^T,   P_m,x = J_xi P_xi,x.
"""

from __future__ import annotations

import time
import warnings
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from scipy.special import chdtri  # chi-square quantile without scipy.stats (40 MB, 0.6 s to import)

from backend import invariant, kernels, landmarks, se3
from backend.camera import StereoCamera, dpi_dq, pi
from backend.config import FilterConfig
from backend.errors import FilterError
from backend.kernels import CORE, ROWS, SQRT_HALF

_NEVER = np.iinfo(np.int64).max  # re-anchoring limit meaning "never"
_TRACK_ROWS = _ID, _GATED, _COUNT, _LIMIT, _OUTLIER = range(5)  # rows of VisualInertialEKF._track
_NONE = np.zeros(0, dtype=bool)  # an empty mask: none


def _track_row(row: int, doc: str) -> property:
    """A read-only attribute that is row ``row`` of ``VisualInertialEKF._track`` (a view)."""
    return property(lambda self: self._track[row], doc=doc)


def _three_rows(a: np.ndarray) -> np.ndarray:
    """(U1): rows [uL, vL, uR, vR] (axis 1 of a (k,4,...) array) -> [uL, (vL + vR)/sqrt 2, uR]."""
    out = a[:, :3].copy()
    out[:, 1] = (a[:, 1] + a[:, 3]) * SQRT_HALF
    return out


@dataclass
class _Innovation:
    """The prior innovation of one step's observations of tracked landmarks, 3-row form (U1)."""

    slots: np.ndarray  # (k,) state slots of the landmarks
    residual: np.ndarray  # (k,3) r = z - h(x)
    off_row: np.ndarray  # (k,) residual of (vL - vR)/sqrt 2: no state in it
    H_x: np.ndarray  # (3k,6) d h / d pose
    H_m: np.ndarray  # (k,3,3) d h / d landmark
    HP: np.ndarray  # (3k,D) H P
    S: np.ndarray  # (3k,3k) H P H^T + R
    nis: np.ndarray  # (k,) r^T S_ii^-1 r + d^2 / sigma^2 (4 dof)
    in_front: np.ndarray  # (k,) bool


POSE = slice(0, 6)  # the state layout: pose, gyro bias, then 3 per landmark from CORE (backend.kernels)
BIAS = slice(6, 9)


@dataclass
class ImuNoise:
    """White noise of the velocity measurements, per axis (the process noise of the prediction)."""

    linear_sigma: np.ndarray  # (3,) m/s
    angular_sigma: np.ndarray  # (3,) rad/s


@dataclass
class StepStats:
    """What one call of :meth:`VisualInertialEKF.update` did."""

    observed: int = 0  # observations handed in
    used: int = 0  # observations of tracked landmarks used in the joint update
    gated: int = 0  # observations rejected by the Mahalanobis gate
    initialized: int = 0  # new landmarks added to the state
    deferred: int = 0  # new features not initialized (disparity too small or too far): retried later
    marginalized: int = 0  # landmarks moved from the state to the map
    reanchored: int = 0  # landmarks re-triangulated from their current observation (tracker drift)
    dropped: int = 0  # landmarks removed as repeatedly gated
    nis_sum: float = 0.0  # sum over used observations of r_i^T S_ii^-1 r_i (expectation 4 each)
    active: int = 0  # landmarks in the state after the step


@dataclass
class HealthMonitor:
    """Watches the NIS and the covariance; collects one message per episode of trouble.

    An episode starts when the windowed NIS per observation leaves [4/f, 4 f] (f = warn_factor)
    or more than half the observations are gated, and ends when it is back inside [4/sqrt f, 4 sqrt f]
    with at most 40 % gated."""

    window: int
    warn_factor: float
    messages: list[str] = field(default_factory=list)
    _nis: deque = field(default_factory=deque)
    _count: deque = field(default_factory=deque)
    _gated: deque = field(default_factory=deque)
    _total_count: int = 0  # sums of _count and _gated (integers: exact)
    _total_gated: int = 0
    _inconsistent: bool = False

    def add_nis(self, step: int, nis_sum: float, count: int, gated: int = 0) -> None:
        """One step's NIS sum over ``count`` used observations, and how many were gated.

        The NIS of used observations is truncated by the gate, so a far too small pixel_sigma
        shows as a high gated share rather than a high NIS: both are watched.
        """
        self._nis.append(nis_sum)
        self._count.append(count)
        self._gated.append(gated)
        self._total_count += count
        self._total_gated += gated
        if len(self._nis) > self.window:
            self._nis.popleft()
            self._total_count -= self._count.popleft()
            self._total_gated -= self._gated.popleft()
        total = self._total_count
        if len(self._nis) < self.window or total < 20:
            return
        mean = sum(self._nis) / total  # summed afresh: no rounding drift over a long run
        gated_share = self._total_gated / (total + self._total_gated)
        bad = mean > 4.0 * self.warn_factor or mean < 4.0 / self.warn_factor or gated_share > 0.5
        if bad and not self._inconsistent:
            self.report(
                f"step {step}: filter inconsistent: mean NIS per observation {mean:.2f} (expected about 4) "
                f"and {100 * gated_share:.0f} % gated over the last {self.window} steps; tune pixel_sigma or the IMU noise"
            )
            self._inconsistent = True
        elif self._inconsistent:  # the episode ends well inside the band (hysteresis: no flapping at its edge)
            f = self.warn_factor**0.5
            self._inconsistent = not (4.0 / f <= mean <= 4.0 * f and gated_share <= 0.4)

    def report(self, message: str) -> None:
        self.messages.append(message)
        warnings.warn(message, RuntimeWarning, stacklevel=3)


class VisualInertialEKF:
    """Stereo visual-inertial EKF on SE(3) with a bounded landmark state (online API).

    Use: ``predict(dt, v, w)`` then ``update(ids, pixels)`` once per time step.
    """

    def __init__(
        self,
        camera: StereoCamera,
        imu_T_cam: np.ndarray,
        config: FilterConfig,
        imu_noise: ImuNoise,
        world_T_imu: np.ndarray | None = None,
        expected_landmarks: int | None = None,
    ) -> None:
        kernels.warm_up()  # compile or load the kernels now (once per process), not in the first step
        self.kernel_seconds = kernels.warm_up_seconds()
        self.camera = camera
        self.config = config.validate()
        self.imu_T_cam = np.array(imu_T_cam, dtype=float)
        self._cam_T_imu = se3.inverse(self.imu_T_cam)
        self.imu_noise = imu_noise
        self._estimate_pose = config.mode == "slam"
        self._use_vision = config.mode != "dead-reckoning"
        self._invariant = config.error_model == "invariant"  # backend.invariant; else the body error above
        if config.full_state and expected_landmarks is not None:
            self.check_full_state_size(expected_landmarks, config)

        self.mu = np.eye(4) if world_T_imu is None else np.array(world_T_imu, dtype=float)
        self.gyro_bias = np.zeros(3)
        self.P = np.zeros((CORE, CORE))
        if self._estimate_pose:
            self.P[POSE, POSE] = np.eye(6) * config.initial_pose_sigma**2
            if config.estimate_gyro_bias:
                self.P[BIAS, BIAS] = np.eye(3) * config.gyro_bias_sigma0**2
        self._R_pix = config.pixel_sigma**2
        # tracker drift: the point a track follows is not quite static (world xyz landmarks only)
        drift = config.track_drift != "no"
        self._landmark_walk = config.landmark_random_walk**2 if drift and config.landmark_parametrization == "xyz" else 0.0
        self._gate = float(chdtri(4, 1.0 - config.gate_probability))  # chi2(4) quantile

        # active landmarks, in state order: parameters, and the counts of _TRACK_ROWS in one array
        # (columns = landmarks: one gather or concatenation a step for all of them)
        self._kind = config.landmark_parametrization
        self._theta = np.zeros((0, 3))  # landmark parameters (backend.landmarks)
        self._theta_first = np.zeros((0, 3))  # their values at initialization (FEJ, body error model only)
        self._anchors = np.zeros((0, 4, 4))  # (inverse depth only: xyz anchors are the identity)
        self._track = np.zeros((len(_TRACK_ROWS), 0), dtype=np.int64)
        self._reanchor = (drift and not config.full_state
                          and (config.reanchor_observations > 0 or config.reanchor_far_observations > 0))
        self._near_limit = config.reanchor_observations or _NEVER
        self._far_limit = config.reanchor_far_observations or _NEVER
        # RANSAC rejection runs of tracks that left the state but may go on (track id -> count, nonzero)
        self._outlier_stash: dict[int, int] = {}
        # the per-landmark float arrays this configuration reads, kept in state order with _track
        self._per_landmark = ("_theta",)
        if not self._invariant and config.first_estimate_jacobians:
            self._per_landmark += ("_theta_first",)
        if self._kind != "xyz":
            self._per_landmark += ("_anchors",)
        self._ids_sorted = np.zeros(0, dtype=np.int64)  # for the id -> slot look-up (_slots_of)
        self._ids_order = np.zeros(0, dtype=np.int64)
        # marginalized landmarks (the map), appended in batches
        self._map_ids: list[np.ndarray] = []
        self._map_pos: list[np.ndarray] = []
        self._map_cov: list[np.ndarray] = []

        self.health = HealthMonitor(config.nis_window, config.nis_warn_factor)
        self.step_index = 0
        self.seconds_bookkeeping = 0.0  # in update(): ended tracks to the map, new landmarks into the state

    # the rows of _track, as views (kernels change the counts in place)
    _ids = _track_row(_ID, "Track id (the feature column) of each landmark.")
    _gated_run = _track_row(_GATED, "Steps in a row the landmark was not used (gated or rejected).")
    _obs_count = _track_row(_COUNT, "Observations since the landmark was anchored.")
    _obs_limit = _track_row(_LIMIT, "... after which it is re-anchored.")
    _outlier_run = _track_row(_OUTLIER, "Steps in a row the RANSAC rejected the landmark's track "
                                        "(``kernels.count_rejections_inplace``).")

    # ------------------------------------------------------------------ public state
    @property
    def world_T_imu(self) -> np.ndarray:
        return self.mu

    @property
    def pose_covariance(self) -> np.ndarray:
        """6x6 covariance of the right perturbation world_T_imu = mu exp(xi^), whatever the error model."""
        if self._invariant:
            return invariant.body_pose_covariance(self.mu, self.P[POSE, POSE])
        return self.P[POSE, POSE].copy()

    @property
    def num_active(self) -> int:
        return self._ids.size

    @staticmethod
    def check_full_state_size(num_landmarks: int, config: FilterConfig) -> None:
        """Refuse a full state whose dense covariance would not fit in ``max_state_mib``."""
        dim = CORE + 3 * num_landmarks
        mib = 8.0 * dim * dim / 2**20
        if mib > config.max_state_mib:
            raise FilterError(
                f"--full-state with {num_landmarks} landmarks needs a {dim}x{dim} covariance "
                f"({mib:.0f} MiB > max_state_mib = {config.max_state_mib:.0f}); run without --full-state"
            )

    # ------------------------------------------------------------------ prediction
    def predict(self, dt: float, linear_velocity: np.ndarray, angular_velocity: np.ndarray) -> None:
        """mu <- mu exp(tau u^);  P_x <- F P_x F^T + Q  (module docstring); xyz landmarks take a
        random walk of ``landmark_random_walk`` (m/sqrt s): P_mm += q^2 tau I."""
        self.step_index += 1
        u = np.concatenate([linear_velocity, np.asarray(angular_velocity) - self.gyro_bias])
        twist = dt * u
        if self._invariant and self._estimate_pose:  # the whole prediction in one compiled call
            noise = self.imu_noise
            q = np.concatenate([noise.linear_sigma, noise.angular_sigma]) * dt
            self.mu = kernels.predict_invariant_step(
                self.mu, self.P, self._theta, twist, q, dt, self.config.estimate_gyro_bias,
                self.config.gyro_bias_random_walk**2 * dt, self._landmark_walk * dt)
            return
        step = se3.exp_se3(twist)
        self.mu = self.mu @ step
        if self._landmark_walk and self._ids.size:
            diag = np.arange(CORE, self.P.shape[0])
            self.P[diag, diag] += self._landmark_walk * dt
        if not self._estimate_pose:
            return
        Phi = np.eye(CORE)
        Phi[POSE, POSE] = se3.adjoint(se3.inverse(step))  # exp(-tau u-curlyhat) = Ad(exp(tau u^)^-1)
        if self.config.estimate_gyro_bias:
            Phi[POSE, BIAS] = -dt * se3.right_jacobian_se3(twist)[:, 3:6]
        P = self.P
        P[:CORE, :] = Phi @ P[:CORE, :]
        P[:, :CORE] = P[:, :CORE] @ Phi.T
        P[CORE:, :CORE] = P[:CORE, CORE:].T  # exact symmetry of the cross blocks
        P[:CORE, :CORE] = 0.5 * (P[:CORE, :CORE] + P[:CORE, :CORE].T)
        noise = self.imu_noise
        diag = np.concatenate([noise.linear_sigma**2, noise.angular_sigma**2]) * dt * dt
        P[np.arange(6), np.arange(6)] += diag
        if self.config.estimate_gyro_bias:
            P[np.arange(6, 9), np.arange(6, 9)] += self.config.gyro_bias_random_walk**2 * dt

    # ------------------------------------------------------------------ update
    def update(self, ids: np.ndarray, pixels: np.ndarray) -> StepStats:
        """Use the stereo observations ``pixels`` (n,4) = [uL vL uR vR] of landmarks ``ids`` (n,)."""
        ids = np.asarray(ids, dtype=np.int64)
        pixels = np.asarray(pixels, dtype=float).reshape(-1, 4)
        stats = StepStats(observed=ids.size)
        if not self._use_vision:
            return stats
        t0 = time.perf_counter()
        # where each observation goes; ended tracks and expired landmarks (re-anchoring) leave
        slots, leaving, ended, restart, stats.reanchored = kernels.plan_update(
            ids, self._ids_sorted, self._ids_order, self._obs_count, self._obs_limit, self._reanchor,
            self.config.full_state)
        stats.marginalized = int(ended.sum())
        if leaving.any():
            remap = self._remove(leaving, to_map=True, ended=ended)
            slots = np.where(slots >= 0, remap[slots], -1)
        known = slots >= 0
        t1 = time.perf_counter()
        if known.any():
            self._joint_update(slots[known], pixels[known], stats)
        t2 = time.perf_counter()
        new = ~known
        if new.any():
            self._initialize(ids[new], pixels[new], stats, restart[new] if stats.reanchored else None)
        self.seconds_bookkeeping += (t1 - t0) + (time.perf_counter() - t2)
        stats.active = self._ids.size
        if stats.used or stats.gated:
            self.health.add_nis(self.step_index, stats.nis_sum, stats.used, stats.gated)
        if self.step_index % 100 == 0:
            self._check_covariance()
        return stats

    def _observation_model(self, slots: np.ndarray, pixels: np.ndarray):
        """Innovations and Jacobians of the observed landmarks in the 3-row form (U1): residual (k,3),
        off_row (k,) (the residual of (vL - vR)/sqrt 2, no state in it), H_xi (k,3,6), H_theta (k,3,3)
        and a mask of points in front of the camera.

        Homogeneous form of backend.landmarks: q = cam_T_imu mu^-1 A (e + B theta), z = Ks pi(q).
        """
        mu_inv = se3.inverse(self.mu)
        if self._invariant:
            return self._observation_model_invariant(mu_inv, slots, pixels)
        q, dw_dtheta = self._project(mu_inv, self._theta[slots], slots)
        in_front = q[:, 2] > 0.1 * np.abs(q[:, 3])
        q[~in_front, 2] = np.abs(q[~in_front, 3]) + 1.0  # placeholder, those rows are gated out
        Ks = self.camera.Ks
        residual = pixels - pi(q) @ Ks.T
        if self.config.first_estimate_jacobians:
            # FEJ (Huang, Mourikis & Roumeliotis 2008): linearize at each landmark's first estimate,
            # so the unobservable directions get no spurious information
            q, dw_dtheta = self._project(mu_inv, self._theta_first[slots], slots)
            q[~in_front, 2] = np.abs(q[~in_front, 3]) + 1.0
        s_imu = q @ self.imu_T_cam.T
        dz_dimu = Ks @ dpi_dq(q) @ self._cam_T_imu  # (k,4,4): d z / d s_imu
        H_theta = dz_dimu @ dw_dtheta
        if self._estimate_pose:
            H_xi = -dz_dimu @ se3.odot(s_imu)
        else:
            H_xi = np.zeros((slots.size, 4, 6))
        return _three_rows(residual), (residual[:, 1] - residual[:, 3]) * SQRT_HALF, _three_rows(H_xi), _three_rows(H_theta), in_front

    def _observation_model_invariant(self, mu_inv: np.ndarray, slots: np.ndarray, pixels: np.ndarray):
        """(I3) of backend.invariant: dz/drho = -M, dz/dphi = 0, dz/dzeta = M at the current estimate
        (``kernels.observe_invariant``)."""
        cam = self.camera
        residual, off_row, H_x, H_m, in_front = kernels.observe_invariant(
            self._theta[slots], self._cam_T_imu @ mu_inv, cam.fx, cam.fy, cam.cx, cam.cy, cam.baseline, pixels)
        if not self._estimate_pose:
            H_x[:] = 0.0
        return residual, off_row, H_x.reshape(-1, ROWS, 6), H_m, in_front

    def _project(self, mu_inv: np.ndarray, theta: np.ndarray, slots: np.ndarray):
        """q = cam_T_imu mu^-1 A (e + B theta) (k,4) and d(mu^-1 w)/d theta ((4,3) or (k,4,3))."""
        local = landmarks.local_point(self._kind, theta)
        if self._kind == "xyz":  # anchors are the identity
            w_world = local
            dw_dtheta = mu_inv @ landmarks.basis(self._kind)  # the same for every landmark
        else:
            anchors = self._anchors[slots]
            w_world = np.einsum("kij,kj->ki", anchors, local)
            dw_dtheta = mu_inv @ anchors @ landmarks.basis(self._kind)
        return w_world @ (self._cam_T_imu @ mu_inv).T, dw_dtheta

    def _innovation(self, slots: np.ndarray, pixels: np.ndarray) -> "_Innovation":
        """The prior innovation of the observed landmarks, in the 3-row form (U1) of the module docstring:
        H P and S = H P H^T + R from the sparsity of H (each 3-row block touches 6 pose and 3 landmark
        columns of P; ``kernels.innovation_covariance``)."""
        if self._invariant:  # (I3) and the products in one compiled call
            cam = self.camera
            out = kernels.innovation_invariant(self.P, self._theta, slots, self.mu, self._cam_T_imu, cam.fx, cam.fy,
                                               cam.cx, cam.cy, cam.baseline, pixels, self._R_pix, self._estimate_pose)
            return _Innovation(slots, *out)
        residual, off_row, H_x, H_m, in_front = self._observation_model(slots, pixels)
        H_x = np.ascontiguousarray(H_x.reshape(-1, 6))
        HP, S, nis = kernels.innovation_covariance(self.P, H_x, np.ascontiguousarray(H_m), slots, self._R_pix,
                                                   residual, off_row)
        return _Innovation(slots, residual, off_row, H_x, H_m, HP, S, nis, in_front)

    def _joint_update(self, slots: np.ndarray, pixels: np.ndarray, stats: StepStats) -> None:
        """Gate, select a consistent set (1-point RANSAC), update, rescue the rest (module docstring)."""
        inn = self._innovation(slots, pixels)
        cfg = self.config
        status, dx, use = kernels.select_and_update_inplace(
            self.P, inn.HP, inn.S, inn.residual, inn.off_row, inn.nis, inn.in_front, slots, self._gate,
            cfg.ransac_threshold_px, self._R_pix, self._outlier_run, cfg.persistent_outlier_steps, self._gated_run)
        if status:  # numerically degenerate step: the prior is kept
            self.health.report(f"step {self.step_index}: update skipped (innovation covariance not positive "
                               f"definite, potrf info {status})")
        elif use.any():
            self._apply_correction(dx)
        stats.used = int(use.sum())
        stats.gated = int(slots.size - stats.used)
        stats.nis_sum = float(inn.nis[use].sum())
        bad = self._gated_run >= self.config.max_consecutive_gated
        if bad.any():
            stats.dropped = int(bad.sum())
            self._remove(bad, to_map=False)

    def _apply_correction(self, dx: np.ndarray) -> None:
        if self._invariant:  # (I5)
            self.mu = kernels.retract_invariant_inplace(self.mu, self._theta, dx)
            self.gyro_bias = self.gyro_bias + dx[BIAS]
            return
        if self._estimate_pose:
            self.mu = self.mu @ se3.exp_se3(dx[POSE])
            self.gyro_bias = self.gyro_bias + dx[BIAS]
        self._theta += dx[CORE:].reshape(-1, 3)

    # ------------------------------------------------------------------ landmarks
    def _initialize(self, ids: np.ndarray, pixels: np.ndarray, stats: StepStats,
                    restart: np.ndarray | None = None) -> None:
        """Stereo triangulation and state augmentation with the pose cross covariance:
        P_mm = J_xi P_xixi J_xi^T + J_z R J_z^T,  P_m,x = J_xi P_xi,x  (backend.landmarks.initialize).
        ``restart`` (n,) marks observations of re-anchored tracks (None: none)."""
        cfg = self.config
        cam = self.camera
        ok, counts, limits = kernels.admit_landmarks(
            ids, pixels, np.zeros(ids.size, dtype=bool) if restart is None else restart, cfg.min_disparity,
            np.inf if cfg.max_depth is None else cfg.max_depth, cam.fx * cam.baseline, self._reanchor,
            cfg.reanchor_far_disparity, self._near_limit, self._far_limit)
        stats.deferred = ids.size - ok.size
        if not ok.size:
            return
        if ok.size < ids.size:
            ids, pixels = ids[ok], pixels[ok]
        n = ids.size
        sigma = cfg.pixel_sigma if cfg.unbiased_triangulation else 0.0
        anchors = None
        if self._invariant:  # xyz: triangulation, (I4) and the augmentation in one compiled call
            self.P, theta = kernels.initialize_invariant(self.P, pixels, self.mu, self.imu_T_cam, cam.fx, cam.fy, cam.cx,
                                                         cam.cy, cam.baseline, sigma, self._R_pix, self._estimate_pose)
        else:
            theta, anchors, J_z, J_xi = landmarks.initialize(self._kind, self.camera, pixels, self.mu, self.imu_T_cam,
                                                             sigma or None)
            J_xi = J_xi.reshape(3 * n, 6) if self._estimate_pose else np.zeros((3 * n, 6))
            self.P = kernels.augment(self.P, np.ascontiguousarray(J_xi), np.ascontiguousarray(J_z), self._R_pix)
        stash = self._outlier_stash
        runs = (np.array([stash.pop(i, 0) for i in ids.tolist()], dtype=np.int64) if stash
                else np.zeros(n, dtype=np.int64))
        track = np.empty((len(_TRACK_ROWS), n), dtype=np.int64)
        track[_ID], track[_GATED], track[_COUNT], track[_LIMIT], track[_OUTLIER] = ids, 0, counts, limits, runs
        self._track = np.concatenate([self._track, track], axis=1)
        new = {"_theta": theta, "_theta_first": theta, "_anchors": anchors}
        for name in self._per_landmark:
            setattr(self, name, np.concatenate([getattr(self, name), new[name]]))
        self._reindex()
        stats.initialized = n

    def _landmark_covariances(self, slots: np.ndarray) -> np.ndarray:
        """Covariances (k,3,3) of the landmark parameters (world positions for the invariant error, I6)."""
        return kernels.landmark_covariances(self.P, slots, self._theta[slots], self._invariant)

    def _to_map(self, slots: np.ndarray) -> None:
        """Append the world-frame estimates of ``slots`` to the map (points at infinity are left out)."""
        if self._kind == "xyz":  # the parameters are the world positions
            self._map_ids.append(self._ids[slots])
            self._map_pos.append(self._theta[slots])
            self._map_cov.append(self._landmark_covariances(slots))
            return
        pos, cov, finite = landmarks.to_world(
            self._kind, self._theta[slots], self._anchors[slots], self._landmark_covariances(slots)
        )
        self._map_ids.append(self._ids[slots][finite])
        self._map_pos.append(pos[finite])
        self._map_cov.append(cov[finite])

    def _remove(self, mask: np.ndarray, to_map: bool, ended: np.ndarray | None = None) -> np.ndarray:
        """Marginalize the landmarks in ``mask`` (drop their rows and columns); returns the new slot
        of each old one (-1: removed). The outlier counts of tracks that may go on (not ``ended``)
        are kept by track id."""
        removed, keep_lm, remap, counted = kernels.plan_removal(mask, _NONE if ended is None else ended,
                                                                self._outlier_run)
        if counted.size:
            self._outlier_stash.update(zip(self._ids[counted].tolist(), self._outlier_run[counted].tolist()))
        if to_map:
            self._to_map(removed)
        self.P = kernels.gather_landmarks(self.P, keep_lm)  # C-ordered, one pass
        self._track = np.take(self._track, keep_lm, axis=1)  # C-ordered (a[:, idx] is not): contiguous rows
        for name in self._per_landmark:
            setattr(self, name, getattr(self, name)[keep_lm])
        self._reindex()
        return remap

    def _slots_of(self, ids: np.ndarray) -> np.ndarray:
        """State slots of ``ids`` (-1 where not in the state)."""
        return kernels.slots_of(np.asarray(ids, dtype=np.int64), self._ids_sorted, self._ids_order)

    def _reindex(self) -> None:
        self._ids_order = np.argsort(self._ids, kind="stable")
        self._ids_sorted = self._ids[self._ids_order]

    def finish(self) -> None:
        """Marginalize every active landmark into the map (end of the sequence)."""
        if self._ids.size:
            self._remove(np.ones(self._ids.size, dtype=bool), to_map=True)

    def landmark_map(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids (K,), positions (K,3), covariances (K,3,3)) of mapped and active landmarks, by id.

        A landmark estimated more than once (its track was cut and re-initialized) keeps the
        estimate with the smallest covariance trace.
        """
        ids, pos, cov = list(self._map_ids), list(self._map_pos), list(self._map_cov)
        if self._ids.size:
            slots = np.arange(self._ids.size)
            anchors = self._anchors if self._kind != "xyz" else None
            p, c, finite = landmarks.to_world(self._kind, self._theta, anchors, self._landmark_covariances(slots))
            ids.append(self._ids[finite])
            pos.append(p[finite])
            cov.append(c[finite])
        ids_all = np.concatenate(ids) if ids else np.zeros(0, dtype=np.int64)
        pos_all = np.concatenate(pos) if pos else np.zeros((0, 3))
        cov_all = np.concatenate(cov) if cov else np.zeros((0, 3, 3))
        trace = np.trace(cov_all, axis1=1, axis2=2)
        order = np.lexsort((trace, ids_all))  # by id, then most certain first
        first = np.ones(order.size, dtype=bool)
        first[1:] = ids_all[order][1:] != ids_all[order][:-1]
        best = order[first]
        return ids_all[best], pos_all[best], cov_all[best]

    # ------------------------------------------------------------------ health
    def _check_covariance(self) -> None:
        """Say so (once per episode) when P is not positive definite, and repair it."""
        estimated = np.ones(self.P.shape[0], dtype=bool)
        if not self._estimate_pose:
            estimated[:CORE] = False
        elif not self.config.estimate_gyro_bias:
            estimated[BIAS] = False
        sub = self.P[np.ix_(estimated, estimated)]
        if sub.size == 0:
            return
        try:  # positive definite: the common case, a Cholesky factor proves it (~10x cheaper than eigh)
            np.linalg.cholesky(sub)
            return
        except np.linalg.LinAlgError:
            pass
        eigval, eigvec = np.linalg.eigh(sub)
        if eigval.min() > -1e-9 * max(eigval.max(), 1e-30):
            return
        self.health.report(
            f"step {self.step_index}: covariance lost positive definiteness (min eigenvalue "
            f"{eigval.min():.3g}); eigenvalues clipped"
        )
        repaired = (eigvec * np.maximum(eigval, 1e-12)) @ eigvec.T
        self.P[np.ix_(estimated, estimated)] = 0.5 * (repaired + repaired.T)
