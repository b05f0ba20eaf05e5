"""Right-invariant error of the pose and the world-xyz landmarks (pure functions).

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
- Observation  s = T^-1 m = T_hat^-1 E^-1 m ~ T_hat^-1 (m_hat + zeta - rho):

      dz/drho = -M,   dz/dphi = 0,   dz/dzeta = M,   M = Ks dpi/dq cam_T_imu T_hat^-1 [I; 0]        (I3)

  No rotation column: a rotation of the whole world is unobservable for every estimate, which is
  why this filter needs no first-estimate Jacobians.
- Landmark initialization  m = T g(z):  zeta = rho + R_hat imu_R_cam dg/dz dz  (no phi column).   (I4)
  (``backend.kernels.initialize_invariant``)
- Correction  X_hat <- exp(dx) X_hat, i.e. (I1) with (rho, phi, zeta) = dx.                       (I5)
- World covariance of a landmark:  dm = zeta - m_hat^ phi (``backend.kernels.landmark_covariances``). (I6)
- Body-frame (right) pose error  xi_body = Ad(T_hat^-1) (rho, phi).                              (I7)
"""

from __future__ import annotations

import numpy as np

from backend import se3


def _hat_batch(v: np.ndarray) -> np.ndarray:
    """(n,3) -> (n,3,3) skew matrices."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def noise_jacobian_pose(world_T_imu_next: np.ndarray, twist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pose part of G J_r(twist) in (I2): pose rows (6,6), and R_phi (3,6), the world-frame
    rotation error per unit twist error, from which landmark i's rows are m_i^ R_phi."""
    J = se3.right_jacobian_se3(twist)
    return se3.adjoint(world_T_imu_next) @ J, world_T_imu_next[:3, :3] @ J[3:6]


def noise_jacobian(world_T_imu_next: np.ndarray, twist: np.ndarray, points: np.ndarray):
    """G J_r(twist) of (I2): how a body-twist error d (6,) moves the error state.

    Returns (pose rows (6,6), landmark rows (K,3,6)); xi_{k+1} = xi_k + [pose; landmarks] @ d.
    (The filter's prediction forms the landmark rows inside ``backend.kernels``.)
    """
    pose, R_phi = noise_jacobian_pose(world_T_imu_next, twist)
    points = np.asarray(points, dtype=float)
    lm = (_hat_batch(points).reshape(-1, 3) @ R_phi).reshape(-1, 3, 6)  # one product, not K small ones
    return pose, lm


def retract(world_T_imu: np.ndarray, points: np.ndarray, d_pose: np.ndarray, d_points: np.ndarray):
    """(I5): exp(dx) X_hat for the pose (4,4) and the landmarks (K,3); returns new copies."""
    R_d, J_l = se3.exp_so3_and_left_jacobian(d_pose[3:])
    E = np.eye(4)  # exp(d_pose^) (Barfoot eq. 7.39) from the same R_d and J_l
    E[:3, :3] = R_d
    E[:3, 3] = J_l @ d_pose[:3]
    pose = E @ world_T_imu
    pts = np.asarray(points) @ R_d.T + np.asarray(d_points).reshape(-1, 3) @ J_l.T
    return pose, pts


def body_pose_covariance(world_T_imu: np.ndarray, P_pose: np.ndarray) -> np.ndarray:
    """(I7): the 6x6 covariance of the right perturbation world_T_imu = mu exp(xi^)."""
    A = se3.adjoint(se3.inverse(world_T_imu))
    out = A @ P_pose @ A.T
    return 0.5 * (out + out.T)
