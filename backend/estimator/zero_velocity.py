"""Zero-velocity updates: the frames at which a real IMU's rig stands still (OpenVINS's ZUPT).

Standing still is the one motion the IMU and the camera can each confirm on their own, and one a
sliding window of clones (``backend.estimator.window``) does not hold by itself: its tracks tie the
clones to one another, so at rest the pose wanders by the pixels' and the IMU's noise (EuRoC
V1_01's 40 pairs before take-off, this update off: the filter's poses make a path of 1.8 cm where
its ground truth moves 6.5 mm). Where
both sensors say "still" and the filter's velocity allows it, the velocity is measured to be zero,
before the frame's observations are used as at any other frame.

The test of the interval from the last frame t0 to this one t1 (T = t1 - t0; the state at t1;
p = ``update.gate_probability``), cheapest first, each only when the one before passed:

Vision. The k tracks seen at both frames move d_i = |z_i(t1) - z_i(t0)|^2 / (2 sigma_px^2), chi2_4
at rest. Their median, not their sum, decides (a few tracks on a moving object or mismatched do
not veto rest): the median of k draws exceeds x with probability P[Binomial(k, F_4(x)) < ceil(k/2)], so

    still when median_i d_i <= x_k = F_4^-1(q_k),  q_k: P[Binomial(k, q_k) <= ceil(k/2) - 1] = 1 - p     (Z6)

with at least ``MIN_TRACKS`` tracks (fewer: vision cannot say, and the frame is not still).

IMU. At rest w = a = 0 in (J2): w_m = b_g + n_g and a_m = -R^T g + b_a + n_a. The n samples in
(t0, t1] give the residuals r_j = [w_m,j - b_g_hat; a_m,j - b_a_hat + R_hat^T g] (6,), their mean
r_bar and their spread. With R = exp(phi^) R_hat (J1), R^T g ~ R_hat^T g + R_hat^T g^ phi, so

    r_bar = H_i dx + n_bar,   H_i = [[0, 0, I, 0, 0], [0, -R_hat^T g^, 0, 0, I]]  on (rho, phi, db_g, nu, db_a),
    cov(n_bar) = N / T,  N = diag(sigma_g^2 I, sigma_a^2 I)   (each sample's white noise sigma^2 / dt),
    s_imu = r_bar^T (H_i P H_i^T + N / T)^-1 r_bar + (T / n) sum_j (r_j - r_bar)^T N^-1 (r_j - r_bar)    (Z7)

chi2 with 6n degrees of freedom at rest (sigma_g, sigma_a the decided densities, ``backend.run.inertial``:
measured at rest, they hold the rig's vibration): still when s_imu <= chi2_{6n}^-1(p).

The velocity's noise and the filter's own velocity. An IMU cannot tell rest from a constant
velocity, so given both tests v = 0 is wrong by the velocity vision could not see. At zero motion
a track's stereo pixels z = Ks pi(s - t) move by -dz/ds t for a small translation t of the camera
(s_i its stereo point, S2), each frame's pixels with noise sigma_px^2: the tracks' least-squares
translation has the covariance C_t = 2 sigma_px^2 (sum_i J_i^T J_i)^-1, J_i = dz/ds (4,3) (tracks of
positive disparity), and v = 0 the noise R_v = R_wc C_t R_wc^T / T^2 (world frame, R_wc =
world_R_imu imu_R_cam). By (J1) v ~ v_hat - v_hat^ phi + nu, so

    H_v = [0, -v_hat^, 0, I, 0],   S = H_v P H_v^T + R_v,   still when v_hat^T S^-1 v_hat <= chi2_3^-1(p)   (Z8)

(a slow constant velocity that both tests miss is refused here once the filter has measured it).

Update. At a still frame, the Kalman update by v = 0 (``StateHelper.update_dense``: dx = P H_v^T
S^-1 (0 - v_hat), P <- P - P H_v^T S^-1 H_v P), the core's retraction (J7) and the clones' (W6);
then the frame's observations, as at every frame.                                                   (Z9)
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .. import chi2
from ..compiled import jit, warms_up
from ..data.inertial import ImuNoiseDensities, ImuSamples
from ..geometry import se3
from ..geometry.camera import StereoCamera, dpi_dq
from .inertial import BA, BG, NU, PHI
from .linalg import kth_smallest
from .state import FilterState
from .state_helper import StateHelper

__all__ = ["MIN_TRACKS", "RestTest", "rest_jacobian", "velocity_jacobian", "imu_rest_statistic",
           "flow_rest_statistic", "median_threshold", "translation_covariance", "ZeroVelocityUpdater"]

#: Tracks at both frames the vision test (Z6) needs at least
MIN_TRACKS = 5


@dataclass(frozen=True)
class RestTest:
    """One interval's test (Z6-Z8): each statistic with its threshold (nan: not computed, a test before
    it failed), the ``tracks`` at both frames, and the decision :attr:`still`."""

    flow_median: float = float("nan")
    flow_threshold: float = float("nan")
    tracks: int = 0
    imu: float = float("nan")
    imu_threshold: float = float("nan")
    velocity_nis: float = float("nan")
    velocity_threshold: float = float("nan")

    @property
    def still(self) -> bool:
        return (self.flow_median <= self.flow_threshold and self.imu <= self.imu_threshold
                and self.velocity_nis <= self.velocity_threshold)


def rest_jacobian(world_R_imu: np.ndarray, gravity: np.ndarray, core: int) -> np.ndarray:
    """(Z7) H_i (6,core): the mean residuals [w; a] at rest against the core's error (J1)."""
    H = np.zeros((6, core))
    H[:3, BG] = np.eye(3)
    H[3:, PHI] = -world_R_imu.T @ se3.hat3(gravity)
    H[3:, BA] = np.eye(3)
    return H


def velocity_jacobian(velocity: np.ndarray, core: int) -> np.ndarray:
    """(Z8) H_v (3,core): the world velocity against the core's error (J1)."""
    H = np.zeros((3, core))
    H[:, PHI] = -se3.hat3(velocity)
    H[:, NU] = np.eye(3)
    return H


def imu_rest_statistic(samples: ImuSamples, t0: float, t1: float, world_R_imu: np.ndarray, gyro_bias: np.ndarray,
                       accel_bias: np.ndarray, P_core: np.ndarray, noise: ImuNoiseDensities,
                       gravity: np.ndarray) -> tuple[float, int]:
    """(Z7) (s_imu, its degrees of freedom 6n) of the samples in (t0, t1]; (nan, 0) without a sample or
    with a density of zero (no noise to test against). ``world_R_imu`` (3,3), the biases (3,),
    ``P_core`` (15,15) the core's covariance at t1."""
    t = samples.time_stamps
    i0, i1 = int(np.searchsorted(t, t0, side="right")), int(np.searchsorted(t, t1, side="right"))
    n = i1 - i0
    if n < 1 or not (noise.gyroscope_noise_density > 0 and noise.accelerometer_noise_density > 0):
        return float("nan"), 0
    T = float(t1 - t0)
    r = np.empty((n, 6))
    r[:, :3] = samples.angular_velocity[i0:i1] - gyro_bias
    r[:, 3:] = samples.linear_acceleration[i0:i1] - accel_bias + world_R_imu.T @ gravity
    r_bar = r.mean(0)
    N = np.repeat([noise.gyroscope_noise_density**2, noise.accelerometer_noise_density**2], 3)
    H = rest_jacobian(world_R_imu, gravity, P_core.shape[0])
    S = H @ P_core @ H.T
    S[np.diag_indices(6)] += N / T
    spread = float(np.sum((r - r_bar) ** 2 / N)) * T / n
    return float(r_bar @ np.linalg.solve(S, r_bar)) + spread, 6 * n


@lru_cache(maxsize=1024)
def median_threshold(k: int, probability: float) -> float:
    """(Z6) x_k: the median of k chi2_4 draws exceeds it with probability 1 - ``probability``."""
    from scipy.special import bdtri  # a real IMU's runs only: a velocity run need not import scipy.special

    q = bdtri((k + 1) // 2 - 1, k, 1.0 - probability)
    return chi2.quantile(4, q)


def flow_rest_statistic(last_ids: np.ndarray, last_pixels: np.ndarray, ids: np.ndarray, pixels: np.ndarray,
                        pixel_var: float) -> tuple[float, np.ndarray]:
    """(Z6) (the median of d_i, the rows of ``ids`` (n,) whose tracks the last frame saw too) of this
    frame's ``pixels`` (n,4) against the last one's; the median nan below ``MIN_TRACKS`` tracks."""
    median, rows = _flow_median(np.ascontiguousarray(last_ids, dtype=np.int64), np.ascontiguousarray(last_pixels),
                                np.ascontiguousarray(ids, dtype=np.int64), np.ascontiguousarray(pixels),
                                float(pixel_var), MIN_TRACKS)
    return median, rows


@jit
def _flow_median(last_ids, last_pixels, ids, pixels, pixel_var, min_tracks):
    """(Z6) :func:`flow_rest_statistic`'s work: the tracks matched by id, d_i, and the ceil(k/2)-th
    smallest of them. Plain loops (a frame's few hundred tracks): numba compiles them in a fraction
    of a second where its sort and search routines take seconds, once after every install."""
    rows = np.empty(ids.size, dtype=np.int64)
    d = np.empty(ids.size)
    k = 0
    for i in range(ids.size):
        for a in range(last_ids.size):
            if last_ids[a] == ids[i]:
                s = 0.0
                for c in range(4):
                    e = pixels[i, c] - last_pixels[a, c]
                    s += e * e
                d[k] = s / (2.0 * pixel_var)
                rows[k] = i
                k += 1
                break
    if k < min_tracks:
        return np.nan, rows[:k]
    return kth_smallest(d[:k], (k + 1) // 2 - 1), rows[:k]  # the median the threshold is made for


def translation_covariance(pixels: np.ndarray, camera: StereoCamera, pixel_var: float) -> np.ndarray | None:
    """(Z8) C_t (3,3): the covariance of the camera's translation between two frames fitted from
    the stereo ``pixels`` (k,4) = [uL vL uR vR] of k tracks at zero motion, each frame's pixels with
    variance ``pixel_var``: the tracks' stereo points s (S2) and J = dz/ds = Ks dpi/dq [I; 0] (S1);
    None when no track has a positive disparity."""
    near = pixels[:, 0] - pixels[:, 2] > 0
    if not near.any():
        return None
    s = camera.triangulate(pixels[near])
    q = np.concatenate([s, np.ones((s.shape[0], 1))], axis=1)
    J = (camera.Ks @ dpi_dq(q))[:, :, :3]
    info = np.einsum("kij,kil->jl", J, J)
    try:
        return 2.0 * pixel_var * np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return None


class ZeroVelocityUpdater:
    """The test (Z6-Z8) and the update (Z9) at each frame of a real IMU's SLAM run; ``interval`` is
    given by the propagation, the frame's tracks by :meth:`step`. ``camera`` and ``cam_T_imu`` (4,4)
    give the velocity's noise (Z8)."""

    def __init__(self, noise: ImuNoiseDensities, gravity: np.ndarray, camera: StereoCamera, cam_T_imu: np.ndarray,
                 pixel_var: float, probability: float) -> None:
        self.noise, self.gravity, self.pixel_var, self.probability = noise, np.asarray(gravity, float), pixel_var, probability
        self.camera = camera
        self.imu_R_cam = np.asarray(cam_T_imu, dtype=float)[:3, :3].T
        self._velocity_gate = chi2.quantile(3, probability)
        self._last: tuple[np.ndarray, np.ndarray] | None = None
        self._interval: tuple[ImuSamples, float, float] | None = None

    def interval(self, imu: ImuSamples, t0: float, t1: float) -> None:
        """The IMU samples of the interval the state was just propagated over."""
        self._interval = (imu, float(t0), float(t1))

    def step(self, state: FilterState, ids: np.ndarray, pixels: np.ndarray, retract) -> bool:
        """Test the interval that ends at this frame (Z6-Z8) and, still, update by v = 0 (Z9) with the
        error model's ``retract(state, dx)`` (J7, W6); returns whether the frame is still."""
        last, self._last = self._last, (ids, pixels)
        interval, self._interval = self._interval, None
        if last is None or interval is None:
            return False
        test, rows = self.test(state, interval, last, ids, pixels)
        if not test.still:
            return False
        H, S = rows
        dx = StateHelper.update_dense(state, H, -state.velocity, S)
        retract(state, dx)
        return True

    def test(self, state: FilterState, interval, last, ids, pixels):
        """(Z6-Z8) the interval's :class:`RestTest`, each test run only when the one before passed, and
        the measurement's (H_v (3,15), S (3,3)) when all were run (else None)."""
        imu, t0, t1 = interval
        median, rows = flow_rest_statistic(*last, ids, pixels, self.pixel_var)
        k = rows.size
        if k < MIN_TRACKS:
            return RestTest(tracks=k), None
        flow = (median, median_threshold(k, self.probability), k)
        if not median <= flow[1]:
            return RestTest(*flow), None
        c = state.core
        s, dof = imu_rest_statistic(imu, t0, t1, state.mu[:3, :3], state.gyro_bias, state.accel_bias,
                                    state.P[:c, :c], self.noise, self.gravity)
        imu_test = (s, chi2.quantile(dof, self.probability) if dof else float("nan"))
        C_t = translation_covariance(pixels[rows], self.camera, self.pixel_var) if s <= imu_test[1] else None
        if C_t is None:
            return RestTest(*flow, *imu_test), None
        R_wc = state.mu[:3, :3] @ self.imu_R_cam
        H = velocity_jacobian(state.velocity, c)
        S = H @ state.P[:c, :c] @ H.T + R_wc @ C_t @ R_wc.T / (t1 - t0) ** 2
        v = state.velocity
        return RestTest(*flow, *imu_test, float(v @ np.linalg.solve(S, v)), self._velocity_gate), (H, S)


@warms_up(only="inertial")
def _warm_up() -> None:
    pixels = np.array([[600.0, 180.0, 560.0, 180.0]] * 6)
    _flow_median(np.arange(6, dtype=np.int64), pixels, np.arange(6, dtype=np.int64), pixels, 0.25, MIN_TRACKS)
