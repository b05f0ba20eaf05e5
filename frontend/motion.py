"""Rigid-motion check of stereo tracks: do the tracked pixels move like fixed 3-D points?

The tracker keeps, for every track, the 3-D point triangulated from its first stereo match, in the
frame of the first camera of the sequence (``world``). Each frame the camera pose ``cam_T_world``
is estimated from all tracks (PnP RANSAC on the left pixels, then Levenberg-Marquardt on the
inliers) and every track is reprojected into both images; a track whose pixels lie farther than a
threshold from its point's projection has slid (an edge, a corner formed by two surfaces at
different depths, a moving object) and is ended. Fundamental-matrix RANSAC cannot see a slide
along the epipolar line, which in forward motion is the direction of the image motion; with the
depth known from stereo, PnP can.

Rectified stereo: the right camera is the left one moved by ``+baseline`` along its x axis, so a
camera-frame point ``p`` projects to ``uL = fx x / z + cx`` and ``uR = fx (x - b) / z + cx``.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["triangulate", "project_stereo", "estimate_pose"]

#: Points must be at least this far in front of the camera to be projected (m).
_MIN_DEPTH = 1e-3


def triangulate(pixels: np.ndarray, K: np.ndarray, baseline: float, world_T_cam: np.ndarray) -> np.ndarray:
    """World points (n,3) of stereo pixels (n,4) ``uL vL uR vR`` (disparity > 0) seen from the
    left camera at ``world_T_cam`` (4,4)."""
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 4)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    z = fx * baseline / (pixels[:, 0] - pixels[:, 2])
    p_in_cam = np.stack([(pixels[:, 0] - cx) * z / fx, (pixels[:, 1] - cy) * z / fy, z], axis=1)
    return p_in_cam @ world_T_cam[:3, :3].T + world_T_cam[:3, 3]


def project_stereo(points_world: np.ndarray, K: np.ndarray, baseline: float, cam_T_world: np.ndarray):
    """(pixels (n,4) ``uL vL uR vR``, in front (n,) bool) of world points seen by the rig."""
    p_in_cam = points_world @ cam_T_world[:3, :3].T + cam_T_world[:3, 3]
    z = p_in_cam[:, 2]
    front = z > _MIN_DEPTH
    z = np.where(front, z, 1.0)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = fx * p_in_cam[:, 0] / z + cx
    v = fy * p_in_cam[:, 1] / z + cy
    return np.stack([u, v, u - fx * baseline / z, v], axis=1), front


def estimate_pose(points_world: np.ndarray, pixels_left: np.ndarray, K: np.ndarray, threshold_px: float,
                  guess_cam_T_world: np.ndarray | None = None) -> np.ndarray | None:
    """``cam_T_world`` (4,4) of the left camera seeing ``points_world`` (n,3) at ``pixels_left``
    (n,2): P3P RANSAC (``threshold_px``), then Levenberg-Marquardt on the inliers from the
    RANSAC pose. None when there are fewer than 6 points or fewer than 6 (or a quarter of the)
    inliers. ``guess_cam_T_world`` is used when RANSAC does not converge to a better pose."""
    n = points_world.shape[0]
    if n < 6:
        return None
    obj = np.ascontiguousarray(points_world, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(pixels_left, dtype=np.float64).reshape(-1, 1, 2)
    K = np.asarray(K, dtype=np.float64)
    try:
        found, rvec, tvec, inliers = cv2.solvePnPRansac(
            obj, img, K, None, iterationsCount=200, reprojectionError=float(threshold_px), confidence=0.999,
            flags=cv2.SOLVEPNP_AP3P,
        )
    except cv2.error:
        found, inliers = False, None
    if not found or inliers is None or len(inliers) < max(6, n // 4):
        if guess_cam_T_world is None:
            return None
        rvec, _ = cv2.Rodrigues(np.ascontiguousarray(guess_cam_T_world[:3, :3]))
        tvec = guess_cam_T_world[:3, 3].reshape(3, 1).copy()
        projected, _ = cv2.projectPoints(obj, rvec, tvec, K, None)
        inliers = np.flatnonzero(np.linalg.norm(projected.reshape(-1, 2) - pixels_left, axis=1) <= threshold_px)
        if inliers.size < max(6, n // 4):
            return None
    inliers = np.asarray(inliers).reshape(-1)
    rvec, tvec = cv2.solvePnPRefineLM(obj[inliers], img[inliers], K, None, rvec, tvec)
    cam_T_world = np.eye(4)
    cam_T_world[:3, :3], _ = cv2.Rodrigues(rvec)
    cam_T_world[:3, 3] = tvec.reshape(3)
    return cam_T_world
