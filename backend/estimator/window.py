"""A sliding window of pose clones: the features of a real IMU's run used without landmark states.

The multi-state constraint filter of Mourikis & Roumeliotis ("A multi-state constraint Kalman
filter for vision-aided inertial navigation", ICRA 2007), as OpenVINS runs it, on the project's
right-invariant errors (``backend.estimator.inertial``, J1). The state is the inertial core (15
rows: rho, phi, db_g, nu, db_a) and up to ``estimator.window`` clones of the pose at the last
frames, 6 rows each, in the order they were taken (``FilterState.clones``); no landmark enters it.

- Clone (W1). At each frame the pose joins the window: T_c = T, its error xi_c = [rho_c; phi_c]
  with T_c = exp(xi_c^) T_hat_c (the pose's own error at that instant), so

      P <- [[P, P E^T], [E P, E P E^T]],   E = [I_6 0]  (the pose rows)

- Propagation (W2). A clone is static and so is its estimate: its error does not move. Only the
  core's (J5) does:  P_cc <- Phi P_cc Phi^T + Q,  P_c,w <- Phi P_c,w,  P_ww unchanged (the
  state helper's ``CoreTransition`` with the interval's Phi and Q).
- A feature (W3). A track seen in clones c_1 .. c_n (n >= 2) is triangulated: the world point p
  minimizing the stereo reprojection errors of its n observations (3 rows each, U1), by
  Gauss-Newton from the median, axis by axis, of its observations' own stereo triangulations.
  Gross errors leave first: an observation that start misses by more than 3 times the chi2_4
  gate's radius (U4), then, after the fit, the worst observation beyond the gate itself, and the
  point is fitted again (twice at most).
- Its residuals (W4). s = T_c^-1 p = T_hat_c^-1 exp(-xi_c^) p ~ T_hat_c^-1 (p - rho_c + p^ phi_c), so
  with M = d(rows)/dq cam_R_world (the observation's Jacobian on a world point, I3):

      r_i = z_i - h(T_hat_c, p_hat) ~ H_c,i xi_c + M_i dp + n_i,   H_c,i = M_i E,  E = [-I, p_hat^]

  The point is not in the state: the 3n rows are multiplied by an orthonormal basis N of the left
  null space of H_p = [M_1; ..; M_n], leaving 3n - 3 rows r_o = H_o xi_w + n_o (H_o = N^T H_x,
  r_o = N^T r) that no longer depend on dp, with the same white noise sigma^2 I. The update needs
  only their information, and N N^T = I - H_p (H_p^T H_p)^-1 H_p^T makes it the Schur complement
  of the point's block of the stacked rows' (no basis formed): with N_i = M_i^T M_i,

      Lambda_f = H_o^T H_o:  block (i, j) = E^T (delta_ij N_i - N_i (H_p^T H_p)^-1 N_j) E
      g_f = H_o^T r_o:       block i = E^T (M_i^T r_i - N_i (H_p^T H_p)^-1 H_p^T r)
      r_o^T r_o = r^T r - r^T H_p (H_p^T H_p)^-1 H_p^T r

  (blocks on the clones the observations were taken in; H_p^T H_p is well conditioned: its spread is
  the point's depth over the baseline).
- Gate (W5). NIS = r_o^T (H_o P_ww H_o^T + sigma^2 I)^-1 r_o + sum d_i^2 / sigma^2 (the off rows
  of U1) <= chi2_{4n-3}^-1(gate_probability); a feature that fails is left out whole. The
  pixels' own (r_o^T r_o + sum d_i^2) / sigma^2 bounds the NIS from above: within the gate it
  decides without S (and is the NIS reported: 0.3 % above the exact one on the room flight); beyond
  it the exact one by the push-through identity, r_o^T S^-1 r_o = (r_o^T r_o - g_f^T (sigma^2 I +
  P_f Lambda_f)^-1 P_f g_f) / sigma^2 (P_f: the clones' block of the feature's observations).
- Update (W6). The information of every feature used at a frame, summed (Lambda, g over the clones'
  6w columns), updates the whole state in the clones' dimension (the push-through identity,
  ``StateHelper.update_window``): the core is corrected through its covariance with the clones,
  then the retraction (J7) of the core and of each clone, T_c <- exp(dx_c^) T_hat_c.
- Marginalization (W7). A track is used when it ends, when its segment reaches size - (id mod
  size/2) observations (staggered, so that some tracks pin every frame's pose, at rest too), and
  at the latest when the window is full and the track was seen in the oldest clone, which then
  leaves: its rows and columns are dropped. A track used at a frame goes on as a new feature from
  its next observation (no pixel is used twice).

A feature's map point is its triangulation, with the covariance G (H_x P_ww H_x^T + sigma^2 I) G^T,
G = (H_p^T H_p)^-1 H_p^T, G H_x = [.. (H_p^T H_p)^-1 N_i E ..]: its pixels' and its clones' uncertainty
(the update it then makes is not in it).

- The trajectory (W8). A clone's estimate improves while tracks that saw it are used; when it
  leaves the window (or the run ends) every track that saw it has been used, and its pose and the
  covariance of its right perturbation (I7, from its 6 x 6 block) are the frame's pose of the run's
  trajectory: a fixed-lag smoother over ``size`` frames (EuRoC's 40 pairs at rest: a path of 2.9
  mm against 11 mm for the pose at each frame's own update). The filter's current pose
  (``VisualInertialEKF.world_T_imu``, the online API) is the first estimate of the same.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .. import chi2
from ..compiled import jit, warms_up
from ..config import EstimatorOptions, Mode
from ..geometry import se3
from .covariance import gather_symmetric
from .invariant import body_pose_covariance
from .layout import SQRT_HALF
from .linalg import inverse3, median_inplace, solve_small
from .state_helper import StateHelper

__all__ = ["WindowStep", "WindowUpdater", "feature_information", "plan_use", "retract_clones", "settled_trajectory",
           "window_in_use", "window_text", "WINDOW_ITERATIONS"]

#: Gauss-Newton iterations of a feature's triangulation (W3)
WINDOW_ITERATIONS = 6
#: Fits of a feature's point: each after the one before left out its worst observation, a gross error (W3)
ATTEMPTS = 3
#: Before the fit, an observation whose squared error from the start point exceeds this many times
#: the chi2_4 gate (U4) is a gross error (the start is a median of single-frame triangulations: their
#: noise is in it) (W3)
SCREEN = 9.0
#: A feature is not used when a point it was seen at lies nearer the camera than this (m)
MIN_DEPTH = 0.1


@jit
def _rows_inplace(R, t, p, fx, fy, baseline, pred, M):
    """The 3-row prediction (U1, without the principal point) of the world point p (3,) from the camera
    cam_T_world = [R t] into ``pred`` (3,), and its Jacobian on p, M = d rows / d q R, into ``M`` (3,3);
    returns the depth."""
    q0 = R[0, 0] * p[0] + R[0, 1] * p[1] + R[0, 2] * p[2] + t[0]
    q1 = R[1, 0] * p[0] + R[1, 1] * p[1] + R[1, 2] * p[2] + t[1]
    q2 = R[2, 0] * p[0] + R[2, 1] * p[1] + R[2, 2] * p[2] + t[2]
    if q2 < MIN_DEPTH:
        return q2
    iz = 1.0 / q2
    s2 = 2.0 * SQRT_HALF
    pred[0] = fx * q0 * iz
    pred[1] = s2 * fy * q1 * iz
    pred[2] = fx * (q0 - baseline) * iz
    # d rows / d q: [fx iz, 0, -fx q0 iz^2], [0, s2 fy iz, -s2 fy q1 iz^2], [fx iz, 0, -fx (q0 - b) iz^2]
    a0, c0 = fx * iz, -fx * q0 * iz * iz
    b1, c1 = s2 * fy * iz, -s2 * fy * q1 * iz * iz
    c2 = -fx * (q0 - baseline) * iz * iz
    for j in range(3):
        M[0, j] = a0 * R[0, j] + c0 * R[2, j]
        M[1, j] = b1 * R[1, j] + c1 * R[2, j]
        M[2, j] = a0 * R[0, j] + c2 * R[2, j]
    return q2


@jit
def _residual_inplace(z, cx, cy, pred, res):
    """The 3-row residual (U1) of the pixels z (4,) against the prediction ``pred`` of
    :func:`_rows_inplace` into ``res`` (3,)."""
    res[0] = z[0] - cx - pred[0]
    res[1] = (z[1] + z[3]) * SQRT_HALF - 2.0 * SQRT_HALF * cy - pred[1]
    res[2] = z[2] - cx - pred[2]


@jit
def _linearize_inplace(obs, slot, Rcw, tcw, p, pixels, fx, fy, cx, cy, baseline, pred, Ms, rs):
    """The 3-row residuals (U1) ``rs[k]`` and Jacobians on the world point ``Ms[k]`` of the observations
    ``obs`` of a feature at the point p (clone ``slot[o]``'s cam_T_world = [Rcw tcw]); False when p lies
    behind one of the cameras."""
    for k in range(obs.size):
        o = obs[k]
        s = slot[o]
        if _rows_inplace(Rcw[s], tcw[s], p, fx, fy, baseline, pred, Ms[k]) < MIN_DEPTH:
            return False
        _residual_inplace(pixels[o], cx, cy, pred, rs[k])
    return True


@jit
def _squared_error(R, t, p, z, fx, fy, cx, cy, baseline, pred, M, res):
    """The squared error (px^2) of the pixels z (4,) of the world point p seen from cam_T_world = [R t]
    over the four rows of (U1), the off row's included; inf behind the camera."""
    if _rows_inplace(R, t, p, fx, fy, baseline, pred, M) < MIN_DEPTH:
        return np.inf
    _residual_inplace(z, cx, cy, pred, res)
    return res[0] ** 2 + res[1] ** 2 + res[2] ** 2 + 0.5 * (z[1] - z[3]) ** 2


@jit
def _expand_inplace(C, P, out, work):
    """E^T C E with E = [-I, P], P = p^ (3,3), into ``out`` (6,6): [[C, -C P], [P C, -P C P]]; ``work``
    (3,3,3) is work space."""
    CP, PC, PCP = work[0], work[1], work[2]
    se3.small_matmul_into(C, P, CP)
    se3.small_matmul_into(P, C, PC)
    se3.small_matmul_into(PC, P, PCP)
    for i in range(3):
        for j in range(3):
            out[i, j] = C[i, j]
            out[i, 3 + j] = -CP[i, j]
            out[3 + i, j] = PC[i, j]
            out[3 + i, 3 + j] = -PCP[i, j]


@jit
def _cholesky3(A, L):
    """L (3,3) lower with L L^T = A (3,3, symmetric); False when A is not positive definite."""
    a = A[0, 0]
    if not a > 0.0:
        return False
    L[0, 1] = L[0, 2] = L[1, 2] = 0.0
    L[0, 0] = np.sqrt(a)
    L[1, 0] = A[1, 0] / L[0, 0]
    L[2, 0] = A[2, 0] / L[0, 0]
    a = A[1, 1] - L[1, 0] * L[1, 0]
    if not a > 0.0:
        return False
    L[1, 1] = np.sqrt(a)
    L[2, 1] = (A[2, 1] - L[2, 0] * L[1, 0]) / L[1, 1]
    a = A[2, 2] - L[2, 0] * L[2, 0] - L[2, 1] * L[2, 1]
    if not a > 0.0:
        return False
    L[2, 2] = np.sqrt(a)
    return True


@jit
def _feature_terms(clones, cam_T_imu, fx, fy, cx, cy, baseline, start, count, slot, pixels, P_ww, pixel_var,
                   gate, obs_gate, iterations):
    """(W3-W5) of :func:`feature_information` without its one BLAS-sized product: returns (points, covs,
    ok, nis, used, [Lambda_d g] (6w,6w+1), W (6w,3a)) with Lambda = Lambda_d - W W^T for the a features
    within the gate."""
    F = start.size
    w = clones.shape[0]
    Lam = np.zeros((6 * w, 6 * w + 1))  # [Lambda g] of the features within the gate
    points = np.zeros((F, 3))
    covs = np.zeros((F, 3, 3))
    ok = np.empty(F, dtype=np.bool_)
    nis = np.empty(F)
    used = np.empty(F, dtype=np.int64)
    Rcw = np.empty((w, 3, 3))
    tcw = np.empty((w, 3))
    for c in range(w):
        C = se3.small_matmul(cam_T_imu, se3.inverse(clones[c]))
        for i in range(3):
            for j in range(3):
                Rcw[c, i, j] = C[i, j]
            tcw[c, i] = C[i, 3]
    pred = np.empty(3)
    M = np.empty((3, 3))
    inv = np.empty((3, 3))
    res = np.empty(3)
    most = 0
    for f in range(F):
        most = max(most, count[f])
    obs = np.empty(most, dtype=np.int64)  # the feature's observations in use
    Ms = np.empty((obs.size, 3, 3))  # ... their Jacobians on the point and residuals (_linearize_inplace)
    rs = np.empty((obs.size, 3))
    Ns = np.empty((obs.size, 3, 3))  # ... M_k^T M_k,
    Mr = np.empty((obs.size, 3))  # ... M_k^T r_k,
    Ys = np.empty((obs.size, 3, 3))  # ... (H_p^T H_p)^-1 N_k
    idx = np.empty(6 * obs.size, dtype=np.int64)  # the clones' columns of the feature's information
    C = np.empty((3, 3))
    work = np.empty((3, 3, 3))
    Lc = np.empty((3, 3))
    Wcols = np.zeros((6 * w, 3 * F))  # the rank-3 terms' columns W of the features within the gate
    accepted = 0
    for f in range(F):
        ok[f], nis[f], used[f] = False, np.inf, 0  # until the feature is fitted
        n = count[f]
        for k in range(n):
            obs[k] = start[f] + k
        # start: the median, axis by axis, of the observations' own stereo triangulations (robust to
        # gross errors)
        starts = np.empty((n, 3))
        m0 = 0
        for k in range(n):
            o = obs[k]
            d = pixels[o, 0] - pixels[o, 2]
            if d <= 0.0:
                continue
            z = fx * baseline / d
            qx, qy = (pixels[o, 0] - cx) * z / fx, (0.5 * (pixels[o, 1] + pixels[o, 3]) - cy) * z / fy
            s = slot[o]
            for a in range(3):  # Rcw^T (q - tcw)
                starts[m0, a] = (Rcw[s, 0, a] * (qx - tcw[s, 0]) + Rcw[s, 1, a] * (qy - tcw[s, 1])
                                 + Rcw[s, 2, a] * (z - tcw[s, 2]))
            m0 += 1
        if m0 == 0:
            continue
        p = np.empty(3)
        column = np.empty(m0)
        for a in range(3):
            for k in range(m0):
                column[k] = starts[k, a]
            p[a] = median_inplace(column)
        # gross errors seen from that start (a random pixel misses by tens of px) leave before the fit
        kept = 0
        for k in range(n):
            o = obs[k]
            s = slot[o]
            if _squared_error(Rcw[s], tcw[s], p, pixels[o], fx, fy, cx, cy, baseline, pred, M, res) <= (
                    SCREEN * obs_gate * pixel_var):
                obs[kept] = o
                kept += 1
        n = kept
        if n < 2:
            continue
        good = True
        for attempt in range(ATTEMPTS):  # fits again without the worst observation while it is a gross error
            for it in range(iterations):
                if not _linearize_inplace(obs[:n], slot, Rcw, tcw, p, pixels, fx, fy, cx, cy, baseline, pred, Ms, rs):
                    good = False
                    break
                JtJ = np.zeros((3, 3))
                Jtr = np.zeros(3)
                for k in range(n):
                    Mk, rk = Ms[k], rs[k]
                    for a in range(3):
                        for b in range(3):
                            JtJ[a, b] += Mk[0, a] * Mk[0, b] + Mk[1, a] * Mk[1, b] + Mk[2, a] * Mk[2, b]
                        Jtr[a] += Mk[0, a] * rk[0] + Mk[1, a] * rk[1] + Mk[2, a] * rk[2]
                if not inverse3(JtJ, inv):
                    good = False
                    break
                step = se3.small_matmul(inv, Jtr)
                big = size = 0.0  # max |step|, max |p| (NaN with a NaN, as numpy's max)
                for a in range(3):
                    p[a] += step[a]
                    if abs(step[a]) > big or math.isnan(step[a]):
                        big = abs(step[a])
                    if abs(p[a]) > size or math.isnan(p[a]):
                        size = abs(p[a])
                if big < 1e-7 * (1.0 + size):
                    break
            if not good or attempt == ATTEMPTS - 1 or n <= 2:
                break
            worst, worst_e = -1, obs_gate * pixel_var
            for k in range(n):
                o = obs[k]
                s = slot[o]
                e = _squared_error(Rcw[s], tcw[s], p, pixels[o], fx, fy, cx, cy, baseline, pred, M, res)
                if e > worst_e:
                    worst, worst_e = k, e
            if worst < 0:
                break
            for k in range(worst, n - 1):
                obs[k] = obs[k + 1]
            n -= 1
        if not good:
            continue
        # (W4) the information of its rows with the point projected out, at p: per observation
        # N_k = M_k^T M_k, H_x,k = M_k E, E = [-I, p^]; the Schur complement of the point's block
        if not _linearize_inplace(obs[:n], slot, Rcw, tcw, p, pixels, fx, fy, cx, cy, baseline, pred, Ms, rs):
            continue
        Hpp = np.zeros((3, 3))
        Hpr = np.zeros(3)
        rr = 0.0
        off = 0.0
        for k in range(n):
            Mk, rk = Ms[k], rs[k]
            for a in range(3):
                for b in range(3):
                    nab = Mk[0, a] * Mk[0, b] + Mk[1, a] * Mk[1, b] + Mk[2, a] * Mk[2, b]
                    Ns[k, a, b] = nab
                    Hpp[a, b] += nab
                mra = Mk[0, a] * rk[0] + Mk[1, a] * rk[1] + Mk[2, a] * rk[2]
                Mr[k, a] = mra
                Hpr[a] += mra
            rr += rk[0] * rk[0] + rk[1] * rk[1] + rk[2] * rk[2]
            o = obs[k]
            d = (pixels[o, 1] - pixels[o, 3]) * SQRT_HALF
            off += d * d
        if not inverse3(Hpp, inv) or not _cholesky3(inv, Lc):
            continue
        u = se3.small_matmul(inv, Hpr)
        ro2 = rr - (Hpr[0] * u[0] + Hpr[1] * u[1] + Hpr[2] * u[2])  # r_o^T r_o
        for k in range(n):
            se3.small_matmul_into(inv, Ns[k], Ys[k])  # (H_p^T H_p)^-1 N_k
        m6 = 6 * n
        # over the observations' clones, in observation order: g_f, the blocks E^T N_k E and the rank-3
        # term's columns W_f = B L (B = [.. E^T N_k ..], L L^T = (H_p^T H_p)^-1): Lambda_f = diag - W_f W_f^T
        gf = np.empty(m6)
        Df = np.empty((n, 6, 6))
        Wf = np.empty((m6, 3))
        P = se3.hat3(p)
        a3 = np.empty(3)
        for k in range(n):
            for i in range(3):
                a3[i] = Mr[k, i] - (Ns[k, i, 0] * u[0] + Ns[k, i, 1] * u[1] + Ns[k, i, 2] * u[2])  # g_f,k = E^T a3
                gf[6 * k + i] = -a3[i]
            gf[6 * k + 3] = a3[1] * p[2] - a3[2] * p[1]  # (p^)^T a3 = -p^ a3 = a3 x p
            gf[6 * k + 4] = a3[2] * p[0] - a3[0] * p[2]
            gf[6 * k + 5] = a3[0] * p[1] - a3[1] * p[0]
            _expand_inplace(Ns[k], P, Df[k], work)
            se3.small_matmul_into(P, Ns[k], C)  # E^T N_k = [-N_k; -p^ N_k]
            for i in range(3):
                for j in range(3):
                    top = 0.0
                    bottom = 0.0
                    for m in range(3):
                        top -= Ns[k, i, m] * Lc[m, j]
                        bottom -= C[i, m] * Lc[m, j]
                    Wf[6 * k + i, j] = top
                    Wf[6 * k + 3 + i, j] = bottom
            for i in range(6):
                idx[6 * k + i] = 6 * slot[obs[k]] + i
        Pf = np.empty((m6, m6))
        for i in range(m6):
            for j in range(m6):
                Pf[i, j] = P_ww[idx[i], idx[j]]
        # the pixels' own (r_o^T r_o + sum d^2) / sigma^2 bounds the NIS from above (S >= sigma^2 I) and
        # decides every feature within the gate; beyond it, exactly (push-through: r_o^T S^-1 r_o =
        # (r_o^T r_o - g_f^T (sigma^2 I + P_f Lambda_f)^-1 P_f g_f) / sigma^2)
        nis[f] = (ro2 + off) / pixel_var
        if nis[f] > gate[n]:
            Lf = np.empty((m6, m6))
            for i in range(m6):
                for j in range(m6):
                    Lf[i, j] = -(Wf[i, 0] * Wf[j, 0] + Wf[i, 1] * Wf[j, 1] + Wf[i, 2] * Wf[j, 2])
            for k in range(n):
                for i in range(6):
                    for j in range(6):
                        Lf[6 * k + i, 6 * k + j] += Df[k, i, j]
            T = se3.small_matmul(Pf, Lf)
            for i in range(m6):
                T[i, i] += pixel_var
            x, solved = solve_small(T, se3.small_matmul(Pf, gf))
            if solved:
                gx = 0.0
                for i in range(m6):
                    gx += gf[i] * x[i]
                nis[f] = (ro2 - gx + off) / pixel_var
        for a in range(3):
            points[f, a] = p[a]
        used[f] = n
        ok[f] = True
        if nis[f] > gate[n]:
            continue
        # the map point's covariance: G (H_x P H_x^T + sigma^2 I) G^T, G H_x = [.. (H_p^T H_p)^-1 N_k E ..]
        GHx = np.empty((3, m6))
        for k in range(n):
            for i in range(3):
                y0, y1, y2 = Ys[k, i, 0], Ys[k, i, 1], Ys[k, i, 2]
                GHx[i, 6 * k] = -y0
                GHx[i, 6 * k + 1] = -y1
                GHx[i, 6 * k + 2] = -y2
                GHx[i, 6 * k + 3] = y1 * p[2] - y2 * p[1]  # row i of Y p^
                GHx[i, 6 * k + 4] = y2 * p[0] - y0 * p[2]
                GHx[i, 6 * k + 5] = y0 * p[1] - y1 * p[0]
        GP = se3.small_matmul(GHx, Pf)
        for i in range(3):
            for j in range(3):
                acc = pixel_var * inv[i, j]
                for k in range(m6):
                    acc += GP[i, k] * GHx[j, k]
                covs[f, i, j] = acc
        # the feature's information joins the frame's: its blocks E^T N_k E and g_f on its clones' rows, and
        # its columns of W (the rank-3 terms' sum W W^T is one product, feature_information's)
        col = 3 * accepted
        accepted += 1
        for k in range(n):
            r0 = 6 * slot[obs[k]]
            for i in range(6):
                Lam[r0 + i, 6 * w] += gf[6 * k + i]
                for j in range(6):
                    Lam[r0 + i, r0 + j] += Df[k, i, j]
                for j in range(3):
                    Wcols[r0 + i, col + j] = Wf[6 * k + i, j]
    return points, covs, ok, nis, used, Lam, Wcols[:, :3 * accepted]


def feature_information(clones, cam_T_imu, fx, fy, cx, cy, baseline, start, count, slot, pixels, P_ww, pixel_var,
                        gate, obs_gate, iterations):
    """(W3-W5) for a batch of features, in one compiled call.

    ``clones`` (w,4,4) world_T_imu of the window; feature f has the observations
    ``start[f] .. start[f] + count[f] - 1`` (oldest first) with clone ``slot`` (int) and ``pixels``
    (4) each; ``P_ww`` (6w,6w) the clones' covariance; ``gate`` (n,) the NIS gate of a feature seen
    n times (W5); ``obs_gate`` the chi2_4 gate of one observation's squared error (px^2 / sigma^2):
    the worst observation beyond it is left out once and the point fitted again (W3). Returns
    (points (F,3), covariances (F,3,3) of those within the gate, ok (F,) bool, nis (F,), used (F,)
    observations kept, [Lambda g] (6w,6w+1)): the information H_o^T H_o and H_o^T r_o of the
    projected rows of the features within the gate (ok and nis <= gate[used]), summed (W4); ok
    False: a point behind a camera or a singular fit. The rank-3 terms' sum W W^T is one BLAS product."""
    points, covs, ok, nis, used, info, W = _feature_terms(clones, cam_T_imu, fx, fy, cx, cy, baseline, start, count,
                                                          slot, pixels, P_ww, pixel_var, gate, obs_gate, iterations)
    if W.shape[1]:
        info[:, :-1] -= W @ W.T
    return points, covs, ok, nis, used, info


@jit
def retract_clones(clones, dx):
    """(W6) T_c <- exp(dx_c^) T_hat_c for each clone (w,4,4), dx (6w,) = [rho_c; phi_c] per clone."""
    out = np.empty_like(clones)
    for c in range(clones.shape[0]):
        E, J = se3.exp_so3_and_left_jacobian(dx[6 * c + 3:6 * c + 6])
        for i in range(3):
            for j in range(3):
                out[c, i, j] = E[i, 0] * clones[c, 0, j] + E[i, 1] * clones[c, 1, j] + E[i, 2] * clones[c, 2, j]
            out[c, i, 3] = (E[i, 0] * clones[c, 0, 3] + E[i, 1] * clones[c, 1, 3] + E[i, 2] * clones[c, 2, 3]
                            + J[i, 0] * dx[6 * c] + J[i, 1] * dx[6 * c + 1] + J[i, 2] * dx[6 * c + 2])
            out[c, 3, i] = 0.0
        out[c, 3, 3] = 1.0
    return out


def window_in_use(config, inertial: bool) -> bool:
    """Whether a run holds a sliding window of clones: a real IMU's (``inertial``) SLAM run with
    ``estimator.window`` above 0 (the default); any other run keeps its landmarks in the state."""
    return inertial and config.estimator.window > 0 and Mode(config.estimator.mode) == Mode.SLAM


def window_text(config, inertial: bool) -> str | None:
    """What a run does with ``estimator.window`` (one line): a real IMU's SLAM run holds that many
    clones; any other run keeps its landmarks in the state, and says so where the option was set to
    other than its default (None then, and where it is 0)."""
    size, mode = config.estimator.window, Mode(config.estimator.mode)
    if not size:
        return None
    if window_in_use(config, inertial):
        return (f"state: a sliding window of {size} pose clones, no landmark in the state (estimator.window; "
                f"the tracks' points are projected out, W1-W7; each frame's pose is written as its clone leaves, W8)")
    if size == EstimatorOptions.window:
        return None
    what = "a velocity run" if not inertial else f"a {mode.value} run"
    return f"note: estimator.window = {size} serves a real IMU's SLAM run; {what} keeps its landmarks in the state"


@jit
def _holds(sorted_keys, key):
    """Whether the ascending ``sorted_keys`` hold ``key`` (binary search)."""
    lo, hi = 0, sorted_keys.size
    while lo < hi:
        mid = (lo + hi) // 2
        if sorted_keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo < sorted_keys.size and sorted_keys[lo] == key


def plan_use(ids, slots, last, current, full, size, stagger):
    """(W7) which tracks of the window's observations (``ids``, ``slots`` (O,), in frame order) a
    frame uses: those of the last frame's ``last`` not in this one's ``current`` (ended), those whose
    observations reach ``size`` - (id mod ``stagger``), and with the window ``full`` those seen in
    clone 0. Returns (rows (R,): the used observations, by track and then oldest first; start (F,),
    count (F,): each used track's run in ``rows``; the tracks left in the window). The sorting is
    numpy's (stable: each track's observations stay oldest first), the grouping compiled."""
    return _plan_groups(ids, slots, np.argsort(ids, kind="stable"), np.sort(last), np.sort(current), full, size,
                        stagger)


@jit
def _plan_groups(ids, slots, order, lst, cur, full, size, stagger):
    """:func:`plan_use` over the observations in ``order`` (their ids ascending), ``lst`` and ``cur``
    sorted."""
    rows = np.empty(ids.size, dtype=np.int64)
    start = np.empty(ids.size, dtype=np.int64)
    count = np.empty(ids.size, dtype=np.int64)
    n_rows = n_used = left = 0
    g0 = 0
    while g0 < ids.size:
        track = ids[order[g0]]
        g1 = g0 + 1
        while g1 < ids.size and ids[order[g1]] == track:
            g1 += 1
        use = g1 - g0 >= size - track % stagger or (full and slots[order[g0]] == 0)
        if not use:
            use = _holds(lst, track) and not _holds(cur, track)
        if use:
            start[n_used] = n_rows
            count[n_used] = g1 - g0
            n_used += 1
            for k in range(g0, g1):
                rows[n_rows] = order[k]
                n_rows += 1
        else:
            left += 1
        g0 = g1
    return rows[:n_rows], start[:n_used], count[:n_used], left


@dataclass
class WindowStep:
    """What one frame of the window did: the observations of the features used and left out (W5),
    their NIS sum and its degrees of freedom (4n - 3 a feature seen n times: its expectation), the
    features mapped, and the tracks in the window after the frame."""

    used: int
    gated: int
    nis_sum: float
    mapped: int
    active: int
    dof: int = 0


class WindowUpdater:
    """The sliding window's bookkeeping and its update (W1-W7), one :meth:`step` per frame: the
    observations in the window (track id, clone slot, pixels), the features a frame uses, the map
    they make. ``size``: the clones the window holds at most; ``gate_probability``: of (W5)."""

    def __init__(self, size: int, camera, cam_T_imu: np.ndarray, pixel_var: float, gate_probability: float,
                 map_) -> None:
        if size < 2:
            raise ValueError(f"a sliding window holds at least 2 clones, got {size}")
        self.size = size
        self.camera = camera
        self.cam_T_imu = np.ascontiguousarray(cam_T_imu, dtype=float)
        self.pixel_var = float(pixel_var)
        self.map = map_
        n = np.arange(size + 2)
        self._gate = np.array([chi2.quantile(max(4 * i - 3, 1), gate_probability) for i in n])  # chi2_{4n-3} quantile by n (W5)
        self._obs_gate = chi2.quantile(4, gate_probability)  # one observation's (U4) (W3)
        self._stagger = max(1, size // 2)  # a track's segments hold size - (id mod this) observations (W7)
        self._ids = np.zeros(0, dtype=np.int64)  # (O,) the window's observations: track id,
        self._slots = np.zeros(0, dtype=np.int64)  # ... clone slot (0: the oldest),
        self._pixels = np.zeros((0, 4))  # ... pixels
        self._last = np.zeros(0, dtype=np.int64)  # the track ids of the last frame
        self._frames: list[int] = []  # the frame of each clone, oldest first
        self._frame = 0  # frames stepped
        self.settled: list[tuple[int, np.ndarray, np.ndarray]] = []  # (W8) (frame, pose (4,4), P block (6,6))

    def step(self, state, ids: np.ndarray, pixels: np.ndarray, correct) -> WindowStep:
        """(W1) the pose joins as the newest clone with this frame's observations; (W3-W6) the tracks
        that ended (seen at the last frame, not at this one), those at their segment's length and,
        with the window full, those seen in its oldest clone are used, each by its observations in
        the window (this frame's included: a track that goes on starts a new segment at the next
        frame, no pixel used twice) (:func:`plan_use`); (W7) the oldest clone leaves.
        ``correct(state, dx)``: the whole state's correction by the update dx (D,): the core's (J7)
        and the clones' (W6)."""
        ids = np.asarray(ids, dtype=np.int64)
        StateHelper.clone(state)
        self._frames.append(self._frame)
        self._frame += 1
        newest = state.clones.shape[0] - 1
        self._ids = np.concatenate([self._ids, ids])
        self._slots = np.concatenate([self._slots, np.full(ids.size, newest, dtype=np.int64)])
        self._pixels = np.concatenate([self._pixels, np.asarray(pixels, dtype=float).reshape(-1, 4)])
        full = newest >= self.size
        rows, start, count, left = plan_use(self._ids, self._slots, self._last, ids, full, self.size, self._stagger)
        self._last = ids
        out = self._use(state, rows, start, count, correct)
        if full:
            self._settle(state, 1)
            StateHelper.drop_oldest_clone(state)
            self._slots -= 1  # none is left in slot 0: its tracks were used
        out.active = left
        return out

    def flush(self, state, correct) -> WindowStep:
        """Use every track left in the window (the end of the run): its features' map points; every
        clone is settled (W8)."""
        rows, start, count, _ = plan_use(self._ids, self._slots, self._ids, self._ids[:0], False, 1, 1)
        out = self._use(state, rows, start, count, correct)
        self._settle(state, state.clones.shape[0])
        return out

    def _settle(self, state, n: int) -> None:
        """(W8) the oldest ``n`` clones' poses and their blocks of P as the window leaves them: each
        frame's pose once every track that saw it was used (:func:`settled_trajectory` reads them)."""
        c = state.core
        for k in range(n):
            rows = slice(c + 6 * k, c + 6 * k + 6)
            self.settled.append((self._frames[k], state.clones[k].copy(), state.P[rows, rows].copy()))
        del self._frames[:n]

    def _use(self, state, rows: np.ndarray, start: np.ndarray, count: np.ndarray, correct) -> WindowStep:
        """(W3-W6) the features of the observations ``rows`` (``start``, ``count`` per track, see
        :func:`plan_use`; a track seen once says nothing: neither used nor gated), then those
        observations leave the window; the state corrected by ``correct`` (core J7, clones W6)."""
        if not rows.size:
            return WindowStep(0, 0, 0.0, 0, 0)
        ids, slots, pixels = self._ids[rows], self._slots[rows], self._pixels[rows]
        keep = np.ones(self._ids.size, dtype=bool)
        keep[rows] = False
        self._ids, self._slots, self._pixels = self._ids[keep], self._slots[keep], self._pixels[keep]
        two = count >= 2
        if not two.any():
            return WindowStep(0, 0, 0.0, 0, 0)
        start, count = start[two], count[two]
        cam, c = self.camera, state.core
        w6 = 6 * state.clones.shape[0]
        points, covs, ok, nis, used, info = feature_information(
            state.clones, self.cam_T_imu, cam.fx, cam.fy, cam.cx, cam.cy, cam.baseline, start, count, slots, pixels,
            np.ascontiguousarray(state.P[c:c + w6, c:c + w6]), self.pixel_var, self._gate, self._obs_gate,
            WINDOW_ITERATIONS)
        good = ok & (nis <= self._gate[used])
        if good.any():
            dx = StateHelper.update_window(state, info, self.pixel_var)
            correct(state, dx)
            self.map.add(ids[start[good]], points[good], covs[good])
        n_used = int(used[good].sum())
        return WindowStep(n_used, int(count.sum()) - n_used, float(nis[good].sum()), int(good.sum()), 0,
                          4 * n_used - 3 * int(good.sum()))


def settled_trajectory(settled: list, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(W8) (poses (N,4,4), covariances (N,6,6) of the right perturbation, I7) of ``frames`` = N frames
    from a window's settled (frame, pose, P block of the left perturbation) entries, one per frame."""
    order = sorted(range(len(settled)), key=lambda i: settled[i][0])
    if [settled[i][0] for i in order] != list(range(frames)):
        raise ValueError(f"the window settled {len(settled)} clones for {frames} frames")
    poses = np.array([settled[i][1] for i in order])
    return poses, body_pose_covariance(poses, np.array([settled[i][2] for i in order]))


@warms_up(only="window")
def _warm_up() -> None:
    clones = np.tile(np.eye(4), (2, 1, 1))
    clones[1, 0, 3] = 0.5
    pixels = np.array([[600.0, 180.0, 560.0, 180.0], [590.0, 180.0, 550.0, 180.0]])
    feature_information(clones, np.eye(4), 700.0, 700.0, 600.0, 180.0, 0.5, np.zeros(1, dtype=np.int64),
                 np.full(1, 2, dtype=np.int64), np.arange(2, dtype=np.int64), pixels, np.eye(12), 1.0,
                 np.full(4, 10.0), 18.5, WINDOW_ITERATIONS)
    ids = np.arange(3, dtype=np.int64)
    plan_use(ids, np.zeros(3, dtype=np.int64), ids, ids[:1], True, 13, 6)
    plan_use(ids, np.zeros(3, dtype=np.int64), ids, ids[:0], False, 1, 1)

    retract_clones(clones, np.zeros(12))
    gather_symmetric(np.eye(20), np.arange(6, 20, dtype=np.int64))  # a clone leaves (W7): the landmarks' warm-up is not a window run's
