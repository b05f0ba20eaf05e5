"""Landmark parametrizations of the body error model, both written as one homogeneous form.

A landmark is 3 state parameters theta, a fixed anchor frame A (4x4) and the homogeneous point

    w_world = A (e + B theta)          (w_world ~ [m; 1] up to scale)                       (L1)

- ``xyz``: A = I, e = e4, B = [e1 e2 e3]: theta is the world position m.
- ``inverse-depth`` (anchored, Civera, Davison & Montiel, IEEE T-RO 2008): A = world_T_cam of
  the camera that first saw the point, e = e3, B = [e1 e2 e4]: theta = (alpha, beta, rho) with
  the point (alpha, beta, 1) / rho in that camera. From a stereo observation,

      alpha = (uL - cx) / fx,   beta = ((vL + vR)/2 - cy) / fy,   rho = (uL - uR) / (fx b),       (L2)

  *linear* in the pixels, so the initial Gaussian is exact; points far away (rho -> 0) stay well
  behaved and still constrain rotation, where xyz's depth is a long non-Gaussian tail.

The projection uses the homogeneous point directly: q = cam_T_imu mu^-1 w_world,
z = Ks pi(q) (pi divides by q3, so the scale of w cancels), and with s = mu^-1 w_world,

    dz/dtheta = Ks dpi/dq cam_T_imu mu^-1 A B,      dz/dxi = -Ks dpi/dq cam_T_imu s^odot

(right perturbation mu exp(xi^), s^odot = [[s4 I, -s_1:3^], [0, 0]]; B2 of ``backend.estimator.body``).
An xyz landmark starts at m = world_T_imu imu_T_cam triangulate(z) (S2, S3 of
``backend.geometry.camera``) with dm/dz = world_R_cam d triangulate/dz and dm/dxi = [R, -R p_imu^];
an inverse-depth one at (L2), whose anchor moves with the pose error: dtheta/dxi = dg/dw
cam_T_imu (h imu_T_cam^T)^odot for the anchored point h.                                    (L3)
"""

from __future__ import annotations

import numpy as np

from ..geometry import se3
from ..geometry.camera import StereoCamera

_E = {"xyz": np.array([0.0, 0.0, 0.0, 1.0]), "inverse-depth": np.array([0.0, 0.0, 1.0, 0.0])}
_B = {
    "xyz": np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]]),
    "inverse-depth": np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 0], [0, 0, 1]]),
}


def local_point(kind: str, theta: np.ndarray) -> np.ndarray:
    """e + B theta: (n,3) -> (n,4) homogeneous point in the anchor frame."""
    return _E[kind] + theta @ _B[kind].T


def basis(kind: str) -> np.ndarray:
    """B (4,3): d(local point)/d(theta)."""
    return _B[kind]


def initialize(
    kind: str, camera: StereoCamera, pixels: np.ndarray, world_T_imu: np.ndarray, imu_T_cam: np.ndarray,
    pixel_sigma: float | None = None,
):
    """Parameters and Jacobians of new landmarks from stereo pixels (n,4).

    Returns theta (n,3), anchors (n,4,4), J_z (n,3,4) = dtheta/dz and J_xi (n,3,6) = dtheta/dxi
    for a right perturbation world_T_imu exp(xi^) of the pose they were seen from (the body error
    model; the invariant model's own, (I4), is ``backend.estimator.invariant.initialize``).
    For ``xyz`` with ``pixel_sigma``, the point is the expected triangulation under that pixel noise
    (S3 of ``backend.geometry.camera``), not the triangulation of the measured pixels.
    """
    n = pixels.shape[0]
    if kind == "xyz":
        R_wi = world_T_imu[:3, :3]
        p_cam, dp_dz = camera.triangulate_with_jacobian(pixels, pixel_sigma or 0.0)
        p_imu = p_cam @ imu_T_cam[:3, :3].T + imu_T_cam[:3, 3]
        theta = p_imu @ R_wi.T + world_T_imu[:3, 3]
        J_z = (R_wi @ imu_T_cam[:3, :3]) @ dp_dz
        J_xi = np.concatenate([np.broadcast_to(R_wi, (n, 3, 3)), -R_wi @ se3.hat3(p_imu)], axis=2)
        anchors = np.zeros((n, 4, 4))
        anchors[:, [0, 1, 2, 3], [0, 1, 2, 3]] = 1.0
        return theta, anchors, J_z, J_xi
    fx, fy, cx, cy, b = camera.fx, camera.fy, camera.cx, camera.cy, camera.baseline
    alpha = (pixels[:, 0] - cx) / fx
    beta = (0.5 * (pixels[:, 1] + pixels[:, 3]) - cy) / fy
    rho = (pixels[:, 0] - pixels[:, 2]) / (fx * b)
    theta = np.stack([alpha, beta, rho], axis=1)
    J_z = np.zeros((n, 3, 4))
    J_z[:, 0, 0] = 1.0 / fx
    J_z[:, 1, 1] = J_z[:, 1, 3] = 0.5 / fy
    J_z[:, 2, 0] = 1.0 / (fx * b)
    J_z[:, 2, 2] = -1.0 / (fx * b)
    # the anchor is fixed at the pose estimate; the pose error at that moment moves the point in
    # the anchor frame: w = E^-1 exp(xi^) E h, dw/dxi = E^-1 (E h)^odot, theta = g(w) = (w1, w2, w4) / w3
    h = local_point(kind, theta)
    dg = np.zeros((n, 3, 4))
    dg[:, 0, 0] = dg[:, 1, 1] = dg[:, 2, 3] = 1.0
    dg[:, 0, 2] = -alpha
    dg[:, 1, 2] = -beta
    dg[:, 2, 2] = -rho
    cam_T_imu = se3.inverse(imu_T_cam)
    J_xi = dg @ cam_T_imu @ se3.odot(h @ imu_T_cam.T)
    anchors = np.broadcast_to(world_T_imu @ imu_T_cam, (n, 4, 4)).copy()
    return theta, anchors, J_z, J_xi


def to_world(kind: str, theta: np.ndarray, anchors: np.ndarray | None, covariances: np.ndarray):
    """World positions (n,3) and covariances (n,3,3) (``anchors`` may be None for xyz); ``finite`` (n,) is False for points at or
    beyond infinity (inverse depth <= 0), whose position is undefined."""
    if kind == "xyz":
        return theta.copy(), covariances.copy(), np.ones(theta.shape[0], dtype=bool)
    w = np.einsum("nij,nj->ni", anchors, local_point(kind, theta))
    finite = w[:, 3] > 1e-9
    scale = np.where(finite, w[:, 3], 1.0)
    pos = w[:, :3] / scale[:, None]
    d_point_dw = np.concatenate([np.broadcast_to(np.eye(3), (theta.shape[0], 3, 3)), -pos[:, :, None]], axis=2)
    J = d_point_dw / scale[:, None, None] @ anchors @ _B[kind]
    cov = J @ covariances @ J.transpose(0, 2, 1)
    return pos, cov, finite
