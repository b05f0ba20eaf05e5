"""Two-view bundle adjustments of step pairs: what the tracks alone say about motion, offset and noise.

For the points seen at steps k and k+h (the same track ids), the unknowns are each point's true
(u, v, disparity) at k, the rigid camera motion k -> k+h and, optionally, the stereo pair's
disparity offset beta (D1 of ``backend.run.stereo_offset``). They minimize the robust (Huber,
``HUBER_PX``) error of all eight measured pixels, ``uL vL uR vR`` at k and at k+h:

    z_k   = [u, v, u - d - beta, v]
    z_k+h = [pi_L(T q(u, v, d)), pi_R(T q(u, v, d)) - beta],  q = the point triangulated at k        (D2)

by Gauss-Newton with the points eliminated (Schur complement), one compiled call for many step
pairs (:func:`_fit_batch`; numpy inverts their normal matrices after). Both frames' pixels are
measurements, so pixel noise in either biases neither the motion nor beta (triangulating at k and
fitting k+h alone would: errors in variables). Pairs whose rows disagree (|vL - vR| beyond the
sequence's :func:`tolerances`) are left out, and after a first fit the points with a residual beyond
its trim are dropped and the fit repeated (gross mismatches).

The fits serve three decisions of a run: the disparity offset (``stereo_offset``, with beta), the
pixel noise and the track drift (``noise``, ``drift``: the residuals' scale for gaps h = 1..3),
and the IMU's error against vision (``noise``: the fitted motion as an IMU-frame twist).
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from ..compiled import jit, warms_up
from ..data.sequence import Sequence
from ..estimator.linalg import inverse3, median_inplace, solve_small
from ..geometry import se3

__all__ = ["TwoViewFit", "Tolerances", "tolerances", "fit_pair", "fit_pairs", "matched_pixels", "pair_steps",
           "pooled_mean_square"]

#: Huber threshold (px) of the fit.
HUBER_PX = 1.0
#: A pair is used only if its rows agree in both frames: |vL - vR| within this (px), or, where the
#: sequence's rows are noisier, within ``ROW_SPREADS`` robust standard deviations of its row
#: differences beyond their median (:func:`tolerances`: noise of 1 px per pixel is 1.4 px of row
#: difference, and a fixed 2 px would cut its tails and bias the measured noise low) ...
ROW_PX = 2.0
ROW_SPREADS = 4.5
#: ... and, after a first fit, every one of its eight residuals is within this (px), or within
#: ``TRIM_SPREADS`` times the rows' noise per pixel where that is wider.
TRIM_PX = 3.0
TRIM_SPREADS = 3.0
#: Gauss-Newton iterations of a fit at most (it stops earlier once a step is below 1e-6 in the
#: motion and 1e-4 px in beta).
ITERATIONS = 8
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
    # computed with the fit (:func:`_fit_batch`, numpy's numbers), else from the residuals when asked:
    scale: float | None = field(default=None, repr=False)  # robust_scale()
    sum_squares: float | None = field(default=None, repr=False)  # the residuals' sum of squares
    disparity: np.ndarray | None = field(default=None, repr=False)  # (n,) px, each kept point's uL - uR at k (N5, T3)

    @property
    def points(self) -> int:
        return self.residuals.shape[0]

    def robust_scale(self) -> float:
        """1.4826 MAD of the residuals, scaled for the unknowns fitted (px per coordinate)."""
        if self.scale is not None:
            return self.scale
        r = self.residuals.ravel()
        return float(1.4826 * np.median(np.abs(r)) * np.sqrt(r.size / max(self.dof, 1)))

    def mean_square(self) -> tuple[float, int]:
        """(sum of squared residuals, their degrees of freedom): a pooled RMS that keeps the heavy
        tail of real tracks (up to the fit's trim), which the robust scale leaves out."""
        if self.sum_squares is not None:
            return self.sum_squares, self.dof
        return float(np.sum(self.residuals**2)), self.dof


def pooled_mean_square(fits: list[TwoViewFit]) -> tuple[float, float]:
    """(the residuals' mean square pooled over ``fits`` (px^2), its standard error): each pair's
    :meth:`TwoViewFit.mean_square`, summed over the pairs' degrees of freedom; the error by the delta
    method over the pairs (their mean squares weighted by their degrees of freedom)."""
    ms = np.array([f.mean_square() for f in fits], dtype=float)  # (ssq, dof) per pair
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
def _predict_point(T, beta, p0, p1, p2, fx, fy, cx, cy, fb, pred):
    """(D2) the 8 predicted pixels of the point (u, v, d) at k into ``pred``; returns what its
    Jacobians reuse: (depth, x (the point at k), q = R x + t (at k+h), z = max(q2, 1e-6))."""
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
    return depth, x0, x1, x2, q0, q1, q2, z


@jit
def _point(T, beta, p0, p1, p2, fx, fy, cx, cy, fb, pred, Jp, Jg, jac, work):
    """(D2) for one point (u, v, d) at k: its 8 predicted pixels into ``pred``; with ``jac`` d/dp
    (8,3) and d/d(delta, beta) (8,7) into ``Jp``, ``Jg``; ``work`` (4,4,3) scratch."""
    depth, x0, x1, x2, q0, q1, q2, z = _predict_point(T, beta, p0, p1, p2, fx, fy, cx, cy, fb, pred)
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


@jit
def _point_jacobians(T, beta, p0, p1, p2, fx, fy, cx, cy, fb, pred, A, G):
    """(D2) for one point (u, v, d) at k, as :func:`_point` with ``jac`` but only the Jacobian rows
    that vary: its 8 predicted pixels into ``pred``; d/dp of the four pixels at k+h into ``A``
    (4,3); d/d(rho, phi) of those four into ``G`` (4,6). The rest is constant:

        d(uL vL uR vR at k)/dp = [[1,0,0], [0,1,0], [1,0,-1], [0,1,0]],  d/d(rho, phi) = 0,
        d(uR at k)/dbeta = d(uR at k+h)/dbeta = -1,  every other d/dbeta = 0.

    With x the point at k (camera), q = R x + t at k+h, P = d(pixels at k+h)/dq (4,3) and
    D = dx/dp (3,3):

        P = [[fx/z, 0, -fx q0/z^2], [0, fy/z, -fy q1/z^2], [fx/z, 0, -fx q0/z^2 + fb/z^2], [0, fy/z, -fy q1/z^2]]
        D = [[d/fx, 0, -x0/p2], [0, d/fy, -x1/p2], [0, 0, -x2/p2]]   (d = fb/p2 the depth)
        A = P R D,  G = [P, -P q^]

    The products skip only the structural zeros of P, D and q^ (x * 0 added to a sum changes
    nothing), each remaining sum in :func:`_point`'s order: the numbers are :func:`_point`'s, bit
    for bit."""
    depth, x0, x1, x2, q0, q1, q2, z = _predict_point(T, beta, p0, p1, p2, fx, fy, cx, cy, fb, pred)
    iz = 1.0 / z
    P00 = fx * iz
    P02 = -fx * q0 * iz * iz
    P11 = fy * iz
    P12 = -fy * q1 * iz * iz
    P22 = P02 + fb * iz * iz
    D00 = depth / fx
    D11 = depth / fy
    D02 = -x0 / p2
    D12 = -x1 / p2
    D22 = -x2 / p2
    RD00, RD01, RD02 = T[0, 0] * D00, T[0, 1] * D11, T[0, 0] * D02 + T[0, 1] * D12 + T[0, 2] * D22
    RD10, RD11, RD12 = T[1, 0] * D00, T[1, 1] * D11, T[1, 0] * D02 + T[1, 1] * D12 + T[1, 2] * D22
    RD20, RD21, RD22 = T[2, 0] * D00, T[2, 1] * D11, T[2, 0] * D02 + T[2, 1] * D12 + T[2, 2] * D22
    A[0, 0], A[0, 1], A[0, 2] = P00 * RD00 + P02 * RD20, P00 * RD01 + P02 * RD21, P00 * RD02 + P02 * RD22
    A[1, 0], A[1, 1], A[1, 2] = P11 * RD10 + P12 * RD20, P11 * RD11 + P12 * RD21, P11 * RD12 + P12 * RD22
    A[2, 0], A[2, 1], A[2, 2] = P00 * RD00 + P22 * RD20, P00 * RD01 + P22 * RD21, P00 * RD02 + P22 * RD22
    A[3, 0], A[3, 1], A[3, 2] = A[1, 0], A[1, 1], A[1, 2]  # vR = vL
    G[0, 0], G[0, 1], G[0, 2] = P00, 0.0, P02
    G[1, 0], G[1, 1], G[1, 2] = 0.0, P11, P12
    G[2, 0], G[2, 1], G[2, 2] = P00, 0.0, P22
    G[0, 3], G[0, 4], G[0, 5] = -(P02 * -q1), -(P00 * -q2 + P02 * q0), -(P00 * q1)
    G[1, 3], G[1, 4], G[1, 5] = -(P11 * q2 + P12 * -q1), -(P12 * q0), -(P11 * -q0)
    G[2, 3], G[2, 4], G[2, 5] = -(P22 * -q1), -(P00 * -q2 + P22 * q0), -(P00 * q1)
    for b in range(6):
        G[3, b] = G[1, b]


@jit
def _gauss_newton(za, zb, fx, fy, cx, cy, baseline, offset, iterations, T0, huber):
    """The Huber-weighted Gauss-Newton of (D2) with the points eliminated (Schur complement), in one
    compiled call: (ok, T, beta, S (g,g) of the last iteration, residuals (n,8) at the end); ok
    False when a residual is not finite or a normal matrix is singular (the residuals then unset).

    Per point i, with J_p (8,3), J_g (8,g) its Jacobians (:func:`_point_jacobians`), W the Huber
    weights and r its residuals:

        H_pp = J_p^T W J_p (+ 1e-9 I),  H_pg = J_p^T W J_g,  b_p = J_p^T W r
        S   += J_g^T W J_g - H_pg^T H_pp^-1 H_pg,   rhs += J_g^T W r - H_pg^T H_pp^-1 b_p

    then S dg = rhs (dg = -(S + 1e-9 I)^-1 rhs the step of the motion and beta) and each point's
    step dp = -H_pp^-1 (b_p + H_pg dg). The constant rows of J_p, J_g (rows 0-3, and beta's column)
    enter each sum in closed form: w0 + w2 etc. below are their products, in the order of the rows."""
    g = 7 if offset else 6
    n = za.shape[0]
    fb = fx * baseline
    T = T0.copy()
    beta = 0.0
    p = np.empty((n, 3))
    z = np.empty((n, 8))
    for i in range(n):
        p[i, 0], p[i, 1], p[i, 2] = za[i, 0], za[i, 1], za[i, 0] - za[i, 2]
        for j in range(4):
            z[i, j], z[i, 4 + j] = za[i, j], zb[i, j]
    res = np.empty((n, 8))
    S = np.zeros((g, g))
    pred = np.empty(8)
    A = np.empty((4, 3))  # J_p rows 4-7
    G = np.empty((4, 6))  # J_g rows 4-7, columns rho, phi
    Hinv = np.empty((n, 3, 3))
    Hpg = np.empty((n, 3, g))
    bp = np.empty((n, 3))
    r = np.empty(8)
    w = np.empty(8)
    Hpp = np.empty((3, 3))
    c = np.empty(3)
    rhs = np.zeros(g)
    for _ in range(iterations):
        S[:] = 0.0
        rhs[:] = 0.0
        for i in range(n):
            _point_jacobians(T, beta, p[i, 0], p[i, 1], p[i, 2], fx, fy, cx, cy, fb, pred, A, G)
            for j in range(8):
                r[j] = pred[j] - z[i, j]
                if not math.isfinite(r[j]):
                    return False, T, beta, S, res
                a = abs(r[j])
                w[j] = 1.0 if a <= huber else huber / max(a, 1e-12)
            w0, w1, w2, w3, w6 = w[0], w[1], w[2], w[3], w[6]
            # rows 0-3 of J_p: (1,0,0), (0,1,0), (1,0,-1), (0,1,0)
            Hpp[0, 0], Hpp[0, 1], Hpp[0, 2] = w0 + w2, 0.0, -w2
            Hpp[1, 0], Hpp[1, 1], Hpp[1, 2] = 0.0, w1 + w3, 0.0
            Hpp[2, 0], Hpp[2, 1], Hpp[2, 2] = -w2, 0.0, w2
            bp[i, 0] = w0 * r[0] + w2 * r[2]
            bp[i, 1] = w1 * r[1] + w3 * r[3]
            bp[i, 2] = -w2 * r[2]
            for a in range(3):
                for b in range(3):
                    s = Hpp[a, b]
                    for k in range(4):
                        s += A[k, a] * w[4 + k] * A[k, b]
                    Hpp[a, b] = s + (1e-9 if a == b else 0.0)
                for b in range(6):
                    s = 0.0
                    for k in range(4):
                        s += A[k, a] * w[4 + k] * G[k, b]
                    Hpg[i, a, b] = s
                s = bp[i, a]
                for k in range(4):
                    s += A[k, a] * w[4 + k] * r[4 + k]
                bp[i, a] = s
            if offset:  # beta's column of J_g: -1 in rows 2 and 6
                Hpg[i, 0, 6] = w2 * -1.0 + A[2, 0] * w6 * -1.0
                Hpg[i, 1, 6] = A[2, 1] * w6 * -1.0
                Hpg[i, 2, 6] = -1.0 * w2 * -1.0 + A[2, 2] * w6 * -1.0
            for a in range(6):
                for b in range(a, 6):
                    s = 0.0
                    for k in range(4):
                        s += G[k, a] * G[k, b] * w[4 + k]
                    S[a, b] += s
                    if b != a:
                        S[b, a] += s
                if offset:
                    s = G[2, a] * -1.0 * w6
                    S[a, 6] += s
                    S[6, a] += s
                s = 0.0
                for k in range(4):
                    s += G[k, a] * w[4 + k] * r[4 + k]
                rhs[a] += s
            if offset:
                S[6, 6] += w2 + w6
                rhs[6] += -1.0 * w2 * r[2] + -1.0 * w6 * r[6]
            if not inverse3(Hpp, Hinv[i]):
                return False, T, beta, S, res
            # S -= Hgp Hpp^-1 Hpg, rhs -= Hgp Hpp^-1 bp
            for a in range(g):
                t0 = Hpg[i, 0, a] * Hinv[i, 0, 0] + Hpg[i, 1, a] * Hinv[i, 1, 0] + Hpg[i, 2, a] * Hinv[i, 2, 0]
                t1 = Hpg[i, 0, a] * Hinv[i, 0, 1] + Hpg[i, 1, a] * Hinv[i, 1, 1] + Hpg[i, 2, a] * Hinv[i, 2, 1]
                t2 = Hpg[i, 0, a] * Hinv[i, 0, 2] + Hpg[i, 1, a] * Hinv[i, 1, 2] + Hpg[i, 2, a] * Hinv[i, 2, 2]
                for b in range(g):
                    S[a, b] -= t0 * Hpg[i, 0, b] + t1 * Hpg[i, 1, b] + t2 * Hpg[i, 2, b]
                rhs[a] -= t0 * bp[i, 0] + t1 * bp[i, 1] + t2 * bp[i, 2]
        M = S.copy()
        for a in range(g):
            M[a, a] += 1e-9
        dg, ok = solve_small(M, rhs)
        if not ok:
            return False, T, beta, S, res
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
    for i in range(n):
        _predict_point(T, beta, p[i, 0], p[i, 1], p[i, 2], fx, fy, cx, cy, fb, pred)
        for j in range(8):
            res[i, j] = pred[j] - z[i, j]
    return True, T, beta, S, res


@jit
def _block_sum(x, lo, n):
    """x[lo:lo+n].sum() for n <= 128 in numpy's order: eight running sums, combined pairwise, then
    the rest one by one (below 8: one by one)."""
    if n < 8:
        s = 0.0
        for i in range(lo, lo + n):
            s += x[i]
        return s
    r0, r1, r2, r3 = x[lo], x[lo + 1], x[lo + 2], x[lo + 3]
    r4, r5, r6, r7 = x[lo + 4], x[lo + 5], x[lo + 6], x[lo + 7]
    i = 8
    while i < n - n % 8:
        j = lo + i
        r0 += x[j]
        r1 += x[j + 1]
        r2 += x[j + 2]
        r3 += x[j + 3]
        r4 += x[j + 4]
        r5 += x[j + 5]
        r6 += x[j + 6]
        r7 += x[j + 7]
        i += 8
    s = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        s += x[lo + i]
        i += 1
    return s


@jit
def _pairwise_sum(x):
    """x.sum() in numpy's order (its pairwise summation of a contiguous float64 array): a
    block of up to 128 by :func:`_block_sum`, a longer range as the sum of its halves (the first
    half's length a multiple of 8), so a compiled sum is numpy's to the bit. The halving runs on an
    explicit stack: numba's cache does not load a recursive kernel safely."""
    los = np.empty(64, dtype=np.int64)
    ns = np.empty(64, dtype=np.int64)
    stage = np.zeros(64, dtype=np.int64)  # 0: to split, 1: first half summed, 2: both
    left = np.empty(64)
    los[0], ns[0] = 0, x.size
    top = 0
    ret = 0.0  # the sum of the range last finished
    while top >= 0:
        m = ns[top]
        if m <= 128:
            ret = _block_sum(x, los[top], m)
            top -= 1
            continue
        half = m // 2
        half -= half % 8
        if stage[top] == 0:
            stage[top] = 1
            los[top + 1], ns[top + 1], stage[top + 1] = los[top], half, 0
            top += 1
        elif stage[top] == 1:
            left[top] = ret
            stage[top] = 2
            los[top + 1], ns[top + 1], stage[top + 1] = los[top] + half, m - half, 0
            top += 1
        else:
            ret = left[top] + ret
            top -= 1
    return ret


@jit
def _noise_of(r, g, squares):
    """(usable, sigma^2) of a fit's residuals ``r`` (n,8) with ``g`` unknowns besides the points: the
    residuals within ``3 HUBER_PX`` (inliers) have dof = inliers - 3n - g degrees of freedom and
    sigma^2 = (their sum of squares) / dof; unusable when dof < 20 or a residual is not finite.
    ``squares``: scratch of at least 8n."""
    n = r.shape[0]
    m = 0
    finite = True
    for i in range(n):
        for j in range(8):
            x = r[i, j]
            if not math.isfinite(x):
                finite = False
            if abs(x) <= 3 * HUBER_PX:
                squares[m] = x * x
                m += 1
    dof = m - 3 * n - g
    if dof < 20 or not finite:
        return False, 0.0
    return True, _pairwise_sum(squares[:m]) / dof


@jit
def _rows_within(r, limit):
    """(n,) bool: the rows of ``r`` (n,8) whose eight entries all lie within ``limit`` in absolute value."""
    n = r.shape[0]
    keep = np.empty(n, dtype=np.bool_)
    for i in range(n):
        ok = True
        for j in range(8):
            if not abs(r[i, j]) <= limit:
                ok = False
        keep[i] = ok
    return keep


@jit
def _fit_batch(za, zb, begin, end, fx, fy, cx, cy, baseline, offset, min_points, iterations, huber, start,
               with_initial, row_px, trim_px):
    """The compiled part of :func:`fit_pair` for many step pairs in one call (the GIL released
    throughout): pair k's matched pixels are ``za[begin[k]:end[k]]``, ``zb[...]`` (n,4);
    ``start`` (4,4) the motion to start from: the identity, or with ``with_initial`` a given one (the
    second fit then starts from the first's motion and is made even when no point was trimmed). Per
    pair: the rows that agree (|vL - vR| <= ``row_px`` in both frames), the first fit, the trimming
    (``trim_px``), the second fit (or the first again), each
    fit's noise (:func:`_noise_of`) and the final residuals' bound; what needs S^-1 is left to the
    caller (numpy's inverse, to keep its numbers). Returns

    - status (m,): 0 no fit, 1 a fit (the second is the first), 2 a fit whose first must pass too;
    - T (m,4,4), beta (m,), S (m,g,g), sigma^2 (m,), dof (m,) of the final fit (dof: residuals
      minus unknowns, as ``TwoViewFit.dof``);
    - beta, S, sigma^2 of the first fit (status 2);
    - the final residuals of pair k: ``residuals[rows[k]:rows[k+1]]`` (n_k,8);
    - their robust scale and sum of squares (m,) each (``TwoViewFit.robust_scale``, ``mean_square``:
      numpy's median and pairwise sum, to the bit);
    - the disparity uL - uR at k of each final residual row's point (total,)."""
    m = begin.size
    g = 7 if offset else 6
    status = np.zeros(m, dtype=np.int64)
    Ts = np.zeros((m, 4, 4))
    betas = np.zeros(m)
    Ss = np.zeros((m, g, g))
    sigma2s = np.zeros(m)
    dofs = np.zeros(m, dtype=np.int64)
    betas1 = np.zeros(m)
    Ss1 = np.zeros((m, g, g))
    sigma2s1 = np.zeros(m)
    total = 0
    for k in range(m):
        total += end[k] - begin[k]
    residuals = np.empty((total, 8))
    disparities = np.empty(total)
    rows = np.zeros(m + 1, dtype=np.int64)
    scales = np.zeros(m)
    sums = np.zeros(m)
    squares = np.empty(8 * max(total, 1))
    for k in range(m):
        rows[k + 1] = rows[k]
        a0, a1 = begin[k], end[k]
        agree = np.empty(a1 - a0, dtype=np.int64)
        n = 0
        for i in range(a0, a1):
            if abs(za[i, 1] - za[i, 3]) <= row_px and abs(zb[i, 1] - zb[i, 3]) <= row_px:
                agree[n] = i
                n += 1
        if n < min_points:
            continue
        A = np.empty((n, 4))
        B = np.empty((n, 4))
        for i in range(n):
            for j in range(4):
                A[i, j] = za[agree[i], j]
                B[i, j] = zb[agree[i], j]
        fit_start = start
        for second in range(2):  # the first fit, then (unless it is the final one) the fit of the kept points
            ok, T, beta, S, r = _gauss_newton(A, B, fx, fy, cx, cy, baseline, offset, iterations, fit_start, huber)
            if ok:
                ok, sigma2 = _noise_of(r, g, squares)
            if not ok:
                break
            keep = _rows_within(r, trim_px)
            kept = 0
            for i in range(r.shape[0]):
                kept += keep[i]
            if second:
                ok = kept == r.shape[0]  # every residual of the final fit within trim_px
                break
            if kept < max(min_points, 2 * n / 3):
                ok = False
                break
            if kept == n and not with_initial:
                break  # the same points from the same start: the same fit
            betas1[k], sigma2s1[k] = beta, sigma2
            for i in range(g):
                for j in range(g):
                    Ss1[k, i, j] = S[i, j]
            A2 = np.empty((kept, 4))
            B2 = np.empty((kept, 4))
            j2 = 0
            for i in range(n):
                if keep[i]:
                    for j in range(4):
                        A2[j2, j] = A[i, j]
                        B2[j2, j] = B[i, j]
                    j2 += 1
            A, B = A2, B2  # the final fit's points
            if with_initial:
                fit_start = T
        if not ok:
            continue
        status[k] = 1 + second
        n2 = r.shape[0]
        for i in range(4):
            for j in range(4):
                Ts[k, i, j] = T[i, j]
        betas[k], sigma2s[k] = beta, sigma2
        for i in range(g):
            for j in range(g):
                Ss[k, i, j] = S[i, j]
        dofs[k] = r.size - 3 * n2 - g
        for i in range(n2):
            disparities[rows[k] + i] = A[i, 0] - A[i, 2]
            for j in range(8):
                residuals[rows[k] + i, j] = r[i, j]
                squares[8 * i + j] = r[i, j] * r[i, j]
        rows[k + 1] = rows[k] + n2
        sums[k] = _pairwise_sum(squares[:8 * n2])
        for i in range(n2):
            for j in range(8):
                squares[8 * i + j] = abs(r[i, j])
        # 1.4826 MAD sqrt(size / dof), in TwoViewFit.robust_scale's order
        scales[k] = 1.4826 * median_inplace(squares[:8 * n2]) * np.sqrt(r.size / max(dofs[k], 1))
    return status, Ts, betas, Ss, sigma2s, dofs, betas1, Ss1, sigma2s1, residuals, rows, scales, sums, disparities


def _usable_inverses(S: np.ndarray, beta: np.ndarray, sigma2: np.ndarray,
                     offset: bool) -> tuple[np.ndarray, np.ndarray]:
    """(S^-1 (m,g,g), usable (m,) bool) of fits' S (m,g,g): numpy's inverse (one call for all; one a
    matrix where one of them is singular); a fit is usable when its inverse is finite and, with
    ``offset``, beta is finite, |beta| < 20 px and its variance S^-1[6,6] sigma^2 finite and positive."""
    if S.shape[0] == 0:
        return S.copy(), np.zeros(0, dtype=bool)
    try:
        S_inv = np.linalg.inv(S)
        usable = np.ones(S.shape[0], dtype=bool)
    except np.linalg.LinAlgError:
        S_inv = np.full_like(S, np.nan)
        usable = np.zeros(S.shape[0], dtype=bool)
        for k in range(S.shape[0]):
            try:
                S_inv[k] = np.linalg.inv(S[k])
                usable[k] = True
            except np.linalg.LinAlgError:
                pass
    usable &= np.isfinite(S_inv).all(axis=(1, 2))
    if offset:
        with np.errstate(invalid="ignore", over="ignore"):
            var = S_inv[:, 6, 6] * sigma2
            usable &= np.isfinite(beta) & np.isfinite(var) & (var > 0) & (np.abs(beta) < 20)
    return S_inv, usable


def _fits(steps, za: np.ndarray, zb: np.ndarray, begin: np.ndarray, end: np.ndarray, cam, offset: bool,
          min_points: int, gap: int, initial: np.ndarray | None = None,
          tolerance: Tolerances | None = None) -> list[TwoViewFit | None]:
    """:func:`fit_pair` of each step pair k (``steps[k]``, pixels ``za[begin[k]:end[k]]``,
    ``zb[...]``, (n,4) float64 C-ordered; ``tolerance``: the rows' and the trim's, by default the
    fixed ones): one compiled call for them all (:func:`_fit_batch`), then
    numpy's inverse of the fits' S (:func:`_usable_inverses`)."""
    if len(steps) == 0:
        return []
    fx, fy, cx, cy, baseline = map(float, cam)
    status, T, beta, S, sigma2, dof, beta1, S1, sigma21, residuals, rows, scales, sums, disparities = _fit_batch(
        za, zb, begin, end, fx, fy, cx, cy, baseline, offset, int(min_points), ITERATIONS, HUBER_PX,
        np.eye(4) if initial is None else np.ascontiguousarray(initial, dtype=float), initial is not None,
        *(tolerance or Tolerances()).bounds())
    good = status > 0
    S_inv, usable = _usable_inverses(S[good], beta[good], sigma2[good], offset)
    ok = np.zeros(status.size, dtype=bool)
    ok[good] = usable
    twice = status == 2  # the first fit must have been usable too
    ok[twice] &= _usable_inverses(S1[twice], beta1[twice], sigma21[twice], offset)[1]
    out: list[TwoViewFit | None] = [None] * status.size
    for j, k in enumerate(np.flatnonzero(good).tolist()):
        if ok[k]:
            s2 = float(sigma2[k])
            out[k] = TwoViewFit(int(steps[k]), gap, T[k], S_inv[j, :6, :6] * s2, float(beta[k]),
                                float(S_inv[j, 6, 6]) * s2 if offset else float("nan"),
                                residuals[rows[k]:rows[k + 1]], int(dof[k]), float(scales[k]), float(sums[k]),
                                disparities[rows[k]:rows[k + 1]])
    return out


def fit_pair(za: np.ndarray, zb: np.ndarray, cam, offset: bool = False, min_points: int = 12,
             step: int = 0, gap: int = 1, initial: np.ndarray | None = None,
             tolerance: Tolerances | None = None) -> TwoViewFit | None:
    """The fit (D2) of one step pair's matched pixels ``za``, ``zb`` (n,4), or None: the pairs whose
    rows agree, then again from the start on the points whose eight residuals all stay within
    the trim (gross mismatches removed, not only down-weighted; where none was, the first fit is
    that fit); None when fewer than
    ``min_points`` remain, a third of them is trimmed, or the fit is degenerate.
    ``cam`` = (fx, fy, cx, cy, baseline); ``initial``: the motion to start from (default: none, for
    the small motions of consecutive steps); ``tolerance``: the rows' and the trim's (the
    sequence's :func:`tolerances`; default the fixed ``ROW_PX``, ``TRIM_PX``)."""
    n = np.array([za.shape[0]])
    return _fits([step], np.ascontiguousarray(za, dtype=float), np.ascontiguousarray(zb, dtype=float), n * 0, n,
                 cam, offset, min_points, gap, initial, tolerance)[0]


@dataclass(frozen=True)
class Tolerances:
    """What the fits (D2) of a sequence take for a match and a fitted point."""

    rows_px: float = ROW_PX  # the largest |vL - vR| of a stereo match
    trim_px: float = TRIM_PX  # the largest residual of a point of the final fit

    def bounds(self) -> tuple[float, float]:
        return float(self.rows_px), float(self.trim_px)


def tolerances(obs_pixels: np.ndarray) -> Tolerances:
    """The fits' tolerances for a sequence's observations ``obs_pixels`` (L,4), from its row
    differences d = vL - vR (median m, robust spread s = 1.4826 MAD; mismatches are a minority, so
    both are the matches'): rows within |m| + ``ROW_SPREADS`` s, a trim of ``TRIM_SPREADS`` s / sqrt 2
    (the noise per pixel), each at least the fixed ``ROW_PX``, ``TRIM_PX``. The walk's re-fit (T4 of
    ``backend.run.drift``) keeps the sequence's: the same estimator on pixels that moved."""
    d = obs_pixels[:, 1] - obs_pixels[:, 3]
    if d.size < 10:
        return Tolerances()
    m = float(np.median(d))
    s = 1.4826 * float(np.median(np.abs(d - m)))
    return Tolerances(max(ROW_PX, abs(m) + ROW_SPREADS * s), max(TRIM_PX, TRIM_SPREADS * s / math.sqrt(2.0)))


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


def matched_pixels(seq: Sequence, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    """(za, zb), (m,4) each: the pixels at steps ``a`` and ``b`` of the tracks seen at both, row by
    row the same track, kept where both disparities exceed ``MIN_DISPARITY``."""
    ids_a, za = seq.observations(a)
    ids_b, zb = seq.observations(b)
    _, ia, ib = np.intersect1d(ids_a, ids_b, assume_unique=True, return_indices=True)
    za, zb = za[ia], zb[ib]
    keep = (za[:, 0] - za[:, 2] > MIN_DISPARITY) & (zb[:, 0] - zb[:, 2] > MIN_DISPARITY)
    return za[keep], zb[keep]


def fit_pairs(seq: Sequence, gap: int = 1, max_pairs: int = 300, offset: bool = False, min_points: int = 12,
              skip: np.ndarray | None = None, steps: np.ndarray | None = None, seed: int = 0,
              walk: float = 0.0) -> list[TwoViewFit]:
    """The fits (D2) of up to ``max_pairs`` step pairs (k, k+``gap``) spread over ``seq`` (see
    :func:`pair_steps`; or exactly the pairs starting at ``steps``), each from the points seen in
    both with a disparity above ``MIN_DISPARITY``. ``walk`` > 0: a displacement e ~ N(0, walk I2)
    px^2 (``numpy.random.default_rng(seed)``) is added to both images' pixels of every point at
    k+``gap`` (the walk's re-fit, T4 of ``backend.run.drift``). The sequence's :func:`tolerances`
    hold."""
    K = seq.K
    tolerance = tolerances(seq.obs_pixels)
    cam = (K[0, 0], K[1, 1], K[0, 2], K[1, 2], seq.baseline)
    ks = np.asarray(pair_steps(seq.num_steps, gap, max_pairs, skip) if steps is None else steps, dtype=np.int64)
    a, b, ptr = _matched_rows(seq.obs_ids, seq.obs_ptr, ks, gap)  # the tracks seen at both, in id order
    za, zb = seq.obs_pixels[a], seq.obs_pixels[b]
    if walk > 0:  # the same move of a point's left and right pixels: its disparity stays
        e = np.random.default_rng(seed).normal(0.0, np.sqrt(walk), (zb.shape[0], 2))
        zb = zb + np.hstack([e, e])
    keep = (za[:, 0] - za[:, 2] > MIN_DISPARITY) & (zb[:, 0] - zb[:, 2] > MIN_DISPARITY)
    kept = np.zeros(keep.size + 1, dtype=np.int64)
    np.cumsum(keep, out=kept[1:])
    begin, end = kept[ptr[:-1]], kept[ptr[1:]]
    used = np.flatnonzero(end - begin >= min_points)  # the pairs with enough points
    za, zb, begin, end, ks = za[keep], zb[keep], begin[used], end[used], ks[used]

    def fit(first: int, every: int = 1) -> list:
        return _fits(ks[first::every], za, zb, np.ascontiguousarray(begin[first::every]),
                     np.ascontiguousarray(end[first::every]), cam, offset, min_points, gap, tolerance=tolerance)

    if used.size < THREADED_PAIRS:
        return [f for f in fit(0) if f is not None]
    # the compiled fits release the GIL: two threads fit every other pair each, one compiled call a
    # thread (:func:`_fits`); the fits in the pairs' order
    pool = ThreadPoolExecutor(FIT_THREADS)
    try:
        shares = list(pool.map(lambda first: fit(first, FIT_THREADS), range(FIT_THREADS)))
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    fits = [None] * used.size
    for first, share in enumerate(shares):
        fits[first::FIT_THREADS] = share
    return [f for f in fits if f is not None]


@jit
def _matched_rows(ids, ptr, steps, gap):
    """(a, b, pairs): for each k of ``steps``, the rows into the observation arrays (CSR: ``ids``
    (L,), ``ptr`` (N+1,), ids strictly increasing within a step) of the tracks seen at both k and
    k+``gap``, in id order (numpy's intersect1d of the two steps' ids); pair j's rows are
    ``a[pairs[j]:pairs[j+1]]``, ``b[...]``."""
    m = steps.size
    bound = 0
    for j in range(m):
        k = steps[j]
        bound += min(ptr[k + 1] - ptr[k], ptr[k + gap + 1] - ptr[k + gap])
    a = np.empty(bound, dtype=np.int64)
    b = np.empty(bound, dtype=np.int64)
    pairs = np.zeros(m + 1, dtype=np.int64)
    n = 0
    for j in range(m):
        k = steps[j]
        i, i_end = ptr[k], ptr[k + 1]
        l, l_end = ptr[k + gap], ptr[k + gap + 1]
        while i < i_end and l < l_end:
            if ids[i] < ids[l]:
                i += 1
            elif ids[i] > ids[l]:
                l += 1
            else:
                a[n], b[n] = i, l
                n += 1
                i += 1
                l += 1
        pairs[j + 1] = n
    return a[:n], b[:n], pairs


@warms_up
def _warm_up() -> None:
    rng = np.random.default_rng(0)
    za = np.column_stack([rng.uniform(100, 1100, 30), rng.uniform(50, 300, 30), np.zeros(30), np.zeros(30)])
    za[:, 2], za[:, 3] = za[:, 0] - rng.uniform(5, 50, 30), za[:, 1]
    cam = (700.0, 700.0, 600.0, 180.0, 0.5)
    for offset in (True, False):
        fit_pair(za, za.copy(), cam, offset)
    fit_pair(za, za.copy(), cam, False, initial=np.eye(4))
    _matched_rows(np.arange(3), np.array([0, 2, 3]), np.zeros(1, dtype=np.int64), 1)
