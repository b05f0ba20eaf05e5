"""Stereo images of a textured-plane world (street scene) with exact, known geometry.

World model
-----------
A :class:`Plane` is a planar convex quadrilateral ``corners = (c0, c1, c2, c3)`` (world frame,
metres, in order around the quad) carrying a grey ``texture`` (H, W) ``uint8``.

Texture convention: continuous texture coordinates ``(s, t)``, ``s`` along a texture row (column
index direction, 0..W) and ``t`` down the rows (0..H); texel (column i, row j) covers the square
``[i, i+1] x [j, j+1]`` and its value sits at its centre ``(i + 1/2, j + 1/2)``. The texture's
outer corners (0,0), (W,0), (W,H), (0,H) map onto c0, c1, c2, c3, projectively; for a
parallelogram (a rectangle included) that is the affine map

    X(s, t) = c0 + s/W (c1 - c0) + t/H (c3 - c0).

So row 0 of the texture runs along the edge c0 -> c1, and for an upright wall c0 is its top-left
corner as seen from the side it is meant to be seen from (planes are drawn from both sides).

Image convention (OpenCV and KITTI): pixel (column u, row v) is centred on the integer point (u, v)
of the pinhole projection ``K p / p_z`` (as :meth:`~vislam.backend.geometry.camera.StereoCamera.project`).

Rendering (:func:`render_pair`)
-------------------------------
``cam_T_world = inverse(world_T_imu @ imu_T_cam)``; the right camera is the left one moved by
``+baseline`` along its x axis (``p_right = p_left - [b, 0, 0]``), so images are rectified: a point
has the same row in both and a disparity ``fx b / z``. Per camera:

1. cull (vectorized): planes with every corner nearer than ``NEAR`` (0.1 m) or every corner
   outside one side of the view frustum;
2. clip each remaining quad against the near plane ``z = NEAR`` (the part behind the camera is cut
   off; the plane is not skipped) and its image against the image rectangle -> a bounding box;
3. texture -> image homography from the plane geometry itself
   ``H = K [R | t] (texture -> world)`` (exact even when corners are behind the camera; for a
   quad entirely in front it equals ``cv2.getPerspectiveTransform`` of the four corners);
4. mip-mapping: the finest texture level (box-filtered halvings, ``cv2.INTER_AREA``, exact
   texel-edge alignment) whose texels are >= 1.07 pixels at the centre of the visible part (area
   scale): no aliasing on far or grazing planes, and edges stay ramps a corner detector can
   localize to subpixel accuracy (at most 2x magnification blur);
5. ``cv2.warpPerspective`` (``INTER_LINEAR``, ``BORDER_CONSTANT`` 0) of that level into the
   bounding box only, and of an all-255 image of the same size with the same map: the coverage
   mask, so the colour comes premultiplied and plane outlines are anti-aliased with half coverage
   exactly on the geometric edge (a ramp one texel of the level wide: 1-2 px at the centre of
   the visible part, wider where the plane comes nearer, narrower where it recedes). For a
   near-clipped plane the coverage is also cut to pixels whose ray meets the plane in front at a
   depth >= ``NEAR`` (a strip between two image lines), so nothing behind the camera is drawn;
6. painter's algorithm: ``out = out (1 - a) + colour`` (uint8) from far to near, sorted by
   ``(layer, -mean depth of the clipped polygon)``. Layers make the street's occlusions right
   where mean depth alone would not (ground below walls): 0 backdrop, 1-2 ground, 3 walls.

:func:`render_depth` gives the ground truth of an image: each pixel's camera-frame depth ``z``
from the plane that paints it last with coverage >= 0.5 (same culling, clipping and order),
``inf`` for the sky, so ``z K^-1 (u, v, 1)`` is the pixel's true 3-D point.

The street world (:func:`build_street_planes`) follows the trajectory; :func:`write_kitti_sequence`
renders a whole sequence in the KITTI odometry layout.
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..backend.data.files import atomic_write
from ..backend.geometry import se3
from . import textures
from .observe import Calibration

__all__ = [
    "NEAR",
    "SKY",
    "Plane",
    "render_image",
    "render_depth",
    "render_pair",
    "build_street_planes",
    "write_kitti_sequence",
    "kitti_calib_text",
]

#: Near clipping depth (m): plane parts nearer than this to a camera are cut off.
NEAR = 0.1
#: Grey level where no plane is drawn (sky); the backdrop textures use it above their skyline.
SKY = 200
#: Bounding boxes are widened by this many pixels (room for the anti-aliased edge ramp).
_BBOX_MARGIN = 2
#: Cap (pixels) on widening a plane's box for its coverage ramp (extremely magnified planes).
_MAX_RAMP_MARGIN = 64
#: Mip-level bias: the finest level whose texels are >= 2^MIP_BIAS pixels (area scale) at the
#: centre of a plane's visible part is drawn (1.07-2.1 px: never minified, at most 2x magnified).
#: Point-sampled INTER_LINEAR of minified texels aliases and biases subpixel corner positions.
MIP_BIAS = 0.1
#: Memory budget of the cached texture pyramids (bytes).
_CACHE_BYTES = 384 * 2**20
#: Random stream of the street world when write_kitti_sequence gets a Scene and no planes.
RENDER_STREAM = 1000


# ---------------------------------------------------------------------------------- planes


def _homography_4pt(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """3x3 projective map sending the 4 points ``src`` (4,2) to ``dst`` (4,2), in float64."""
    A = np.zeros((8, 8))
    b = np.zeros(8)
    for i, ((x, y), (u, v)) in enumerate(zip(src, dst)):
        A[2 * i] = [x, y, 1, 0, 0, 0, -u * x, -u * y]
        A[2 * i + 1] = [0, 0, 0, x, y, 1, -v * x, -v * y]
        b[2 * i], b[2 * i + 1] = u, v
    h = np.linalg.solve(A, b)
    return np.append(h, 1.0).reshape(3, 3)


@dataclass(frozen=True, eq=False)
class Plane:
    """A textured planar convex quad (see the module docstring for the texture convention).

    ``layer``: drawing group (lower first; depth-sorted within a group). ``gain``: the texture
    is multiplied by it (clipped to 255), e.g. to shade walls differently. ``max_distance``: not
    drawn by a camera farther than this (m) from every point of the quad's bounding sphere (keeps
    kilometres of street from being drawn as specks on the horizon).
    """

    corners: np.ndarray  # (4,3) world, in order around the quad
    texture: np.ndarray  # (H,W) uint8
    layer: int = 3
    gain: float = 1.0
    max_distance: float = np.inf

    def __post_init__(self) -> None:
        c = np.array(self.corners, dtype=float)
        if c.shape != (4, 3) or not np.all(np.isfinite(c)):
            raise ValueError(f"plane corners must be a finite (4, 3) array, got shape {c.shape}")
        tex = np.asarray(self.texture)
        if tex.dtype != np.uint8 or tex.ndim != 2 or min(tex.shape) < 2:
            raise ValueError(f"plane texture must be a 2-D uint8 image of at least 2 x 2, got {tex.dtype} {tex.shape}")
        if not (np.isfinite(self.gain) and self.gain >= 0):
            raise ValueError(f"plane gain must be >= 0, got {self.gain!r}")
        if not float(self.max_distance) > 0:
            raise ValueError(f"plane max_distance must be > 0, got {self.max_distance!r}")
        u1, u2, d = c[1] - c[0], c[3] - c[0], c[2] - c[0]
        normal = np.cross(u1, u2)
        size = max(np.linalg.norm(u1), np.linalg.norm(u2), np.linalg.norm(d))
        if np.linalg.norm(normal) <= 1e-12 * size * size:
            raise ValueError("plane corners are degenerate (c0, c1, c3 collinear)")
        normal /= np.linalg.norm(normal)
        if abs(normal @ d) > 1e-6 * size + 1e-9:
            raise ValueError(f"plane corners are not coplanar (c2 off the plane by {abs(normal @ d):.3g} m)")
        # c2 in the (u1, u2) frame; convex quad in this order needs a, b > 0 and a + b > 1
        (a2, b2), *_ = np.linalg.lstsq(np.stack([u1, u2], axis=1), d, rcond=None)
        if not (a2 > 0 and b2 > 0 and a2 + b2 > 1):
            raise ValueError("plane corners must form a convex quad, in order around it")
        h, w = tex.shape
        if abs(a2 - 1.0) < 1e-12 and abs(b2 - 1.0) < 1e-12:
            G = np.diag([1.0 / w, 1.0 / h, 1.0])  # parallelogram: affine
        else:
            G = _homography_4pt(
                np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]]),
                np.array([[0.0, 0.0], [1.0, 0.0], [a2, b2], [0.0, 1.0]]),
            )
        # (s, t, 1) -> homogeneous world point [X w; w]
        tex_to_world = np.array([[*u1, 0.0], [*u2, 0.0], [*c[0], 1.0]]).T @ G
        c.setflags(write=False)
        tex_to_world.setflags(write=False)
        object.__setattr__(self, "corners", c)
        object.__setattr__(self, "texture", tex)
        object.__setattr__(self, "layer", int(self.layer))
        object.__setattr__(self, "gain", float(self.gain))
        object.__setattr__(self, "max_distance", float(self.max_distance))
        object.__setattr__(self, "tex_to_world", tex_to_world)

    def point(self, st: np.ndarray) -> np.ndarray:
        """World points (n,3) of continuous texture coordinates ``st`` (n,2)."""
        st = np.asarray(st, dtype=float).reshape(-1, 2)
        X = np.concatenate([st, np.ones((st.shape[0], 1))], axis=1) @ self.tex_to_world.T
        return X[:, :3] / X[:, 3:4]


def _as_plane(p) -> Plane:
    return p if isinstance(p, Plane) else Plane(*p)


# ---------------------------------------------------------------------------------- texture pyramids


def _level_dims(height: int, width: int) -> list[tuple[int, int]]:
    """(h, w) of every pyramid level: halvings (rounded) while the smaller side is >= 8."""
    dims = [(int(height), int(width))]
    while min(dims[-1]) >= 8:
        h, w = dims[-1]
        dims.append((max(1, round(h / 2)), max(1, round(w / 2))))
    return dims


def _build_pyramid(plane: Plane) -> list[np.ndarray]:
    """[texture * gain] and its box-filtered halvings (``cv2.INTER_AREA``: level-l texel i covers
    level-0 texels [i w/w_l, (i+1) w/w_l], so every level has the same continuous coordinates)."""
    tex = plane.texture
    if plane.gain != 1.0:
        tex = np.clip(tex.astype(np.float32) * plane.gain + 0.5, 0, 255).astype(np.uint8)
    else:
        tex = np.ascontiguousarray(tex)
    levels = [tex]
    for h, w in _level_dims(*tex.shape)[1:]:
        levels.append(cv2.resize(levels[-1], (w, h), interpolation=cv2.INTER_AREA))
    return levels


class _PyramidCache:
    """LRU of per-plane pyramids keyed by plane identity (entries die with their plane)."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self.bytes = 0
        self.items: OrderedDict[int, tuple] = OrderedDict()
        self.lock = threading.RLock()  # re-entrant: a weakref callback may run under it

    def get(self, plane: Plane) -> list[np.ndarray]:
        key = id(plane)
        with self.lock:
            item = self.items.get(key)
            if item is not None and item[0]() is plane:
                self.items.move_to_end(key)
                return item[1]
        levels = _build_pyramid(plane)
        nbytes = sum(a.nbytes for a in levels)
        with self.lock:
            old = self.items.pop(key, None)
            if old is not None:
                self.bytes -= old[2]
            self.items[key] = (weakref.ref(plane, lambda ref, k=key: self._drop(k, ref)), levels, nbytes)
            self.bytes += nbytes
            while self.bytes > self.max_bytes and len(self.items) > 1:
                _, (_, _, n) = self.items.popitem(last=False)
                self.bytes -= n
        return levels

    def _drop(self, key: int, ref) -> None:
        with self.lock:
            item = self.items.get(key)
            if item is not None and item[0] is ref:
                del self.items[key]
                self.bytes -= item[2]


_PYRAMIDS = _PyramidCache(_CACHE_BYTES)


# ---------------------------------------------------------------------------------- one image


def _clip_near(poly: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a 3-D polygon (n,3) (camera frame) to z >= near."""
    out = []
    n = poly.shape[0]
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        ina, inb = a[2] >= near, b[2] >= near
        if ina:
            out.append(a)
        if ina != inb:
            f = (near - a[2]) / (b[2] - a[2])
            out.append(a + f * (b - a))
    return np.array(out).reshape(-1, 3)


def _clip_halfplanes(poly: np.ndarray, lines) -> np.ndarray:
    """Clip a 2-D polygon (n,2) to the half-planes ``l0 x + l1 y + l2 >= 0``."""
    pts = [tuple(map(float, p)) for p in poly]
    for a, b, c in lines:
        if not pts:
            break
        val = [a * x + b * y + c for x, y in pts]
        out = []
        n = len(pts)
        for i in range(n):
            j = (i + 1) % n
            if val[i] >= 0:
                out.append(pts[i])
            if (val[i] >= 0) != (val[j] >= 0):
                f = val[i] / (val[i] - val[j])
                out.append((pts[i][0] + f * (pts[j][0] - pts[i][0]), pts[i][1] + f * (pts[j][1] - pts[i][1])))
        pts = out
    return np.array(pts, dtype=float).reshape(-1, 2)


class _World:
    """Planes stacked for vectorized culling and homographies."""

    def __init__(self, planes) -> None:
        self.planes = [_as_plane(p) for p in planes]
        n = len(self.planes)
        self.corners = np.stack([p.corners for p in self.planes]) if n else np.zeros((0, 4, 3))
        self.tex_to_world = np.stack([p.tex_to_world for p in self.planes]) if n else np.zeros((0, 4, 3))
        self.layer = np.array([p.layer for p in self.planes], dtype=np.int64)
        self.centre = self.corners.mean(axis=1)
        radius = np.linalg.norm(self.corners - self.centre[:, None], axis=2).max(axis=1) if n else np.zeros(0)
        self.reach = radius + np.array([p.max_distance for p in self.planes])  # (P,) may be inf
        dims = [_level_dims(*p.texture.shape) for p in self.planes]
        self.n_levels = np.array([len(d) for d in dims], dtype=np.int64)
        top = int(self.n_levels.max()) if n else 1
        # (P, L, 2): level-0 texels per level texel (sx, sy); unused levels repeat the last one
        self.scale = np.ones((n, top, 2))
        for i, d in enumerate(dims):
            h0, w0 = d[0]
            s = np.array([[w0 / w, h0 / h] for h, w in d])
            self.scale[i, : len(d)] = s
            self.scale[i, len(d) :] = s[-1]


def _frustum_keep(corners_cam: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(P,) bool: planes neither entirely nearer than NEAR nor entirely outside one side of the
    frustum (with the bounding-box margin)."""
    x, y, z = corners_cam[..., 0], corners_cam[..., 1], corners_cam[..., 2]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    m = _BBOX_MARGIN
    out = (z < NEAR).all(axis=1)
    out |= (fx * x + (cx + m) * z < 0).all(axis=1)  # left of u = -m
    out |= (fx * x + (cx - width + 1 - m) * z > 0).all(axis=1)  # right of u = width - 1 + m
    out |= (fy * y + (cy + m) * z < 0).all(axis=1)
    out |= (fy * y + (cy - height + 1 - m) * z > 0).all(axis=1)
    return ~out


def _project(K: np.ndarray, p: np.ndarray) -> np.ndarray:
    q = p @ K.T
    return q[..., :2] / q[..., 2:3]


_OPAQUE = np.full((1, 1), 255, dtype=np.uint8)
_OPAQUE_LOCK = threading.Lock()


def _opaque(h: int, w: int) -> np.ndarray:
    """An all-255 (h, w) uint8 view: the coverage source image of a texture of that size."""
    global _OPAQUE
    with _OPAQUE_LOCK:
        if _OPAQUE.shape[0] < h or _OPAQUE.shape[1] < w:
            _OPAQUE = np.full((max(h, _OPAQUE.shape[0]), max(w, _OPAQUE.shape[1])), 255, dtype=np.uint8)
        return _OPAQUE[:h, :w]


def _texture_jacobian(H_inv: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """d(s, t)/d(u, v) (n, k, 2, 2) of the maps image -> texture ``H_inv`` (n, 3, 3) at the
    pixels (x, y) (n, k)."""
    Hi = H_inv[:, None]
    q = [Hi[..., i, 0] * x + Hi[..., i, 1] * y + Hi[..., i, 2] for i in range(3)]
    with np.errstate(divide="ignore", invalid="ignore"):
        s, t = q[0] / q[2], q[1] / q[2]
        J = np.empty(x.shape + (2, 2))
        J[..., 0, 0] = (Hi[..., 0, 0] - s * Hi[..., 2, 0]) / q[2]
        J[..., 0, 1] = (Hi[..., 0, 1] - s * Hi[..., 2, 1]) / q[2]
        J[..., 1, 0] = (Hi[..., 1, 0] - t * Hi[..., 2, 0]) / q[2]
        J[..., 1, 1] = (Hi[..., 1, 1] - t * Hi[..., 2, 1]) / q[2]
    return J


def _smallest_singular_value(J: np.ndarray) -> np.ndarray:
    """Smallest singular value of 2x2 matrices (..., 2, 2)."""
    a = np.sum(J * J, axis=(-2, -1))
    det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
    return np.sqrt(np.maximum(0.5 * (a - np.sqrt(np.maximum(a * a - 4.0 * det * det, 0.0))), 0.0))


def _render(
    world: _World, cam_T_world: np.ndarray, K: np.ndarray, width: int, height: int, background: float,
    depth_out: np.ndarray | None = None,
) -> np.ndarray:
    """The grey image; if ``depth_out`` (height, width) float is given, each pixel a plane paints with
    coverage >= 0.5 also gets that plane's depth (camera z) there, in the same painter's order."""
    R, t = cam_T_world[:3, :3], cam_T_world[:3, 3]
    m = _BBOX_MARGIN
    corners_cam = world.corners @ R.T + t
    keep = _frustum_keep(corners_cam, K, width, height)
    keep &= np.linalg.norm(world.centre @ R.T + t, axis=1) <= world.reach
    idx = np.flatnonzero(keep)
    cc = corners_cam[idx]
    clipped = cc[:, :, 2].min(axis=1) < NEAR
    n = idx.shape[0]
    lo = np.zeros((n, 2))
    hi = np.zeros((n, 2))
    centre = np.zeros((n, 2))
    probe = np.zeros((n, 4, 2))  # points whose texel size bounds the coverage ramp's reach
    depth = np.zeros(n)
    ok = np.ones(n, dtype=bool)
    # planes entirely in front: bounding box of the projected corners, cut to the image
    front = np.flatnonzero(~clipped)
    uv = _project(K, cc[front])
    lo[front] = uv.min(axis=1)
    hi[front] = uv.max(axis=1)
    centre[front] = uv.mean(axis=1)
    probe[front] = uv
    depth[front] = cc[front, :, 2].mean(axis=1)
    # planes crossing the near plane: clip in 3-D, then against the image rectangle
    frame = [(1.0, 0.0, m), (-1.0, 0.0, width - 1 + m), (0.0, 1.0, m), (0.0, -1.0, height - 1 + m)]
    for j in np.flatnonzero(clipped):
        poly = _clip_near(cc[j], NEAR)
        if poly.shape[0] < 3:
            ok[j] = False
            continue
        p2 = _clip_halfplanes(_project(K, poly), frame)
        if p2.shape[0] < 3:
            ok[j] = False
            continue
        lo[j], hi[j], centre[j] = p2.min(axis=0), p2.max(axis=0), p2.mean(axis=0)
        probe[j] = [lo[j], [hi[j, 0], lo[j, 1]], hi[j], [lo[j, 0], hi[j, 1]]]
        depth[j] = poly[:, 2].mean()
    x0 = np.clip(np.floor(lo[:, 0]) - m, 0, width).astype(np.int64)
    y0 = np.clip(np.floor(lo[:, 1]) - m, 0, height).astype(np.int64)
    x1 = np.clip(np.ceil(hi[:, 0]) + m + 1, 0, width).astype(np.int64)
    y1 = np.clip(np.ceil(hi[:, 1]) + m + 1, 0, height).astype(np.int64)
    ok &= (x1 > x0) & (y1 > y0)
    keep = np.flatnonzero(ok)
    idx, clipped, depth, centre, probe = idx[keep], clipped[keep], depth[keep], centre[keep], probe[keep]
    x0, y0, x1, y1 = x0[keep], y0[keep], x1[keep], y1[keep]
    canvas = np.full((height, width), int(round(background)), dtype=np.uint8)
    if idx.shape[0] == 0:
        return canvas
    A = world.tex_to_world[idx]
    H = np.einsum("ij,jk,nkl->nil", K, cam_T_world[:3, :], A)  # texture (s, t, 1) -> image
    det = np.linalg.det(H)
    good = np.isfinite(det) & (np.abs(det) > 1e-300)
    H[~good] = np.eye(3)
    H_inv = np.linalg.inv(H)
    # mip level from the area scale of image -> texture at a visible point
    cx = np.clip(centre[:, 0], x0, x1 - 1)
    cy = np.clip(centre[:, 1], y0, y1 - 1)
    r = np.einsum("nk,nkl->nl", A[:, 3, :], H_inv)  # 1 / depth of the plane along pixel rays
    inv_depth = r[:, 0] * cx + r[:, 1] * cy + r[:, 2]
    use_centre = inv_depth > 0
    cx = np.where(use_centre, cx, centre[:, 0])
    cy = np.where(use_centre, cy, centre[:, 1])
    J = _texture_jacobian(H_inv, cx[:, None], cy[:, None])[:, 0]  # (n, 2, 2)
    area = np.abs(J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        level = np.ceil(0.5 * np.log2(area) + MIP_BIAS)
    level = np.where(np.isfinite(level), level, 0.0)
    level = np.clip(level, 0, world.n_levels[idx] - 1).astype(np.int64)
    sc = world.scale[idx, level]  # (n, 2) level-0 texels per texel of the level
    # the coverage ramp reaches half a texel beyond the edge: widen the box by the largest
    # half texel (pixels) at the probes (corners, or box corners when clipped), within the box
    px = np.clip(probe[..., 0], x0[:, None], x1[:, None] - 1)
    py = np.clip(probe[..., 1], y0[:, None], y1[:, None] - 1)
    in_front = r[:, None, 0] * px + r[:, None, 1] * py + r[:, None, 2] > 0
    Jp = _texture_jacobian(H_inv, px, py) / sc[:, None, :, None]  # level texels per pixel
    with np.errstate(divide="ignore", invalid="ignore"):
        texel_px = 1.0 / _smallest_singular_value(Jp)
    texel_px = np.where(in_front & np.isfinite(texel_px), texel_px, 0.0).max(axis=1)
    extra = np.clip(np.ceil(0.5 * texel_px) + 1 - m, 0, _MAX_RAMP_MARGIN).astype(np.int64)
    x0, y0 = np.maximum(x0 - extra, 0), np.maximum(y0 - extra, 0)
    x1, y1 = np.minimum(x1 + extra, width), np.minimum(y1 + extra, height)
    # bbox pixel -> image pixel -> continuous texture -> OpenCV coordinates of the level
    S_inv = np.zeros((idx.shape[0], 3, 3))
    S_inv[:, 0, 0], S_inv[:, 1, 1], S_inv[:, 2, 2] = 1.0 / sc[:, 0], 1.0 / sc[:, 1], 1.0
    S_inv[:, 0, 2] = S_inv[:, 1, 2] = -0.5
    B = np.zeros((idx.shape[0], 3, 3))
    B[:, 0, 0] = B[:, 1, 1] = B[:, 2, 2] = 1.0
    B[:, 0, 2], B[:, 1, 2] = x0, y0
    M = S_inv @ H_inv @ B
    r_box = np.einsum("nk,nkl->nl", r, B)  # 1 / depth along the rays of box pixels
    order = np.lexsort((-depth, world.layer[idx]))  # layer first, then far to near
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    for j in order:
        if not good[j]:
            continue
        w, h = int(x1[j] - x0[j]), int(y1[j] - y0[j])
        src = _PYRAMIDS.get(world.planes[idx[j]])[level[j]]
        sub = canvas[y0[j] : y1[j], x0[j] : x1[j]]
        colour = cv2.warpPerspective(src, M[j], (w, h), flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        alpha = cv2.warpPerspective(_opaque(*src.shape), M[j], (w, h), flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        if clipped[j]:
            # keep pixels whose ray meets the plane in front, at a depth >= NEAR: 0 < r.x <= 1 / NEAR
            a, b, c = r_box[j]
            eps = 1e-12 * (abs(a) + abs(b) + abs(c))
            box = np.array([[-1.0, -1.0], [w, -1.0], [w, h], [-1.0, h]])
            region = _clip_halfplanes(box, [(a, b, c - eps), (-a, -b, 1.0 / NEAR - c)])
            mask = np.zeros((h, w), dtype=np.uint8)
            if region.shape[0] >= 3:
                cv2.fillConvexPoly(mask, np.round(region * 16).astype(np.int32), 1, cv2.LINE_8, 4)
            cv2.multiply(colour, mask, dst=colour)
            cv2.multiply(alpha, mask, dst=alpha)
        if depth_out is not None:
            covered = alpha >= 128  # coverage >= 0.5
            a, b, c = r_box[j]  # 1 / depth = a x + b y + c at box pixel (x, y)
            ys, xs = np.nonzero(covered)
            depth_out[y0[j] : y1[j], x0[j] : x1[j]][covered] = 1.0 / (a * xs + b * ys + c)
        # premultiplied "over": out = out (255 - alpha) / 255 + colour
        cv2.multiply(sub, cv2.bitwise_not(alpha), dst=sub, scale=1.0 / 255.0)
        cv2.add(sub, colour, dst=sub)
    return canvas


def _cameras(world_T_imu: np.ndarray, calibration: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """(cam_T_world left, cam_T_world right) 4x4."""
    left = se3.inverse(np.asarray(world_T_imu, dtype=float) @ calibration.imu_T_cam)
    right = left.copy()
    right[0, 3] -= calibration.baseline
    return left, right


_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()
_LAST_WORLD: tuple | None = None  # (plane ids, _World) of the last plane list rendered


def _pool() -> ThreadPoolExecutor:
    """Two worker threads (PNG encoding runs there while the next pair renders)."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(max_workers=2, thread_name_prefix="vislam-render")
        return _POOL


def _world_of(planes) -> _World:
    """The stacked world of ``planes``; reused while the same planes are rendered again (the cache
    holds the planes, so their ids stay unique)."""
    global _LAST_WORLD
    if isinstance(planes, _World):
        return planes
    planes = list(planes)
    key = tuple(map(id, planes))
    with _POOL_LOCK:
        last = _LAST_WORLD
    if last is not None and last[0] == key:
        return last[1]
    world = _World(planes)
    with _POOL_LOCK:
        _LAST_WORLD = (tuple(map(id, world.planes)), world) if world.planes == planes else None
    return world


def render_image(planes, cam_T_world: np.ndarray, K: np.ndarray, image_size, background: float = SKY) -> np.ndarray:
    """One grey image (height, width) uint8 of ``planes`` seen by a pinhole camera ``K`` at
    ``cam_T_world`` (4x4); ``image_size = (width, height)``; ``background``: grey level where no
    plane is drawn."""
    width, height = (int(v) for v in image_size)
    return _render(_world_of(planes), np.asarray(cam_T_world, dtype=float), np.asarray(K, dtype=float), width, height, background)


def render_depth(planes_or_world, cam_T_world: np.ndarray, K: np.ndarray, image_size) -> np.ndarray:
    """Depth image (height, width) float64 of what :func:`render_image` draws: at each pixel the
    camera-frame z (m) of the last plane, in the painter's order (layer, then far to near), that
    covers it by >= 0.5; ``inf`` where no plane does (sky). ``image_size = (width, height)``.
    Within a plane the inverse depth is affine in (u, v), so interpolating ``1 / depth``
    bilinearly between pixels of one plane is exact."""
    width, height = (int(v) for v in image_size)
    depth = np.full((height, width), np.inf)
    _render(_world_of(planes_or_world), np.asarray(cam_T_world, dtype=float), np.asarray(K, dtype=float),
            width, height, SKY, depth_out=depth)
    return depth


def render_pair(planes, world_T_imu: np.ndarray, calibration: Calibration, background: float = SKY):
    """(left, right) rectified grey images (height, width) uint8 of ``planes`` (:class:`Plane` or
    ``(corners, texture)`` tuples) from the IMU pose ``world_T_imu`` (4x4) of the rig
    ``calibration`` (K, baseline, image size, imu_T_cam)."""
    world = _world_of(planes)
    left_T, right_T = _cameras(world_T_imu, calibration)
    K = np.asarray(calibration.K, dtype=float)
    w, h = calibration.width, calibration.height
    return _render(world, left_T, K, w, h, background), _render(world, right_T, K, w, h, background)


# ---------------------------------------------------------------------------------- street world


class _StreetFrame:
    """Arc length along the IMU path, heading and road level; straight on beyond both ends."""

    def __init__(self, world_T_imu: np.ndarray, imu_height: float) -> None:
        poses = np.asarray(world_T_imu, dtype=float)
        pos = poses[:, :3, 3]
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos[:, :2], axis=0), axis=1))])
        yaw = np.unwrap(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
        _, unique = np.unique(s, return_index=True)
        self.s, self.pos, self.yaw = s[unique], pos[unique], yaw[unique]
        self.imu_height = float(imu_height)
        self.length = float(self.s[-1])

    def heading(self, sq) -> np.ndarray:
        return np.interp(np.asarray(sq, dtype=float), self.s, self.yaw)

    def place(self, sq, lateral, height) -> np.ndarray:
        """World points at arc length ``sq``, lateral offset (left +) and height above the road."""
        sq, lateral, height = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (sq, lateral, height)))
        inside = np.clip(sq, self.s[0], self.s[-1])
        p = np.stack([np.interp(inside, self.s, self.pos[:, i]) for i in range(3)], axis=-1)
        yaw = np.interp(inside, self.s, self.yaw)
        extra = sq - inside
        p[..., 0] += extra * np.cos(yaw)
        p[..., 1] += extra * np.sin(yaw)
        p[..., 0] -= lateral * np.sin(yaw)
        p[..., 1] += lateral * np.cos(yaw)
        p[..., 2] += height - self.imu_height
        return p

    def cut(self, s0: float, length: float, max_turn: float) -> float:
        """End of a segment starting at ``s0``: ``s0 + length`` or earlier where the heading has
        turned by ``max_turn`` (keeps chords close to the curved path)."""
        grid = np.linspace(s0, s0 + length, 64)
        turn = np.abs(self.heading(grid) - self.heading(s0))
        over = np.flatnonzero(turn > max_turn)
        return float(grid[max(over[0] - 1, 1)]) if over.size else s0 + length


def _crop(rng: np.random.Generator, tex: np.ndarray, width_px: int, height_px: int, bottom: bool) -> np.ndarray:
    """A (height_px, width_px) view of ``tex`` (clamped to its size) at a random column, at the
    bottom (walls: shops at street level) or at a random row."""
    h, w = tex.shape
    cw, ch = min(max(width_px, 2), w), min(max(height_px, 2), h)
    x = int(rng.integers(0, w - cw + 1))
    y = h - ch if bottom else int(rng.integers(0, h - ch + 1))
    return tex[y : y + ch, x : x + cw]


def _wall(frame: _StreetFrame, s_a: float, s_b: float, lat_a: float, lat_b: float, height: float) -> np.ndarray:
    """Corners (top-left, top-right, bottom-right, bottom-left) of a vertical wall from
    (s_a, lat_a) to (s_b, lat_b) standing on the road level of s_a and s_b."""
    bottom = frame.place([s_a, s_b], [lat_a, lat_b], [0.0, 0.0])
    top = bottom.copy()
    top[:, 2] += height
    return np.stack([top[0], top[1], bottom[1], bottom[0]])


def build_street_planes(
    world_T_imu: np.ndarray,
    rng,
    *,
    imu_height: float = 0.93,
    ahead: float = 70.0,
    behind: float = 10.0,
    setback=(8.0, 12.0),
    building_length=(8.0, 25.0),
    building_height=(6.0, 18.0),
    road_halfwidth: float = 8.2,
    far_lateral=(35.0, 60.0),
    texture_bank: int = 8,
    max_distance: float = 300.0,
) -> list[Plane]:
    """Textured planes of a street along the IMU path ``world_T_imu`` (N,4,4) (road level
    ``imu z - imu_height``, as :mod:`synth.landmarks`), from ``behind`` metres before the start
    to ``ahead`` metres past the end:

    * facades (layer 3): on each side, buildings ``building_length`` long and
      ``building_height`` high, each a vertical rectangle along the chord of the path at a
      random lateral ``setback`` (|y| 8-12 m), cut where the path turns by > 0.25 rad, with
      side walls where neighbours with different setbacks touch and occasional gaps; textures
      are crops of a bank of :func:`synth.textures.facade` (2 cm/texel, shops at street level);
    * far buildings (layer 3) at |y| in ``far_lateral``, 15-45 m long, 10-40 m high;
    * road (layer 2): tiles |y| <= ``road_halfwidth`` (asphalt, lane lines, kerbs, paving), 6 m
      long or shorter where the path turns by > 0.06 rad, each a planar parallelogram along the
      chord (sloped with the road), lengthened at both ends to cover the wedges between tiles on
      bends (lane lines kink slightly there); verge (layer 1): tiles of up to 12 m (0.15 rad)
      from |y| 8 m to 45 m;
    * backdrop (layer 0): a ring of 64 vertical panels around the whole path, 250 m beyond its
      farthest point, from 15 m below the lowest road level to 75 m above the highest, with a
      skyline texture (silhouettes up to 70 m) whose sky matches :data:`SKY` (the background).

    Buildings that would come within 7 m (facades) or 25 m (far row) of the path are dropped
    (tight bends). Street planes carry ``max_distance`` (the backdrop ring does not): farther
    ones are not drawn; the ring (>= 250 m away) is behind them anyway. ``rng``: a numpy Generator or an int seed; the result is a pure function of it.
    """
    from scipy.spatial import cKDTree

    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(int(rng))
    frame = _StreetFrame(world_T_imu, imu_height)
    s_start, s_end = -float(behind), frame.length + float(ahead)
    path_pts = frame.place(np.arange(s_start, s_end + 1.0, 1.0), 0.0, imu_height)[:, :2]
    tree = cKDTree(path_pts)
    bank = max(1, int(texture_bank))
    planes: list[Plane] = []

    def clear_of_path(corners: np.ndarray, clearance: float) -> bool:
        a, b = corners[3, :2], corners[2, :2]
        n = max(2, int(np.linalg.norm(b - a)) + 1)
        samples = a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)
        return bool(np.all(tree.query(samples)[0] >= clearance))

    # ---- facades (near) and far buildings
    near_bank: list[np.ndarray] = []
    far_bank: list[np.ndarray] = []

    def bank_texture(store, make, size=bank):
        if len(store) < size:
            store.append(make())
            return store[-1]
        return store[int(rng.integers(0, len(store)))]

    def row_of_buildings(side, lateral, length, height, gap, clearance, mpt, store, make, walls):
        s0 = s_start + float(rng.uniform(0.0, 5.0))
        prev = None  # (s_end, lateral, height) of the previous building when contiguous
        while s0 < s_end:
            s1 = min(frame.cut(s0, float(rng.uniform(*length)), 0.25), s_end + 5.0)
            lat = side * float(rng.uniform(*lateral))
            hgt = float(rng.uniform(*height))
            # as seen from the street, texture left-to-right runs along +s on the left side
            sa, sb = (s0, s1) if side > 0 else (s1, s0)
            corners = _wall(frame, sa, sb, lat, lat, hgt)
            ok = clear_of_path(corners, clearance)
            if ok:
                tex = bank_texture(store, make)
                crop = _crop(rng, tex, round((s1 - s0) / mpt), round(hgt / mpt), bottom=True)
                planes.append(Plane(corners, crop, 3, float(rng.uniform(0.8, 1.15)), max_distance))
                if walls and prev is not None and abs(prev[1] - lat) > 0.05:
                    # side wall joining the two fronts; as high as the one nearer the street
                    wh = prev[2] if abs(prev[1]) < abs(lat) else hgt
                    # seen from behind (the camera comes along +s), left-to-right is towards -y
                    wc = _wall(frame, s0, s0, max(prev[1], lat), min(prev[1], lat), wh)
                    if clear_of_path(wc, clearance):
                        crop = _crop(rng, tex, round(abs(lat - prev[1]) / mpt), round(wh / mpt), bottom=True)
                        planes.append(Plane(wc, crop, 3, float(rng.uniform(0.6, 0.95)), max_distance))
            gap_len = 0.0 if rng.uniform() < gap[0] else float(rng.uniform(*gap[1:]))
            prev = (s1, lat, hgt) if ok and gap_len == 0.0 else None
            s0 = s1 + gap_len

    for side in (1.0, -1.0):
        row_of_buildings(
            side, setback, building_length, building_height, (0.6, 1.0, 6.0), 7.0, 0.02, near_bank,
            lambda: textures.facade(rng, (2048, 1024), 0.02), walls=True,
        )
        row_of_buildings(
            side, far_lateral, (15.0, 45.0), (10.0, 40.0), (0.3, 2.0, 25.0), 25.0, 0.05, far_bank,
            lambda: textures.facade(rng, (1024, 1024), 0.05), walls=False,
        )

    # ---- ground: road tiles (layer 2) and verge tiles (layer 1)
    def ground_tiles(tile_len, max_turn, lat_in, lat_out, layer, store, make, crop_mpt):
        s0 = s_start
        while s0 < s_end:
            s1 = min(frame.cut(s0, tile_len, max_turn), s_end)
            if s1 - s0 < 0.5:
                break
            a, b = frame.place([s0, s1], [0.0, 0.0], [0.0, 0.0])
            chord = b - a
            length = float(np.linalg.norm(chord[:2]))
            if length < 1e-6:
                s0 = s1
                continue
            direction = chord / length  # along the chord, sloped with the road
            left = np.array([-direction[1], direction[0], 0.0]) / np.linalg.norm(direction[:2])
            turn = abs(float(frame.heading(s1) - frame.heading(s0)))
            ext = 0.5 * abs(lat_out) * np.tan(min(turn, 1.2)) + 0.3
            a_ext, b_ext = a - ext * direction, b + ext * direction
            tex = bank_texture(store, make, max(1, bank // 2))
            tiles = [(lat_in, lat_out)] if lat_in < 0 else [(lat_in, lat_out), (-lat_out, -lat_in)]
            for lo, hi in tiles:
                # texture rows run along the street, row 0 at lateral ``lo`` (as textures.road)
                corners = np.stack([a_ext + lo * left, b_ext + lo * left, b_ext + hi * left, a_ext + hi * left])
                if crop_mpt is None:
                    crop = tex
                else:
                    crop = _crop(rng, tex, round((length + 2 * ext) / crop_mpt), tex.shape[0], bottom=True)
                planes.append(Plane(corners, crop, layer, float(rng.uniform(0.9, 1.1)), max_distance))
            s0 = s1

    road_bank: list[np.ndarray] = []
    verge_bank: list[np.ndarray] = []
    ground_tiles(
        6.0, 0.06, -road_halfwidth, road_halfwidth, 2, road_bank,
        lambda: textures.road(rng, (1024, 1024), (0.012, 2 * road_halfwidth / 1024), road_halfwidth), 0.012,
    )
    ground_tiles(12.0, 0.15, 8.0, 45.0, 1, verge_bank, lambda: textures.verge(rng, (512, 1024)), None)

    # ---- backdrop ring
    ground = frame.pos[:, 2] - frame.imu_height
    z_lo, z_hi, z_mid = float(ground.min()), float(ground.max()), float(np.median(ground))
    centre = 0.5 * (path_pts.min(axis=0) + path_pts.max(axis=0))
    radius = float(np.max(np.linalg.norm(path_pts - centre, axis=1))) + 250.0
    skyline_height = 70.0  # m above the median road level
    top, bottom = z_hi + skyline_height + 5.0, z_lo - 15.0
    horizon = (top - z_mid) / (top - bottom)
    n_panels = 64
    sky_bank = [
        textures.skyline(rng, (256, 512), sky=SKY, horizon=horizon, max_height=skyline_height / (top - bottom))
        for _ in range(min(bank, 4))
    ]
    angles = np.linspace(0.0, 2.0 * np.pi, n_panels + 1)
    for k in range(n_panels):
        # seen from inside, left-to-right runs clockwise (decreasing angle)
        a0, a1 = angles[k + 1], angles[k]
        p0 = centre + radius * np.array([np.cos(a0), np.sin(a0)])
        p1 = centre + radius * np.array([np.cos(a1), np.sin(a1)])
        corners = np.array([[*p0, top], [*p1, top], [*p1, bottom], [*p0, bottom]])
        planes.append(Plane(corners, sky_bank[k % len(sky_bank)], layer=0, gain=1.0))
    return planes


# ---------------------------------------------------------------------------------- KITTI layout


def kitti_calib_text(calibration: Calibration) -> str:
    """``calib.txt`` of the KITTI odometry layout: ``P0:`` and ``P1:`` rectified 3x4 projection
    matrices (row-major, ``%.12e``), P1[0,3] = -fx baseline."""
    K = np.asarray(calibration.K, dtype=float)
    P0 = np.hstack([K, np.zeros((3, 1))])
    P1 = K @ np.hstack([np.eye(3), np.array([[-calibration.baseline], [0.0], [0.0]])])
    return "".join(f"{name}: " + " ".join(f"{v:.12e}" for v in P.ravel()) + "\n" for name, P in (("P0", P0), ("P1", P1)))


def _write_text(path: Path, text: str) -> None:
    with atomic_write(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def write_kitti_sequence(
    out_dir,
    source,
    planes=None,
    *,
    seed: int | None = None,
    png_compression: int = 1,
    progress=None,
) -> Path:
    """Render a sequence into ``out_dir`` (created if missing) in the KITTI odometry layout:
    ``image_0/NNNNNN.png`` (left) and ``image_1/NNNNNN.png`` (right) 8-bit grey, ``calib.txt``
    (:func:`kitti_calib_text`), ``times.txt`` (seconds since the first stamp, ``%.6e`` a line) and
    ``poses.txt`` (world_T_cam0 = world_T_imu imu_T_cam of each frame, 12 numbers row-major,
    ``%.6e``; world = the synthetic world frame of ``gt_tum.txt``, not KITTI's first-camera frame).

    ``source``: a :class:`synth.scene.Scene` (true poses, its time stamps and calibration) or a
    tuple ``(world_T_imu (N,4,4), times (N,), calibration)``. ``planes``: the world to render;
    None builds :func:`build_street_planes` from the poses with the Generator
    ``default_rng([seed, RENDER_STREAM])`` (``seed`` defaults to the scene's seed, else 0).
    ``progress``: optional callable(frame_index, n_frames). Returns the directory.
    """
    if hasattr(source, "world_T_imu_true"):
        poses = np.asarray(source.world_T_imu_true, dtype=float)
        times = np.asarray(source.sequence.time_stamps, dtype=float)
        calibration = source.config.calibration
        if seed is None:
            seed = int(source.config.seed)
    else:
        poses, times, calibration = source
        poses = np.asarray(poses, dtype=float)
        times = np.asarray(times, dtype=float)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or times.shape != (poses.shape[0],):
        raise ValueError(f"need poses (N,4,4) and times (N,), got {poses.shape} and {times.shape}")
    out = Path(out_dir)
    (out / "image_0").mkdir(parents=True, exist_ok=True)
    (out / "image_1").mkdir(parents=True, exist_ok=True)
    params = [cv2.IMWRITE_PNG_COMPRESSION, int(png_compression)]
    paths = [(out / "image_0" / f"{k:06d}.png", out / "image_1" / f"{k:06d}.png") for k in range(poses.shape[0])]
    render_to_png(poses, calibration, paths, planes, seed=seed, params=params, progress=progress)
    _write_text(out / "calib.txt", kitti_calib_text(calibration))
    _write_text(out / "times.txt", "".join(f"{t:.6e}\n" for t in times - times[0]))
    world_T_cam = poses @ np.asarray(calibration.imu_T_cam, dtype=float)
    _write_text(out / "poses.txt", "".join(" ".join(f"{v:.6e}" for v in T[:3].ravel()) + "\n" for T in world_T_cam))
    return out


def render_to_png(poses: np.ndarray, calibration, paths, planes=None, *, seed: int | None = None, params=(),
                  progress=None) -> None:
    """Render the stereo pair of every pose ``poses`` (N,4,4) of the rig ``calibration`` and write it
    to ``paths[k]`` = (left PNG, right PNG); each pair is encoded on a worker while the next one
    renders. ``planes``: the world (None: :func:`build_street_planes` along the poses with
    ``default_rng([seed or 0, RENDER_STREAM])``); ``params``: cv2.imwrite's; ``progress(k, n)``."""
    if planes is None:
        planes = build_street_planes(poses, np.random.default_rng([0 if seed is None else int(seed), RENDER_STREAM]))
    world = _world_of(planes)
    n = poses.shape[0]
    pending = None
    for k in range(n):
        left, right = render_pair(world, poses[k], calibration)
        if pending is not None:  # the previous pair was encoded on a worker while this one rendered
            pending.result()
        pending = _pool().submit(_write_pngs, paths[k], left, right, list(params))
        if progress is not None:
            progress(k, n)
    if pending is not None:
        pending.result()


def _write_pngs(paths, left: np.ndarray, right: np.ndarray, params) -> None:
    for path, img in zip(paths, (left, right)):
        if not cv2.imwrite(str(path), img, params):
            raise OSError(f"could not write {path}")
