"""Two-view bundle adjustments of step pairs: what the tracks alone say about motion, offset and noise.

For the points seen at steps k and k+h (the same track ids), the unknowns are each point's true
(u, v, disparity) at k, the rigid camera motion k -> k+h and, optionally, the stereo pair's
disparity offset beta (D1 of ``backend.run.stereo_offset``). They minimize the robust (Huber,
``HUBER_PX``) error of all eight measured pixels, ``uL vL uR vR`` at k and at k+h:

    z_k   = [u, v, u - d - beta, v]
    z_k+h = [pi_L(T q(u, v, d)), pi_R(T q(u, v, d)) - beta],  q = the point triangulated at k        (D2)

by Gauss-Newton with the points eliminated (Schur complement). Both frames' pixels are
measurements, so pixel noise in either biases neither the motion nor beta (triangulating at k and
fitting k+h alone would: errors in variables). Pairs whose rows disagree (|vL - vR| > ``ROW_PX``)
are left out, and after a first fit the points with a residual beyond ``TRIM_PX`` are dropped and
the fit repeated (gross mismatches).

The fits serve three decisions of a run: the disparity offset (``stereo_offset``, with beta), the
pixel noise and the track drift (``noise``, ``drift``: the residuals' scale for gaps h = 1..3),
and the IMU's error against vision (``noise``: the fitted motion as an IMU-frame twist).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..data.sequence import Sequence
from ..geometry import se3

__all__ = ["TwoViewFit", "fit_pair", "fit_pairs", "pair_steps", "pooled_mean_square"]

#: Huber threshold (px) of the fit.
HUBER_PX = 1.0
#: A pair is used only if its rows agree within this (px) in both frames ...
ROW_PX = 2.0
#: ... and, after a first fit, every one of its eight residuals is within this (px).
TRIM_PX = 3.0
#: A point enters a fit only with a disparity above this (px) in both frames.
MIN_DISPARITY = 1.0


@dataclass
class TwoViewFit:
    """One step pair's two-view bundle adjustment (D2)."""

    step: int  # k
    gap: int  # h
    b_T_a: np.ndarray  # (4,4) camera motion: maps points of the camera at k into the camera at k+h
    motion_covariance: np.ndarray  # (6,6) of the left perturbation of b_T_a ([rho, phi]), at the fit's noise
    beta: float  # disparity offset (px); 0 when not fitted
    beta_variance: float  # its variance (px^2); nan when not fitted
    residuals: np.ndarray  # (n,8) pixels predicted - measured of the points kept
    dof: int  # residuals minus unknowns

    @property
    def points(self) -> int:
        return self.residuals.shape[0]

    def robust_scale(self) -> float:
        """1.4826 MAD of the residuals, scaled for the unknowns fitted (px per coordinate)."""
        r = self.residuals.ravel()
        return float(1.4826 * np.median(np.abs(r)) * np.sqrt(r.size / max(self.dof, 1)))

    def mean_square(self, trim: float = TRIM_PX) -> tuple[float, int]:
        """(sum of squared residuals within ``trim`` px, their degrees of freedom): a pooled RMS
        that keeps the heavy tail of real tracks, which the robust scale leaves out."""
        r = self.residuals.ravel()
        kept = np.abs(r) <= trim
        return float(np.sum(r[kept] ** 2)), int(kept.sum()) - (r.size - self.dof)


def pooled_mean_square(fits: list[TwoViewFit], trim: float = TRIM_PX) -> tuple[float, float]:
    """(the residuals' mean square pooled over ``fits`` (px^2), its standard error): each pair's
    :meth:`TwoViewFit.mean_square`, summed over the pairs' degrees of freedom; the error by the delta
    method over the pairs (their mean squares weighted by their degrees of freedom)."""
    ms = np.array([f.mean_square(trim) for f in fits], dtype=float)  # (ssq, dof) per pair
    ssq, dof = ms[:, 0], np.maximum(ms[:, 1], 1.0)
    M = ssq.sum() / dof.sum()
    se = np.sqrt(np.sum(dof**2 * (ssq / dof - M) ** 2)) / dof.sum()
    return float(M), float(se)


def _predict(T: np.ndarray, beta: float, p: np.ndarray, cam, jacobians: bool = False):
    """Predicted pixels (n,8), ``uL vL uR vR`` at k then at k+h, of the points ``p`` (n,3) = (u, v,
    true disparity) at k moved by ``T`` (4,4, camera k -> k+h) and seen with the offset ``beta``
    (D2). With ``jacobians``: also d/dp (n,8,3) and d/d(delta, beta) (n,8,7), where
    ``T <- exp(delta^) T``, ``delta = (rho, phi)`` (so dq/drho = I, dq/dphi = -q^)."""
    fx, fy, cx, cy, baseline = cam
    fb = fx * baseline
    n = p.shape[0]
    depth = fb / p[:, 2]
    x = np.stack([(p[:, 0] - cx) * depth / fx, (p[:, 1] - cy) * depth / fy, depth], axis=1)
    q = x @ T[:3, :3].T + T[:3, 3]
    z = np.maximum(q[:, 2], 1e-6)
    u = fx * q[:, 0] / z + cx
    v = fy * q[:, 1] / z + cy
    pred = np.stack([p[:, 0], p[:, 1], p[:, 0] - p[:, 2] - beta, p[:, 1],
                     u, v, u - fb / z - beta, v], axis=1)
    if not jacobians:
        return pred
    Jp = np.zeros((n, 8, 3))
    Jp[:, 0, 0] = Jp[:, 2, 0] = 1.0
    Jp[:, 1, 1] = Jp[:, 3, 1] = 1.0
    Jp[:, 2, 2] = -1.0
    # d pi / d q for the rows uL, vL, uR, vR at k+h
    iz = 1.0 / z
    P = np.zeros((n, 4, 3))
    P[:, 0, 0] = P[:, 2, 0] = fx * iz
    P[:, 0, 2] = -fx * q[:, 0] * iz * iz
    P[:, 2, 2] = P[:, 0, 2] + fb * iz * iz
    P[:, 1, 1] = P[:, 3, 1] = fy * iz
    P[:, 1, 2] = P[:, 3, 2] = -fy * q[:, 1] * iz * iz
    dx_dp = np.zeros((n, 3, 3))
    dx_dp[:, 0, 0] = depth / fx
    dx_dp[:, 1, 1] = depth / fy
    dx_dp[:, :, 2] = -x / p[:, 2:3]
    Jp[:, 4:, :] = P @ (T[:3, :3] @ dx_dp)
    Jg = np.zeros((n, 8, 7))
    Jg[:, 4:, 0:3] = P
    hat = np.zeros((n, 3, 3))
    hat[:, 0, 1], hat[:, 0, 2], hat[:, 1, 2] = -q[:, 2], q[:, 1], -q[:, 0]
    hat[:, 1, 0], hat[:, 2, 0], hat[:, 2, 1] = q[:, 2], -q[:, 1], q[:, 0]
    Jg[:, 4:, 3:6] = -P @ hat
    Jg[:, 2, 6] = Jg[:, 6, 6] = -1.0
    return pred, Jp, Jg


def _bundle_adjust(za: np.ndarray, zb: np.ndarray, cam, offset: bool, iterations: int = 8,
                   initial: np.ndarray | None = None):
    """(T, beta, S^-1 of the motion (and beta), residuals (n,8), dof, sigma^2) or None: the
    Huber-weighted Gauss-Newton of (D2) with the points eliminated (Schur complement); ``offset``:
    beta is fitted (7 unknowns besides the points), else held at 0 (6); ``initial``: the motion to
    start from (default: none)."""
    g = 7 if offset else 6
    z = np.concatenate([za, zb], axis=1)  # (n,8)
    T = np.eye(4) if initial is None else np.array(initial, dtype=float)
    beta = 0.0
    p = np.stack([za[:, 0], za[:, 1], za[:, 0] - za[:, 2]], axis=1)
    S = None
    for _ in range(iterations):
        pred, Jp, Jg = _predict(T, beta, p, cam, jacobians=True)
        Jg = Jg[:, :, :g]
        r = pred - z
        if not np.all(np.isfinite(r)):
            return None
        a = np.abs(r)
        w = np.where(a <= HUBER_PX, 1.0, HUBER_PX / np.maximum(a, 1e-12))
        JpW = (Jp * w[:, :, None]).transpose(0, 2, 1)  # (n,3,8)
        Hpp = JpW @ Jp + 1e-9 * np.eye(3)
        Hpg = JpW @ Jg  # (n,3,g)
        Jg2 = Jg.reshape(-1, g)
        Hgg = Jg2.T @ (Jg2 * w.reshape(-1, 1))
        bp = (JpW @ r[:, :, None])[:, :, 0]
        bg = Jg2.T @ (w * r).reshape(-1)
        try:
            Hpp_inv = np.linalg.inv(Hpp)
            HgpHinv = Hpg.transpose(0, 2, 1) @ Hpp_inv  # (n,g,3)
            S = Hgg - (HgpHinv @ Hpg).sum(axis=0)
            rhs = bg - (HgpHinv @ bp[:, :, None]).sum(axis=0)[:, 0]
            dg = -np.linalg.solve(S + 1e-9 * np.eye(g), rhs)
        except np.linalg.LinAlgError:
            return None
        dp = -(Hpp_inv @ (bp + Hpg @ dg)[:, :, None])[:, :, 0]
        T = se3.exp_se3(dg[:6]) @ T
        if offset:
            beta += dg[6]
        p += dp
        p[:, 2] = np.maximum(p[:, 2], 1e-3)
        if (not offset or abs(dg[6]) < 1e-4) and np.all(np.abs(dg[:6]) < 1e-6):
            break
    r = _predict(T, beta, p, cam) - z
    inliers = np.abs(r) <= 3 * HUBER_PX
    dof = int(inliers.sum()) - 3 * z.shape[0] - g
    if dof < 20 or not np.all(np.isfinite(r)):
        return None
    sigma2 = float(np.sum(r[inliers] ** 2) / dof)
    try:
        S_inv = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(S_inv)):
        return None
    if offset:
        var = float(S_inv[6, 6]) * sigma2
        if not (np.isfinite(beta) and np.isfinite(var) and var > 0 and abs(beta) < 20):
            return None
    return T, beta, S_inv, r, r.size - 3 * z.shape[0] - g, sigma2


def fit_pair(za: np.ndarray, zb: np.ndarray, cam, offset: bool = False, min_points: int = 12,
             step: int = 0, gap: int = 1, initial: np.ndarray | None = None) -> TwoViewFit | None:
    """The fit (D2) of one step pair's matched pixels ``za``, ``zb`` (n,4), or None: the pairs whose
    rows agree, then again from the start on the points whose eight residuals all stay within
    ``TRIM_PX`` (gross mismatches removed, not only down-weighted); None when fewer than
    ``min_points`` remain, a third of them is trimmed, or the fit is degenerate.
    ``cam`` = (fx, fy, cx, cy, baseline); ``initial``: the motion to start from (default: none, for
    the small motions of consecutive steps)."""
    rows = (np.abs(za[:, 1] - za[:, 3]) <= ROW_PX) & (np.abs(zb[:, 1] - zb[:, 3]) <= ROW_PX)
    za, zb = za[rows], zb[rows]
    if za.shape[0] < min_points:
        return None
    first = _bundle_adjust(za, zb, cam, offset, initial=initial)
    if first is None:
        return None
    keep = np.abs(first[3]).max(axis=1) <= TRIM_PX
    if keep.sum() < max(min_points, 2 * za.shape[0] / 3):
        return None
    second = _bundle_adjust(za[keep], zb[keep], cam, offset, initial=None if initial is None else first[0])
    if second is None or np.abs(second[3]).max() > TRIM_PX:
        return None
    T, beta, S_inv, r, dof, sigma2 = second
    beta_var = float(S_inv[6, 6]) * sigma2 if offset else float("nan")
    return TwoViewFit(step, gap, T, S_inv[:6, :6] * sigma2, float(beta), beta_var, r, dof)


def pair_steps(num_steps: int, gap: int, max_pairs: int, skip: np.ndarray | None = None) -> np.ndarray:
    """Up to ``max_pairs`` steps k, spread evenly over the sequence, with k + ``gap`` inside it and
    no step of k+1 .. k+gap in ``skip`` (bool (N,): repeated frames, whose content froze)."""
    candidates = np.arange(max(num_steps - gap, 0))
    if skip is not None and candidates.size:
        bad = np.zeros(candidates.size, dtype=bool)
        for j in range(1, gap + 1):
            bad |= skip[candidates + j]
        candidates = candidates[~bad]
    if candidates.size > max_pairs:
        candidates = candidates[np.unique(np.linspace(0, candidates.size - 1, max_pairs).round().astype(np.int64))]
    return candidates


def fit_pairs(seq: Sequence, gap: int = 1, max_pairs: int = 300, offset: bool = False, min_points: int = 12,
              skip: np.ndarray | None = None, steps: np.ndarray | None = None, extra_noise: float = 0.0,
              seed: int = 0) -> list[TwoViewFit]:
    """The fits (D2) of up to ``max_pairs`` step pairs (k, k+``gap``) spread over ``seq`` (see
    :func:`pair_steps`; or exactly the pairs starting at ``steps``), each from the points seen in
    both with a disparity above ``MIN_DISPARITY``. ``extra_noise`` > 0: white noise of that sigma
    (px, ``numpy.random.default_rng(seed)``) is added to every pixel first (a SIMEX re-fit)."""
    K = seq.K
    cam = (K[0, 0], K[1, 1], K[0, 2], K[1, 2], seq.baseline)
    rng = np.random.default_rng(seed) if extra_noise > 0 else None
    fits = []
    for k in pair_steps(seq.num_steps, gap, max_pairs, skip) if steps is None else steps:
        ids_a, za = seq.observations(int(k))
        ids_b, zb = seq.observations(int(k) + gap)
        _, ia, ib = np.intersect1d(ids_a, ids_b, assume_unique=True, return_indices=True)
        za, zb = za[ia], zb[ib]
        if rng is not None:
            za = za + rng.normal(0.0, extra_noise, za.shape)
            zb = zb + rng.normal(0.0, extra_noise, zb.shape)
        keep = (za[:, 0] - za[:, 2] > MIN_DISPARITY) & (zb[:, 0] - zb[:, 2] > MIN_DISPARITY)
        if keep.sum() < min_points:
            continue
        fit = fit_pair(za[keep], zb[keep], cam, offset, min_points, int(k), gap)
        if fit is not None:
            fits.append(fit)
    return fits
