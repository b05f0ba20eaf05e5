"""The joint update of pose and landmarks with a step's stereo observations (compiled).

Given the prior innovation of the k observations of landmarks in the state (residual r, H P and
S = H P H^T + R from the error model, ``backend.estimator.invariant`` or ``.body``):

Three rows per observation. The pixel noise is white (sigma^2 I) and on rectified pairs the rows
of H for vL and vR are equal, so the orthogonal change of rows

    [uL, vL, uR, vR] -> [uL, (vL + vR)/sqrt 2, uR | (vL - vR)/sqrt 2]                           (U1)

leaves the noise sigma^2 I and puts all the state information in the first three rows; the last
has H = 0 and only adds d^2 / sigma^2 to the NIS. The update from 3 rows is identical to the one
from 4 (the NIS, gate and RANSAC errors are computed over all 4), at (3/4)^2 of the dense work.
Each 3-row block of H touches 6 pose and 3 landmark columns of P.

Gate. Observation i is used only if in front of the camera and

    NIS_i = r_i^T S_ii^-1 r_i + d_i^2 / sigma^2 <= chi2_4^-1(gate_probability)                  (U4)

1-point RANSAC (Civera et al., J. Field Robotics 2010), every gated observation a hypothesis: the
update with observation j alone changes every residual by H dx_j = (S - R)_{:,j} S_jj^-1 r_j, so
all hypotheses cost products with the S already formed; the one whose updated 4-pixel errors
are within ``ransac_threshold_px`` for the most observations wins.                           (U5)

Joint update, with S = L L^T over the rows of the inliers (Cholesky),

    A = L^-1 H P,   w = L^-1 r,   dx = A^T w,   P <- P - A^T A                                 (U2)

the symmetric form of P - K S K^T (equal to the Joseph form for the optimal gain K), one triangle
by BLAS syrk and mirrored, so P stays exactly symmetric.

Rescue. The observations RANSAC rejected are tested again against the inliers' update: with
X = L^-1 S_ir, residual r_r - X^T w and covariance S_rr - X^T X (U4 on those); the ones that pass
join the update, whose factor over [inliers; rescued] is [[L, 0], [X_ok^T, L_o]] with
L_o L_o^T = S_oo - X_ok^T X_ok, so S is factored once.                                          (U3)

:func:`select_and_update_inplace` does U4, U5, U3 and U2 in one call.

Second-order terms of the prediction (Gelb, "Applied Optimal Estimation", 1974, the truncated
second-order filter; Bar-Shalom, Li and Kirubarajan 2001, 10.3). A row h_j(q) = c_j w_j / q_z of
the camera point q (c = fx, sqrt 2 fy, fx; w = x, y, x - b) is curved in depth, and at the 5-20 px
disparities of street and aerial scenes a landmark's depth is uncertain by several per cent: the
expected pixel is not the pixel of the expected point. With Sigma_q = J (S_ii - sigma^2 I) J^T the
covariance of q (J = d q / d rows, the inverse of (I3)'s d rows / d q, so that no model's Jacobians
are needed: S_ii - sigma^2 I = H_i P H_i^T) and H_j = d^2 h_j / d q^2,

    r_i <- r_i - b_i,   b_ij = 1/2 tr(H_j Sigma_q),   S_ii <- S_ii + C_i,   C_i,jl = 1/2 tr(H_j Sigma_q H_l Sigma_q)   (U7)

where H_j has d^2 h_j / dw dz = -c_j / z^2 and d^2 h_j / dz^2 = 2 c_j w_j / z^3 only. The gain and
P's update (U2) use that S. A first-order filter predicts the pixels of an uncertain landmark
nearer the image centre and at a smaller disparity than they fall on average (E[1/z] > 1/E[z]),
with too small an S; the errors of many such observations do not average out, and no noise level
repairs them. On synthetic streets and aerial scenes with 1 px of white noise (truth known, the
filter told the true noise, 12 runs of 300 steps on each of three geometries,
``benchmarks/pixel_noise_consistency.py``) the pose NEES goes from 7.0-9.9 to 5.7-6.6 (expected 6)
and the position error down by a third (street 0.19-0.25 -> 0.12-0.15 m); at 0.5 px it changes
little (pose NEES 5.4-7.6 -> 5.1-6.8). :func:`second_order_inplace`; ``update.second_order``.

Observations of unequal noise (N5: a variance per observation) enter by whitening (U6,
:func:`whiten`): each observation's rows scaled to the one variance the compiled update takes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..compiled import jit, warms_up
from ..geometry import se3
from .layout import CORE, SQRT_HALF, landmark_row
from .linalg import cholesky_upper_inplace, downdate_lower, solve_lower_inplace
from .covariance import mirror_lower_inplace


def three_rows(a: np.ndarray) -> np.ndarray:
    """(U1): rows [uL, vL, uR, vR] (axis 1 of a (k,4,...) array) -> [uL, (vL + vR)/sqrt 2, uR]."""
    out = a[:, :3].copy()
    out[:, 1] = (a[:, 1] + a[:, 3]) * SQRT_HALF
    return out


@dataclass
class Innovation:
    """The prior innovation of one step's observations of landmarks in the state, 3-row form (U1)."""

    residual: np.ndarray  # (k,3) r = z - h(x)
    off_row: np.ndarray  # (k,) residual of (vL - vR)/sqrt 2: no state in it
    H_x: np.ndarray  # (3k,6) d h / d pose
    H_m: np.ndarray  # (k,3,3) d h / d landmark
    HP: np.ndarray  # (3k,D) H P
    S: np.ndarray  # (3k,3k) H P H^T + R
    nis: np.ndarray  # (k,) (U4), 4 dof
    in_front: np.ndarray  # (k,) bool
    variance: np.ndarray | None = None  # (k,) each observation's own pixel variance, once whitened (U6)


@jit
def _nis3(S, r0, r1, r2):
    """r^T S^-1 r for a symmetric 3x3 S (Cholesky); inf when S is not positive definite."""
    l00 = S[0, 0]
    if not l00 > 0.0:
        return np.inf
    l00 = np.sqrt(l00)
    l10 = S[1, 0] / l00
    l20 = S[2, 0] / l00
    d1 = S[1, 1] - l10 * l10
    if not d1 > 0.0:
        return np.inf
    l11 = np.sqrt(d1)
    l21 = (S[2, 1] - l20 * l10) / l11
    d2 = S[2, 2] - l20 * l20 - l21 * l21
    if not d2 > 0.0:
        return np.inf
    l22 = np.sqrt(d2)
    w0 = r0 / l00
    w1 = (r1 - l10 * w0) / l11
    w2 = (r2 - l20 * w0 - l21 * w1) / l22
    return w0 * w0 + w1 * w1 + w2 * w2


@jit
def innovation_covariance(P, H_x, H_m, slots, pixel_var, residual, off_row, core=CORE):
    """H P (3k,D), S = H P H^T + R (3k,3k) and the NIS (k,) of each observation (4 dof: its
    3-row block plus off_row^2 / sigma^2, U1), for H given as H_x (3k,6) on the pose and
    H_m (k,3,3) on landmark ``slots`` (each 3-row block touches 6 + 3 columns of P); the landmark
    slots start at row ``core`` of P (``layout.CORE``; 15 for the inertial state)."""
    D = P.shape[0]
    k = slots.size
    m = 3 * k
    HP = np.zeros((m, D))
    for i in range(k):
        base = landmark_row(core, slots[i])
        for a in range(3):
            r = 3 * i + a
            out = HP[r]
            for j in range(6):
                h = H_x[r, j]
                if h != 0.0:
                    row = P[j]
                    for c in range(D):
                        out[c] += h * row[c]
            for t in range(3):
                h = H_m[i, a, t]
                row = P[base + t]
                for c in range(D):
                    out[c] += h * row[c]
    S = np.empty((m, m))
    for r in range(m):  # lower triangle (r2 <= r), mirrored: S exactly symmetric
        hp = HP[r]
        for r2 in range(r + 1):
            i2 = r2 // 3
            b = r2 - 3 * i2
            base = landmark_row(core, slots[i2])
            s = 0.0
            for j in range(6):
                s += hp[j] * H_x[r2, j]
            for t in range(3):
                s += hp[base + t] * H_m[i2, b, t]
            S[r, r2] = s
            S[r2, r] = s
    for r in range(m):
        S[r, r] += pixel_var
    return HP, S, block_nis(S, residual, off_row, pixel_var)


@jit
def block_nis(S, residual, off_row, pixel_var):
    """(U4) the NIS (k,) of each observation: its 3-row block of S and off_row^2 / sigma^2."""
    k = residual.shape[0]
    nis = np.empty(k)
    Sb = np.empty((3, 3))  # the block, C-ordered as _rescue_test's (one compiled _nis3)
    for i in range(k):
        o = 3 * i
        for a in range(3):
            for b in range(3):
                Sb[a, b] = S[o + a, o + b]
        nis[i] = _nis3(Sb, residual[i, 0], residual[i, 1], residual[i, 2]) + off_row[i] ** 2 / pixel_var
    return nis


#: (U7) the terms are formed with the camera point's covariance scaled down to at most this relative
#: depth sigma s: 1 / z expands as E[1 / (1 + x)] = 1 + s^2 + 3 s^4 + 15 s^6 + ... (x ~ N(0, s^2)),
#: a series that diverges, and at s = 0.25 the first term left out is a fifth of the one kept; a
#: landmark known to worse than that (a far point after one observation) gets the correction of
#: s = 0.25, a part of its own (unbounded, the terms reached 25 px on ece276a2019_0042's 4-5 px
#: disparities). Scaled, not skipped, so that they do not switch off and on as a landmark's depth
#: sigma crosses the bound.
SECOND_ORDER_MAX_DEPTH_SIGMA = 0.25


@jit
def second_order_inplace(residual, S, off_row, nis, in_front, pixels, fx, fy, cx, cy, baseline, pixel_var):
    """(U7) the second-order terms of the stereo prediction, in place: each observation's residual
    (k,3) less its bias b_i, its 3x3 block of S (3k,3k) plus C_i, its NIS (k,) recomputed (U4).
    ``pixels`` (k,4) are the measured [uL vL uR vR] the residuals were formed from (the predicted
    rows are the measured ones less the residual); ``S`` was formed with R = pixel_var I (before any
    whitening, U6). Sigma_q is scaled down to a relative depth sigma of ``SECOND_ORDER_MAX_DEPTH_SIGMA``
    where it is larger. Observations behind the camera, or predicted at a non-positive disparity,
    are left as they are."""
    k = residual.shape[0]
    fxb = fx * baseline
    J = np.empty((3, 3))
    Jt = np.empty((3, 3))
    Sb = np.empty((3, 3))
    A = np.empty((3, 3))
    Sig = np.empty((3, 3))
    M = np.empty((3, 3, 3))
    coef = np.empty(3)
    w = np.empty(3)
    changed = np.zeros(k, dtype=np.bool_)
    for i in range(k):
        if not in_front[i]:
            continue
        o = 3 * i
        uL = pixels[i, 0] - residual[i, 0]
        vs = (pixels[i, 1] + pixels[i, 3]) * SQRT_HALF - residual[i, 1]  # sqrt 2 v of the prediction
        uR = pixels[i, 2] - residual[i, 2]
        d = uL - uR
        if not d > 0.0:
            continue
        changed[i] = True
        z = fxb / d
        x = (uL - cx) * z / fx
        y = (vs * SQRT_HALF - cy) * z / fy
        # J = d q / d [uL, sqrt 2 v, uR] (the triangulation's Jacobian, S2, in the rows of U1)
        J[0, 0], J[0, 1], J[0, 2] = z / fx - x / d, 0.0, x / d
        J[1, 0], J[1, 1], J[1, 2] = -y / d, SQRT_HALF * z / fy, y / d
        J[2, 0], J[2, 1], J[2, 2] = -z / d, 0.0, z / d
        for a in range(3):
            for b in range(3):
                Jt[b, a] = J[a, b]
                Sb[a, b] = S[o + a, o + b] - (pixel_var if a == b else 0.0)  # H_i P H_i^T
        se3.small_matmul_into(se3.small_matmul_into(J, Sb, A), Jt, Sig)  # Sigma_q = J Sb J^T
        rel2 = Sig[2, 2] / (z * z)  # the depth's relative variance: the expansion holds where it is small
        if rel2 > SECOND_ORDER_MAX_DEPTH_SIGMA ** 2:
            shrink = SECOND_ORDER_MAX_DEPTH_SIGMA ** 2 / rel2
            for a in range(3):
                for b in range(3):
                    Sig[a, b] *= shrink
        coef[0], coef[1], coef[2] = fx, 2.0 * SQRT_HALF * fy, fx
        w[0], w[1], w[2] = x, y, x - baseline
        for j in range(3):
            aj = 1 if j == 1 else 0  # the row's numerator: x (uL, uR) or y (v)
            hw = -coef[j] / (z * z)  # d^2 h_j / dw dz
            hz = 2.0 * coef[j] * w[j] / (z * z * z)  # d^2 h_j / dz^2
            residual[i, j] -= hw * Sig[aj, 2] + 0.5 * hz * Sig[2, 2]  # 1/2 tr(H_j Sigma)
            for b in range(3):  # M_j = H_j Sigma: row aj = hw Sigma[2], row 2 = hw Sigma[aj] + hz Sigma[2]
                M[j, 0, b] = 0.0
                M[j, 1, b] = 0.0
                M[j, aj, b] = hw * Sig[2, b]
                M[j, 2, b] = hw * Sig[aj, b] + hz * Sig[2, b]
        for j in range(3):  # C_jm = 1/2 tr(M_j M_m), added to the block (symmetric)
            for m in range(j + 1):
                t = 0.0
                for a in range(3):
                    for b in range(3):
                        t += M[j, a, b] * M[m, b, a]
                S[o + j, o + m] += 0.5 * t
                if m != j:
                    S[o + m, o + j] += 0.5 * t
    updated = block_nis(S, residual, off_row, pixel_var)  # (U4) with the new residuals and blocks
    for i in range(k):
        if changed[i]:
            nis[i] = updated[i]


def pixel_variance(sigma2: float, per_disparity: float, disparity: np.ndarray) -> np.ndarray:
    """(N5 of ``backend.run.noise``) each observation's pixel variance sigma^2 + b d (px^2), for
    disparities ``disparity`` (k,) px (a negative one counted as 0)."""
    return sigma2 + per_disparity * np.maximum(np.asarray(disparity, dtype=float), 0.0)


def whitened_residuals(S: np.ndarray, residual: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(R4) e_i = L_i^-1 r_i (n,3) of the observations ``rows`` (n,) of an innovation (3-row form,
    U1), S_ii = L_i L_i^T its 3x3 block of ``S`` (3k,3k); N(0, I3) under the filter's model."""
    idx = 3 * np.asarray(rows)[:, None] + np.arange(3)
    L = np.linalg.cholesky(S[idx[:, :, None], idx[:, None, :]])
    return np.linalg.solve(L, residual[rows][:, :, None])[:, :, 0]


def huber_inflation(nis: np.ndarray, threshold: float, gate: float) -> np.ndarray | None:
    """(U8) Huber's weights on each observation's Mahalanobis distance d = sqrt(NIS) (4 dof), as
    factors on its noise variance: 1 up to d^2 = ``threshold``, d / sqrt(threshold) beyond (the
    weight psi(d) / d = c / d of Huber's loss), 1 again beyond the ``gate``, which rejects those
    anyway (U4). None when every factor is 1. (k,)"""
    nis = np.asarray(nis, dtype=float)
    down = (nis > threshold) & (nis <= gate)
    if not down.any():
        return None
    out = np.ones(nis.size)
    out[down] = np.sqrt(nis[down] / threshold)
    return out


def whiten(inn: Innovation, obs_var: np.ndarray, ref_var: float) -> Innovation:
    """(U6) observations of their own pixel variances ``obs_var`` (k,) (N5) as observations of the
    one variance ``ref_var`` the compiled update takes: ``inn`` was formed with R = ref_var I, so

        S_true = S + diag(obs_var_i - ref_var)   (3 rows each),   w_i = sqrt(ref_var / obs_var_i),
        r' = w r,  off' = w off,  H' = w H,  (HP)' = w HP,  S' = W S_true W = H' P H'^T + ref_var I,

    an exact change of the measurement's units: the gain, dx and P's update are those of R_i =
    obs_var_i I, and the NIS (chi-square gate, U4) is unchanged by it. The 1-point RANSAC's
    threshold (U5) then counts in units of sqrt(ref_var): an observation's error is judged against
    its own noise. Returns a new Innovation (``variance`` set)."""
    w = np.sqrt(ref_var / obs_var)
    w3 = np.repeat(w, 3)
    S = inn.S.copy()
    S[np.diag_indices_from(S)] += np.repeat(obs_var - ref_var, 3)
    S *= w3[:, None]
    S *= w3[None, :]
    residual = inn.residual * w[:, None]
    off_row = inn.off_row * w
    return Innovation(residual, off_row, inn.H_x * w3[:, None], inn.H_m * w[:, None, None], inn.HP * w3[:, None], S,
                      block_nis(S, residual, off_row, ref_var), inn.in_front, obs_var)


@jit
def one_point_ransac(S, residual, off_row, candidates, pixel_var, threshold):
    """1-point RANSAC for the EKF (Civera et al., J. Field Robotics 2010), every candidate a hypothesis.

    Hypothesis j: the EKF update with observation j alone, dx_j = P H_j^T S_jj^-1 r_j. It changes
    every residual by H dx_j = (S - R)_{:,j} S_jj^-1 r_j, so all hypotheses cost products with the
    S already formed. An observation supports j when its updated 4-pixel error (the 3 rows and the
    row difference, which no hypothesis changes) is within ``threshold``; the hypothesis with the
    most support wins (ties: the smaller summed error), and its supporters are returned as a mask
    over all observations. A moving car ahead, tracked by several features that agree with each
    other but not with the scene, loses.
    """
    k = candidates.size
    rows = _block_rows(candidates)
    m = rows.size // 3
    a = np.empty((m, 3))  # S_jj^-1 r_j by Cramer's rule (S_jj a gated, regular innovation block)
    for jj in range(m):
        o = rows[3 * jj]
        s00, s01, s02 = S[o, o], S[o, o + 1], S[o, o + 2]
        s10, s11, s12 = S[o + 1, o], S[o + 1, o + 1], S[o + 1, o + 2]
        s20, s21, s22 = S[o + 2, o], S[o + 2, o + 1], S[o + 2, o + 2]
        c0, c1, c2 = s11 * s22 - s12 * s21, -(s10 * s22 - s12 * s20), s10 * s21 - s11 * s20
        det = s00 * c0 + s01 * c1 + s02 * c2
        r0, r1, r2 = residual[o // 3, 0], residual[o // 3, 1], residual[o // 3, 2]
        a[jj, 0] = c0 / det * r0 + -(s01 * s22 - s02 * s21) / det * r1 + (s01 * s12 - s02 * s11) / det * r2
        a[jj, 1] = c1 / det * r0 + (s00 * s22 - s02 * s20) / det * r1 + -(s00 * s12 - s02 * s10) / det * r2
        a[jj, 2] = c2 / det * r0 + -(s00 * s21 - s01 * s20) / det * r1 + (s00 * s11 - s01 * s10) / det * r2
    err = np.empty((m, m))
    for ii in range(m):
        oi = rows[3 * ii]
        off2 = off_row[oi // 3] ** 2
        for jj in range(m):
            oj = rows[3 * jj]
            s = off2
            for t in range(3):
                ch = S[oi + t, oj] * a[jj, 0] + S[oi + t, oj + 1] * a[jj, 1] + S[oi + t, oj + 2] * a[jj, 2]
                if ii == jj:
                    ch -= pixel_var * a[jj, t]
                d = residual[oi // 3, t] - ch
                s += d * d
            err[ii, jj] = np.sqrt(s)
    best = 0
    best_score = -np.inf
    for jj in range(m):
        support = 0
        total = 0.0
        for ii in range(m):
            e = err[ii, jj]
            if e <= threshold:
                support += 1
            total += min(e, 1e6)
        score = support - 1e-6 * total / (m * 1e3)
        if score > best_score:
            best_score = score
            best = jj
    out = np.zeros(k, dtype=np.bool_)
    for ii in range(m):
        if err[ii, best] <= threshold:
            out[rows[3 * ii] // 3] = True
    return out


@jit
def _rescue_test(X, w, S, rest_rows, residual, off_row, pixel_var, gate):
    """(U3) the chi-square test of the rest's observations (rows ``rest_rows`` of their 3-row blocks,
    :func:`_block_rows`) after the update with the inliers: residual r_r - X^T w and covariance
    S_rr - X^T X (diagonal 3x3 blocks only), with X = L^-1 S_ir (3 m_i, 3 m_r) and w = L^-1 r_i.
    Returns a mask over the rest's observations."""
    mr = rest_rows.size // 3
    ok = np.zeros(mr, dtype=np.bool_)
    n = X.shape[0]
    Sb = np.empty((3, 3))
    r = np.empty(3)
    for jj in range(mr):
        c = 3 * jj
        o = rest_rows[c]
        for a in range(3):
            s = 0.0
            for t in range(n):
                s += X[t, c + a] * w[t]
            r[a] = residual[o // 3, a] - s
            for b in range(3):
                s = 0.0
                for t in range(n):
                    s += X[t, c + a] * X[t, c + b]
                Sb[a, b] = S[o + a, o + b] - s
        ok[jj] = _nis3(Sb, r[0], r[1], r[2]) + off_row[o // 3] ** 2 / pixel_var <= gate
    return ok


@jit
def _block_rows(mask):
    """Rows of the 3-row blocks (U1) of the observations where ``mask``, in order."""
    n = 0
    for i in range(mask.size):
        n += mask[i]
    rows = np.empty(3 * n, dtype=np.int64)
    n = 0
    for i in range(mask.size):
        if mask[i]:
            for a in range(3):
                rows[n + a] = 3 * i + a
            n += 3
    return rows


@jit
def joint_update_inplace(P, HP, S, residual, off_row, inlier, rest, pixel_var, gate):
    """The joint update (U2) with the ``inlier`` observations and those of ``rest`` that pass the
    rescue test after it (U3), given the prior H P (3k,D), S = H P H^T + R (3k,3k) and residuals
    (k,3) of all k observations. P is changed in place, exactly symmetric.

    With L L^T = S_ii over the inliers' rows and w = L^-1 r_i, the rest are tested (``_rescue_test``)
    on r_r - X^T w and S_rr - X^T X, X = L^-1 S_ir; the factor of S over [inliers; rescued] is the
    block [[L, 0], [X_ok^T, L_o]] with L_o L_o^T = S_oo - X_ok^T X_ok, so S is factored once. Then

        A = L^-1 H P,   w = L^-1 r,   P <- P - A^T A  (syrk, lower triangle, mirrored),   dx = A^T w.

    Returns (status, dx (D,), used mask (k,)): status is 0, or LAPACK potrf's info > 0 when an
    innovation covariance is not positive definite, in which case P is left unchanged.
    """
    k = inlier.size
    D = P.shape[0]
    dx = np.zeros(D)
    used = np.zeros(k, dtype=np.bool_)
    rows_i = _block_rows(inlier)
    mi = rows_i.size
    U = np.empty((mi, mi))  # upper triangle: L^T
    for a in range(mi):
        for b in range(a, mi):
            U[a, b] = S[rows_i[a], rows_i[b]]
    info = cholesky_upper_inplace(U)
    if info != 0:
        return info, dx, used
    rows_r = _block_rows(rest)
    mr = rows_r.size
    w = np.empty((mi + mr, 1))  # L^-1 r over [inliers; rescued]
    for a in range(mi):
        w[a, 0] = residual[rows_i[a] // 3, rows_i[a] % 3]
    solve_lower_inplace(U, w[:mi])
    cols = rows_r[:0]  # the rescued rows' positions in rows_r
    if mr:
        X = np.empty((mi, mr))
        for a in range(mi):
            for b in range(mr):
                X[a, b] = S[rows_i[a], rows_r[b]]
        solve_lower_inplace(U, X)
        cols = _block_rows(_rescue_test(X, w[:mi, 0], S, rows_r, residual, off_row, pixel_var, gate))
        mo = cols.size
        if mo:
            J = np.zeros((mi + mo, mi + mo))  # upper triangle: [[L, 0], [X_ok^T, L_o]]^T
            for a in range(mi):
                for b in range(a, mi):
                    J[a, b] = U[a, b]
                for b in range(mo):
                    J[a, mi + b] = X[a, cols[b]]
            Uo = np.empty((mo, mo))
            for a in range(mo):
                for b in range(a, mo):
                    s = S[rows_r[cols[a]], rows_r[cols[b]]]
                    for t in range(mi):
                        s -= X[t, cols[a]] * X[t, cols[b]]
                    Uo[a, b] = s
            info = cholesky_upper_inplace(Uo)
            if info != 0:
                return info, dx, used
            for a in range(mo):
                row = rows_r[cols[a]]
                s = residual[row // 3, row % 3]
                for t in range(mi):
                    s -= X[t, cols[a]] * w[t, 0]
                w[mi + a, 0] = s
            solve_lower_inplace(Uo, w[mi:mi + mo])
            for a in range(mo):
                for b in range(a, mo):
                    J[mi + a, mi + b] = Uo[a, b]
            U = J
    m = mi + cols.size
    A = np.empty((m, D))  # H P over [inliers; rescued]
    for a in range(m):
        row = HP[rows_i[a] if a < mi else rows_r[cols[a - mi]]]
        for c in range(D):
            A[a, c] = row[c]
    solve_lower_inplace(U, A)
    downdate_lower(P, A)
    mirror_lower_inplace(P)
    for a in range(m):
        wa = w[a, 0]
        row = A[a]
        for c in range(D):
            dx[c] += row[c] * wa
    for a in range(0, m, 3):
        used[(rows_i[a] if a < mi else rows_r[cols[a - mi]]) // 3] = True
    return 0, dx, used


@jit
def count_rejections_inplace(outlier_run, slots, rejected, limit):
    """Steps in a row the RANSAC rejected each track: ``outlier_run`` (per landmark slot) counts one
    more where ``rejected`` and restarts at 0 for the other observations of ``slots``; True where the
    count reaches ``limit``: such a track (a car ahead, followed by several features that agree with
    each other and not with the scene) is not rescued. The filter keeps the counts of a track that
    leaves the state and goes on (re-anchoring) by its id (``FilterState.stash_outlier_runs``)."""
    out = np.zeros(slots.size, dtype=np.bool_)
    for j in range(slots.size):
        s = slots[j]
        outlier_run[s] = outlier_run[s] + 1 if rejected[j] else 0
        out[j] = rejected[j] and outlier_run[s] >= limit
    return out


@jit
def select_and_update_inplace(P, HP, S, residual, off_row, nis, in_front, slots, gate, ransac_threshold, pixel_var,
                              outlier_run, persistent_steps, gated_run):
    """One step's selection and joint update (``VisualInertialEKF.update``) in one call: the
    chi-square gate on ``nis``; with ``ransac_threshold`` > 0 and 3 candidates or more the 1-point
    RANSAC (:func:`one_point_ransac`), whose rejected observations are not offered to the rescue once
    ``outlier_run`` reaches ``persistent_steps`` (0: not counted); then :func:`joint_update_inplace`. Finally
    ``gated_run`` (per slot) is reset for the used observations and counts one more for the others.
    (:func:`count_rejections_inplace` counts the RANSAC's rejections.)
    Returns (status, dx, used) as :func:`joint_update_inplace`; on status != 0 nothing is used."""
    k = slots.size
    use = np.empty(k, dtype=np.bool_)
    n_use = 0
    for j in range(k):
        use[j] = in_front[j] and nis[j] <= gate
        if use[j]:
            n_use += 1
    rest = np.zeros(k, dtype=np.bool_)
    if ransac_threshold > 0 and n_use >= 3:
        inlier = one_point_ransac(S, residual, off_row, use, pixel_var, ransac_threshold)
        for j in range(k):
            rest[j] = use[j] and not inlier[j]
        if persistent_steps:
            persistent = count_rejections_inplace(outlier_run, slots, rest, persistent_steps)
            for j in range(k):
                rest[j] = rest[j] and not persistent[j]
        use = inlier
    status = 0
    dx = np.zeros(P.shape[0])
    n_use = 0
    for j in range(k):
        if use[j]:
            n_use += 1
    if n_use:
        status, dx, use = joint_update_inplace(P, HP, S, residual, off_row, use, rest, pixel_var, gate)
        if status:
            use[:] = False
    for j in range(k):
        gated_run[slots[j]] = 0 if use[j] else gated_run[slots[j]] + 1
    return status, dx, use


@warms_up(only="landmarks")
def _warm_up() -> None:
    """The kernels a run calls from Python (``backend.compiled``): the RANSAC, the joint update and the
    rejection counts run inside :func:`select_and_update_inplace`; :func:`block_nis` also in :func:`whiten`;
    :func:`second_order_inplace` (U7)."""
    D, k = CORE + 6, 2
    P = np.eye(D)
    slots = np.arange(k, dtype=np.int64)
    H_x = np.ones((3 * k, 6))
    H_m = np.ones((k, 3, 3))
    residual = np.ones((k, 3))
    off_row = np.zeros(k)
    HP, S, nis = innovation_covariance(P, H_x, H_m, slots, 1.0, residual, off_row, CORE)  # core given, as the models pass it
    block_nis(S, residual, off_row, 1.0)  # whiten (U6) calls it from Python
    pixels = np.array([[600.0, 180.0, 560.0, 180.0]] * k)
    second_order_inplace(residual.copy(), S.copy(), off_row, nis.copy(), np.ones(k, dtype=np.bool_), pixels,
                         700.0, 700.0, 600.0, 180.0, 0.5, 1.0)
    counts = np.zeros(k, dtype=np.int64)
    select_and_update_inplace(P.copy(), HP, S, residual, off_row, nis, np.ones(k, dtype=np.bool_), slots, 9.0, 2.0,
                              1.0, counts, 10, counts.copy())
