"""Drift-free refinement of tracked points: affine alignment against each track's first patch.

Frame-to-frame translational Lucas-Kanade drifts: when a patch grows or shears between frames
(a car driving towards a wall, the ground seen from two cameras), the best translation is
biased towards where the patch's gradients are, by about ``(scale - 1)`` times a few pixels, in
the same direction frame after frame. Following Shi and Tomasi (1994), each track keeps the patch
it was born with (``template``, left image, first frame) and every new position (left or right
image) is refined by aligning that patch with an affine warp,

    image point = A x + t,     x in the template's pixel grid centred on 0,

so errors do not accumulate. The alignment is the inverse-compositional Gauss-Newton of Baker and
Matthews (2004): template gradients and the 6x6 Hessian are computed once per track. Patches are
compared after removing their mean and dividing by their norm (gain and offset of the exposure
drop out). The normalized residual ``|I(W x) - T(x)|`` (0 = identical, 2 = opposite; about 0.1
for a good match) measures how well the patch still matches and lets a caller end tracks that
no longer look like their start (occlusion, a corner formed by two surfaces that slide apart).

All points are processed together: one ``cv2.remap`` samples every warped patch per iteration.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Templates", "make_templates", "isotropy", "align"]


@dataclass
class Templates:
    """Per-track reference patches (n tracks, P x P pixels each)."""

    patch: np.ndarray  # (n, P*P) float32, zero mean, unit norm
    steepest_t: np.ndarray  # (n, 6, P*P) float32: (gradient times d(warp)/d(params) at identity)^T
    hessian_inv: np.ndarray  # (n, 6, 6) float32

    @property
    def size(self) -> int:
        return int(round(np.sqrt(self.patch.shape[1])))

    def __len__(self) -> int:
        return self.patch.shape[0]

    def take(self, index) -> "Templates":
        return Templates(self.patch[index], self.steepest_t[index], self.hessian_inv[index])

    @staticmethod
    def concat(parts: list["Templates"]) -> "Templates":
        return Templates(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("patch", "steepest_t", "hessian_inv")))

    @staticmethod
    def empty(size: int) -> "Templates":
        return Templates(np.zeros((0, size * size), np.float32), np.zeros((0, 6, size * size), np.float32),
                         np.zeros((0, 6, 6), np.float32))


def _grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel offsets (x, y), each (size*size,) float32, of a size x size patch centred on 0."""
    h = (size - 1) / 2.0
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) - np.float32(h)
    return x.ravel(), y.ravel()


def _sample(img: np.ndarray, A: np.ndarray, t: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """(n, k) float32 bilinear samples of ``img`` at ``A [gx gy] + t`` for each of n warps (n may be 0)."""
    if t.shape[0] == 0:
        return np.zeros((0, gx.size), np.float32)
    A = A.astype(np.float32, copy=False)
    t = t.astype(np.float32, copy=False)
    mx = A[:, 0, 0:1] * gx + A[:, 0, 1:2] * gy + t[:, 0:1]
    my = A[:, 1, 0:1] * gx + A[:, 1, 1:2] * gy + t[:, 1:2]
    return cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _normalize(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(zero-mean unit-norm rows, their norm before scaling)."""
    p = p - p.mean(axis=1, keepdims=True)
    norm = np.sqrt(np.einsum("nk,nk->n", p, p))
    return p / np.maximum(norm, 1e-6)[:, None], norm


def make_templates(img: np.ndarray, centres: np.ndarray, size: int, min_texture: float = 1e-3) -> tuple[Templates, np.ndarray]:
    """Templates of ``size`` x ``size`` pixels (odd) centred on ``centres`` (n,2) of the float32
    image ``img``; also (n,) bool: the patch has texture in every direction (smallest eigenvalue
    of its normalized gradient matrix >= ``min_texture``)."""
    n = centres.shape[0]
    if n == 0:
        return Templates.empty(size), np.zeros(0, bool)
    big = size + 2
    gx, gy = _grid(big)
    eye = np.broadcast_to(np.eye(2, dtype=np.float32), (n, 2, 2))
    raw = _sample(img, eye, centres.astype(np.float32), gx, gy).reshape(n, big, big)
    patch, norm = _normalize(raw[:, 1:-1, 1:-1].reshape(n, -1))
    scale = (1.0 / np.maximum(norm, 1e-6))[:, None]
    dx = ((raw[:, 1:-1, 2:] - raw[:, 1:-1, :-2]) * 0.5).reshape(n, -1) * scale
    dy = ((raw[:, 2:, 1:-1] - raw[:, :-2, 1:-1]) * 0.5).reshape(n, -1) * scale
    x, y = _grid(size)
    # params p = (a11 - 1, a21, a12, a22 - 1, tx, ty): W(x; p) = [(1+p0) x + p2 y + p4, p1 x + (1+p3) y + p5]
    sd_t = np.stack([dx * x, dy * x, dx * y, dy * y, dx, dy], axis=1).astype(np.float32)  # (n, 6, k)
    H = (sd_t @ sd_t.transpose(0, 2, 1)).astype(np.float64)
    # texture: smallest eigenvalue of the translation block [[sum dx^2, sum dx dy], [., sum dy^2]]
    a, b, c = H[:, 4, 4], H[:, 4, 5], H[:, 5, 5]
    smallest = 0.5 * (a + c - np.sqrt((a - c) ** 2 + 4 * b * b))
    ok = (norm > 1e-3) & (smallest >= min_texture)
    H += np.eye(6) * (1e-6 * np.trace(H, axis1=1, axis2=2)[:, None, None] + 1e-12)
    return Templates(patch.astype(np.float32), sd_t, np.linalg.inv(H).astype(np.float32)), ok


def isotropy(img: np.ndarray, centres: np.ndarray, size: int) -> np.ndarray:
    """(n,) smallest over largest eigenvalue (0..1) of the gradient matrix of the ``size`` x
    ``size`` patches of the float32 image ``img`` centred on ``centres`` (n,2): near 0 for a patch
    of edges all in one direction, 1 for texture alike in every direction."""
    n = centres.shape[0]
    if n == 0:
        return np.zeros(0)
    big = size + 2
    gx, gy = _grid(big)
    eye = np.broadcast_to(np.eye(2, dtype=np.float32), (n, 2, 2))
    raw = _sample(img, eye, centres.astype(np.float32), gx, gy).reshape(n, big, big)
    dx = (raw[:, 1:-1, 2:] - raw[:, 1:-1, :-2]).reshape(n, -1)
    dy = (raw[:, 2:, 1:-1] - raw[:, :-2, 1:-1]).reshape(n, -1)
    a, b, c = (np.einsum("nk,nk->n", u, v).astype(np.float64) for u, v in ((dx, dx), (dx, dy), (dy, dy)))
    root = np.sqrt((a - c) ** 2 + 4 * b * b)
    return (a + c - root) / np.maximum(a + c + root, 1e-12)


def align(img: np.ndarray, templates: Templates, A: np.ndarray, t: np.ndarray, iterations: int = 10,
          epsilon: float = 0.02) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refine the warps (A (n,2,2), t (n,2)) mapping each template into the float32 image ``img``.

    Returns (A, t, residual (n,)): the normalized residual norm at the last evaluation (before the
    last, smallest update; see the module docstring). A warp stops iterating once its translation
    update is below ``epsilon`` px.
    """
    n = t.shape[0]
    A = np.array(A, dtype=np.float64).reshape(n, 2, 2)
    t = np.array(t, dtype=np.float64).reshape(n, 2)
    residual = np.zeros(n)
    if n == 0:
        return A, t, residual
    gx, gy = _grid(templates.size)
    active = np.arange(n)  # warps still iterating; the arrays below hold their rows only
    patch, steepest_t, hessian_inv = templates.patch, templates.steepest_t, templates.hessian_inv
    A_act, t_act = A.copy(), t.copy()
    for _ in range(max(1, iterations)):
        warped, _ = _normalize(_sample(img, A_act, t_act, gx, gy))
        r = warped - patch
        residual[active] = np.sqrt(np.einsum("nk,nk->n", r, r))
        b = (steepest_t @ r[:, :, None])[:, :, 0]
        dp = (hessian_inv @ b[:, :, None])[:, :, 0].astype(np.float64)
        # W <- W o W(dp)^-1, with W(dp) = [[1 + dp0, dp2, dp4], [dp1, 1 + dp3, dp5]]
        a00, a10, a01, a11 = 1.0 + dp[:, 0], dp[:, 1], dp[:, 2], 1.0 + dp[:, 3]
        det = a00 * a11 - a01 * a10
        D_inv = np.empty((active.size, 2, 2))
        D_inv[:, 0, 0], D_inv[:, 0, 1], D_inv[:, 1, 0], D_inv[:, 1, 1] = a11 / det, -a01 / det, -a10 / det, a00 / det
        shift = -(D_inv @ dp[:, 4:6, None])[:, :, 0]
        step = (A_act @ shift[:, :, None])[:, :, 0]
        t_act += step
        A_act = A_act @ D_inv
        A[active], t[active] = A_act, t_act
        going = np.abs(step).max(axis=1) >= epsilon
        if not going.any():
            break
        if not going.all():
            active, A_act, t_act = active[going], A_act[going], t_act[going]
            patch, steepest_t, hessian_inv = patch[going], steepest_t[going], hessian_inv[going]
    return A, t, residual
