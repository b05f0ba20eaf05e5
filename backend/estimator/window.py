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

      r_i = z_i - h(T_hat_c, p_hat) ~ H_c,i xi_c + M_i dp + n_i,   H_c,i = [-M_i, M_i p_hat^]

  The point is not in the state: the 3n rows are multiplied by the left null space of
  H_p = [M_1; ..; M_n] (Householder reflections zeroing its 3 columns), leaving 3n - 3 rows
  r_o = H_o xi_w + n_o that no longer depend on dp, with the same white noise sigma^2 I.
- Gate (W5). NIS = r_o^T (H_o P_ww H_o^T + sigma^2 I)^-1 r_o + sum d_i^2 / sigma^2 (the off rows
  of U1) <= chi2_{4n-3}^-1(gate_probability); a feature that fails is left out whole. The
  pixels' own (r_o^T r_o + sum d_i^2) / sigma^2 bounds the NIS from above: within the gate it
  decides without S (and is the NIS reported: 0.3 % above the exact one on the room flight).
- Update (W6). The rows of every feature used at a frame, stacked (m rows over the clones' 6w
  columns), update the whole state in the clones' dimension whatever m (the push-through identity,
  ``StateHelper.update_window``): the core is corrected through its covariance with the clones,
  then the retraction (J7) of the core and of each clone, T_c <- exp(dx_c^) T_hat_c.
- Marginalization (W7). A track is used when it ends, when its segment reaches size - (id mod
  size/2) observations (staggered, so that some tracks pin every frame's pose, at rest too), and
  at the latest when the window is full and the track was seen in the oldest clone, which then
  leaves: its rows and columns are dropped. A track used at a frame goes on as a new feature from
  its next observation (no pixel is used twice).

A feature's map point is its triangulation, with the covariance G (H_x P_ww H_x^T + sigma^2 I) G^T,
G = (H_p^T H_p)^-1 H_p^T: its pixels' and its clones' uncertainty (the update it then makes is not in it).

- The trajectory (W8). A clone's estimate improves while tracks that saw it are used; when it
  leaves the window (or the run ends) every track that saw it has been used, and its pose and the
  covariance of its right perturbation (I7, from its 6 x 6 block) are the frame's pose of the run's
  trajectory: a fixed-lag smoother over ``size`` frames (EuRoC's 40 pairs at rest: a path of 2.9
  mm against 11 mm for the pose at each frame's own update). The filter's current pose
  (``VisualInertialEKF.world_T_imu``, the online API) is the first estimate of the same.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scipy.special import chdtri

from ..compiled import jit, warms_up
from ..config import Mode
from ..geometry import se3
from .invariant import body_pose_covariance
from .layout import SQRT_HALF
from .linalg import inverse3
from .state_helper import StateHelper

__all__ = ["WindowStep", "WindowUpdater", "feature_rows", "plan_use", "retract_clones", "settled_trajectory",
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
def _linearize_inplace(obs, n, slot, Rcw, tcw, p, pixels, fx, fy, cx, cy, baseline, pred, Ms, rs):
    """The 3-row residuals (U1) ``rs[k]`` and Jacobians on the world point ``Ms[k]`` of the first n
    observations ``obs`` of a feature at the point p (clone ``slot[o]``'s cam_T_world = [Rcw tcw]);
    False when p lies behind one of the cameras."""
    for k in range(n):
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
def _householder_inplace(A, col, v, s):
    """Reflect rows col.. of A so that column ``col`` is zero below row col (one Householder step);
    ``v`` (rows,) and ``s`` (columns,) are work space. Row by row: A is C-ordered."""
    m, ncols = A.shape
    norm = 0.0
    for i in range(col, m):
        norm += A[i, col] * A[i, col]
    norm = np.sqrt(norm)
    if norm == 0.0:
        return
    alpha = -norm if A[col, col] > 0 else norm
    vv = 0.0
    for i in range(col, m):
        v[i] = A[i, col]
    v[col] -= alpha
    for i in range(col, m):
        vv += v[i] * v[i]
    if vv == 0.0:
        return
    for j in range(col, ncols):
        s[j] = 0.0
    for i in range(col, m):
        vi = v[i]
        for j in range(col, ncols):
            s[j] += vi * A[i, j]
    f = 2.0 / vv
    for i in range(col, m):
        vi = f * v[i]
        for j in range(col, ncols):
            A[i, j] -= vi * s[j]


@jit
def feature_rows(clones, cam_T_imu, fx, fy, cx, cy, baseline, start, count, slot, pixels, P_ww, pixel_var,
                 gate, obs_gate, iterations):
    """(W3-W5) for a batch of features, in one call.

    ``clones`` (w,4,4) world_T_imu of the window; feature f has the observations
    ``start[f] .. start[f] + count[f] - 1`` (oldest first) with clone ``slot`` (int) and ``pixels``
    (4) each; ``P_ww`` (6w,6w) the clones' covariance; ``gate`` (n,) the NIS gate of a feature seen
    n times (W5); ``obs_gate`` the chi2_4 gate of one observation's squared error (px^2 / sigma^2):
    the worst observation beyond it is left out once and the point fitted again (W3). Returns
    (points (F,3), covariances (F,3,3) of those within the gate, ok (F,) bool, nis (F,), used (F,) observations kept,
    [H r] (R,6w+1)): the projected rows of the features within the gate (ok and nis <= gate[used]),
    3 used - 3 each, in their order; ok False: a point behind a camera or a singular fit."""
    F = start.size
    w = clones.shape[0]
    total = 0
    for f in range(F):
        total += 3 * count[f] - 3
    rows = 0  # rows written
    Hr = np.zeros((total, 6 * w + 1))  # [H | r]
    points = np.zeros((F, 3))
    covs = np.zeros((F, 3, 3))
    ok = np.zeros(F, dtype=np.bool_)
    nis = np.full(F, np.inf)
    used = np.zeros(F, dtype=np.int64)
    Rcw = np.empty((w, 3, 3))
    tcw = np.empty((w, 3))
    for c in range(w):
        C = cam_T_imu @ se3.inverse(clones[c])
        Rcw[c] = C[:3, :3]
        tcw[c] = C[:3, 3]
    pred = np.empty(3)
    M = np.empty((3, 3))
    inv = np.empty((3, 3))
    res = np.empty(3)
    obs = np.empty(count.max() if F else 0, dtype=np.int64)  # the feature's observations in use
    Ms = np.empty((obs.size, 3, 3))  # ... their Jacobians on the point and residuals (_linearize_inplace)
    rs = np.empty((obs.size, 3))
    for f in range(F):
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
            qc = np.array([(pixels[o, 0] - cx) * z / fx, (0.5 * (pixels[o, 1] + pixels[o, 3]) - cy) * z / fy, z])
            s = slot[o]
            starts[m0] = Rcw[s].T @ (qc - tcw[s])
            m0 += 1
        if m0 == 0:
            continue
        p = np.empty(3)
        for a in range(3):
            p[a] = np.median(starts[:m0, a])
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
                if not _linearize_inplace(obs, n, slot, Rcw, tcw, p, pixels, fx, fy, cx, cy, baseline, pred, Ms, rs):
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
                step = inv @ Jtr
                p = p + step
                if np.abs(step).max() < 1e-7 * (1.0 + np.abs(p).max()):
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
        lo, hi = slot[obs[0]], slot[obs[n - 1]] + 1  # the clones it spans (observations oldest first)
        ncol = 6 * (hi - lo)
        # the rows at p (W4): A = [H_p | H_x over the clones lo..hi-1 | r]
        if not _linearize_inplace(obs, n, slot, Rcw, tcw, p, pixels, fx, fy, cx, cy, baseline, pred, Ms, rs):
            continue
        A = np.zeros((3 * n, 3 + ncol + 1))
        off = 0.0
        for k in range(n):
            o = obs[k]
            base = 3 + 6 * (slot[o] - lo)
            Mk = Ms[k]
            for a in range(3):
                # row a of M p^ (p^ the cross-product matrix of p)
                A[3 * k + a, base + 3] = Mk[a, 1] * p[2] - Mk[a, 2] * p[1]
                A[3 * k + a, base + 4] = Mk[a, 2] * p[0] - Mk[a, 0] * p[2]
                A[3 * k + a, base + 5] = Mk[a, 0] * p[1] - Mk[a, 1] * p[0]
                for b in range(3):
                    A[3 * k + a, b] = Mk[a, b]
                    A[3 * k + a, base + b] = -Mk[a, b]
                A[3 * k + a, 3 + ncol] = rs[k, a]
            d = (pixels[o, 1] - pixels[o, 3]) * SQRT_HALF
            off += d * d
        Hp = np.ascontiguousarray(A[:, :3])
        if not inverse3(Hp.T @ Hp, inv):
            continue
        Psub = np.ascontiguousarray(P_ww[6 * lo:6 * hi, 6 * lo:6 * hi])
        GHx = inv @ (Hp.T @ np.ascontiguousarray(A[:, 3:3 + ncol]))  # G H_x, G = (H_p^T H_p)^-1 H_p^T
        v = np.empty(3 * n)
        sw = np.empty(A.shape[1])
        for col in range(3):
            _householder_inplace(A, col, v, sw)
        m = 3 * n - 3
        Ho = np.ascontiguousarray(A[3:, 3:3 + ncol])
        ro = np.ascontiguousarray(A[3:, 3 + ncol])
        # S = H_o P_ww H_o^T + sigma^2 I >= sigma^2 I: the NIS is at most the pixels' own, which decides
        # every feature within the gate without S (the bound is 0.3 % above the NIS on the room flight)
        nis[f] = (ro @ ro + off) / pixel_var
        if nis[f] > gate[n]:  # then exactly
            S = Ho @ Psub @ Ho.T
            for i in range(m):
                S[i, i] += pixel_var
            nis[f] = ro @ np.linalg.solve(S, ro) + off / pixel_var
        points[f] = p
        used[f] = n
        ok[f] = True
        if nis[f] > gate[n]:
            continue
        # the map point's covariance: G (H_x P H_x^T + sigma^2 I) G^T
        covs[f] = GHx @ Psub @ GHx.T + pixel_var * inv
        for i in range(m):  # the rows of the features within the gate, one after the other
            Hr[rows + i, 6 * w] = ro[i]
            for j in range(ncol):
                Hr[rows + i, 6 * lo + j] = Ho[i, j]
        rows += m
    return points, covs, ok, nis, used, Hr[:rows]


@jit
def retract_clones(clones, dx):
    """(W6) T_c <- exp(dx_c^) T_hat_c for each clone (w,4,4), dx (6w,) = [rho_c; phi_c] per clone."""
    out = clones.copy()
    for c in range(clones.shape[0]):
        E, J = se3.exp_so3_and_left_jacobian(dx[6 * c + 3:6 * c + 6].copy())
        out[c, :3, :3] = E @ np.ascontiguousarray(clones[c, :3, :3])
        out[c, :3, 3] = E @ clones[c, :3, 3].copy() + J @ dx[6 * c:6 * c + 3].copy()
    return out


def window_in_use(config, inertial: bool) -> bool:
    """Whether a run holds a sliding window of clones: a real IMU's (``inertial``) SLAM run with
    ``estimator.window`` set; any other run keeps its landmarks in the state."""
    return inertial and config.estimator.window > 0 and Mode(config.estimator.mode) == Mode.SLAM


def window_text(config, inertial: bool) -> str | None:
    """What a run does with ``estimator.window`` (one line), None when it is off: a real IMU's SLAM
    run holds that many clones; any other run keeps landmarks in the state, and says so."""
    size, mode = config.estimator.window, Mode(config.estimator.mode)
    if not size:
        return None
    if window_in_use(config, inertial):
        return (f"state: a sliding window of {size} pose clones, no landmark in the state (estimator.window; "
                f"the tracks' points are projected out, W1-W7; each frame's pose is written as its clone leaves, W8)")
    what = "a velocity run" if not inertial else f"a {mode.value} run"
    return f"note: estimator.window = {size} serves a real IMU's SLAM run; {what} keeps its landmarks in the state"


@jit
def plan_use(ids, slots, last, current, full, size, stagger):
    """(W7) which tracks of the window's observations (``ids``, ``slots`` (O,), in frame order) a
    frame uses: those of the last frame's ``last`` not in this one's ``current`` (ended), those whose
    observations reach ``size`` - (id mod ``stagger``), and with the window ``full`` those seen in
    clone 0. Returns (rows (R,): the used observations, by track and then oldest first; start (F,),
    count (F,): each used track's run in ``rows``; the tracks left in the window)."""
    order = np.argsort(ids, kind="mergesort")  # stable: each track's observations stay oldest first
    cur = np.sort(current)
    lst = np.sort(last)
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
            i = np.searchsorted(lst, track)
            j = np.searchsorted(cur, track)
            use = (i < lst.size and lst[i] == track) and not (j < cur.size and cur[j] == track)
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
    their NIS sum, the features mapped, and the tracks in the window after the frame."""

    used: int
    gated: int
    nis_sum: float
    mapped: int
    active: int


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
        self._gate = chdtri(np.maximum(4 * n - 3, 1), 1.0 - gate_probability)  # chi2_{4n-3} quantile by n (W5)
        self._obs_gate = float(chdtri(4, 1.0 - gate_probability))  # one observation's (U4) (W3)
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
        points, covs, ok, nis, used, Hr = feature_rows(
            state.clones, self.cam_T_imu, cam.fx, cam.fy, cam.cx, cam.cy, cam.baseline, start, count, slots, pixels,
            np.ascontiguousarray(state.P[c:c + w6, c:c + w6]), self.pixel_var, self._gate, self._obs_gate,
            WINDOW_ITERATIONS)
        good = ok & (nis <= self._gate[used])
        if good.any():
            dx = StateHelper.update_window(state, Hr, self.pixel_var)
            correct(state, dx)
            self.map.add(ids[start[good]], points[good], covs[good])
        n_used = int(used[good].sum())
        return WindowStep(n_used, int(count.sum()) - n_used, float(nis[good].sum()), int(good.sum()), 0)


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
    feature_rows(clones, np.eye(4), 700.0, 700.0, 600.0, 180.0, 0.5, np.zeros(1, dtype=np.int64),
                 np.full(1, 2, dtype=np.int64), np.arange(2, dtype=np.int64), pixels, np.eye(12), 1.0,
                 np.full(4, 10.0), 18.5, WINDOW_ITERATIONS)
    ids = np.arange(3, dtype=np.int64)
    plan_use(ids, np.zeros(3, dtype=np.int64), ids, ids[:1], True, 13, 6)
    plan_use(ids, np.zeros(3, dtype=np.int64), ids, ids[:0], False, 1, 1)

    retract_clones(clones, np.zeros(12))
