"""The inertial state propagated by every sample of a real IMU: the right-invariant error on SE_2(3).

The project's invariant model (``backend.estimator.invariant``, I1-I8) extended by the velocity
(Barrau & Bonnabel, "The invariant extended Kalman filter as a stable observer", IEEE TAC 2017;
the biases break the group structure only in their own columns). Attitude, velocity, position and
the landmarks are one element of SE_{2+K}(3),

    X = (R, v, p, m_1 .. m_K),   biases b_g, b_a in R^3,

with the error E = X X_hat^-1 = exp(xi) and additive bias errors:

    R = exp(phi^) R_hat,  v = exp(phi^) v_hat + J_l(phi) nu,  p = exp(phi^) p_hat + J_l(phi) rho,
    m_i = exp(phi^) m_hat_i + J_l(phi) zeta_i,  b_g = b_g_hat + db_g,  b_a = b_a_hat + db_a          (J1)

The error state is ``[rho, phi, db_g, nu, db_a, zeta_1 .. zeta_K]``: the pose and the gyro bias
first as in the velocity model (``backend.estimator.layout``), so that the observation (I3), the
landmark initialization (I4) and the world covariances (I6) hold unchanged; :data:`CORE_INERTIAL`
= 15 rows precede the landmarks.

IMU model (``backend.data.inertial``), world frame gravity-aligned, g = [0, 0, -9.81]:

    w_m = w + b_g + n_g,   a_m = R^T (a - g) + b_a + n_a                                          (J2)

Mean over one interval of length dt with constant w = w_m - b_g and f = a_m - b_a (each the mean
of the two samples bounding the interval; samples at frame times are interpolated):

    R+ = R Exp(w dt),   v+ = v + g dt + R J_l(w dt) f dt,   p+ = p + v dt + g dt^2/2 + R N(w dt) f dt^2
    N(theta) = int_0^1 (1 - s) Exp(s theta) ds
             = I/2 + (a - sin a)/a^2 K + (1/2 - (1 - cos a)/a^2) K^2,   a = |theta|, K = theta^/a  (J3)

exact for a constant body rate and specific force (a closed form rather than RK4: exact in the
rotation, no sub-steps, one Exp a sample). Error dynamics, to first order (hats dropped):

    rho' = nu - p^ R (db_g + n_g)
    phi' = -R (db_g + n_g)
    nu'  = g^ phi - v^ R (db_g + n_g) - R (db_a + n_a)
    zeta_i' = -m_i^ R (db_g + n_g) = m_i^ phi'
    db_g' = w_g,   db_a' = w_a                                                                    (J4)

The (rho, phi, nu) block is autonomous (A0 = [[0 0 I], [0 0 0], [0 g^ 0]]: the invariant
property); the estimate enters only through the bias columns and the noise map G.

Discretization over one interval, A and G held at its midpoint's estimate: A is nilpotent (A^4 = 0), so

    Phi = I + A dt + A^2 dt^2/2 + A^3 dt^3/6      exactly, and
    Q = int_0^dt Phi(s) G Qc G^T Phi(s)^T ds,  Qc = diag(sigma_g^2, sigma_a^2, sigma_wg^2, sigma_wa^2) (J5)

(Kalibr's densities squared), with M = G Qc G^T taken to third order in dt like Phi:

    Q = M dt + (A M + M A^T) dt^2/2 + (A^2 M + 2 A M A^T + M A^2T) dt^3/6

(the first terms left out are O(dt^4 |A|^2 |M|): 2e-8 of Q at 200 Hz against the exact integral).
Intervals compose: Phi <- Phi_i Phi, Q <- Phi_i Q Phi_i^T + Q_i.

Landmarks are static, so zeta_i changes by m_i^ times phi's change. With Delta = Phi[phi, :] - E_phi
(3 x 15) and L = [m_1^; ..; m_K^] (3K x 3), for the core c and the landmarks l:

    P_cc <- Phi P_cc Phi^T + Q
    P_cl <- Phi P_cl + (Phi P_cc Delta^T + Q[:, phi]) L^T
    P_ll <- P_ll + L Delta P_cl + (L Delta P_cl)^T + L (Delta P_cc Delta^T + Q[phi, phi]) L^T     (J6)

(old P_cc and P_cl on the right), O(D^2) per frame whatever the IMU's rate.
Correction: X <- exp(dx) X_hat by (J1) with the update dx; biases added.                      (J7)
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from ..compiled import jit, warms_up
from ..data.inertial import ImuNoiseDensities, ImuSamples
from ..geometry import se3
from .invariant import InvariantModel, innovation as invariant_innovation, world_covariances
from .state import FilterState

__all__ = [
    "CORE_INERTIAL", "RHO", "PHI", "BG", "NU", "BA", "STANDARD_GRAVITY",
    "InertialMean", "Propagation", "propagate", "integrate_samples", "interval_knots", "integrate_kernel",
    "propagate_covariance", "InertialTransition",
    "retract_inertial", "InertialStart", "InertialModel",
]

#: Rows of the inertial error state before the landmarks: rho, phi, db_g, nu, db_a (J1)
CORE_INERTIAL = 15
RHO, PHI, BG, NU, BA = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15)
#: The default gravity magnitude (m/s^2): the world's z axis points up, gravity is [0, 0, -g]
STANDARD_GRAVITY = 9.81

@dataclass
class InertialMean:
    """The mean of the inertial state: ``world_T_imu`` (4,4), ``velocity`` (3,) m/s in the world,
    ``gyro_bias`` (3,) rad/s, ``accel_bias`` (3,) m/s^2."""

    world_T_imu: np.ndarray
    velocity: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray

    def copy(self) -> "InertialMean":
        return InertialMean(self.world_T_imu.copy(), self.velocity.copy(), self.gyro_bias.copy(),
                            self.accel_bias.copy())


@dataclass
class Propagation:
    """One frame interval's propagation of the core (J5): ``Phi`` (15,15), ``Q`` (15,15)."""

    Phi: np.ndarray
    Q: np.ndarray


@jit
def _so3_terms(theta):
    """(Exp(theta^), J_l(theta), N(theta)) of (J3), each (3,3); Taylor series below 1e-4 rad."""
    a2 = theta[0] * theta[0] + theta[1] * theta[1] + theta[2] * theta[2]
    a = np.sqrt(a2)
    W = se3.hat3(theta)
    W2 = W @ W
    if a < 1e-4:
        c_exp1, c_exp2 = 1.0 - a2 / 6.0, 0.5 - a2 / 24.0
        c_j1, c_j2 = 0.5 - a2 / 24.0, 1.0 / 6.0 - a2 / 120.0
        c_n1, c_n2 = 1.0 / 6.0 - a2 / 120.0, 1.0 / 24.0 - a2 / 720.0
    else:
        s, c = np.sin(a), np.cos(a)
        c_exp1, c_exp2 = s / a, (1.0 - c) / a2
        c_j1, c_j2 = (1.0 - c) / a2, (a - s) / (a2 * a)
        c_n1, c_n2 = (a - s) / (a2 * a), (0.5 - (1.0 - c) / a2) / a2
    E = np.eye(3) + c_exp1 * W + c_exp2 * W2
    J = np.eye(3) + c_j1 * W + c_j2 * W2
    N = 0.5 * np.eye(3) + c_n1 * W + c_n2 * W2
    return E, J, N


@jit
def _error_matrices(R, v, p, gravity):
    """(J4) A (15,15) and G (15,12) at the estimate (R, v, p); noise order [n_g, n_a, w_g, w_a]."""
    A = np.zeros((15, 15))
    G = np.zeros((15, 12))
    pR = se3.hat3(p) @ R
    vR = se3.hat3(v) @ R
    gh = se3.hat3(gravity)
    for i in range(3):
        A[i, 9 + i] = 1.0  # rho' = nu
        for j in range(3):
            A[i, 6 + j] = -pR[i, j]
            A[3 + i, 6 + j] = -R[i, j]
            A[9 + i, 3 + j] = gh[i, j]
            A[9 + i, 6 + j] = -vR[i, j]
            A[9 + i, 12 + j] = -R[i, j]
            G[i, j] = -pR[i, j]
            G[3 + i, j] = -R[i, j]
            G[9 + i, j] = -vR[i, j]
            G[9 + i, 3 + j] = -R[i, j]
        G[6 + i, 6 + i] = 1.0
        G[12 + i, 9 + i] = 1.0
    return A, G


@jit
def integrate_kernel(R, v, p, bg, ba, times, acc, gyr, gravity, qc, covariance=True):
    """(J3) and (J5) over the knots ``times`` (n,) with samples ``acc``, ``gyr`` (n,3) at them:
    returns (R, v, p, Phi (15,15), Q (15,15)) at the last knot. ``qc`` (12,): the continuous noise
    variances [sigma_g^2 x3, sigma_a^2 x3, sigma_wg^2 x3, sigma_wa^2 x3]; ``covariance`` False: the
    mean alone (Phi = I, Q = 0)."""
    Phi = np.eye(15)
    Q = np.zeros((15, 15))
    R = R.copy()
    v = v.copy()
    p = p.copy()
    for k in range(times.size - 1):
        dt = times[k + 1] - times[k]
        w = 0.5 * (gyr[k] + gyr[k + 1]) - bg
        f = 0.5 * (acc[k] + acc[k + 1]) - ba
        if covariance:
            # A and G at the interval's midpoint (second order in dt; J3 over dt/2)
            Eh, Jh, Nh = _so3_terms(w * (0.5 * dt))
            h = 0.5 * dt
            v_mid = v + gravity * h + (R @ (Jh @ f)) * h
            p_mid = p + v * h + 0.5 * gravity * h * h + (R @ (Nh @ f)) * (h * h)
            A, G = _error_matrices(R @ Eh, v_mid, p_mid, gravity)
            GQG = np.zeros((15, 15))
            for i in range(15):
                for j in range(15):
                    s = 0.0
                    for t in range(12):
                        s += G[i, t] * qc[t] * G[j, t]
                    GQG[i, j] = s
            A2 = A @ A
            Phi_k = np.eye(15) + A * dt + A2 * (dt * dt / 2.0) + (A2 @ A) * (dt * dt * dt / 6.0)
            AM = A @ GQG
            A2M = A @ AM
            AMA = AM @ A.T
            Qk = GQG * dt + (AM + AM.T) * (dt * dt / 2.0) + (A2M + A2M.T + 2.0 * AMA) * (dt * dt * dt / 6.0)
            Phi = Phi_k @ Phi
            Q = Phi_k @ Q @ Phi_k.T + Qk
        # the mean (J3)
        E, J, N = _so3_terms(w * dt)
        RJf = R @ (J @ f)
        RNf = R @ (N @ f)
        for i in range(3):
            p[i] = p[i] + v[i] * dt + 0.5 * gravity[i] * dt * dt + RNf[i] * dt * dt
            v[i] = v[i] + gravity[i] * dt + RJf[i] * dt
        R = R @ E
    for i in range(15):  # exact symmetry
        for j in range(i):
            s = 0.5 * (Q[i, j] + Q[j, i])
            Q[i, j] = s
            Q[j, i] = s
    return R, v, p, Phi, Q


def _at(t: np.ndarray, x: np.ndarray, when: float) -> np.ndarray:
    """The samples x (L,3) stamped t (L,) linearly interpolated at ``when`` (held at the record's ends)."""
    j = int(np.searchsorted(t, when))
    if j <= 0:
        return x[0]
    if j >= t.size:
        return x[-1]
    a = (when - t[j - 1]) / (t[j] - t[j - 1])
    return (1.0 - a) * x[j - 1] + a * x[j]


#: The last call's (a weak reference to its samples, t0, t1, its knots), set in one assignment: a
#: run's filter and its dead reckoning ask for the same interval, one after the other
_LAST_KNOTS: list = [None]


def interval_knots(imu: ImuSamples, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The knots of one frame interval [t0, t1]: t0, every sample stamped strictly inside, t1, with the
    samples linearly interpolated at t0 and t1 (held at the record's ends). Returns times (n,),
    specific force (n,3), rate (n,3)."""
    last = _LAST_KNOTS[0]
    if last is not None and last[0]() is imu and last[1] == t0 and last[2] == t1:
        return last[3]
    t = imu.time_stamps
    lo, hi = int(np.searchsorted(t, t0, side="right")), int(np.searchsorted(t, t1, side="left"))
    times = np.empty(hi - lo + 2)
    times[0], times[1:-1], times[-1] = t0, t[lo:hi], t1
    out = []
    for x in (imu.linear_acceleration, imu.angular_velocity):
        knots = np.empty((times.size, 3))
        knots[0], knots[1:-1], knots[-1] = _at(t, x, t0), x[lo:hi], _at(t, x, t1)
        out.append(knots)
    _LAST_KNOTS[0] = (weakref.ref(imu), t0, t1, (times, out[0], out[1]))
    return times, out[0], out[1]


def continuous_variances(noise: ImuNoiseDensities) -> np.ndarray:
    """Qc (12,) of (J5) from Kalibr's densities."""
    return np.repeat(np.array([noise.gyroscope_noise_density, noise.accelerometer_noise_density,
                               noise.gyroscope_random_walk, noise.accelerometer_random_walk]) ** 2, 3)


def propagate(mean: InertialMean, imu: ImuSamples, t0: float, t1: float, noise: ImuNoiseDensities | None,
              gravity: np.ndarray) -> tuple[InertialMean, Propagation | None]:
    """The mean at t1 from the mean at t0 by every IMU sample between (J3), and the core's transition
    and noise over the interval (J5); ``noise`` None: the mean alone (the Propagation is None)."""
    times, acc, gyr = interval_knots(imu, t0, t1)
    T = mean.world_T_imu
    qc = continuous_variances(noise) if noise is not None else np.zeros(12)
    # contiguous copies: the signature the warm-up compiled (a view of T would be another one, compiled mid-run)
    R, v, p, Phi, Q = integrate_kernel(np.ascontiguousarray(T[:3, :3]), mean.velocity, np.ascontiguousarray(T[:3, 3]),
                                       mean.gyro_bias, mean.accel_bias,
                                       times, acc, gyr, np.asarray(gravity, dtype=float), qc,
                                       noise is not None)
    out = mean.copy()
    out.world_T_imu = np.eye(4)
    out.world_T_imu[:3, :3] = R
    out.world_T_imu[:3, 3] = p
    out.velocity = v
    return out, (Propagation(Phi, Q) if noise is not None else None)


def integrate_samples(imu: ImuSamples, times: np.ndarray,
                      gyro_bias: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(J3) the mean alone from the identity at ``times[0]`` with zero velocity, at each of ``times``
    (K,): (R (K,3,3), p (K,3), v (K,3)) in the first frame's axes, of the samples' own motion (no
    gravity, no accelerometer bias; the gyro bias removed)."""
    zero = np.zeros(3)
    ba = g = zero
    R, v, p = np.eye(3), zero, zero
    Rs, ps, vs = [R], [p], [v]
    for a, b in zip(times[:-1], times[1:]):
        knots, acc, gyr = interval_knots(imu, a, b)
        R, v, p, _, _ = integrate_kernel(R, v, p, gyro_bias, ba, knots, acc, gyr, g, np.zeros(12), False)
        Rs.append(R)
        ps.append(p)
        vs.append(v)
    return np.array(Rs), np.array(ps), np.array(vs)


def propagate_covariance(P: np.ndarray, prop: Propagation, points: np.ndarray) -> np.ndarray:
    """(J6): the covariance (D,D), D = 15 + 3K, after the interval, for the world landmarks ``points``
    (K,3) (static during it). Returns a new exactly symmetric matrix."""
    Phi, Q = prop.Phi, prop.Q
    c = CORE_INERTIAL
    Pcc, Pcl, Pll = P[:c, :c], P[:c, c:], P[c:, c:]
    out = np.empty_like(P)
    out[:c, :c] = Phi @ Pcc @ Phi.T + Q
    if points.shape[0]:
        Delta = Phi[PHI].copy()
        Delta[:, PHI] -= np.eye(3)
        L = se3.hat3(points).reshape(-1, 3)  # (3K,3): the m_i^ stacked
        cross = Phi @ Pcl + (Phi @ Pcc @ Delta.T + Q[:, PHI]) @ L.T
        out[:c, c:] = cross
        out[c:, :c] = cross.T
        LU = L @ (Delta @ Pcl)
        M = Delta @ Pcc @ Delta.T + Q[PHI, PHI]
        out[c:, c:] = Pll + LU + LU.T + L @ M @ L.T
    return 0.5 * (out + out.T)


@dataclass
class InertialTransition:
    """(J6) for one frame interval: :func:`propagate_covariance` with the interval's ``prop`` and the
    world landmarks ``points`` (K,3)."""

    prop: Propagation
    points: np.ndarray

    def apply(self, P: np.ndarray) -> np.ndarray:
        return propagate_covariance(P, self.prop, self.points)


def retract_inertial(mean: InertialMean, points: np.ndarray, dx: np.ndarray) -> InertialMean:
    """(J7): X <- exp(dx) X_hat for dx = [rho, phi, db_g, nu, db_a, zeta_1 .. zeta_K]; the world
    ``points`` (K,3) move in place."""
    E, J = se3.exp_so3_and_left_jacobian(dx[PHI])
    out = mean.copy()
    T = mean.world_T_imu
    out.world_T_imu = np.eye(4)
    out.world_T_imu[:3, :3] = E @ T[:3, :3]
    out.world_T_imu[:3, 3] = E @ T[:3, 3] + J @ dx[RHO]
    out.velocity = E @ mean.velocity + J @ dx[NU]
    out.gyro_bias = mean.gyro_bias + dx[BG]
    out.accel_bias = mean.accel_bias + dx[BA]
    if points.shape[0]:
        z = dx[CORE_INERTIAL:].reshape(-1, 3)
        points[...] = points @ E.T + z @ J.T
    return out


@dataclass
class InertialStart:
    """What the filter starts from: the ``mean`` at the first frame, the core's ``covariance`` (15,15)
    of (J1), the IMU's ``noise`` densities and the ``gravity`` vector (3,) of the world frame."""

    mean: InertialMean
    covariance: np.ndarray
    noise: ImuNoiseDensities
    gravity: np.ndarray


class InertialModel(InvariantModel):
    """The right-invariant error on SE_{2+K}(3) with biases (module docstring): the observation (I3),
    the landmark initialization (I4) and the world covariances (I6) of the invariant model with the
    landmark slots after the 15 core rows; the prediction by every IMU sample (:meth:`propagate`)."""

    freezes = False

    def __init__(self, camera, imu_T_cam, start: InertialStart, estimate_pose: bool) -> None:
        super().__init__(camera, imu_T_cam, "xyz", estimate_pose, True)
        self.noise = start.noise
        self.gravity = np.asarray(start.gravity, dtype=float)

    def predict(self, state, twist, q, dt, bias_walk_var) -> None:
        raise TypeError("the inertial state moves by IMU samples: VisualInertialEKF.propagate(imu, t0, t1)")

    def propagate(self, state: FilterState, imu: ImuSamples, t0: float, t1: float) -> InertialTransition | None:
        """The mean by (J3) from t0 to t1; returns P's prediction (J5, J6), None with the pose held
        fixed (mapping: the mean only)."""
        mean = InertialMean(state.mu, state.velocity, state.gyro_bias, state.accel_bias)
        new, prop = propagate(mean, imu, t0, t1, self.noise if self.estimate_pose else None, self.gravity)
        state.mu, state.velocity = new.world_T_imu, new.velocity
        return InertialTransition(prop, state.theta) if prop is not None else None

    def correct(self, state: FilterState, dx: np.ndarray) -> None:
        mean = retract_inertial(InertialMean(state.mu, state.velocity, state.gyro_bias, state.accel_bias),
                                state.theta, dx)
        state.mu, state.velocity = mean.world_T_imu, mean.velocity
        state.gyro_bias, state.accel_bias = mean.gyro_bias, mean.accel_bias


@warms_up(only="inertial")
def _warm_up() -> None:
    t = np.array([0.0, 0.005, 0.01])
    acc = np.tile([0.0, 0.0, 9.81], (3, 1))
    for covariance in (True, False):
        integrate_kernel(np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), t, acc, np.zeros((3, 3)),
                         np.array([0.0, 0.0, -9.81]), np.ones(12) * 1e-6, covariance)
    # the invariant kernels with the landmark slots after the 15 core rows
    k = 2
    P = np.eye(CORE_INERTIAL + 3 * k)
    slots = np.arange(k, dtype=np.int64)
    points = np.ones((k, 3)) + 5.0
    pixels = np.array([[600.0, 180.0, 560.0, 180.0]] * k)
    invariant_innovation(P, points, slots, np.eye(4), np.eye(4), 700.0, 700.0, 600.0, 180.0, 0.5, pixels, 1.0, True,
                         CORE_INERTIAL)
    world_covariances(P, slots, points, CORE_INERTIAL)
    from .covariance import gather_landmarks
    gather_landmarks(P, np.arange(1, dtype=np.int64), CORE_INERTIAL)
