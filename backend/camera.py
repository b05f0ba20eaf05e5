"""Rectified stereo pinhole camera model (ECE276A visual-inertial SLAM notes).

A point ``p_in_cam`` (optical frame: x right, y down, z forward) with homogeneous
``q = [p_in_cam; 1]`` is observed as ``z = [uL, vL, uR, vR] = Ks @ pi(q)``,
``pi(q) = q / q[2]``. Every function is vectorized over leading axes: (n, 3) points
give (n, 4) pixels, and a single (3,) point gives (4,).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit


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


@njit(cache=True, nogil=True, error_model="numpy")
def _triangulate_rows(z, fx, fy, cx, cy, baseline, sigma):
    """Compiled core of :meth:`StereoCamera.triangulate_with_jacobian` for z (n,4): the point
    (the unscented mean when sigma > 0) (n,3) and d triangulate / d z at the pixels (n,3,4)."""
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

    def projection_jacobian(self, p_in_cam: np.ndarray) -> np.ndarray:
        """dz/dp = Ks dpi/dq([p; 1]) P^T with P^T = [I3; 0], in closed form; (..., 3) -> (..., 4, 3):
        rows uL: [fx, 0, -fx x/z]/z, vL and vR: [0, fy, -fy y/z]/z, uR: [fx, 0, -fx (x - b)/z]/z."""
        p = np.asarray(p_in_cam, dtype=float)
        x, y, inv_z = p[..., 0], p[..., 1], 1.0 / p[..., 2]
        J = np.zeros(p.shape[:-1] + (4, 3))
        J[..., 0, 0] = J[..., 2, 0] = self.K[0, 0] * inv_z
        J[..., 1, 1] = J[..., 3, 1] = self.K[1, 1] * inv_z
        J[..., 0, 2] = -self.K[0, 0] * x * inv_z * inv_z
        J[..., 2, 2] = -self.K[0, 0] * (x - self.baseline) * inv_z * inv_z
        J[..., 1, 2] = J[..., 3, 2] = -self.K[1, 1] * y * inv_z * inv_z
        return J

    def triangulate(self, z: np.ndarray) -> np.ndarray:
        """Point from pixels: depth = fx b / (uL - uR), x = (uL - cx) depth / fx,
        y = ((vL + vR)/2 - cy) depth / fy; (..., 4) -> (..., 3).

        Needs positive disparity; zero gives inf and negative gives a point behind the camera.
        """
        return self.triangulate_with_jacobian(z)[0]

    def triangulate_mean(self, z: np.ndarray, pixel_sigma: float) -> np.ndarray:
        """E[triangulate(z + n)], n ~ N(0, pixel_sigma^2 I4), by the unscented transform (Julier &
        Uhlmann 1997: 2N+1 = 9 sigma points z +- sqrt(3) sigma e_i, weights -1/3 and 1/6), exact to
        second order; (..., 4) -> (..., 3).

        Depth from disparity is biased, E[f b / d] ~ (f b / d) (1 + 2 sigma^2 / d^2) > f b / d, so the
        point at the measured pixels sits too near. Where a sigma point would halve the disparity
        (d <= 2 sqrt(3) sigma) the expansion is meaningless and the plain triangulation is returned.
        The point is linear in vL and vR, so their four sigma points sum to 4 x the centre and
        only the four shifts of uL and uR are evaluated: mean = centre / 3 + (sum of those) / 6.
        """
        return self.triangulate_with_jacobian(z, pixel_sigma)[0]

    def triangulate_with_jacobian(self, z: np.ndarray, pixel_sigma: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(:meth:`triangulate_mean` with ``pixel_sigma``, or :meth:`triangulate` with 0, and
        :meth:`triangulation_jacobian`) in one compiled pass; (..., 4) -> ((..., 3), (..., 3, 4))."""
        z = np.asarray(z, dtype=float)
        rows = np.ascontiguousarray(z.reshape(-1, 4))
        points, J = _triangulate_rows(rows, self.fx, self.fy, self.cx, self.cy, self.baseline, float(pixel_sigma))
        return points.reshape(z.shape[:-1] + (3,)), J.reshape(z.shape[:-1] + (3, 4))

    def triangulation_jacobian(self, z: np.ndarray) -> np.ndarray:
        """d triangulate / d z; (..., 4) -> (..., 3, 4).

        With d = uL - uR and p = (x, y, depth): dp/duL = ([b, 0, 0] - p) / d,
        dp/duR = p / d, dy/dvL = dy/dvR = depth / (2 fy).
        """
        return self.triangulate_with_jacobian(z)[1]
