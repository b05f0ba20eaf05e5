"""The right-invariant error model of the pose and the world-xyz landmarks (the default).

Barrau & Bonnabel, "An EKF-SLAM algorithm with consistency properties" (arXiv 1510.06263, 2015)
and "The invariant extended Kalman filter as a stable observer" (IEEE TAC 2017). Pose and
landmarks together are one element of SE_{K+1}(3),

    X = (R, p, m_1 .. m_K),   X1 X2 = (R1 R2, R1 p2 + p1, R1 m2_i + m1_i),

and the error is E = X X_hat^-1 = exp(xi) with xi = (rho, phi, zeta_1 .. zeta_K):

    R = exp(phi^) R_hat,  p = exp(phi^) p_hat + J_l(phi) rho,  m_i = exp(phi^) m_hat_i + J_l(phi) zeta_i   (I1)

so to first order  dp = rho + phi x p_hat,  dm_i = zeta_i + phi x m_hat_i  (a world-frame error
that moves the landmarks with the pose's rotation). With body-frame velocity inputs the error
does not depend on the estimate:

- Prediction  T_{k+1} = T_k exp(tau (u - b - n)^),  landmarks static:

      xi_{k+1} = xi_k + G (J_r(tau u_hat) tau (-[0; db] - n)),   G = Ad_X(X_hat_{k+1}) on pose vectors   (I2)

  where Ad_X of a pose vector (rho, phi) is  (R rho + p^ R phi, R phi; m_i^ R phi for each i).
  The pose-pose Jacobian is the identity: the error is autonomous; noise and bias enter through G.
  (:func:`predict_step`, :class:`InvariantTransition`, :func:`predict_covariance_inplace`)
- Observation  s = T^-1 m = T_hat^-1 E^-1 m ~ T_hat^-1 (m_hat + zeta - rho):

      dz/drho = -M,   dz/dphi = 0,   dz/dzeta = M,   M = Ks dpi/dq cam_T_imu T_hat^-1 [I; 0]        (I3)

  No rotation column: a rotation of the whole world is unobservable for every estimate, which is
  why this filter needs no first-estimate Jacobians. (:func:`observe`, :func:`innovation`)
- Landmark initialization  m = T g(z):  zeta = rho + R_hat imu_R_cam dg/dz dz  (no phi column).   (I4)
  (:func:`initialize`; ``StateHelper.augment`` applies A1)
- Correction  X_hat <- exp(dx) X_hat, i.e. (I1) with (rho, phi, zeta) = dx.                       (I5)
  (:func:`retract_inplace`)
- World covariance of a landmark:  dm = zeta - m_hat^ phi  (:func:`world_covariances`).          (I6)
- Body-frame (right) pose error  xi_body = Ad(T_hat^-1) (rho, phi)  (:func:`body_pose_covariance`). (I7)
- A frozen step (the frame repeats the previous one; the content moved with the camera): the pose
  is predicted by (I2) while each landmark keeps its body-frame point s = T^-1 m. To first order
  s = s_hat + R_hat^T (zeta - rho) (the rotation error cancels), so s_k = s_k-1 gives

      zeta_k = dR zeta_k-1 + (I - dR) rho_k-1 + (rho_k - rho_k-1),   dR = R_hat_k R_hat_k-1^T,
      m_hat_k = T_hat_k T_hat_k-1^-1 m_hat_k-1                                                     (I8)

  with rho_k - rho_k-1 the translation rows of (I2)'s bias and noise terms; P <- F P F^T + G Q G^T
  applied as a row map twice (O(D^2)). (:func:`predict_frozen`, :class:`FrozenTransition`)

The model moves the mean; P's prediction is a transition (:class:`InvariantTransition`,
:class:`FrozenTransition`) that ``StateHelper.propagate`` applies. The prediction, the
innovation, the initialization and the correction are each one compiled call.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..compiled import jit, warms_up
from ..geometry import se3
from ..geometry.camera import triangulate_rows
from .covariance import mirror_lower_inplace
from .layout import CORE, LEVER_ROWS, POSE, SQRT_HALF, landmark_row
from .lever_arm import SensitivityTransition, twist_columns
from .linalg import add_product_lower
from .model import ErrorModel
from .state_helper import NewLandmarks
from .update import Innovation, innovation_covariance


# ---------------------------------------------------------------- prediction (I2)
@jit
def predict_covariance_inplace(P, G_pose, R_phi, points, q, dt, bias, bias_walk_var, lever, tau_omega):
    """(I2) P <- F P F^T + G Q G^T  with  F = I + g E_c^T,  g = G [E_b, E_r]  on the constant rows c.

    G (D,6) maps a body-twist error to the error state: pose rows ``G_pose`` (6,6), landmark rows
    m_i^ R_phi (3,6) for the world points ``points`` (K,3); q (6,) = the twist noise sigmas times
    tau. The constant rows c: the gyro bias's 6..8 where ``bias`` (E_b = -tau [0; I]) and the
    residual lever arm's ``lever`` .. + 2 where ``lever`` >= 0 (E_r = -[(tau omega)^; 0] of V1,
    ``tau_omega`` (3,) the step's rotation). With C = P[:, c] and P_cc = P[c, c], F P F^T = P + g C^T +
    C g^T + g P_cc g^T, so P += Z X^T with X = [g, C, G diag(q)] and Z = [g P_cc + C, g, G diag(q)]:
    one BLAS product, added on the lower triangle and mirrored (no constant row: F = I and
    X = G diag(q)). The bias takes a random walk of variance ``bias_walk_var`` a step; the lever arm none.
    """
    D = P.shape[0]
    K = points.shape[0]
    core = D - 3 * K  # CORE, + 1 with the disparity offset (O1), + 3 with the lever arm (V1)
    nb = 3 if bias else 0
    nc = nb + (3 if lever >= 0 else 0)
    w = 2 * nc + 6
    X = np.zeros((D, w))
    Z = np.zeros((D, w))
    G = X[:, w - 6:]
    se3.put_block(G, 0, 0, G_pose)
    for i in range(K):
        W = se3.hat3(points[i])
        r = landmark_row(core, i)
        for a in range(3):  # rows of m_i^ R_phi
            for c in range(6):
                G[r + a, c] = W[a, 0] * R_phi[0, c] + W[a, 1] * R_phi[1, c] + W[a, 2] * R_phi[2, c]
    if nc:
        cols = np.empty(nc, dtype=np.int64)
        for c in range(nb):
            cols[c] = 6 + c
        for c in range(nc - nb):
            cols[nb + c] = lever + c
        Wo = se3.hat3(tau_omega)
        for i in range(D):
            for c in range(nb):
                X[i, c] = -dt * G[i, 3 + c]  # g = G E_b
            for c in range(nc - nb):
                X[i, nb + c] = -(G[i, 0] * Wo[0, c] + G[i, 1] * Wo[1, c] + G[i, 2] * Wo[2, c])  # g = G E_r
            for c in range(nc):
                X[i, nc + c] = P[i, cols[c]]  # C
        for i in range(D):
            for b in range(nc):
                s = X[i, nc + b]
                for a in range(nc):
                    s += X[i, a] * P[cols[a], cols[b]]
                Z[i, b] = s
                Z[i, nc + b] = X[i, b]
    for i in range(D):
        for c in range(6):
            G[i, c] *= q[c]
            Z[i, w - 6 + c] = G[i, c]
    add_product_lower(P, Z, X)
    mirror_lower_inplace(P)
    if bias:
        for c in range(3):
            P[6 + c, 6 + c] += bias_walk_var


@jit
def predict_step(world_T_imu, twist):
    """One prediction's mean and noise map: mu_next = mu exp(tau u^) (P1 of
    ``backend.estimator.propagation``) and G_pose = Ad(mu_next) J_r(twist) of (I2); its rotation
    rows R_phi = G_pose[3:6]. Returns (mu_next (4,4), G_pose (6,6))."""
    step, J_r = se3.exp_se3_and_right_jacobian(twist)
    mu = np.empty((4, 4))
    for i in range(4):
        for j in range(4):
            mu[i, j] = world_T_imu[i, 0] * step[0, j] + world_T_imu[i, 1] * step[1, j] \
                + world_T_imu[i, 2] * step[2, j] + world_T_imu[i, 3] * step[3, j]
    A = se3.adjoint(mu)
    G_pose = np.empty((6, 6))
    for i in range(6):
        for j in range(6):
            s = 0.0
            for k in range(6):
                s += A[i, k] * J_r[k, j]
            G_pose[i, j] = s
    return mu, G_pose


@dataclass
class InvariantTransition:
    """(I2) for one step: :func:`predict_covariance_inplace` with the noise map ``G_pose`` (6,6) at
    the propagated pose, the world ``points`` (K,3), twist noise ``q`` (6,), ``dt``, the bias in the
    state or not and its walk's variance; the lever arm's first row (-1: not in the state) and the
    step's rotation tau omega (3,) for its columns (V1)."""

    G_pose: np.ndarray
    points: np.ndarray
    q: np.ndarray
    dt: float
    bias: bool
    bias_walk_var: float
    lever: int = -1
    tau_omega: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def apply(self, P: np.ndarray) -> np.ndarray:
        predict_covariance_inplace(P, self.G_pose, np.ascontiguousarray(self.G_pose[3:6]), self.points, self.q,
                                   self.dt, self.bias, self.bias_walk_var, self.lever,
                                   np.ascontiguousarray(self.tau_omega, dtype=np.float64))
        return P


@dataclass
class FrozenTransition:
    """(I8) for one frozen step: P <- F P F^T + N N^T with F the row map of (I8) (``dR``, the columns
    ``g`` (6,c) of the pose rows on the constant rows ``cols`` (c,): the bias's, the lever arm's of V1)
    and N the noise map (``G`` (6,6) scaled by ``q`` on the pose and on every landmark's translation
    rows), and the bias walk; the landmark rows start at ``core``."""

    dR: np.ndarray
    g: np.ndarray
    G: np.ndarray
    q: np.ndarray
    bias: bool
    bias_walk_var: float
    core: int = CORE
    cols: np.ndarray = field(default_factory=lambda: np.arange(6, 9))

    def apply(self, P: np.ndarray) -> np.ndarray:
        D = P.shape[0]
        core = self.core
        K = (D - core) // 3
        dR, g, cols = self.dR, self.g, self.cols
        I_dR = np.eye(3) - dR

        def rows(M: np.ndarray) -> np.ndarray:
            """F M for the linear map F of (I8) on the rows of M (D, n)."""
            out = M.copy()
            out[POSE] += g @ M[cols]
            if K:
                lm = M[core:].reshape(K, 3, -1)
                out[core:] = (np.einsum("ab,kbn->kan", dR, lm) + (I_dR @ M[0:3] + g[0:3] @ M[cols])[None]).reshape(3 * K, -1)
            return out

        FP = rows(P)
        new = rows(np.ascontiguousarray(FP.T))
        N = np.zeros((D, 6))
        N[POSE] = self.G * self.q[None, :]
        if K:
            N[core:] = np.tile(self.G[0:3] * self.q[None, :], (K, 1))
        new += N @ N.T
        if self.bias:
            new[np.arange(6, 9), np.arange(6, 9)] += self.bias_walk_var
        P[...] = 0.5 * (new + new.T)
        return P


def predict_frozen(world_T_imu: np.ndarray, points: np.ndarray, twist: np.ndarray, q: np.ndarray, dt: float,
                   bias: bool, bias_walk_var: float, imu_weight: np.ndarray | None = None, core: int = CORE,
                   lever: int = -1, lever_considered: bool = False, rotation: bool = False):
    """(I8) one frozen step: returns (mu_next = mu exp(twist^), P's transition); the world
    ``points`` (K,3) move in place with the body. ``q`` (6,): the twist's noise sigmas;
    ``imu_weight`` (6,): the share of each axis of the twist that came from the IMU (1: all; less
    when the twist fuses another prediction), scaling the bias's columns (its rotation) and the
    lever arm's (V1, its translation; ``lever``: its first row, -1 where not in the state). The
    transition is a :class:`FrozenTransition`, with the lever arm's columns where it is estimated and
    wrapped in its sensitivity's where it is ``lever_considered`` (V2; with ``rotation``, also the
    samples' frame rotation's, V4)."""
    mu = world_T_imu @ se3.exp_se3(twist)
    G = se3.adjoint(mu) @ se3.right_jacobian_se3(twist)  # (6,6) body twist error -> (rho, phi)
    weight = np.ones(6) if imu_weight is None else np.asarray(imu_weight, dtype=float)
    g = -dt * G[:, 3:6] * weight[None, 3:6] if bias else np.zeros((6, 3))
    cols = np.arange(6, 9)
    g_lever = G @ twist_columns(twist, weight, rotation) if lever >= 0 else None
    if lever >= 0 and not lever_considered:
        g = np.concatenate([g, g_lever], axis=1)
        cols = np.r_[cols, lever:lever + LEVER_ROWS]
    dR = mu[:3, :3] @ world_T_imu[:3, :3].T
    if points.shape[0]:
        step = mu @ se3.inverse(world_T_imu)
        points[...] = points @ step[:3, :3].T + step[:3, 3]
    transition = FrozenTransition(dR, g, G, np.asarray(q, dtype=float), bias, bias_walk_var, core, cols)
    if lever >= 0 and lever_considered:
        return mu, SensitivityTransition(transition, lever, g_lever, core)
    return mu, transition


# ---------------------------------------------------------------- observation (I3, U1)
@jit
def observe(points, cam_T_world, fx, fy, cx, cy, baseline, pixels):
    """(I3) in the 3-row form (U1) for world points (k,3) seen at ``pixels`` (k,4) = [uL vL uR vR].

    q = cam_T_world m (depth z), z_hat = Ks pi(q); M = dz/dm = dpi-rows @ cam_R_world;
    rows [uL, (vL + vR)/sqrt 2, uR]: H_m = M rows, H_x = [-M, 0] (no rotation column).
    Returns residual (k,3), off_row (k,) = (r_vL - r_vR)/sqrt 2, H_x (3k,6), H_m (k,3,3) and
    in_front (k,) = z > 0.1 (the others get placeholder rows and are gated out by the caller).
    """
    k = points.shape[0]
    residual = np.empty((k, 3))
    off_row = np.empty(k)
    H_x = np.zeros((3 * k, 6))
    H_m = np.empty((k, 3, 3))
    in_front = np.empty(k, dtype=np.bool_)
    R = cam_T_world[:3, :3]
    fxb = fx * baseline
    for i in range(k):
        qx = R[0, 0] * points[i, 0] + R[0, 1] * points[i, 1] + R[0, 2] * points[i, 2] + cam_T_world[0, 3]
        qy = R[1, 0] * points[i, 0] + R[1, 1] * points[i, 1] + R[1, 2] * points[i, 2] + cam_T_world[1, 3]
        qz = R[2, 0] * points[i, 0] + R[2, 1] * points[i, 1] + R[2, 2] * points[i, 2] + cam_T_world[2, 3]
        in_front[i] = qz > 0.1
        if not in_front[i]:
            qz = 1.0
        iz = 1.0 / qz
        uL = fx * qx * iz + cx
        v = fy * qy * iz + cy
        uR = uL - fxb * iz
        residual[i, 0] = pixels[i, 0] - uL
        residual[i, 1] = ((pixels[i, 1] - v) + (pixels[i, 3] - v)) * SQRT_HALF
        residual[i, 2] = pixels[i, 2] - uR
        off_row[i] = (pixels[i, 1] - pixels[i, 3]) * SQRT_HALF
        # d(pixel row)/d(q_cam) for uL, v (times sqrt 2 for the summed row), uR
        dq = np.empty((3, 3))
        dq[0, 0], dq[0, 1], dq[0, 2] = fx * iz, 0.0, -fx * qx * iz * iz
        s2 = 2.0 * SQRT_HALF
        dq[1, 0], dq[1, 1], dq[1, 2] = 0.0, s2 * fy * iz, -s2 * fy * qy * iz * iz
        dq[2, 0], dq[2, 1], dq[2, 2] = fx * iz, 0.0, -fx * (qx - baseline) * iz * iz
        for a in range(3):
            for b in range(3):
                s = dq[a, 0] * R[0, b] + dq[a, 1] * R[1, b] + dq[a, 2] * R[2, b]
                H_m[i, a, b] = s
                H_x[3 * i + a, b] = -s
    return residual, off_row, H_x, H_m, in_front


@jit
def innovation(P, theta, slots, world_T_imu, cam_T_imu, fx, fy, cx, cy, baseline, pixels, pixel_var, pose, core=CORE):
    """The prior innovation in one call: :func:`observe` of the landmarks ``slots`` (world points
    theta[slots]) from cam_T_world = cam_T_imu world_T_imu^-1, then the products H P and S of
    ``backend.estimator.update``; H_x = 0 when ``pose`` is False (poses held fixed). Returns
    (residual, off_row, H_x (3k,6), H_m, H P, S, NIS, in_front)."""
    cam_T_world = se3.small_matmul(cam_T_imu, se3.inverse(world_T_imu))
    points = np.empty((slots.size, 3))
    for i in range(slots.size):
        for a in range(3):
            points[i, a] = theta[slots[i], a]
    residual, off_row, H_x, H_m, in_front = observe(points, cam_T_world, fx, fy, cx, cy, baseline, pixels)
    if not pose:
        H_x[:] = 0.0
    HP, S, nis = innovation_covariance(P, H_x, H_m, slots, pixel_var, residual, off_row, core)
    return residual, off_row, H_x, H_m, HP, S, nis, in_front


# ---------------------------------------------------------------- initialization (I4)
@jit
def initialize(pixels, world_T_cam, fx, fy, cx, cy, baseline, sigma, pose):
    """New world-xyz landmarks from stereo pixels (n,4), in one call: m = world_T_cam triangulate(z)
    (world_T_cam (4,4) = world_T_imu imu_T_cam; the unscented mean for sigma > 0, S3 of
    ``backend.geometry.camera``), J_z = world_R_cam d triangulate/dz and (I4) J_xi = [I 0] (zero
    when ``pose`` is False: poses held fixed). Returns (m (n,3), J_xi (3n,6), J_z (n,3,4)) for (A1).
    The caller multiplies world_T_cam with numpy (a matrix product in a kernel compiles numba's
    BLAS call, about 0.5 s, for this one product)."""
    n = pixels.shape[0]
    p_cam, dp_dz = triangulate_rows(pixels, fx, fy, cx, cy, baseline, sigma)
    points = np.empty((n, 3))
    J_z = np.empty((n, 3, 4))
    J_xi = np.zeros((3 * n, 6))
    for i in range(n):
        for a in range(3):
            points[i, a] = (world_T_cam[a, 0] * p_cam[i, 0] + world_T_cam[a, 1] * p_cam[i, 1]
                            + world_T_cam[a, 2] * p_cam[i, 2] + world_T_cam[a, 3])
            for t in range(4):
                J_z[i, a, t] = (world_T_cam[a, 0] * dp_dz[i, 0, t] + world_T_cam[a, 1] * dp_dz[i, 1, t]
                                + world_T_cam[a, 2] * dp_dz[i, 2, t])
            if pose:
                J_xi[3 * i + a, a] = 1.0
    return points, J_xi, J_z


# ---------------------------------------------------------------- correction (I5)
@jit
def retract_inplace(world_T_imu, points, dx, core=CORE):
    """(I5) exp(dx) X_hat: returns the new pose exp(dx_pose^) world_T_imu and moves the world points
    (K,3) in place, m <- R_d m + J_l zeta (the state dx = [rho, phi, bias (3), zeta_1 .. zeta_K])."""
    E, J = se3.exp_se3_and_left_jacobian(dx[:6])
    pose = np.empty((4, 4))
    for i in range(4):
        for j in range(4):
            pose[i, j] = E[i, 0] * world_T_imu[0, j] + E[i, 1] * world_T_imu[1, j] + E[i, 2] * world_T_imu[2, j] \
                + E[i, 3] * world_T_imu[3, j]
    for k in range(points.shape[0]):
        r = landmark_row(core, k)
        z = dx[r:r + 3]
        x0, x1, x2 = points[k, 0], points[k, 1], points[k, 2]
        for i in range(3):
            points[k, i] = (E[i, 0] * x0 + E[i, 1] * x1 + E[i, 2] * x2
                            + J[i, 0] * z[0] + J[i, 1] * z[1] + J[i, 2] * z[2])
    return pose


# ---------------------------------------------------------------- covariances in the world and body frames
@jit
def world_covariances(P, slots, points, core=CORE):
    """(I6) covariances (k,3,3) of the world positions ``points`` (k,3) of the landmarks ``slots``:
    dm = zeta - m^ phi, so Cov(m) = A P_phiphi A^T + A P_phi,zeta + (A P_phi,zeta)^T + P_zeta
    with A = -m^ (symmetrized)."""
    k = slots.size
    out = np.empty((k, 3, 3))
    for i in range(k):
        s = landmark_row(core, slots[i])
        for a in range(3):
            for b in range(3):
                out[i, a, b] = P[s + a, s + b]
        A = se3.hat3(-points[i])
        AP = np.zeros((3, 3))  # A P_phiphi
        AX = np.zeros((3, 3))  # A P_phi,zeta
        for a in range(3):
            for b in range(3):
                for t in range(3):
                    AP[a, b] += A[a, t] * P[3 + t, 3 + b]
                    AX[a, b] += A[a, t] * P[3 + t, s + b]
        for a in range(3):
            for b in range(3):
                v = out[i, a, b] + AX[a, b] + AX[b, a]
                for t in range(3):
                    v += AP[a, t] * A[b, t]
                out[i, a, b] = v
        for a in range(3):
            for b in range(a):
                v = 0.5 * (out[i, a, b] + out[i, b, a])
                out[i, a, b] = v
                out[i, b, a] = v
    return out


def body_pose_covariance(world_T_imu: np.ndarray, P_pose: np.ndarray) -> np.ndarray:
    """(I7): the covariance (..., 6, 6) of the right perturbation world_T_imu = mu exp(xi^) from that
    of the left one ``P_pose`` (..., 6, 6), ``world_T_imu`` (..., 4, 4) (one pose or N):
    Ad(mu^-1) P Ad(mu^-1)^T, Ad(mu^-1) = [[R^T, (-R^T p)^ R^T], [0, R^T]]."""
    R_inv = np.swapaxes(world_T_imu[..., :3, :3], -1, -2)
    p_inv = -np.einsum("...ij,...j->...i", R_inv, world_T_imu[..., :3, 3])
    A = np.zeros(world_T_imu.shape[:-2] + (6, 6))
    A[..., :3, :3] = A[..., 3:, 3:] = R_inv
    A[..., :3, 3:] = se3.hat3(p_inv) @ R_inv
    out = A @ P_pose @ np.swapaxes(A, -1, -2)
    return 0.5 * (out + np.swapaxes(out, -1, -2))


# ---------------------------------------------------------------- the model
class InvariantModel(ErrorModel):
    """The right-invariant error (module docstring); world-xyz landmarks only."""

    freezes = True

    def predict_frozen(self, state, twist, q, dt, bias_walk_var, imu_weight=None) -> FrozenTransition:
        if not self.estimate_pose:  # mapping: the poses are held, the landmarks move with them
            q = np.zeros(6)
        lever = state.lever_row if state.lever_row is not None and self.estimate_pose else -1
        state.mu, transition = predict_frozen(state.mu, state.theta, twist, q, dt,
                                              self.estimate_bias and self.estimate_pose, bias_walk_var, imu_weight,
                                              state.core, lever, state.lever_considered,
                                              state.carries_rotation)
        return transition

    def predict(self, state, twist, q, dt, bias_walk_var) -> InvariantTransition | None:
        if not self.estimate_pose:
            self.predict_mean_only(state, se3.exp_se3(twist))
            return None
        state.mu, G_pose = predict_step(state.mu, twist)
        if state.lever_share:  # (V2) the sensitivity column only
            inner = InvariantTransition(G_pose, state.theta, q, dt, self.estimate_bias, bias_walk_var)
            return SensitivityTransition(inner, state.lever_row,
                                         G_pose @ twist_columns(twist, rotation=state.carries_rotation))
        lever = -1 if state.lever_row is None else state.lever_row
        return InvariantTransition(G_pose, state.theta, q, dt, self.estimate_bias, bias_walk_var, lever,
                                   np.array(twist[3:6], dtype=float))

    def innovation(self, state, slots, pixels, pixel_var) -> Innovation:
        cam = self.camera
        residual, off_row, H_x, H_m, HP, S, nis, in_front = innovation(
            state.P, state.theta, slots, state.mu, self.cam_T_imu, cam.fx, cam.fy, cam.cx, cam.cy, cam.baseline,
            pixels, pixel_var, self.estimate_pose, state.core)
        return Innovation(residual, off_row, H_x, H_m, HP, S, nis, in_front)

    def initialize(self, state, pixels, sigma) -> NewLandmarks:
        cam = self.camera
        theta, J_xi, J_z = initialize(pixels, state.mu @ self.imu_T_cam, cam.fx, cam.fy, cam.cx, cam.cy, cam.baseline,
                                      sigma, self.estimate_pose)
        return NewLandmarks(theta, None, J_xi, J_z)

    def correct(self, state, dx) -> None:
        state.mu = retract_inplace(state.mu, state.theta, dx, state.core)
        state.gyro_bias = state.gyro_bias + dx[6:9]

    def world_landmarks(self, state, slots):
        theta = state.theta[slots]  # world positions: every one finite
        P, rows = state.considered_state(slots)  # (V2) with a considered lever arm's share
        return theta, world_covariances(P, rows, theta, state.core), np.ones(slots.size, dtype=bool)

    def pose_covariance(self, state) -> np.ndarray:
        return body_pose_covariance(state.mu, state.covariance_of(POSE))


@warms_up(only="landmarks")
def _warm_up() -> None:
    """The kernels a run calls from Python (``backend.compiled``; :func:`observe` runs inside :func:`innovation`)."""
    D, k = CORE + 6, 2
    P = np.eye(D)
    slots = np.arange(k, dtype=np.int64)
    points = np.ones((k, 3))
    twist = np.full(6, 0.01)
    predict_covariance_inplace(P.copy(), np.eye(6), np.ones((3, 6)), points, np.ones(6), 0.1, True, 1e-8, -1,
                               np.zeros(3))
    pose, _ = predict_step(np.eye(4), twist)
    retract_inplace(pose, points.copy(), np.full(D, 1e-3), CORE)
    pixels = np.array([[600.0, 180.0, 560.0, 180.0]] * k)
    # the arguments as the model passes them (core given: an omitted default would be another signature)
    innovation(P, points + 5.0, slots, np.eye(4), np.eye(4), 700.0, 700.0, 600.0, 180.0, 0.5, pixels, 1.0, True, CORE)
    initialize(pixels, np.eye(4), 700.0, 700.0, 600.0, 180.0, 0.5, 1.0, True)
    world_covariances(P, slots, points, CORE)
