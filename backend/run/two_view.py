"""Two-view bundle adjustments of step pairs: what the tracks alone say about motion, offset and noise.

For the points seen at steps k and k+h (the same track ids), the unknowns are each point's true
(u, v, disparity) at k, the rigid camera motion k -> k+h and, optionally, the stereo pair's
disparity offset beta (D1 of ``backend.run.stereo_offset``). They minimize the robust (Huber,
``HUBER_PX``) error of all eight measured pixels, ``uL vL uR vR`` at k and at k+h:

    z_k   = [u, v, u - d - beta, v]
    z_k+h = [pi_L(T q(u, v, d)), pi_R(T q(u, v, d)) - beta],  q = the point triangulated at k        (D2)

by Gauss-Newton with the points eliminated (Schur complement), one compiled call a fit. Both frames' pixels are
measurements, so pixel noise in either biases neither the motion nor beta (triangulating at k and
fitting k+h alone would: errors in variables). Pairs whose rows disagree (|vL - vR| > ``ROW_PX``)
are left out, and after a first fit the points with a residual beyond ``TRIM_PX`` are dropped and
the fit repeated (gross mismatches).

The fits serve three decisions of a run: the disparity offset (``stereo_offset``, with beta), the
pixel noise and the track drift (``noise``, ``drift``: the residuals' scale for gaps h = 1..3),
and the IMU's error against vision (``noise``: the fitted motion as an IMU-frame twist).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..compiled import jit, warms_up
from ..data.sequence import Sequence
from ..estimator.linalg import inverse3, solve_small
from ..geometry import se3

__all__ = ["TwoViewFit", "fit_pair", "fit_pairs", "matched_pixels", "pair_steps", "pooled_mean_square"]

#: Huber threshold (px) of the fit.
HUBER_PX = 1.0
#: A pair is used only if its rows agree within this (px) in both frames ...
ROW_PX = 2.0
#: ... and, after a first fit, every one of its eight residuals is within this (px).
TRIM_PX = 3.0
#: A point enters a fit only with a disparity above this (px) in both frames.
MIN_DISPARITY = 1.0
#: Threads that fit step pairs (the compiled fit releases the GIL); fewer pairs than
#: ``THREADED_PAIRS`` are fitted in the calling thread.
FIT_THREADS = 2
THREADED_PAIRS = 32


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
    (D2), by the compiled model the fit uses (:func:`_point`). With ``jacobians``: also d/dp
    (n,8,3) and d/d(delta, beta) (n,8,7), where ``T <- exp(delta^) T``, ``delta = (rho, phi)``
    (so dq/drho = I, dq/dphi = -q^)."""
    fx, fy, cx, cy, baseline = map(float, cam)
    pred, Jp, Jg = _predict_all(np.ascontiguousarray(T, dtype=float), float(beta), np.ascontiguousarray(p, dtype=float),
                                fx, fy, cx, cy, fx * baseline, jacobians)
    return (pred, Jp, Jg) if jacobians else pred


@jit
def _predict_all(T, beta, p, fx, fy, cx, cy, fb, jac):
    """:func:`_point` for every point: (pred (n,8), Jp (n,8,3), Jg (n,8,7); zeros without ``jac``)."""
    n = p.shape[0]
    pred = np.empty((n, 8))
    Jp = np.zeros((n, 8, 3))
    Jg = np.zeros((n, 8, 7))
    work = np.empty((4, 4, 3))
    for i in range(n):
        _point(T, beta, p[i, 0], p[i, 1], p[i, 2], fx, fy, cx, cy, fb, pred[i], Jp[i], Jg[i], jac, work)
    return pred, Jp, Jg


@jit
def _point(T, beta, p0, p1, p2, fx, fy, cx, cy, fb, pred, Jp, Jg, jac, work):
    """(D2) for one point (u, v, d) at k: its 8 predicted pixels into ``pred``; with ``jac`` d/dp
    (8,3) and d/d(delta, beta) (8,7) into ``Jp``, ``Jg``; ``work`` (4,4,3) scratch."""
    depth = fb / p2
    x0 = (p0 - cx) * depth / fx
    x1 = (p1 - cy) * depth / fy
    x2 = depth
    q0 = T[0, 0] * x0 + T[0, 1] * x1 + T[0, 2] * x2 + T[0, 3]
    q1 = T[1, 0] * x0 + T[1, 1] * x1 + T[1, 2] * x2 + T[1, 3]
    q2 = T[2, 0] * x0 + T[2, 1] * x1 + T[2, 2] * x2 + T[2, 3]
    z = max(q2, 1e-6)
    u = fx * q0 / z + cx
    v = fy * q1 / z + cy
    pred[0], pred[1], pred[2], pred[3] = p0, p1, p0 - p2 - beta, p1
    pred[4], pred[5], pred[6], pred[7] = u, v, u - fb / z - beta, v
    if not jac:
        return
    Jp[:] = 0.0
    Jg[:] = 0.0
    Jp[0, 0] = Jp[2, 0] = 1.0
    Jp[1, 1] = Jp[3, 1] = 1.0
    Jp[2, 2] = -1.0
    iz = 1.0 / z
    P = work[0]
    P[:] = 0.0
    P[0, 0] = P[2, 0] = fx * iz
    P[0, 2] = -fx * q0 * iz * iz
    P[2, 2] = P[0, 2] + fb * iz * iz
    P[1, 1] = P[3, 1] = fy * iz
    P[1, 2] = P[3, 2] = -fy * q1 * iz * iz
    D = work[1, :3]  # dx/dp
    D[:] = 0.0
    D[0, 0] = depth / fx
    D[1, 1] = depth / fy
    D[0, 2] = -x0 / p2
    D[1, 2] = -x1 / p2
    D[2, 2] = -x2 / p2
    RD = work[2, :3]
    for a in range(3):
        for b in range(3):
            RD[a, b] = T[a, 0] * D[0, b] + T[a, 1] * D[1, b] + T[a, 2] * D[2, b]
    hat = work[3, :3]
    hat[:] = 0.0
    hat[0, 1], hat[0, 2], hat[1, 2] = -q2, q1, -q0
    hat[1, 0], hat[2, 0], hat[2, 1] = q2, -q1, q0
    for r in range(4):
        for b in range(3):
            Jp[4 + r, b] = P[r, 0] * RD[0, b] + P[r, 1] * RD[1, b] + P[r, 2] * RD[2, b]
            Jg[4 + r, b] = P[r, b]
            Jg[4 + r, 3 + b] = -(P[r, 0] * hat[0, b] + P[r, 1] * hat[1, b] + P[r, 2] * hat[2, b])
    Jg[2, 6] = Jg[6, 6] = -1.0


#: The rows of (D2) whose Jacobian in the motion and beta is not zero (uR at k: beta only; the four
#: pixels at k+h), in the order of the rows: the sums below skip only exact zeros.
_MOTION_ROWS = (2, 4, 5, 6, 7)


@jit
def _gauss_newton(za, zb, fx, fy, cx, cy, baseline, offset, iterations, T0, huber):
    """The Huber-weighted Gauss-Newton of (D2) with the points eliminated (Schur complement), in one
    compiled call: (ok, T, beta, S (g,g) of the last iteration, residuals (n,8) at the end); ok
    False when a residual is not finite or a normal matrix is singular."""
    g = 7 if offset else 6
    n = za.shape[0]
    fb = fx * baseline
    T = T0.copy()
    beta = 0.0
    p = np.empty((n, 3))
    for i in range(n):
        p[i, 0], p[i, 1], p[i, 2] = za[i, 0], za[i, 1], za[i, 0] - za[i, 2]
    z = np.empty((n, 8))
    se3.put_block(z, 0, 0, za)
    se3.put_block(z, 0, 4, zb)
    S = np.zeros((g, g))
    pred = np.empty(8)
    Jp = np.zeros((8, 3))
    Jg = np.zeros((8, 7))
    Hinv = np.empty((n, 3, 3))
    Hpg = np.empty((n, 3, g))
    bp = np.empty((n, 3))
    r = np.empty(8)
    w = np.empty(8)
    Hpp = np.empty((3, 3))
    work = np.empty((4, 4, 3))
    c = np.empty(3)
    rhs = np.zeros(g)
    for _ in range(iterations):
        S[:] = 0.0
        rhs[:] = 0.0
        for i in range(n):
            _point(T, beta, p[i, 0], p[i, 1], p[i, 2], fx, fy, cx, cy, fb, pred, Jp, Jg, True, work)
            for j in range(8):
                r[j] = pred[j] - z[i, j]
                if not np.isfinite(r[j]):
                    return False, T, beta, S, np.zeros((n, 8))
                a = abs(r[j])
                w[j] = 1.0 if a <= huber else huber / max(a, 1e-12)
            for a in range(3):
                for b in range(3):
                    s = 0.0
                    for j in range(8):
                        s += Jp[j, a] * w[j] * Jp[j, b]
                    Hpp[a, b] = s + (1e-9 if a == b else 0.0)
                for b in range(g):
                    s = 0.0
                    for j in _MOTION_ROWS:
                        s += Jp[j, a] * w[j] * Jg[j, b]
                    Hpg[i, a, b] = s
                s = 0.0
                for j in range(8):
                    s += Jp[j, a] * w[j] * r[j]
                bp[i, a] = s
            for a in range(g):
                for b in range(a, g):
                    s = 0.0
                    for j in _MOTION_ROWS:
                        s += Jg[j, a] * Jg[j, b] * w[j]
                    S[a, b] += s
                    if b != a:
                        S[b, a] += s
                s = 0.0
                for j in _MOTION_ROWS:
                    s += Jg[j, a] * w[j] * r[j]
                rhs[a] += s
            if not inverse3(Hpp, Hinv[i]):
                return False, T, beta, S, np.zeros((n, 8))
            # S -= Hgp Hpp^-1 Hpg, rhs -= Hgp Hpp^-1 bp
            for a in range(g):
                t0 = Hpg[i, 0, a] * Hinv[i, 0, 0] + Hpg[i, 1, a] * Hinv[i, 1, 0] + Hpg[i, 2, a] * Hinv[i, 2, 0]
                t1 = Hpg[i, 0, a] * Hinv[i, 0, 1] + Hpg[i, 1, a] * Hinv[i, 1, 1] + Hpg[i, 2, a] * Hinv[i, 2, 1]
                t2 = Hpg[i, 0, a] * Hinv[i, 0, 2] + Hpg[i, 1, a] * Hinv[i, 1, 2] + Hpg[i, 2, a] * Hinv[i, 2, 2]
                for b in range(g):
                    S[a, b] -= t0 * Hpg[i, 0, b] + t1 * Hpg[i, 1, b] + t2 * Hpg[i, 2, b]
                rhs[a] -= t0 * bp[i, 0] + t1 * bp[i, 1] + t2 * bp[i, 2]
        A = S.copy()
        for a in range(g):
            A[a, a] += 1e-9
        dg, ok = solve_small(A, rhs)
        if not ok:
            return False, T, beta, S, np.zeros((n, 8))
        for a in range(g):
            dg[a] = -dg[a]
        for i in range(n):
            for a in range(3):
                s = bp[i, a]
                for b in range(g):
                    s += Hpg[i, a, b] * dg[b]
                c[a] = s
            for a in range(3):
                p[i, a] -= Hinv[i, a, 0] * c[0] + Hinv[i, a, 1] * c[1] + Hinv[i, a, 2] * c[2]
            p[i, 2] = max(p[i, 2], 1e-3)
        E = se3.exp_se3(dg[:6])
        T = se3.small_matmul(E, T)
        if offset:
            beta += dg[6]
        small = True
        for a in range(6):
            if not abs(dg[a]) < 1e-6:
                small = False
        if (not offset or abs(dg[6]) < 1e-4) and small:
            break
    res = np.empty((n, 8))
    for i in range(n):
        _point(T, beta, p[i, 0], p[i, 1], p[i, 2], fx, fy, cx, cy, fb, pred, Jp, Jg, False, work)
        for j in range(8):
            res[i, j] = pred[j] - z[i, j]
    return True, T, beta, S, res


def _bundle_adjust(za: np.ndarray, zb: np.ndarray, cam, offset: bool, iterations: int = 8,
                   initial: np.ndarray | None = None):
    """(T, beta, S^-1 of the motion (and beta), residuals (n,8), dof, sigma^2) or None: the
    Huber-weighted Gauss-Newton of (D2) with the points eliminated (:func:`_gauss_newton`);
    ``offset``: beta is fitted (7 unknowns besides the points), else held at 0 (6); ``initial``:
    the motion to start from (default: none)."""
    g = 7 if offset else 6
    T0 = np.eye(4) if initial is None else np.array(initial, dtype=float)
    fx, fy, cx, cy, baseline = map(float, cam)
    ok, T, beta, S, r = _gauss_newton(np.ascontiguousarray(za, dtype=float), np.ascontiguousarray(zb, dtype=float),
                                      fx, fy, cx, cy, baseline, offset, iterations, T0, HUBER_PX)
    if not ok:
        return None
    n = za.shape[0]
    inliers = np.abs(r) <= 3 * HUBER_PX
    dof = int(inliers.sum()) - 3 * n - g
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
    return T, beta, S_inv, r, r.size - 3 * n - g, sigma2


def fit_pair(za: np.ndarray, zb: np.ndarray, cam, offset: bool = False, min_points: int = 12,
             step: int = 0, gap: int = 1, initial: np.ndarray | None = None) -> TwoViewFit | None:
    """The fit (D2) of one step pair's matched pixels ``za``, ``zb`` (n,4), or None: the pairs whose
    rows agree, then again from the start on the points whose eight residuals all stay within
    ``TRIM_PX`` (gross mismatches removed, not only down-weighted; where none was, the first fit is
    that fit); None when fewer than
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
    if keep.all() and initial is None:
        second = first  # the same points from the same start: the same fit
    else:
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


def matched_pixels(seq: Sequence, a: int, b: int, rng: np.random.Generator | None = None,
                   extra_noise: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(za, zb), (m,4) each: the pixels at steps ``a`` and ``b`` of the tracks seen at both, row by
    row the same track, kept where both disparities exceed ``MIN_DISPARITY``; with ``rng``, white
    noise of ``extra_noise`` px is added to every pixel first (the disparities are those of the
    noisy pixels)."""
    ids_a, za = seq.observations(a)
    ids_b, zb = seq.observations(b)
    _, ia, ib = np.intersect1d(ids_a, ids_b, assume_unique=True, return_indices=True)
    za, zb = za[ia], zb[ib]
    if rng is not None:
        za = za + rng.normal(0.0, extra_noise, za.shape)
        zb = zb + rng.normal(0.0, extra_noise, zb.shape)
    keep = (za[:, 0] - za[:, 2] > MIN_DISPARITY) & (zb[:, 0] - zb[:, 2] > MIN_DISPARITY)
    return za[keep], zb[keep]


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
    pairs = []
    for k in pair_steps(seq.num_steps, gap, max_pairs, skip) if steps is None else steps:
        za, zb = matched_pixels(seq, int(k), int(k) + gap, rng, extra_noise)  # the noise drawn in step order
        if za.shape[0] >= min_points:
            pairs.append((int(k), za, zb))

    def fit(pair):
        return fit_pair(pair[1], pair[2], cam, offset, min_points, pair[0], gap)

    if len(pairs) < THREADED_PAIRS:
        return [f for f in map(fit, pairs) if f is not None]
    # the compiled fit releases the GIL: two threads fit every other pair each (one task a thread: a
    # task a pair cost more in waiting than the fits), each as alone; the fits in the pairs' order
    pool = ThreadPoolExecutor(FIT_THREADS)
    try:
        shares = list(pool.map(lambda first: [fit(p) for p in pairs[first::FIT_THREADS]], range(FIT_THREADS)))
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    fits = [None] * len(pairs)
    for first, share in enumerate(shares):
        fits[first::FIT_THREADS] = share
    return [f for f in fits if f is not None]


@warms_up
def _warm_up() -> None:
    rng = np.random.default_rng(0)
    za = np.column_stack([rng.uniform(100, 1100, 30), rng.uniform(50, 300, 30), np.zeros(30), np.zeros(30)])
    za[:, 2], za[:, 3] = za[:, 0] - rng.uniform(5, 50, 30), za[:, 1]
    cam = (700.0, 700.0, 600.0, 180.0, 0.5)
    for offset in (True, False):
        _bundle_adjust(za, za.copy(), cam, offset, iterations=1)
