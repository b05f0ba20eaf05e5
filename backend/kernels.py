"""Compiled kernels of the EKF step (numba): the small-matrix work between the BLAS calls.

Why compiled: at the filter's sizes (D ~ 210 states, ~140 measurement rows, ~65 landmarks) the
dense BLAS work of a step takes ~0.35 ms, but written with numpy the rest of the step was ~100
array calls of 5-20 us each plus several passes over the D x D covariance (~3 ms a step on the
real drives). Each kernel below replaces one group of those calls with a single loop nest over
the same numbers; the equations are the ones of ``backend.ekf`` and ``backend.invariant``, cited
by their labels (U1-U3, I2-I6). The BLAS/LAPACK routines they call (potrf, trsm, syrk, gemm)
are declared in ``backend.linalg``. A step of the default (invariant) filter is a handful of
calls: ``predict_invariant_step``; then ``plan_update`` (where each observation goes),
``plan_removal`` + ``gather_landmarks`` (ended tracks to the map), ``innovation_invariant``,
``select_and_update_inplace`` (gate, RANSAC, the joint update), ``retract_invariant_inplace``,
``admit_landmarks`` + ``initialize_invariant`` (new landmarks).

Compiled on first use and cached beside this file (``cache=True``): the first run after an
install compiles for ~30 s; later processes load the cache in ~0.5 s (numba's start-up).
All kernels are pure functions except the ones named ``*_inplace`` (and ``plan_update``, which
counts the observations in place).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from backend import se3
from backend.camera import _triangulate_rows
from backend.linalg import add_product_lower, cholesky_upper_inplace, downdate_lower, solve_lower_inplace

# the filter's state layout and 3-row observation form (backend.ekf imports them from here)
CORE = 9  # pose (6) + gyro bias (3): the landmark slots start here
ROWS = 3  # rows per observation (U1): [uL, (vL + vR)/sqrt 2, uR]
SQRT_HALF = float(np.sqrt(0.5))

_jit = njit(cache=True, nogil=True, error_model="numpy")


# ---------------------------------------------------------------- symmetric matrices
@_jit
def mirror_lower_inplace(P):
    """Copy the lower triangle of the square C-ordered P onto its upper triangle (exact symmetry)."""
    n = P.shape[0]
    for i in range(n):
        for j in range(i):
            P[j, i] = P[i, j]


@_jit
def gather_symmetric(P, keep):
    """P[keep][:, keep] as a new C-ordered matrix, in one pass (marginalization: rows and
    columns of the dropped states removed; exact for a Gaussian)."""
    n = keep.size
    out = np.empty((n, n))
    for i in range(n):
        row = P[keep[i]]
        for j in range(n):
            out[i, j] = row[keep[j]]
    return out


@_jit
def augment(P, J_xi, J_z, pixel_var):
    """EKF-SLAM state augmentation with n new landmarks theta = g(z, mu) (``backend.ekf`` docstring):

        P_m,x = J_xi P_xi,x  (3n,D),   P_mm = J_xi P_xixi J_xi^T + blockdiag(sigma^2 J_z J_z^T)  (3n,3n)

    for the pose Jacobian J_xi (3n,6) and the pixel Jacobians J_z (n,3,4). Returns
    [[P, P_m,x^T], [P_m,x, P_mm]] as a new C-ordered matrix, exactly symmetric.
    """
    D = P.shape[0]
    n3 = J_xi.shape[0]
    out = np.empty((D + n3, D + n3))
    out[:D, :D] = P
    cross = np.zeros((n3, D))
    for i in range(n3):
        for j in range(6):
            h = J_xi[i, j]
            if h != 0.0:
                row = P[j]
                for c in range(D):
                    cross[i, c] += h * row[c]
    for i in range(n3):
        for j in range(D):
            out[D + i, j] = cross[i, j]
            out[j, D + i] = cross[i, j]
    for i in range(n3):
        for j in range(i + 1):
            s = 0.0
            for t in range(6):
                s += cross[i, t] * J_xi[j, t]
            if i // 3 == j // 3:  # the pixel part, block diagonal
                lm = i // 3
                a, b = i - 3 * lm, j - 3 * lm
                for t in range(4):
                    s += pixel_var * J_z[lm, a, t] * J_z[lm, b, t]
            out[D + i, D + j] = s
            out[D + j, D + i] = s
    return out


@_jit
def gather_landmarks(P, keep):
    """P over the pose, the bias and the landmark slots ``keep`` (marginalization of the others)."""
    idx = np.empty(CORE + 3 * keep.size, dtype=np.int64)
    for i in range(CORE):
        idx[i] = i
    for i in range(keep.size):
        for a in range(3):
            idx[CORE + 3 * i + a] = CORE + 3 * keep[i] + a
    return gather_symmetric(P, idx)


@_jit
def initialize_invariant(P, pixels, world_T_imu, imu_T_cam, fx, fy, cx, cy, baseline, sigma, pixel_var, pose):
    """New world-xyz landmarks of the invariant filter from stereo pixels (n,4), in one call:
    m = world_T_imu imu_T_cam triangulate(z) (the unscented mean for sigma > 0, backend.camera),
    J_z = world_R_cam d triangulate/dz and (I4) J_xi = [I 0] (zero when ``pose`` is False: poses
    held fixed), then :func:`augment`. Returns (the augmented P, m (n,3))."""
    n = pixels.shape[0]
    p_cam, dp_dz = _triangulate_rows(pixels, fx, fy, cx, cy, baseline, sigma)
    world_T_cam = world_T_imu @ imu_T_cam
    points = np.empty((n, 3))
    J_z = np.empty((n, 3, 4))
    J_xi = np.zeros((3 * n, 6))
    for i in range(n):
        for a in range(3):
            points[i, a] = (world_T_cam[a, 0] * p_cam[i, 0] + world_T_cam[a, 1] * p_cam[i, 1]
                            + world_T_cam[a, 2] * p_cam[i, 2] + world_T_cam[a, 3])
            for t in range(4):
                J_z[i, a, t] = (world_T_cam[a, 0] * dp_dz[i, 0, t] + world_T_cam[a, 1] * dp_dz[i, 1, t]
                                + world_T_cam[a, 2] * dp_dz[i, 2, t])
            if pose:
                J_xi[3 * i + a, a] = 1.0
    return augment(P, J_xi, J_z, pixel_var), points


@_jit
def landmark_covariances(P, slots, points, invariant):
    """Covariances (k,3,3) of the landmarks in ``slots``: their 3x3 diagonal blocks of P, or with the
    right-invariant error (``invariant``) those of the world positions ``points`` (k,3), (I6):
    dm = zeta - m^ phi, so Cov(m) = A P_phiphi A^T + A P_phi,zeta + (A P_phi,zeta)^T + P_zeta
    with A = -m^ (symmetrized)."""
    k = slots.size
    out = np.empty((k, 3, 3))
    A = np.zeros((3, 3))
    for i in range(k):
        s = CORE + 3 * slots[i]
        for a in range(3):
            for b in range(3):
                out[i, a, b] = P[s + a, s + b]
        if not invariant:
            continue
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        A[0, 1], A[0, 2] = z, -y  # A = -hat(m)
        A[1, 0], A[1, 2] = -z, x
        A[2, 0], A[2, 1] = y, -x
        AP = np.zeros((3, 3))  # A P_phiphi
        AX = np.zeros((3, 3))  # A P_phi,zeta
        for a in range(3):
            for b in range(3):
                for t in range(3):
                    AP[a, b] += A[a, t] * P[3 + t, 3 + b]
                    AX[a, b] += A[a, t] * P[3 + t, s + b]
        for a in range(3):
            for b in range(3):
                v = out[i, a, b] + AX[a, b] + AX[b, a]
                for t in range(3):
                    v += AP[a, t] * A[b, t]
                out[i, a, b] = v
        for a in range(3):
            for b in range(a):
                v = 0.5 * (out[i, a, b] + out[i, b, a])
                out[i, a, b] = v
                out[i, b, a] = v
    return out


# ---------------------------------------------------------------- bookkeeping
@_jit
def slots_of(ids, ids_sorted, ids_order):
    """State slots of ``ids`` (-1 where not in the state), for the state's ids sorted (``ids_sorted``)
    and their slots (``ids_order``)."""
    n = ids_sorted.size
    slots = np.full(ids.size, -1, dtype=np.int64)
    for j in range(ids.size):
        pos = np.searchsorted(ids_sorted, ids[j])
        if pos < n and ids_sorted[pos] == ids[j]:
            slots[j] = ids_order[pos]
    return slots


@_jit
def plan_update(ids, ids_sorted, ids_order, obs_count, obs_limit, reanchor, full_state):
    """Where a step's observations go (backend.ekf ``update``), for the state's landmark ids sorted
    (``ids_sorted``, at slots ``ids_order``). Returns the slot of each observation's landmark (-1:
    new); the landmarks that leave before the joint update: the tracks not seen (``ended``, unless
    ``full_state``) and with ``reanchor`` those seen beyond their ``obs_limit`` observations
    (counted in ``obs_count`` in place); the observations that restart such a track; their number."""
    slots = slots_of(ids, ids_sorted, ids_order)
    ended = np.zeros(ids_sorted.size, dtype=np.bool_)
    if not full_state:
        ended[:] = True
    restart = np.zeros(ids.size, dtype=np.bool_)
    for j in range(ids.size):
        if slots[j] >= 0:
            ended[slots[j]] = False
    leaving = ended.copy()
    expired = 0
    for j in range(ids.size):
        s = slots[j]
        if reanchor and s >= 0:
            obs_count[s] += 1
            if obs_count[s] > obs_limit[s]:
                leaving[s] = True
                restart[j] = True
                expired += 1
    return slots, leaving, ended, restart, expired


@_jit
def admit_landmarks(ids, pixels, restart, min_disparity, max_depth, fx_baseline, reanchor, far_disparity,
                    near_limit, far_limit):
    """Which new features start landmarks: disparity > ``min_disparity`` and depth fx b / d <=
    ``max_depth`` (the others wait for a later observation). Returns their indices, and for each
    the observations it lives for before re-anchoring (``far_limit`` when anchored below
    ``far_disparity``: distant points drift little) and the count of its anchoring observation:
    1, or with ``reanchor`` 1 + id mod limit on a track's first landmark (not ``restart``), so that
    landmarks born together are not all re-anchored at once (backend.ekf docstring)."""
    ok = np.empty(ids.size, dtype=np.int64)
    n = 0
    for j in range(ids.size):
        d = pixels[j, 0] - pixels[j, 2]
        if d > min_disparity and fx_baseline / d <= max_depth:
            ok[n] = j
            n += 1
    ok = ok[:n]
    counts = np.ones(n, dtype=np.int64)
    limits = np.empty(n, dtype=np.int64)
    for i in range(n):
        j = ok[i]
        limits[i] = far_limit if pixels[j, 0] - pixels[j, 2] < far_disparity else near_limit
        if reanchor and not restart[j] and limits[i] < np.iinfo(np.int64).max:
            counts[i] += ids[j] % limits[i]
    return ok, counts, limits


@_jit
def plan_removal(mask, ended, outlier_run):
    """Index arrays of a marginalization of the landmark slots ``mask``: the removed slots, the kept
    ones, the new slot of each old one (-1: removed), and the removed ones whose tracks go on (not
    ``ended``, an empty array meaning none ended) with a RANSAC rejection run to keep."""
    n = mask.size
    removed = np.flatnonzero(mask)
    keep = np.flatnonzero(~mask)
    remap = np.full(n, -1, dtype=np.int64)
    for i in range(keep.size):
        remap[keep[i]] = i
    counted = np.empty(removed.size, dtype=np.int64)
    c = 0
    for s in removed:
        if outlier_run[s] > 0 and not (ended.size and ended[s]):
            counted[c] = s
            c += 1
    return removed, keep, remap, counted[:c]


# ---------------------------------------------------------------- single-pose SE(3) (backend.se3, compiled)
_coefficients = _jit(se3._coefficients)  # the same closed forms / Taylor series, compiled


@_jit
def _mm3(A, B):
    """A @ B of 3x3 matrices (no BLAS call for 27 products)."""
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]
    return out


@_jit
def _hat(x, y, z):
    W = np.zeros((3, 3))
    W[0, 1], W[0, 2], W[1, 0], W[1, 2], W[2, 0], W[2, 1] = -z, y, z, -x, -y, x
    return W


@_jit
def _exp_se3_parts(xi):
    """exp(xi^) (4,4) and J_l(theta) (3,3) of the twist xi = [rho, theta] (Barfoot eqs. 7.14, 7.37, 7.39)."""
    W = _hat(xi[3], xi[4], xi[5])
    WW = _mm3(W, W)
    a, b, c, _, _, _ = _coefficients(np.sqrt(xi[3] ** 2 + xi[4] ** 2 + xi[5] ** 2))
    T = np.zeros((4, 4))
    J = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            e = 1.0 if i == j else 0.0
            T[i, j] = e + a * W[i, j] + b * WW[i, j]
            J[i, j] = e + b * W[i, j] + c * WW[i, j]
    for i in range(3):
        T[i, 3] = J[i, 0] * xi[0] + J[i, 1] * xi[1] + J[i, 2] * xi[2]
    T[3, 3] = 1.0
    return T, J


@_jit
def _right_jacobian_se3(xi):
    """J_r(xi) = J_l(-xi) = [[J_l(-theta), Q(-rho, -theta)], [0, J_l(-theta)]] (Barfoot eqs. 7.85-7.87)."""
    W = _hat(-xi[3], -xi[4], -xi[5])
    Pm = _hat(-xi[0], -xi[1], -xi[2])
    _, b, c, _, e, f = _coefficients(np.sqrt(xi[3] ** 2 + xi[4] ** 2 + xi[5] ** 2))
    WW = _mm3(W, W)
    WP, PW = _mm3(W, Pm), _mm3(Pm, W)
    WPW = _mm3(WP, W)
    WWP, PWW = _mm3(WW, Pm), _mm3(PW, W)
    WPWW, WWPW = _mm3(WPW, W), _mm3(WW, PW)
    J = np.zeros((6, 6))
    for i in range(3):
        for j in range(3):
            jl = (1.0 if i == j else 0.0) + b * W[i, j] + c * WW[i, j]
            J[i, j] = jl
            J[3 + i, 3 + j] = jl
            J[i, 3 + j] = (0.5 * Pm[i, j] + c * (WP[i, j] + PW[i, j] + WPW[i, j])
                           + e * (WWP[i, j] + PWW[i, j] - 3.0 * WPW[i, j]) + f * (WPWW[i, j] + WWPW[i, j]))
    return J


@_jit
def retract_invariant_inplace(world_T_imu, points, dx):
    """(I5) exp(dx) X_hat: returns the new pose exp(dx_pose^) world_T_imu and moves the world points
    (K,3) in place, m <- R_d m + J_l zeta (the state dx = [rho, phi, bias (3), zeta_1 .. zeta_K])."""
    E, J = _exp_se3_parts(dx[:6])
    pose = np.empty((4, 4))
    for i in range(4):
        for j in range(4):
            pose[i, j] = E[i, 0] * world_T_imu[0, j] + E[i, 1] * world_T_imu[1, j] + E[i, 2] * world_T_imu[2, j] \
                + E[i, 3] * world_T_imu[3, j]
    for k in range(points.shape[0]):
        z = dx[CORE + 3 * k:CORE + 3 * k + 3]
        x0, x1, x2 = points[k, 0], points[k, 1], points[k, 2]
        for i in range(3):
            points[k, i] = (E[i, 0] * x0 + E[i, 1] * x1 + E[i, 2] * x2
                            + J[i, 0] * z[0] + J[i, 1] * z[1] + J[i, 2] * z[2])
    return pose


# ---------------------------------------------------------------- prediction
@_jit
def predict_invariant_inplace(P, G_pose, R_phi, points, q, dt, bias, bias_walk_var):
    """(I2) P <- F P F^T + G Q G^T  with  F = I + g e_b^T,  g = -tau G_omega  (backend.invariant).

    G (D,6) maps a body-twist error to the error state: pose rows ``G_pose`` (6,6), landmark rows
    m_i^ R_phi (3,6) for the world points ``points`` (K,3); q (6,) = the twist noise sigmas times
    tau. With C = P[:, b] and P_bb = P[b, b], F P F^T = P + g C^T + C g^T + g P_bb g^T, so
    P += Z X^T with X = [g, C, G diag(q)] and Z = [g P_bb + C, g, G diag(q)] (D x 12): one BLAS
    product, added on the lower triangle and mirrored. ``bias``: the gyro bias is in the state
    (else F = I and X = G diag(q)); it takes a random walk of variance ``bias_walk_var`` a step.
    """
    D = P.shape[0]
    K = points.shape[0]
    w = 12 if bias else 6
    X = np.zeros((D, w))
    Z = np.zeros((D, w))
    G = X[:, w - 6:]
    G[:6] = G_pose
    for i in range(K):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        r = CORE + 3 * i
        for c in range(6):  # rows of hat(m_i) @ R_phi
            G[r, c] = -z * R_phi[1, c] + y * R_phi[2, c]
            G[r + 1, c] = z * R_phi[0, c] - x * R_phi[2, c]
            G[r + 2, c] = -y * R_phi[0, c] + x * R_phi[1, c]
    if bias:
        for i in range(D):
            for c in range(3):
                X[i, c] = -dt * G[i, 3 + c]  # g
                X[i, 3 + c] = P[i, 6 + c]  # C
        for i in range(D):
            for b in range(3):
                s = X[i, 3 + b]
                for a in range(3):
                    s += X[i, a] * P[6 + a, 6 + b]
                Z[i, b] = s
                Z[i, 3 + b] = X[i, b]
    for i in range(D):
        for c in range(6):
            G[i, c] *= q[c]
            Z[i, w - 6 + c] = G[i, c]
    add_product_lower(P, Z, X)
    mirror_lower_inplace(P)
    if bias:
        for c in range(3):
            P[6 + c, 6 + c] += bias_walk_var


@_jit
def predict_invariant_step(world_T_imu, P, points, twist, q, dt, bias, bias_walk_var, landmark_walk_var):
    """One prediction of the invariant filter: mu <- mu exp(tau u^) (course eq. for the mean), the
    landmark random walk (P_mm += ``landmark_walk_var`` I) and (I2) by :func:`predict_invariant_inplace`
    with G_pose = Ad(mu_next) J_r(twist), R_phi = R_next J_r[3:6] (backend.invariant.noise_jacobian_pose).
    Returns mu_next; P is changed in place."""
    step, _ = _exp_se3_parts(twist)
    mu = np.empty((4, 4))
    for i in range(4):
        for j in range(4):
            mu[i, j] = world_T_imu[i, 0] * step[0, j] + world_T_imu[i, 1] * step[1, j] \
                + world_T_imu[i, 2] * step[2, j] + world_T_imu[i, 3] * step[3, j]
    if landmark_walk_var != 0.0:
        for i in range(CORE, P.shape[0]):
            P[i, i] += landmark_walk_var
    J = _right_jacobian_se3(twist)
    R = mu[:3, :3]
    pR = _mm3(_hat(mu[0, 3], mu[1, 3], mu[2, 3]), R)
    G_pose = np.zeros((6, 6))  # Ad(mu) J, Ad = [[R, p^ R], [0, R]] (Barfoot eq. 7.48)
    R_phi = np.zeros((3, 6))
    for i in range(3):
        for j in range(6):
            top = 0.0
            bot = 0.0
            for t in range(3):
                top += R[i, t] * J[t, j] + pR[i, t] * J[3 + t, j]
                bot += R[i, t] * J[3 + t, j]
            G_pose[i, j] = top
            G_pose[3 + i, j] = bot
            R_phi[i, j] = bot
    predict_invariant_inplace(P, G_pose, R_phi, points, q, dt, bias, bias_walk_var)
    return mu


# ---------------------------------------------------------------- observation (I3, U1)
@_jit
def observe_invariant(points, cam_T_world, fx, fy, cx, cy, baseline, pixels):
    """(I3) in the 3-row form (U1) for world points (k,3) seen at ``pixels`` (k,4) = [uL vL uR vR].

    q = cam_T_world m (depth z), z_hat = Ks pi(q); M = dz/dm = dpi-rows @ cam_R_world;
    rows [uL, (vL + vR)/sqrt 2, uR]: H_m = M rows, H_x = [-M, 0] (no rotation column).
    Returns residual (k,3), off_row (k,) = (r_vL - r_vR)/sqrt 2, H_x (3k,6), H_m (k,3,3) and
    in_front (k,) = z > 0.1 (the others get placeholder rows and are gated out by the caller).
    """
    k = points.shape[0]
    residual = np.empty((k, 3))
    off_row = np.empty(k)
    H_x = np.zeros((3 * k, 6))
    H_m = np.empty((k, 3, 3))
    in_front = np.empty(k, dtype=np.bool_)
    R = cam_T_world[:3, :3]
    fxb = fx * baseline
    for i in range(k):
        qx = R[0, 0] * points[i, 0] + R[0, 1] * points[i, 1] + R[0, 2] * points[i, 2] + cam_T_world[0, 3]
        qy = R[1, 0] * points[i, 0] + R[1, 1] * points[i, 1] + R[1, 2] * points[i, 2] + cam_T_world[1, 3]
        qz = R[2, 0] * points[i, 0] + R[2, 1] * points[i, 1] + R[2, 2] * points[i, 2] + cam_T_world[2, 3]
        in_front[i] = qz > 0.1
        if not in_front[i]:
            qz = 1.0
        iz = 1.0 / qz
        uL = fx * qx * iz + cx
        v = fy * qy * iz + cy
        uR = uL - fxb * iz
        residual[i, 0] = pixels[i, 0] - uL
        residual[i, 1] = ((pixels[i, 1] - v) + (pixels[i, 3] - v)) * SQRT_HALF
        residual[i, 2] = pixels[i, 2] - uR
        off_row[i] = (pixels[i, 1] - pixels[i, 3]) * SQRT_HALF
        # d(pixel row)/d(q_cam) for uL, v (times sqrt 2 for the summed row), uR
        dq = np.empty((3, 3))
        dq[0, 0], dq[0, 1], dq[0, 2] = fx * iz, 0.0, -fx * qx * iz * iz
        s2 = 2.0 * SQRT_HALF
        dq[1, 0], dq[1, 1], dq[1, 2] = 0.0, s2 * fy * iz, -s2 * fy * qy * iz * iz
        dq[2, 0], dq[2, 1], dq[2, 2] = fx * iz, 0.0, -fx * (qx - baseline) * iz * iz
        for a in range(3):
            for b in range(3):
                s = dq[a, 0] * R[0, b] + dq[a, 1] * R[1, b] + dq[a, 2] * R[2, b]
                H_m[i, a, b] = s
                H_x[3 * i + a, b] = -s
    return residual, off_row, H_x, H_m, in_front


@_jit
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


@_jit
def innovation_covariance(P, H_x, H_m, slots, pixel_var, residual, off_row):
    """H P (3k,D), S = H P H^T + R (3k,3k) and the NIS (k,) of each observation (4 dof: its
    3-row block plus off_row^2 / sigma^2, U1), for H given as H_x (3k,6) on the pose and
    H_m (k,3,3) on landmark ``slots`` (each 3-row block touches 6 + 3 columns of P)."""
    D = P.shape[0]
    k = slots.size
    m = 3 * k
    HP = np.zeros((m, D))
    for i in range(k):
        base = CORE + 3 * slots[i]
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
            base = CORE + 3 * slots[i2]
            s = 0.0
            for j in range(6):
                s += hp[j] * H_x[r2, j]
            for t in range(3):
                s += hp[base + t] * H_m[i2, b, t]
            S[r, r2] = s
            S[r2, r] = s
    for r in range(m):
        S[r, r] += pixel_var
    nis = np.empty(k)
    for i in range(k):
        o = 3 * i
        nis[i] = _nis3(S[o:o + 3, o:o + 3], residual[i, 0], residual[i, 1], residual[i, 2]) + off_row[i] ** 2 / pixel_var
    return HP, S, nis


@_jit
def innovation_invariant(P, theta, slots, world_T_imu, cam_T_imu, fx, fy, cx, cy, baseline, pixels, pixel_var, pose):
    """The invariant filter's prior innovation in one call: :func:`observe_invariant` of the landmarks
    ``slots`` (world points theta[slots]) from cam_T_world = cam_T_imu world_T_imu^-1, then
    :func:`innovation_covariance`; H_x = 0 when ``pose`` is False (poses held fixed). Returns
    (residual, off_row, H_x (3k,6), H_m, H P, S, NIS, in_front)."""
    imu_T_world = np.zeros((4, 4))
    for i in range(3):
        for j in range(3):
            imu_T_world[i, j] = world_T_imu[j, i]
        imu_T_world[i, 3] = -(world_T_imu[0, i] * world_T_imu[0, 3] + world_T_imu[1, i] * world_T_imu[1, 3]
                              + world_T_imu[2, i] * world_T_imu[2, 3])
    imu_T_world[3, 3] = 1.0
    cam_T_world = cam_T_imu @ imu_T_world
    points = np.empty((slots.size, 3))
    for i in range(slots.size):
        points[i] = theta[slots[i]]
    residual, off_row, H_x, H_m, in_front = observe_invariant(points, cam_T_world, fx, fy, cx, cy, baseline, pixels)
    if not pose:
        H_x[:] = 0.0
    HP, S, nis = innovation_covariance(P, H_x, H_m, slots, pixel_var, residual, off_row)
    return residual, off_row, H_x, H_m, HP, S, nis, in_front


# ---------------------------------------------------------------- outliers (U3)
@_jit
def _solve3(S, r):
    """S^-1 r for a 3x3 S by Cramer's rule (S is a gated, regular innovation block)."""
    a, b, c = S[0, 0], S[0, 1], S[0, 2]
    d, e, f = S[1, 0], S[1, 1], S[1, 2]
    g, h, i = S[2, 0], S[2, 1], S[2, 2]
    A, B, C = e * i - f * h, -(d * i - f * g), d * h - e * g
    det = a * A + b * B + c * C
    inv = np.empty((3, 3))
    inv[0, 0], inv[1, 0], inv[2, 0] = A / det, B / det, C / det
    inv[0, 1], inv[1, 1], inv[2, 1] = -(b * i - c * h) / det, (a * i - c * g) / det, -(a * h - b * g) / det
    inv[0, 2], inv[1, 2], inv[2, 2] = (b * f - c * e) / det, -(a * f - c * d) / det, (a * e - b * d) / det
    out = np.empty(3)
    for t in range(3):
        out[t] = inv[t, 0] * r[0] + inv[t, 1] * r[1] + inv[t, 2] * r[2]
    return out


@_jit
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
    idx = np.flatnonzero(candidates)
    m = idx.size
    a = np.empty((m, 3))
    for jj in range(m):
        o = 3 * idx[jj]
        a[jj] = _solve3(S[o:o + 3, o:o + 3], residual[idx[jj]])
    err = np.empty((m, m))
    for ii in range(m):
        oi = 3 * idx[ii]
        off2 = off_row[idx[ii]] ** 2
        for jj in range(m):
            oj = 3 * idx[jj]
            s = off2
            for t in range(3):
                ch = S[oi + t, oj] * a[jj, 0] + S[oi + t, oj + 1] * a[jj, 1] + S[oi + t, oj + 2] * a[jj, 2]
                if ii == jj:
                    ch -= pixel_var * a[jj, t]
                d = residual[idx[ii], t] - ch
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
            out[idx[ii]] = True
    return out


@_jit
def _rescue_test(X, w, S, rest_idx, residual, off_row, pixel_var, gate):
    """(U3) the chi-square test of the ``rest_idx`` observations after the update with the inliers:
    residual r_r - X^T w and covariance S_rr - X^T X (diagonal 3x3 blocks only), with X = L^-1 S_ir
    (3 m_i, 3 m_r) and w = L^-1 r_i. Returns a mask over ``rest_idx``."""
    mr = rest_idx.size
    ok = np.zeros(mr, dtype=np.bool_)
    n = X.shape[0]
    Sb = np.empty((3, 3))
    for jj in range(mr):
        o = 3 * rest_idx[jj]
        c = 3 * jj
        r = np.empty(3)
        for a in range(3):
            s = 0.0
            for t in range(n):
                s += X[t, c + a] * w[t]
            r[a] = residual[rest_idx[jj], a] - s
            for b in range(3):
                s = 0.0
                for t in range(n):
                    s += X[t, c + a] * X[t, c + b]
                Sb[a, b] = S[o + a, o + b] - s
        ok[jj] = _nis3(Sb, r[0], r[1], r[2]) + off_row[rest_idx[jj]] ** 2 / pixel_var <= gate
    return ok


@_jit
def _gather_rows(M, rows):
    """M[rows] as a new C-ordered array."""
    out = np.empty((rows.size, M.shape[1]))
    for a in range(rows.size):
        out[a] = M[rows[a]]
    return out


@_jit
def _block_rows(obs):
    """Rows of the 3-row blocks (U1) of observations ``obs``."""
    rows = np.empty(3 * obs.size, dtype=np.int64)
    for i in range(obs.size):
        for a in range(3):
            rows[3 * i + a] = 3 * obs[i] + a
    return rows


@_jit
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
    obs_i = np.flatnonzero(inlier)
    rows_i = _block_rows(obs_i)
    mi = rows_i.size
    U = np.empty((mi, mi))  # upper triangle: L^T
    for a in range(mi):
        for b in range(a, mi):
            U[a, b] = S[rows_i[a], rows_i[b]]
    info = cholesky_upper_inplace(U)
    if info != 0:
        return info, dx, used
    w = np.empty((mi, 1))
    for a in range(mi):
        w[a, 0] = residual[rows_i[a] // 3, rows_i[a] % 3]
    solve_lower_inplace(U, w)
    obs_r = np.flatnonzero(rest)
    obs_ok = obs_r[:0]
    X = np.empty((mi, 0))
    ok = np.zeros(0, dtype=np.bool_)
    if obs_r.size:
        rows_r = _block_rows(obs_r)
        X = np.empty((mi, rows_r.size))
        for a in range(mi):
            for b in range(rows_r.size):
                X[a, b] = S[rows_i[a], rows_r[b]]
        solve_lower_inplace(U, X)
        ok = _rescue_test(X, w[:, 0], S, obs_r, residual, off_row, pixel_var, gate)
        obs_ok = obs_r[ok]
    if obs_ok.size:
        rows_o = _block_rows(obs_ok)
        cols = _block_rows(np.flatnonzero(ok))
        mo = rows_o.size
        m = mi + mo
        J = np.zeros((m, m))  # upper triangle: [[L, 0], [X_ok^T, L_o]]^T
        for a in range(mi):
            for b in range(a, mi):
                J[a, b] = U[a, b]
            for b in range(mo):
                J[a, mi + b] = X[a, cols[b]]
        Uo = np.empty((mo, mo))
        for a in range(mo):
            for b in range(a, mo):
                s = S[rows_o[a], rows_o[b]]
                for t in range(mi):
                    s -= X[t, cols[a]] * X[t, cols[b]]
                Uo[a, b] = s
        info = cholesky_upper_inplace(Uo)
        if info != 0:
            return info, dx, used
        wo = np.empty((mo, 1))
        for a in range(mo):
            s = residual[rows_o[a] // 3, rows_o[a] % 3]
            for t in range(mi):
                s -= X[t, cols[a]] * w[t, 0]
            wo[a, 0] = s
        solve_lower_inplace(Uo, wo)
        for a in range(mo):
            for b in range(a, mo):
                J[mi + a, mi + b] = Uo[a, b]
        rows = np.concatenate((rows_i, rows_o))
        w = np.concatenate((w, wo))
        U = J
    else:
        rows = rows_i
    A = _gather_rows(HP, rows)
    solve_lower_inplace(U, A)
    downdate_lower(P, A)
    mirror_lower_inplace(P)
    for a in range(rows.size):
        wa = w[a, 0]
        row = A[a]
        for c in range(D):
            dx[c] += row[c] * wa
    used[obs_i] = True
    used[obs_ok] = True
    return 0, dx, used


@_jit
def count_rejections_inplace(outlier_run, slots, rejected, limit):
    """Steps in a row the RANSAC rejected each track: ``outlier_run`` (per landmark slot) counts one
    more where ``rejected`` and restarts at 0 for the other observations of ``slots``; True where the
    count reaches ``limit``: such a track (a car ahead, followed by several features that agree with
    each other and not with the scene) is not rescued. The filter keeps the counts of a track that
    leaves the state and goes on (re-anchoring) by its id (backend.ekf ``_remove``)."""
    out = np.zeros(slots.size, dtype=np.bool_)
    for j in range(slots.size):
        s = slots[j]
        outlier_run[s] = outlier_run[s] + 1 if rejected[j] else 0
        out[j] = rejected[j] and outlier_run[s] >= limit
    return out


@_jit
def select_and_update_inplace(P, HP, S, residual, off_row, nis, in_front, slots, gate, ransac_threshold, pixel_var,
                              outlier_run, persistent_steps, gated_run):
    """One step's selection and joint update (backend.ekf, ``_joint_update``) in one call: the
    chi-square gate on ``nis``; with ``ransac_threshold`` > 0 and 3 candidates or more the 1-point
    RANSAC (:func:`one_point_ransac`), whose rejected observations are not offered to the rescue once
    ``outlier_run`` reaches ``persistent_steps`` (0: not counted); then :func:`joint_update_inplace`. Finally
    ``gated_run`` (per slot) is reset for the used observations and counts one more for the others.
    (:func:`count_rejections_inplace` counts the RANSAC's rejections.)
    Returns (status, dx, used) as :func:`joint_update_inplace`; on status != 0 nothing is used."""
    k = slots.size
    use = np.empty(k, dtype=np.bool_)
    for j in range(k):
        use[j] = in_front[j] and nis[j] <= gate
    rest = np.zeros(k, dtype=np.bool_)
    if ransac_threshold > 0 and use.sum() >= 3:
        inlier = one_point_ransac(S, residual, off_row, use, pixel_var, ransac_threshold)
        for j in range(k):
            rest[j] = use[j] and not inlier[j]
        if persistent_steps:
            rest &= ~count_rejections_inplace(outlier_run, slots, rest, persistent_steps)
        use = inlier
    status = 0
    dx = np.zeros(P.shape[0])
    if use.any():
        status, dx, use = joint_update_inplace(P, HP, S, residual, off_row, use, rest, pixel_var, gate)
        if status:
            use[:] = False
    for j in range(k):
        gated_run[slots[j]] = 0 if use[j] else gated_run[slots[j]] + 1
    return status, dx, use


_warm = False
_warm_seconds = 0.0  # what warm_up took in this process
slow_notice = None  # optional callable, called once when warm_up is still busy after NOTICE_AFTER s
NOTICE_AFTER = 2.0


def warm_up() -> float:
    """Compile (first run after an install: ~15-20 s) or load from the cache (~0.5 s) every kernel,
    with the argument types the filter passes, so that no step pays for it. Once per process;
    returns the seconds spent (0 when already done), which a run reports apart from its timing.
    When it takes longer than ``NOTICE_AFTER`` seconds, ``slow_notice()`` (if set, e.g. by the
    command line to say that it is compiling) is called from a timer thread."""
    global _warm, _warm_seconds
    if _warm:
        return 0.0
    import threading
    import time

    timer = threading.Timer(NOTICE_AFTER, slow_notice) if slow_notice is not None else None
    if timer is not None:
        timer.daemon = True
        timer.start()
    t0 = time.perf_counter()
    try:
        _call_every_kernel()
    finally:
        if timer is not None:
            timer.cancel()
    _warm = True
    _warm_seconds = time.perf_counter() - t0
    return _warm_seconds


def warm_up_seconds() -> float:
    """Seconds this process spent in :func:`warm_up` (0 before it ran): the start-up cost a run
    reports apart from its timing, whoever called ``warm_up`` first."""
    return _warm_seconds


def _call_every_kernel() -> None:
    """Each kernel once, on tiny arguments of the types and layouts the filter passes."""
    D, k = CORE + 6, 2
    P = np.eye(D)
    slots = np.arange(k, dtype=np.int64)
    mirror_lower_inplace(P)
    gather_symmetric(P, np.arange(D - 3, dtype=np.int64))
    augment(P, np.zeros((3, 6)), np.ones((1, 3, 4)), 1.0)
    gather_landmarks(P, np.arange(k, dtype=np.int64))
    ids = np.arange(k, dtype=np.int64)
    counts = np.ones(k, dtype=np.int64)
    plan_update(ids, ids, ids, counts, counts.copy(), True, False)
    slots_of(ids, ids, ids)
    pixels = np.array([[600.0, 180.0, 560.0, 180.0]] * k)
    admit_landmarks(ids, pixels, np.zeros(k, dtype=np.bool_), 1.0, np.inf, 350.0, True, 6.0, 3, 25)
    mask = np.array([True, False])
    plan_removal(mask, mask, counts)
    plan_removal(mask, np.zeros(0, dtype=np.bool_), counts)
    points = np.ones((k, 3))
    landmark_covariances(P, slots, points, True)
    predict_invariant_inplace(P.copy(), np.eye(6), np.ones((3, 6)), points, np.ones(6), 0.1, True, 1e-8)
    twist = np.full(6, 0.01)
    pose = predict_invariant_step(np.eye(4), P.copy(), points, twist, np.ones(6), 0.1, True, 1e-8, 1e-6)
    retract_invariant_inplace(pose, points.copy(), np.full(D, 1e-3))
    pixels = np.array([[600.0, 180.0, 560.0, 180.0]] * k)
    residual, off_row, H_x, H_m, in_front = observe_invariant(points + 5.0, np.eye(4), 700.0, 700.0, 600.0, 180.0, 0.5,
                                                              pixels)
    HP, S, nis = innovation_covariance(P, H_x, H_m, slots, 1.0, residual, off_row)
    innovation_invariant(P, points + 5.0, slots, np.eye(4), np.eye(4), 700.0, 700.0, 600.0, 180.0, 0.5, pixels, 1.0, True)
    one_point_ransac(S, residual, off_row, np.ones(k, dtype=np.bool_), 1.0, 2.0)
    inlier = np.array([True, False])
    joint_update_inplace(P.copy(), HP, S, residual, off_row, inlier, ~inlier, 1.0, 1e9)
    counts = np.zeros(k, dtype=np.int64)
    count_rejections_inplace(counts, slots, inlier, 3)
    select_and_update_inplace(P.copy(), HP, S, residual, off_row, nis, in_front, slots, 9.0, 2.0, 1.0, counts, 10,
                              counts.copy())
    _triangulate_rows(pixels, 700.0, 700.0, 600.0, 180.0, 0.5, 1.0)
    initialize_invariant(P, pixels, np.eye(4), np.eye(4), 700.0, 700.0, 600.0, 180.0, 0.5, 1.0, 1.0, True)
    from backend.conventions import _left_errors  # the convention test's (backend.conventions imports no kernel)
    from backend.timing import _repeats_sorted  # the repeated-frame test of every step

    _repeats_sorted(slots, pixels, slots, pixels)

    _left_errors(np.eye(4)[None], np.zeros(k, dtype=np.int64), points + 5.0, pixels[:, :2].copy(),
                 700.0, 700.0, 600.0, 180.0)
