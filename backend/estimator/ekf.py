"""The visual-inertial EKF on SE(3): one object, stepped one time step at a time (the online API).

Each step is ``predict(dt, v, w)`` then ``update(ids, pixels)``:

- predict: the mean by (P1) and the covariance by the error model (I2, or B1), with the IMU's
  white noise and the gyro bias' random walk; world-xyz landmarks of drifting tracks take a
  random walk, each by its depth from the tracks' measured pixel walk (R3, T3 of
  ``backend.run.drift``), or ``drift.landmark_random_walk`` (m/sqrt s: P_mm += q^2 tau I) when set;
- update: the step's observations go to their landmarks (``backend.estimator.tracks``); tracks
  that ended leave the state for the map (A2) and, with drifting tracks, old landmarks are
  re-anchored (R1); the observations of landmarks in the state update pose and landmarks jointly
  (U1-U5, ``backend.estimator.update``) with the error model's innovation and correction; new
  tracks start landmarks from their stereo pair (A1 with I4, or B4); the health is watched (H1,
  H2).

The error models move the mean and say what each step does to the covariance; ``StateHelper``
(``backend.estimator.state_helper``) is the only code that changes it (propagate, update,
augment, marginalize, repair). State layout, error models and every equation:
``backend.estimator.layout``, ``.state_helper``, ``.model``, ``.invariant``, ``.body``,
``.covariance``, ``.update``, ``.tracks``; ``docs/design.md`` maps each
equation to the function that runs it and the test that checks it.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from .. import chi2
from ..compiled import warm_up, warm_up_seconds
from ..config import Choice, Config, ErrorModel as ErrorModelKind, Mode
from ..errors import FilterError
from ..geometry import se3
from ..geometry.camera import StereoCamera
from .body import BodyModel
from ..data.inertial import ImuSamples
from .health import HealthMonitor
from .inertial import CORE_INERTIAL, InertialModel, InertialStart
from .invariant import InvariantModel
from .layout import BIAS, CORE, LEVER_ROWS, OFFSET, POSE, state_dimension
from .lever_arm import LeverArmEstimate, carried_prior, consider_information
from .model import ErrorModel
from .offset import OffsetEstimate, corrected_pixels, offset_innovation
from .propagation import ImuNoise
from .state import FilterState
from .state_helper import CoreTransition, StateHelper
from .tracks import TrackTest, admit_landmarks, plan_update
from .update import huber_inflation, pixel_variance, second_order_inplace, whiten, whitened_residuals
from .window import WindowStep, WindowUpdater, retract_clones, window_in_use
from .zero_velocity import ZeroVelocityUpdater

__all__ = ["VisualInertialEKF", "StepStats", "ImuNoise", "check_full_state_size", "make_error_model"]

_NEVER = np.iinfo(np.int64).max  # re-anchoring limit meaning "never"
#: Degrees of freedom of the Student-t innovation likelihood (L1)
LIKELIHOOD_NU = 4.0


@dataclass
class StepStats:
    """What one call of :meth:`VisualInertialEKF.update` did."""

    observed: int = 0  # observations handed in
    used: int = 0  # observations of tracked landmarks used in the joint update
    gated: int = 0  # observations rejected by the Mahalanobis gate
    initialized: int = 0  # new landmarks added to the state
    deferred: int = 0  # new features not initialized (disparity too small or too far): retried later
    marginalized: int = 0  # landmarks moved from the state to the map
    reanchored: int = 0  # landmarks re-triangulated from their current observation (drifting tracks, R1)
    dropped: int = 0  # landmarks removed as repeatedly gated
    rejected: int = 0  # tracks the per-track test rejected (R4): their landmarks removed, their later observations ignored
    nis_sum: float = 0.0  # sum over used observations of their NIS (expectation 4 each, U4; a window's: W5)
    nis_dof: int = 0  # the degrees of freedom of nis_sum, its expectation: 4 a used observation; 4n - 3 a window's feature seen n times (W5)
    log_likelihood: float = 0.0  # sum over observations in front of the camera of their Student-t log-likelihood (L1)
    tested: int = 0  # observations in that sum
    active: int = 0  # landmarks in the state after the step
    still: bool = False  # the rig stood still (Z6-Z8): v = 0 measured before the observations (Z9)


def check_full_state_size(num_landmarks: int, max_state_mib: float) -> None:
    """Refuse a full state whose dense covariance would not fit in ``max_state_mib``."""
    dim = state_dimension(CORE, num_landmarks)
    mib = 8.0 * dim * dim / 2**20
    if mib > max_state_mib:
        raise FilterError(
            f"--full-state with {num_landmarks} landmarks needs a {dim}x{dim} covariance "
            f"({mib:.0f} MiB > max_state_mib = {max_state_mib:.0f}); run without --full-state"
        )


def make_error_model(config: Config, camera: StereoCamera, imu_T_cam: np.ndarray) -> ErrorModel:
    """The error model the configuration names (``estimator.error_model``)."""
    est = config.estimator
    args = (camera, imu_T_cam, config.landmarks.parametrization, est.mode == Mode.SLAM, est.estimate_gyro_bias)
    if est.error_model == ErrorModelKind.INVARIANT:
        return InvariantModel(*args)
    return BodyModel(*args, first_estimate_jacobians=est.first_estimate_jacobians)


class LandmarkMap:
    """Landmarks that left the state: world positions and covariances, appended in batches."""

    def __init__(self) -> None:
        self._ids: list[np.ndarray] = []
        self._positions: list[np.ndarray] = []
        self._covariances: list[np.ndarray] = []

    def add(self, ids: np.ndarray, positions: np.ndarray, covariances: np.ndarray) -> None:
        self._ids.append(ids)
        self._positions.append(positions)
        self._covariances.append(covariances)

    def best(self, more: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None):
        """(ids (K,), positions (K,3), covariances (K,3,3)) by id, with ``more`` (the active landmarks);
        a track estimated more than once (re-anchored) keeps the estimate of smallest covariance trace."""
        ids, pos, cov = list(self._ids), list(self._positions), list(self._covariances)
        if more is not None:
            ids.append(more[0])
            pos.append(more[1])
            cov.append(more[2])
        ids_all = np.concatenate(ids) if ids else np.zeros(0, dtype=np.int64)
        pos_all = np.concatenate(pos) if pos else np.zeros((0, 3))
        cov_all = np.concatenate(cov) if cov else np.zeros((0, 3, 3))
        trace = np.trace(cov_all, axis1=1, axis2=2)
        order = np.lexsort((trace, ids_all))  # by id, then most certain first
        first = np.ones(order.size, dtype=bool)
        first[1:] = ids_all[order][1:] != ids_all[order][:-1]
        best = order[first]
        return ids_all[best], pos_all[best], cov_all[best]


_CONTROLLER = None


def _blas_controller():
    """One threadpoolctl controller per process (finding the BLAS libraries takes ~0.5 ms)."""
    global _CONTROLLER
    if _CONTROLLER is None:
        from threadpoolctl import ThreadpoolController

        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER


class VisualInertialEKF:
    """Stereo visual-inertial EKF on SE(3) with a bounded landmark state (online API).

    Parameters
    ----------
    camera : StereoCamera
        The rectified stereo pair.
    imu_T_cam : array, shape (4, 4)
        Maps camera-frame points into the IMU frame.
    config : Config
        The options (the tables ``estimator``, ``noise``, ``update``, ``landmarks``, ``drift``,
        ``health`` are read).
    imu_noise : ImuNoise or None
        White noise of the velocity measurements per axis (the velocity model; None with ``inertial``).
    world_T_imu : array, shape (4, 4), optional
        The first pose (default: the identity, the world frame).
    expected_landmarks : int, optional
        With ``estimator.full_state``: refuse at once when that many would not fit.
    inertial : InertialStart, optional
        A real IMU instead of velocities: the inertial state (attitude, velocity, position, gyro and
        accelerometer biases; ``backend.estimator.inertial``) starts from it, and
        ``propagate(imu, t0, t1)`` replaces ``predict``. With ``estimator.window`` set (SLAM mode) the
        state holds that many pose clones instead of landmarks (``backend.estimator.window``).

    lever_prior : array, shape (3, 3) or (6, 6), optional
        The prior covariance (m^2) of the residual lever arm of the IMU's velocities (V1-V3 of
        ``backend.estimator.lever_arm``; the velocity model's SLAM runs), (6,6) with the rotation of the
        samples' frame (rad^2, V4) after it: considered by default (V2), the lever arm alone estimated
        with ``estimator.estimate_lever_arm``; None: ``noise.lever_arm_sigma``^2 I where that is set,
        else no such state.

    Use: ``predict(dt, v, w)`` (or ``propagate(imu, t0, t1)``) then ``update(ids, pixels)`` once per
    time step, ``finish()`` at the end. While the filter lives (until ``close()`` or garbage collection) the process's BLAS uses
    ``execution.blas_threads`` threads (one by default: at the filter's ~200 x 200 sizes more
    threads are slower, up to 40x on a busy machine), whatever the caller set; ``close()`` gives
    the caller's setting back. (Limiting per call instead costs ~0.1 ms a step: OpenBLAS re-sizes
    its pool each time.)
    """

    def __init__(
        self,
        camera: StereoCamera,
        imu_T_cam: np.ndarray,
        config: Config,
        imu_noise: ImuNoise,
        world_T_imu: np.ndarray | None = None,
        expected_landmarks: int | None = None,
        inertial: InertialStart | None = None,
        lever_prior: np.ndarray | None = None,
    ) -> None:
        window = window_in_use(config, inertial is not None)
        warm_up(inertial=inertial is not None, window=window)  # compile or load the kernels now (once per process), not in the first step
        self.kernel_seconds = warm_up_seconds()
        self.camera = camera
        self.config = config.validate()
        est, noise, drift = config.estimator, config.noise, config.drift
        if est.full_state and expected_landmarks is not None:
            check_full_state_size(expected_landmarks, est.max_state_mib)
        self.imu_noise = imu_noise
        self.estimate_pose = est.mode == Mode.SLAM
        self.use_vision = est.mode != Mode.DEAD_RECKONING
        self.inertial = inertial is not None
        self._lever_prior = None  # (k,k) the residual lever arm's prior (and V4's rotation's), where the state holds it (V1)
        if self.inertial:
            self.model = InertialModel(camera, imu_T_cam, inertial, self.estimate_pose)
            m = inertial.mean
            self.state = FilterState(mu=np.array(m.world_T_imu, dtype=float), gyro_bias=np.array(m.gyro_bias, float),
                                     core=CORE_INERTIAL, velocity=np.array(m.velocity, float),
                                     accel_bias=np.array(m.accel_bias, float))
            StateHelper.set_prior(self.state, inertial.covariance)
        else:
            self.model = make_error_model(config, camera, imu_T_cam)
            offset_sigma = noise.stereo_offset_sigma if self.use_vision and not window else None
            if lever_prior is None and noise.lever_arm_sigma:
                lever_prior = noise.lever_arm_sigma**2 * np.eye(LEVER_ROWS)
            if lever_prior is not None:
                lever_prior = carried_prior(lever_prior, est.estimate_lever_arm)
            lever = lever_prior is not None and self.estimate_pose
            lever_dim = np.shape(lever_prior)[0] if lever else 0
            core = CORE + 1 if offset_sigma else CORE
            lever_row = core if lever else None
            core += lever_dim
            self.state = FilterState(
                mu=np.eye(4) if world_T_imu is None else np.array(world_T_imu, dtype=float),
                theta_first=np.zeros((0, 3)) if "theta_first" in self.model.per_landmark else None,
                anchors=np.zeros((0, 4, 4)) if "anchors" in self.model.per_landmark else None,
                core=core, offset_row=OFFSET if offset_sigma else None,
                offset_considered=bool(offset_sigma) and not est.estimate_stereo_offset,
                lever_row=lever_row, lever_considered=lever and not est.estimate_lever_arm,
                lever_information=consider_information(lever_prior) if lever else None,
            )
            prior = np.zeros((core, core))
            if self.estimate_pose:
                prior[POSE, POSE] = np.eye(6) * noise.initial_pose_sigma**2
                if est.estimate_gyro_bias:
                    prior[BIAS, BIAS] = np.eye(3) * noise.gyro_bias_sigma0**2
            if offset_sigma:  # (O1) the residual disparity offset
                prior[OFFSET, OFFSET] = offset_sigma**2
            if lever:  # (V1) the residual lever arm of the IMU's velocities
                rows = slice(lever_row, lever_row + lever_dim)
                prior[rows, rows] = np.asarray(lever_prior, dtype=float)
            self._lever_prior = np.asarray(lever_prior, dtype=float) if lever else None
            StateHelper.set_prior(self.state, prior)
        if noise.pixel_sigma is None:
            raise FilterError("noise.pixel_sigma is unset: set it, or let vislam.decide() identify it from the data "
                              "(vislam.OnlineRun, vislam.run_sequence)")
        self._pixel_var = noise.pixel_sigma**2
        self._var_per_disparity = noise.pixel_variance_per_disparity or 0.0  # (N5): 0 = white pixel noise
        # drifting tracks: the point a track follows is not quite static (world xyz landmarks only)
        drifting = drift.track_drift != Choice.NO
        xyz = config.landmarks.parametrization == "xyz"
        walking = drifting and xyz
        constant = drift.landmark_random_walk
        self._landmark_walk = constant**2 if walking and constant is not None else 0.0  # m^2/s, every landmark
        self._pixel_walk = ((drift.pixel_walk or 0.0, drift.pixel_walk_per_disparity or 0.0)
                            if walking and constant is None else (0.0, 0.0))  # (R3) px^2 a step: at d = 0, per px of d
        self._gate = chi2.quantile(4, config.update.gate_probability)  # chi2(4) quantile (U4)
        hp = config.update.huber_probability
        self._huber = chi2.quantile(4, hp) if hp else 0.0  # (U8)
        self.track_test = (TrackTest(drift.track_test_probability, drift.track_test_min_observations)
                           if drift.track_test_probability and not window else None)  # (R4): the landmark update's
        self._reanchor = (drifting and not est.full_state
                          and (drift.reanchor_observations > 0 or drift.reanchor_far_observations > 0))
        self._near_limit = drift.reanchor_observations or _NEVER
        self._far_limit = drift.reanchor_far_observations or _NEVER
        self.map = LandmarkMap()
        self.health = HealthMonitor(config.health.nis_window, config.health.nis_warn_factor)
        self.step_index = 0
        self.track_likelihood = False  # fill StepStats.log_likelihood (L1): for identification runs
        self.seconds_bookkeeping = 0.0  # in update(): ended tracks to the map, new landmarks into the state
        self._blas_limit = _blas_controller().limit(limits=config.execution.blas_threads, user_api="blas")
        self.window = None  # the sliding window of pose clones (W1-W7), a real IMU's SLAM run only
        if window:
            self.window = WindowUpdater(est.window, camera, self.model.cam_T_imu, self._pixel_var,
                                        config.update.gate_probability, self.map)
            self.state.clones = np.zeros((0, 4, 4))
        self.zero_velocity = None  # zero-velocity updates (Z6-Z9), a real IMU's SLAM run only
        if self.inertial and self.estimate_pose and config.update.zero_velocity:
            self.zero_velocity = ZeroVelocityUpdater(inertial.noise, inertial.gravity, camera, self.model.cam_T_imu,
                                                     self._pixel_var, config.update.gate_probability)

    # ------------------------------------------------------------------ public state
    @property
    def world_T_imu(self) -> np.ndarray:
        """The pose estimate, shape (4, 4)."""
        return self.state.mu

    @property
    def gyro_bias(self) -> np.ndarray:
        """The gyro bias estimate, shape (3,), rad/s."""
        return self.state.gyro_bias

    @property
    def pose_covariance(self) -> np.ndarray:
        """6x6 covariance of the right perturbation world_T_imu = mu exp(xi^), whatever the error model."""
        return self.model.pose_covariance(self.state)

    @property
    def disparity_offset(self) -> OffsetEstimate | None:
        """The residual disparity offset in the state (O1, O4), or None where it is not."""
        st = self.state
        if st.offset_row is None:
            return None
        return OffsetEstimate(st.offset, float(np.sqrt(max(st.P[st.offset_row, st.offset_row], 0.0))),
                              float(self.config.noise.stereo_offset_sigma), not st.offset_considered)

    @property
    def lever_arm(self) -> LeverArmEstimate | None:
        """The residual lever arm of the IMU's velocities in the state (V1, V2), or None where it is not."""
        st = self.state
        if st.lever_row is None:
            return None
        rows = np.arange(st.lever_row, st.lever_row + LEVER_ROWS)
        prior_sd = np.sqrt(np.diag(self._lever_prior))
        rotation = np.degrees(prior_sd[LEVER_ROWS:]).tolist() if st.carries_rotation else None
        return LeverArmEstimate(st.lever_arm.tolist(), np.sqrt(np.maximum(st.P[rows, rows], 0.0)).tolist(),
                                prior_sd[:LEVER_ROWS].tolist(), not st.lever_considered, rotation)

    @property
    def num_active(self) -> int:
        """Landmarks in the state."""
        return self.state.num_landmarks

    # ------------------------------------------------------------------ prediction
    def predict(self, dt: float, linear_velocity: np.ndarray, angular_velocity: np.ndarray) -> None:
        """Move the estimate by the IMU velocities over ``dt`` seconds: (P1) and the error model's
        covariance prediction (I2 or B1)."""
        self.step_index += 1
        twist, q = self._imu_twist(dt, linear_velocity, angular_velocity)
        transition = self.model.predict(self.state, twist, q, dt, self.config.noise.gyro_bias_random_walk**2 * dt)
        StateHelper.propagate(self.state, transition, self._walk(dt))

    def propagate(self, imu: ImuSamples, t0: float, t1: float) -> None:
        """Move the inertial state from t0 to t1 by every IMU sample between (J3, J5, J6 of
        ``backend.estimator.inertial``); the filter must have been made with ``inertial``."""
        if not self.inertial:
            raise TypeError("propagate() needs the inertial state: VisualInertialEKF(..., inertial=InertialStart(...))")
        self.step_index += 1
        transition = self.model.propagate(self.state, imu, t0, t1)
        if self.zero_velocity is not None:
            self.zero_velocity.interval(imu, t0, t1)
        if self.window is not None:  # clones after the core, not landmarks (W2)
            StateHelper.propagate(self.state, CoreTransition(transition.prop.Phi, transition.prop.Q))
            return
        StateHelper.propagate(self.state, transition, self._walk(t1 - t0))

    @property
    def velocity(self) -> np.ndarray | None:
        """The world-frame velocity (3,) m/s of the inertial state (None in the velocity model)."""
        return self.state.velocity

    @property
    def accel_bias(self) -> np.ndarray | None:
        """The accelerometer bias (3,) m/s^2 of the inertial state (None in the velocity model)."""
        return self.state.accel_bias

    def _imu_twist(self, dt: float, linear_velocity: np.ndarray, angular_velocity: np.ndarray):
        """(the step's body twist tau (v, w - b) (6,), its noise sigmas times tau (6,)) from the IMU sample."""
        w = np.asarray(angular_velocity) - self.state.gyro_bias
        v = np.asarray(linear_velocity)
        if self.state.lever_row is not None and not self.state.lever_considered:  # (V1) estimated: v - omega x r
            v = v - np.cross(w, self.state.lever_arm)
        u = np.concatenate([v, w])
        noise = self.imu_noise
        return dt * u, np.concatenate([noise.linear_sigma, noise.angular_sigma]) * dt

    def predict_frozen(self, dt: float, linear_velocity: np.ndarray, angular_velocity: np.ndarray,
                       prior: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """A step into a frame that repeats the previous one (its content froze while the rig moved on):
        the pose moves by the IMU's twist, fused with ``prior`` = (a twist tau u (6,), its sigmas (6,)),
        a prediction of the step's motion from elsewhere (inverse-variance weights per axis); the
        landmarks keep their body-frame points (I8). Error models that cannot carry landmarks through
        (``ErrorModel.freezes``) end every track instead (A2): the IMU alone bridges the step."""
        self.step_index += 1
        twist, q = self._imu_twist(dt, linear_velocity, angular_velocity)
        weight = np.ones(6)
        if prior is not None and self.estimate_pose:
            w_imu, w_prior = 1.0 / np.maximum(q, 1e-300) ** 2, 1.0 / np.maximum(prior[1], 1e-300) ** 2
            twist = (w_imu * twist + w_prior * prior[0]) / (w_imu + w_prior)
            q = 1.0 / np.sqrt(w_imu + w_prior)
            weight = w_imu / (w_imu + w_prior)
        bias_walk = self.config.noise.gyro_bias_random_walk**2 * dt
        if not self.model.freezes:
            self.finish()
            transition = self.model.predict(self.state, twist, q, dt, bias_walk)
        else:
            transition = self.model.predict_frozen(self.state, twist, q, dt, bias_walk, weight)
        StateHelper.propagate(self.state, transition, self._walk(dt))

    def _walk(self, dt: float) -> float | np.ndarray:
        """The landmarks' random walk over one step of ``dt`` s: a configured ``drift.landmark_random_walk``
        q as q^2 dt for every landmark, else each landmark's from the tracks' pixel walk (T3),
        q(d) = q_0 + q_d d px^2 a step, as a lateral walk at its depth z in the camera (fx b / z = d):

            var = (z / fx)^2 q(fx b / z) = (z / fx)^2 q_0 + q_d b z / fx     m^2 a step, x y z each      (R3)

        (an isotropic walk of the lateral size: along the ray a point's depth is far less certain anyway).
        Returns a number or (n,) per landmark slot."""
        if self._landmark_walk:
            return self._landmark_walk * dt
        q0, qd = self._pixel_walk
        if not (q0 or qd) or not self.state.num_landmarks:
            return 0.0
        cam_T_world = self.model.cam_T_imu @ se3.inverse(self.state.mu)
        z = np.abs(self.state.theta @ cam_T_world[2, :3] + cam_T_world[2, 3])
        cam = self.camera
        return (z / cam.fx) ** 2 * q0 + qd * cam.baseline * z / cam.fx

    # ------------------------------------------------------------------ update
    def update(self, ids: np.ndarray, pixels: np.ndarray) -> StepStats:
        """Use the stereo observations ``pixels`` (n,4) = [uL vL uR vR] of the tracks ``ids`` (n,)."""
        ids = np.asarray(ids, dtype=np.int64)
        pixels = np.asarray(pixels, dtype=float).reshape(-1, 4)
        stats = StepStats(observed=ids.size)
        if not self.use_vision:
            return stats
        if self.track_test is not None and ids.size:  # (R4) rejected tracks stay out
            admitted = self.track_test.admitted(ids)
            if not admitted.all():
                ids, pixels = ids[admitted], pixels[admitted]
        if self.zero_velocity is not None:  # (Z6-Z9) standing still: v = 0 measured, then the frame's vision as always
            stats.still = self.zero_velocity.step(self.state, ids, pixels, self._correct)
        if self.window is not None:
            return self._window_step(self.window.step(self.state, ids, pixels, self._correct), stats)
        t0 = time.perf_counter()
        st = self.state
        # where each observation goes; ended tracks and expired landmarks (re-anchoring) leave
        slots, leaving, ended, restart, stats.reanchored = plan_update(
            ids, *st.index, st.obs_count, st.obs_limit, self._reanchor, self.config.estimator.full_state)
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
        stats.active = st.num_landmarks
        stats.nis_dof = 4 * stats.used
        if stats.used or stats.gated:
            self.health.add_nis(self.step_index, stats.nis_sum, stats.used, stats.gated)
        if self.step_index % 100 == 0:
            self._check_covariance()
        return stats

    def _correct(self, state, dx: np.ndarray) -> None:
        """The mean corrected by the update ``dx`` (D,): the error model's retraction (J7) of the core
        and the landmarks, a window's clones by theirs (W6)."""
        if self.window is None:
            self.model.correct(state, dx)
            if state.offset_row is not None:
                state.offset += float(dx[state.offset_row])
            if state.lever_row is not None:
                state.lever_arm = state.lever_arm + dx[state.lever_row:state.lever_row + LEVER_ROWS]
            return
        c = state.core
        self.model.correct(state, dx[:c])
        if state.clones.shape[0]:
            state.clones = retract_clones(state.clones, dx[c:])

    def _window_step(self, step: WindowStep, stats: StepStats) -> StepStats:
        """A window's frame (W1-W7) in the step's counts and the health."""
        stats.used, stats.gated, stats.nis_sum, stats.nis_dof = step.used, step.gated, step.nis_sum, step.dof
        stats.marginalized, stats.active = step.mapped, step.active
        if stats.used or stats.gated:
            self.health.add_nis(self.step_index, stats.nis_sum, stats.used, stats.gated)
        if self.step_index % 100 == 0:
            self._check_covariance()
        return stats

    def _joint_update(self, slots: np.ndarray, pixels: np.ndarray, stats: StepStats) -> None:
        """Gate, 1-point RANSAC, rescue and the joint update (U1-U5) in one compiled call, then the
        error model's correction; landmarks gated too often in a row are dropped."""
        st = self.state
        pixel_var = self._pixel_var
        if st.offset:  # (O1) the right column corrected by the offset's mean (0 unless estimated)
            pixels = corrected_pixels(pixels, st.offset)
        obs_var = None
        if self._var_per_disparity:  # (N5) each observation's variance, by whitening (U6)
            obs_var = self._observation_variance(pixels)
            pixel_var = float(np.median(obs_var))
        inn = self.model.innovation(st, slots, pixels, pixel_var)
        if st.offset_row is not None:  # (O2)
            inn = offset_innovation(inn, st.P, st.offset_row, pixel_var)
        if self.config.update.second_order:  # (U7) before whitening: S was formed with R = pixel_var I
            cam = self.camera
            second_order_inplace(inn.residual, inn.S, inn.off_row, inn.nis, inn.in_front, pixels, cam.fx, cam.fy,
                                 cam.cx, cam.cy, cam.baseline, pixel_var)
        upd = self.config.update
        formed = inn  # with R = pixel_var I
        if obs_var is not None:
            inn = whiten(formed, obs_var, pixel_var)
        nis = inn.nis  # the NIS under the noise model, what the health check reads (U4)
        if self._huber:  # (U8) Huber's weights from the prior NIS: their observations' variances inflated
            inflate = huber_inflation(nis, self._huber, self._gate)
            if inflate is not None:
                inn = whiten(formed, (pixel_var if obs_var is None else obs_var) * inflate, pixel_var)
        result = StateHelper.update(st, inn, slots, self._gate, upd.ransac_threshold_px, pixel_var,
                                    upd.persistent_outlier_steps)
        use = result.used
        if result.status:  # numerically degenerate step: the prior is kept
            self.health.report(f"step {self.step_index}: update skipped (innovation covariance not positive "
                               f"definite, potrf info {result.status})")
        elif use.any():
            self._correct(st, result.dx)
        stats.used = int(use.sum())
        stats.gated = int(slots.size - stats.used)
        stats.nis_sum = float(nis[use].sum())
        if self.track_likelihood:
            stats.log_likelihood, stats.tested = self._log_likelihood(inn, pixel_var)
        bad = st.gated_run >= upd.max_consecutive_gated
        stats.dropped = int(bad.sum())
        if self.track_test is not None and use.any() and not result.status:  # (R4)
            rows = np.flatnonzero(use)
            rejected = self.track_test.add(st.ids[slots[rows]], whitened_residuals(inn.S, inn.residual, rows))
            stats.rejected = int(rejected.sum())
            bad[slots[rows[rejected]]] = True
        if bad.any():
            self._remove(bad, to_map=False)

    def _observation_variance(self, pixels: np.ndarray) -> np.ndarray:
        """(N5) sigma_i^2 = pixel_sigma^2 + b d_i (k,) of observations ``pixels`` (k,4), d = uL - uR."""
        return pixel_variance(self._pixel_var, self._var_per_disparity, pixels[:, 0] - pixels[:, 2])

    def _log_likelihood(self, inn, pixel_var: float) -> tuple[float, int]:
        """(L1) the prior innovations' log-likelihood, observation by observation (their 4 rows: the
        3x3 block of S and the off row's sigma^2), heavy-tailed so that a gross outlier does not decide
        a comparison yet an overconfident model still pays for its residuals (a multivariate Student-t
        of ``LIKELIHOOD_NU`` degrees of freedom and scale S_ii; constants dropped):

            sum_i -1/2 ((nu + 4) log(1 + NIS_i / nu) + log det S_ii + log sigma_i^2)

        over the observations in front of the camera (a whitened innovation, U6, in its own units:
        det S_ii = det S'_ii (sigma_i^2 / pixel_var)^3)."""
        front = np.flatnonzero(inn.in_front)
        if not front.size:
            return 0.0, 0
        rows = 3 * front[:, None] + np.arange(3)
        blocks = inn.S[rows[:, :, None], rows[:, None, :]]
        sign, logdet = np.linalg.slogdet(blocks)
        ok = sign > 0
        nu = LIKELIHOOD_NU
        nis = inn.nis[front][ok]
        if inn.variance is None:
            log_var = np.full(ok.sum(), np.log(pixel_var))
            logdet = logdet[ok]
        else:
            log_var = np.log(inn.variance[front][ok])
            logdet = logdet[ok] + 3.0 * (log_var - np.log(pixel_var))
        total = -0.5 * float(np.sum((nu + 4.0) * np.log1p(nis / nu) + logdet + log_var))
        return total, int(ok.sum())

    # ------------------------------------------------------------------ landmarks
    def _initialize(self, ids: np.ndarray, pixels: np.ndarray, stats: StepStats,
                    restart: np.ndarray | None = None) -> None:
        """Start landmarks from the stereo pixels of new tracks (A1 with I4 or B4) where disparity and
        depth allow; ``restart`` (n,) marks observations of re-anchored tracks (None: none)."""
        lm, cam = self.config.landmarks, self.camera
        if self.state.offset:  # (O1) triangulated from the corrected right column
            pixels = corrected_pixels(pixels, self.state.offset)
        ok, counts, limits = admit_landmarks(
            ids, pixels, np.zeros(ids.size, dtype=bool) if restart is None else restart, lm.min_disparity,
            np.inf if lm.max_depth is None else lm.max_depth, cam.fx * cam.baseline, self._reanchor,
            self.config.drift.reanchor_far_disparity, self._near_limit, self._far_limit)
        stats.deferred = ids.size - ok.size
        if not ok.size:
            return
        if ok.size < ids.size:
            ids, pixels = ids[ok], pixels[ok]
        sigma = self.config.noise.pixel_sigma if lm.unbiased_triangulation else 0.0
        new = self.model.initialize(self.state, pixels, sigma)
        if self.state.offset_row is not None:  # (O3) d theta / d offset: the uR column of J_z
            new = dataclasses.replace(new, J_offset=np.ascontiguousarray(new.J_z[:, :, 2]).reshape(-1))
        if self._var_per_disparity:  # (N5) each landmark from its own pixels' variance: J_z scaled to the reference
            scale = np.sqrt(self._observation_variance(pixels) / self._pixel_var)
            new = dataclasses.replace(new, J_z=np.ascontiguousarray(new.J_z * scale[:, None, None]))
        StateHelper.augment(self.state, ids, new, self._pixel_var, counts, limits)
        stats.initialized = ids.size

    def _remove(self, mask: np.ndarray, to_map: bool, ended: np.ndarray | None = None) -> np.ndarray:
        """Marginalize the landmarks in ``mask`` (A2), to the map if ``to_map`` (points at infinity are
        left out); returns the new slot of each old one (-1: removed)."""
        if to_map:
            slots = np.flatnonzero(mask)
            pos, cov, finite = self.model.world_landmarks(self.state, slots)
            if not finite.all():  # points at infinity (inverse depth <= 0) have no position
                slots, pos, cov = slots[finite], pos[finite], cov[finite]
            self.map.add(self.state.ids[slots], pos, cov)
        return StateHelper.marginalize(self.state, mask, ended)

    def finish(self) -> None:
        """Marginalize every active landmark into the map (end of the sequence); a window uses the
        tracks left in it."""
        if self.window is not None:
            self._window_step(self.window.flush(self.state, self._correct), StepStats())
            return
        if self.state.num_landmarks:
            self._remove(np.ones(self.state.num_landmarks, dtype=bool), to_map=True)

    def close(self) -> None:
        """Give the process its BLAS threads back (also when the filter is garbage-collected)."""
        limit, self._blas_limit = getattr(self, "_blas_limit", None), None
        if limit is not None:
            limit.restore_original_limits()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown: the libraries may be gone
            pass

    def landmark_map(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids (K,), positions (K,3), covariances (K,3,3)) of mapped and active landmarks, by id.

        A landmark estimated more than once (its track was re-anchored) keeps the estimate with the
        smallest covariance trace.
        """
        active = None
        if self.state.num_landmarks:
            pos, cov, finite = self.model.world_landmarks(self.state, np.arange(self.state.num_landmarks))
            active = (self.state.ids[finite], pos[finite], cov[finite])
        return self.map.best(active)

    # ------------------------------------------------------------------ health
    def _check_covariance(self) -> None:
        """(H2): say so (once per episode) when P is not positive definite, and repair it."""
        estimated = self.state.estimated(self.estimate_pose, self.config.estimator.estimate_gyro_bias or self.inertial)
        worst = StateHelper.repair(self.state, estimated)
        if worst is not None:
            self.health.report(f"step {self.step_index}: covariance lost positive definiteness (min eigenvalue "
                               f"{worst:.3g}); eigenvalues clipped")
