"""Rectified stereo pinhole camera model (ECE276A visual-inertial SLAM notes).

A point ``p_in_cam`` (optical frame: x right, y down, z forward) with homogeneous
``q = [p_in_cam; 1]`` is observed as

    z = [uL, vL, uR, vR] = Ks pi(q),   pi(q) = q / q_3,
    Ks = [[fx, 0, cx, 0], [0, fy, cy, 0], [fx, 0, cx, -fx b], [0, fy, cy, 0]]                  (S1)

and triangulated from its pixels with d = uL - uR as

    depth = fx b / d,   x = (uL - cx) depth / fx,   y = ((vL + vR)/2 - cy) depth / fy.         (S2)

Depth from disparity is biased, E[fx b / d] ~ (fx b / d)(1 + 2 sigma^2 / d^2) > fx b / d, so a new
point starts at the expected triangulation under the pixel noise, by the unscented transform
(Julier & Uhlmann 1997: sigma points z +- sqrt(3) sigma e_i, weights -1/3 and 1/6).            (S3)

Every function is vectorized over leading axes: (n, 3) points give (n, 4) pixels, and a single
(3,) point gives (4,).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..compiled import jit, warms_up


def pi(q: np.ndarray) -> np.ndarray:
    """Projection pi(q) = q / q_3 (ECE276A; 0-based q[2]); (..., 4) -> (..., 4)."""
    q = np.asarray(q, dtype=float)
    return q / q[..., 2:3]


def dpi_dq(q: np.ndarray) -> np.ndarray:
    """d pi / d q = (1/q3) [[1,0,-q1/q3,0],[0,1,-q2/q3,0],[0,0,0,0],[0,0,-q4/q3,1]]; (..., 4) -> (..., 4, 4)."""
    q = np.asarray(q, dtype=float)
    inv_depth = 1.0 / q[..., 2]
    J = np.zeros(q.shape[:-1] + (4, 4))
    J[..., 0, 0] = J[..., 1, 1] = J[..., 3, 3] = inv_depth
    J[..., 0, 2] = -q[..., 0] * inv_depth**2
    J[..., 1, 2] = -q[..., 1] * inv_depth**2
    J[..., 3, 2] = -q[..., 3] * inv_depth**2
    return J


def _homogeneous(p: np.ndarray) -> np.ndarray:
    p = np.asarray(p, dtype=float)
    return np.concatenate([p, np.ones(p.shape[:-1] + (1,))], axis=-1)


@jit
def triangulate_rows(z, fx, fy, cx, cy, baseline, sigma):
    """(S2), or (S3) when sigma > 0, for pixels z (n,4): the points (n,3) and d triangulate / d z at
    the pixels (n,3,4); the compiled core of :meth:`StereoCamera.triangulate_with_jacobian`."""
    n = z.shape[0]
    points = np.empty((n, 3))
    J = np.zeros((n, 3, 4))
    c = np.sqrt(3.0) * sigma
    for i in range(n):
        uL, uR = z[i, 0], z[i, 2]
        v = 0.5 * (z[i, 1] + z[i, 3])
        d = uL - uR
        depth = fx * baseline / d
        x = (uL - cx) * depth / fx
        y = (v - cy) * depth / fy
        if sigma > 0.0 and d > 2.0 * c:  # centre / 3 + (the four shifts of uL and uR) / 6
            sx, sy, sz = x / 3.0, y / 3.0, depth / 3.0
            for du, dd in ((c, c), (-c, -c), (0.0, -c), (0.0, c)):  # uL +- c, uR +- c
                dep = fx * baseline / (d + dd)
                sx += (uL + du - cx) * dep / fx / 6.0
                sy += (v - cy) * dep / fy / 6.0
                sz += dep / 6.0
            points[i, 0], points[i, 1], points[i, 2] = sx, sy, sz
        else:
            points[i, 0], points[i, 1], points[i, 2] = x, y, depth
        J[i, 0, 0] = (baseline - x) / d
        J[i, 1, 0] = -y / d
        J[i, 2, 0] = -depth / d
        J[i, 0, 2] = x / d
        J[i, 1, 2] = y / d
        J[i, 2, 2] = depth / d
        J[i, 1, 1] = J[i, 1, 3] = 0.5 * depth / fy
    return points, J


@dataclass(frozen=True, eq=False)
class StereoCamera:
    """Left intrinsics ``K`` (3x3) and ``baseline`` (metres) of a rectified stereo pair.

    ``eq=False``: equality/hash are by identity (a numpy field makes field-wise ``==`` ambiguous).
    """

    K: np.ndarray
    baseline: float

    def __post_init__(self) -> None:
        K = np.array(self.K, dtype=float)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"K must be a finite 3x3 matrix with fx, fy > 0, got {self.K!r}")
        baseline = float(self.baseline)
        if not np.isfinite(baseline) or baseline <= 0:
            raise ValueError(f"baseline must be a finite positive number of metres, got {self.baseline!r}")
        K.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "baseline", baseline)
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        Ks = np.array([[fx, 0.0, cx, 0.0], [0.0, fy, cy, 0.0], [fx, 0.0, cx, -fx * baseline], [0.0, fy, cy, 0.0]])
        Ks.setflags(write=False)
        object.__setattr__(self, "_Ks", Ks)

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def Ks(self) -> np.ndarray:
        """Stereo calibration [[fx,0,cx,0],[0,fy,cy,0],[fx,0,cx,-fx b],[0,fy,cy,0]] (ECE276A); read-only."""
        return self._Ks

    def project(self, p_in_cam: np.ndarray) -> np.ndarray:
        """Pixels z = Ks pi([p; 1]); (..., 3) -> (..., 4) = [uL, vL, uR, vR]."""
        return pi(_homogeneous(p_in_cam)) @ self.Ks.T

    def triangulate(self, z: np.ndarray) -> np.ndarray:
        """Point from pixels: depth = fx b / (uL - uR), x = (uL - cx) depth / fx,
        y = ((vL + vR)/2 - cy) depth / fy; (..., 4) -> (..., 3).

        Needs positive disparity; zero gives inf and negative gives a point behind the camera.
        """
        return self.triangulate_with_jacobian(z)[0]

    def triangulate_with_jacobian(self, z: np.ndarray, pixel_sigma: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(S2) (:meth:`triangulate`), or with ``pixel_sigma`` > 0 the expected triangulation under that
        pixel noise (S3), and d triangulate / d z, in one compiled pass; (..., 4) -> ((..., 3), (..., 3, 4)).

        With d = uL - uR and p = (x, y, depth): dp/duL = ([b, 0, 0] - p) / d, dp/duR = p / d,
        dy/dvL = dy/dvR = depth / (2 fy). Sigma points of (S3) that would halve the disparity
        (d <= 2 sqrt(3) sigma) make the expansion meaningless: there the plain triangulation is
        returned. The point is linear in vL and vR, so their four sigma points sum to 4 x the centre
        and only the four shifts of uL and uR are evaluated: mean = centre / 3 + (sum of those) / 6."""
        z = np.asarray(z, dtype=float)
        rows = np.ascontiguousarray(z.reshape(-1, 4))
        points, J = triangulate_rows(rows, self.fx, self.fy, self.cx, self.cy, self.baseline, float(pixel_sigma))
        return points.reshape(z.shape[:-1] + (3,)), J.reshape(z.shape[:-1] + (3, 4))

@warms_up
def _warm_up() -> None:
    triangulate_rows(np.array([[600.0, 180.0, 560.0, 180.0]] * 2), 700.0, 700.0, 600.0, 180.0, 0.5, 1.0)
