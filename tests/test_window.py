"""The sliding window of pose clones (``backend.estimator.window``, W1-W8): a feature's information
against rows built independently from perturbed clones, the update against the Kalman update of
the stacked rows, the clone operations, gross errors, the settled trajectory, and a Monte Carlo run
of the room flight."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vislam.backend.config import Config
from vislam.backend.evaluation.consistency import average_band, trajectory_nees
from vislam.backend.evaluation.metrics import trajectory_errors
from vislam.backend.estimator.inertial import CORE_INERTIAL
from vislam.backend.estimator.invariant import body_pose_covariance
from vislam.backend.estimator.state import FilterState
from vislam.backend.estimator.state_helper import CoreTransition, StateHelper
from vislam.backend.estimator.window import feature_information, retract_clones
from vislam.backend.geometry import se3
from vislam.backend.run.inertial import run_inertial
from vislam.synth.inertial_scene import InertialSceneConfig, make_inertial_scene

FX, FY, CX, CY, BASELINE = 450.0, 440.0, 370.0, 240.0, 0.11
NO_GATE = 1e12


def _cam_T_imu() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]  # camera z along the IMU's x
    T[:3, 3] = [0.02, -0.05, 0.01]
    return T


def _pixels(world_T_imu: np.ndarray, p: np.ndarray) -> np.ndarray:
    C = _cam_T_imu() @ se3.inverse(world_T_imu)
    q = C[:3, :3] @ p + C[:3, 3]
    return np.array([FX * q[0] / q[2] + CX, FY * q[1] / q[2] + CY, FX * (q[0] - BASELINE) / q[2] + CX,
                     FY * q[1] / q[2] + CY])


def _information(clones, pixels, slots=None, obs_gate=NO_GATE):
    n = pixels.shape[0]
    w = clones.shape[0]
    slots = np.arange(n, dtype=np.int64) if slots is None else slots
    return feature_information(clones, _cam_T_imu(), FX, FY, CX, CY, BASELINE, np.zeros(1, dtype=np.int64),
                               np.full(1, n, dtype=np.int64), slots, np.ascontiguousarray(pixels), np.eye(6 * w) * 1e-4,
                               0.25, np.full(n + 2, NO_GATE), obs_gate, 8)


def _clones(rng, w):
    return np.array([se3.exp_se3(np.r_[rng.normal(0, 0.3, 3), rng.normal(0, 0.1, 3)]) for _ in range(w)])


def _stacked_rows(clones, p, pixels):
    """The 3 rows (U1) of each observation c at the estimates and their Jacobians on the clones' left
    perturbations (6w columns) and on the point, by central differences: r (3n,), H_x (3n,6w), H_p (3n,3)."""
    w = clones.shape[0]
    s = np.sqrt(0.5)

    def rows(T, q):
        z = _pixels(T, q)
        return np.array([z[0] - CX, (z[1] + z[3]) * s - 2 * s * CY, z[2] - CX])

    r = np.concatenate([[z[0] - CX, (z[1] + z[3]) * s - 2 * s * CY, z[2] - CX] - rows(clones[c], p)
                        for c, z in enumerate(pixels)])
    Hx, Hp, h = np.zeros((3 * w, 6 * w)), np.zeros((3 * w, 3)), 1e-6
    for c in range(w):
        for j in range(6):
            e = np.zeros(6)
            e[j] = h
            Hx[3 * c:3 * c + 3, 6 * c + j] = (rows(se3.exp_se3(e) @ clones[c], p)
                                              - rows(se3.exp_se3(-e) @ clones[c], p)) / (2 * h)
        for j in range(3):
            e = np.zeros(3)
            e[j] = h
            Hp[3 * c:3 * c + 3, j] = (rows(clones[c], p + e) - rows(clones[c], p - e)) / (2 * h)
    return r, Hx, Hp


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_feature_information_is_that_of_the_clone_rows_with_the_point_projected_out(seed):
    """(W4) Pixels made by clones T_c = exp(xi_c^) T_hat_c (the true ones) of a point p: exact pixels
    of the estimates give the point and g = 0; for the moved clones, [Lambda g] equals H_o^T [H_o r_o]
    built independently (the rows' Jacobians by central differences, N an orthonormal basis of the
    left null space of H_p by SVD, H_o = N^T H_x, r_o = N^T r), and g = Lambda xi to first order."""
    from scipy.linalg import null_space

    rng = np.random.default_rng(seed)
    w = 5
    clones = _clones(rng, w)
    p = np.array([5.0, 0.7, -0.4]) + rng.normal(0, 0.3, 3)
    exact = np.array([_pixels(T, p) for T in clones])
    points, _, ok, _, used, info = _information(clones, exact)
    assert ok[0] and used[0] == w and info.shape == (6 * w, 6 * w + 1)
    np.testing.assert_allclose(points[0], p, atol=1e-9)
    assert np.abs(info[:, -1]).max() < 1e-9 * np.abs(info[:, :-1]).max()
    xi = rng.normal(0, 1e-5, 6 * w)
    true = np.array([se3.exp_se3(xi[6 * c:6 * c + 6]) @ clones[c] for c in range(w)])
    moved = np.array([_pixels(T, p) for T in true])
    points, _, ok, _, _, info = _information(clones, moved)
    assert ok[0]
    r, Hx, Hp = _stacked_rows(clones, points[0], moved)
    N = null_space(Hp.T)
    assert N.shape == (3 * w, 3 * w - 3)
    Ho, ro = N.T @ Hx, N.T @ r
    Lam, g = info[:, :-1], info[:, -1]
    np.testing.assert_allclose(Lam, Ho.T @ Ho, rtol=0, atol=1e-6 * np.abs(Lam).max())
    np.testing.assert_allclose(g, Ho.T @ ro, rtol=0, atol=1e-6 * np.abs(g).max())
    assert np.abs(g).max() > 1e-3 * np.abs(Lam).max() * np.abs(xi).max()  # the motion is seen
    np.testing.assert_allclose(g, Lam @ xi, rtol=0, atol=1e-3 * np.abs(g).max())


def test_a_global_motion_of_clones_and_point_is_not_seen():
    """The information does not see what no camera can: the clones and the point moved together by
    one rigid motion give the same pixels, and Lambda maps that motion (xi_c = xi for every clone in
    the left perturbation) to zero."""
    rng = np.random.default_rng(3)
    w = 4
    clones = _clones(rng, w)
    p = np.array([4.0, -0.5, 0.3])
    _, _, ok, _, _, info = _information(clones, np.array([_pixels(T, p) for T in clones]))
    Lam = info[:, :-1]
    assert ok[0] and np.abs(Lam).max() > 0
    for xi in (np.r_[1.0, -2.0, 0.5, 0, 0, 0], np.r_[0, 0, 0, 0.3, -0.1, 0.7]):
        assert np.abs(Lam @ np.tile(xi, w)).max() < 1e-9 * np.abs(Lam).max()


def test_a_gross_error_leaves_the_feature_and_the_rest_is_used():
    """(W3) One observation replaced by a far pixel: it is left out (used = n - 1) and the point is
    the one the others see; with the gate off it would be kept."""
    rng = np.random.default_rng(4)
    w = 6
    clones = _clones(rng, w)
    p = np.array([5.0, 0.2, 0.1])
    pixels = np.array([_pixels(T, p) for T in clones]) + rng.normal(0, 0.3, (w, 4))
    pixels[2] += [25.0, -14.0, 25.0, -14.0]
    points, _, ok, _, used, _ = _information(clones, pixels, obs_gate=18.47)
    assert ok[0] and used[0] == w - 1
    assert np.linalg.norm(points[0] - p) < 0.05
    _, _, _, _, used_all, _ = _information(clones, pixels)
    assert used_all[0] == w


def test_a_feature_beyond_the_bound_gets_its_exact_nis():
    """(W5) the pixels' own bound (r_o^T r_o + sum d^2) / sigma^2 decides within the gate; a feature
    beyond it gets the exact r_o^T (H_o P H_o^T + sigma^2 I)^-1 r_o + sum d^2 / sigma^2, here against the
    textbook S of the independently built rows (a gate of 0 forces it)."""
    from scipy.linalg import null_space

    rng = np.random.default_rng(9)
    w = 4
    clones = _clones(rng, w)
    p = np.array([4.5, 0.3, -0.2])
    pixels = np.array([_pixels(T, p) for T in clones]) + rng.normal(0, 0.5, (w, 4))
    A = rng.normal(size=(6 * w, 6 * w))
    P_ww = 1e-4 * (A @ A.T) + 1e-5 * np.eye(6 * w)
    args = (clones, _cam_T_imu(), FX, FY, CX, CY, BASELINE, np.zeros(1, dtype=np.int64), np.full(1, w, dtype=np.int64),
            np.arange(w, dtype=np.int64), np.ascontiguousarray(pixels), P_ww, 0.25)
    points, _, ok, bound, _, _ = feature_information(*args, np.full(w + 2, NO_GATE), NO_GATE, 8)
    _, _, _, exact, _, info = feature_information(*args, np.zeros(w + 2), NO_GATE, 8)
    r, Hx, Hp = _stacked_rows(clones, points[0], pixels)
    N = null_space(Hp.T)
    Ho, ro = N.T @ Hx, N.T @ r
    off = np.sum(((pixels[:, 1] - pixels[:, 3]) * np.sqrt(0.5)) ** 2)
    S = Ho @ P_ww @ Ho.T + 0.25 * np.eye(3 * w - 3)
    np.testing.assert_allclose(exact[0], ro @ np.linalg.solve(S, ro) + off / 0.25, rtol=1e-5)
    np.testing.assert_allclose(bound[0], (ro @ ro + off) / 0.25, rtol=1e-5)
    assert exact[0] < bound[0] and not info.any()  # beyond the gate of 0: left out


def _state_with_clones(rng, w):
    state = FilterState(mu=np.eye(4), core=CORE_INERTIAL, velocity=np.zeros(3), accel_bias=np.zeros(3))
    A = rng.normal(size=(CORE_INERTIAL, CORE_INERTIAL))
    StateHelper.set_prior(state, A @ A.T + np.eye(CORE_INERTIAL))
    state.clones = np.zeros((0, 4, 4))
    for _ in range(w):
        StateHelper.clone(state)
        B = rng.normal(size=(CORE_INERTIAL, CORE_INERTIAL)) * 0.1
        state.P = CoreTransition(np.eye(CORE_INERTIAL) + B, 0.01 * np.eye(CORE_INERTIAL)).apply(state.P)
    return state


def test_clone_copies_the_pose_and_drop_removes_the_oldest():
    """(W1) a clone's rows are the pose's (its covariance with everything, itself included); (W7) the
    oldest clone's rows and columns leave, the rest unchanged."""
    rng = np.random.default_rng(5)
    state = _state_with_clones(rng, 3)
    P0 = state.P.copy()
    StateHelper.clone(state)
    D = P0.shape[0]
    np.testing.assert_array_equal(state.P[:D, :D], P0)
    np.testing.assert_array_equal(state.P[D:, :D], P0[:6])
    np.testing.assert_array_equal(state.P[D:, D:], P0[:6, :6])
    np.testing.assert_array_equal(state.P, state.P.T)
    before = state.P.copy()
    StateHelper.drop_oldest_clone(state)
    keep = np.r_[0:CORE_INERTIAL, CORE_INERTIAL + 6:before.shape[0]]
    np.testing.assert_array_equal(state.P, before[np.ix_(keep, keep)])
    assert state.clones.shape[0] == 3


def test_clone_transition_moves_only_the_core():
    """(W2) P <- F P F^T + blockdiag(Q, 0) with F = blockdiag(Phi, I): the clones are static."""
    rng = np.random.default_rng(6)
    state = _state_with_clones(rng, 2)
    Phi = np.eye(CORE_INERTIAL) + 0.1 * rng.normal(size=(CORE_INERTIAL, CORE_INERTIAL))
    Q = np.diag(rng.uniform(0.01, 0.1, CORE_INERTIAL))
    D = state.P.shape[0]
    F = np.eye(D)
    F[:CORE_INERTIAL, :CORE_INERTIAL] = Phi
    G = np.zeros((D, D))
    G[:CORE_INERTIAL, :CORE_INERTIAL] = Q
    expected = F @ state.P @ F.T + G
    out = CoreTransition(Phi, Q).apply(state.P.copy())
    np.testing.assert_allclose(out, expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(out, out.T)


@pytest.mark.parametrize("rows", [10, 40])
def test_window_update_is_the_kalman_update_of_the_stacked_rows(rows):
    """(W6) fewer and more rows than the clones' columns, given as their information [H^T H, H^T r]:
    P and dx equal the textbook update P - P H^T (H P H^T + sigma^2 I)^-1 H P over the whole state,
    H zero on the core."""
    rng = np.random.default_rng(7)
    state = _state_with_clones(rng, 3)
    D, c = state.P.shape[0], CORE_INERTIAL
    H_w = rng.normal(size=(rows, D - c))
    r = rng.normal(size=rows)
    H = np.zeros((rows, D))
    H[:, c:] = H_w
    P = state.P.copy()
    S = H @ P @ H.T + 0.3 * np.eye(rows)
    K = P @ H.T @ np.linalg.inv(S)
    dx = StateHelper.update_window(state, np.column_stack([H_w.T @ H_w, H_w.T @ r]), 0.3)
    np.testing.assert_allclose(dx, K @ r, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(state.P, P - K @ S @ K.T, rtol=1e-8, atol=1e-10)
    np.testing.assert_array_equal(state.P, state.P.T)


def test_retract_clones_is_the_left_exponential():
    """(W6) T_c <- exp(dx_c^) T_hat_c, clone by clone."""
    rng = np.random.default_rng(8)
    clones = _clones(rng, 3)
    dx = rng.normal(0, 0.2, 18)
    out = retract_clones(clones, dx)
    for c in range(3):
        np.testing.assert_allclose(out[c], se3.exp_se3(dx[6 * c:6 * c + 6]) @ clones[c], atol=1e-12)


def test_room_flight_with_a_window_is_accurate_and_consistent():
    """12 runs of one 10 s room flight (2 % gross outliers; IMU noise, biases and pixels drawn anew)
    with a window of 13 clones: in flight (from 3 s on) the average pose NEES is in its 95 % band for
    at least 90 % of steps (99 % measured), never above it at rest and take-off, each run's ATE is
    under 2 cm (about 6 mm), and the NIS per observation is within 7 % of what its degrees of freedom
    expect (4n - 3 a feature seen n times, W5; 0.998 measured)."""
    cfg = InertialSceneConfig(duration=10.0, seed=3)
    config = Config()  # the default: a window of 13
    assert config.estimator.window == 13
    nees, ates, nis = [], [], []
    for run in range(12):
        bias = np.random.default_rng(500 + run).normal(0.0, 0.1, 3)
        scene = make_inertial_scene(dataclasses.replace(cfg, accel_bias0=tuple(bias)), noise_seed=100 + run)
        res = run_inertial(scene.sequence, config)
        assert res.stats.landmarks_mapped > 100  # the features' points make the map
        t = scene.sequence.time_stamps
        nees.append(trajectory_nees(res.time_stamps, res.world_T_imu, res.pose_covariance, t, scene.world_T_imu_true,
                                    gravity_aligned=True).pose_nees[1:])
        ates.append(trajectory_errors(res.time_stamps, res.world_T_imu, t, scene.world_T_imu_true).ate_rmse)
        nis.append(res.stats.mean_nis / res.stats.nis_expected)  # its expectation: 4n - 3 dof a feature (W5)
        assert 3.0 < res.stats.nis_expected < 4.0
    assert 0.93 <= np.mean(nis) <= 1.07, nis
    avg = np.mean(nees, axis=0)
    lo, hi = average_band(6, len(nees))
    flying = avg[60:]
    assert np.mean((flying >= lo) & (flying <= hi)) >= 0.9, np.mean((flying >= lo) & (flying <= hi))
    assert np.all(avg[:60] <= hi)
    assert max(ates) < 0.02, ates


def test_a_window_run_writes_each_frame_as_its_clone_left():
    """(W8) a window run's trajectory holds each frame once, as its clone left the window: no less
    certain than the filter was at the frame (the filtered covariance minus the settled one, both of
    the filter's own left perturbation, is positive semidefinite: later updates only add
    information), and closer to the truth over the flight than the filter's pose at each frame's own
    update."""
    scene = make_inertial_scene(InertialSceneConfig(duration=6.0, seed=4), noise_seed=11)
    filtered, covs, filters = [], [], []

    def observe(k, ekf, stats):
        filtered.append(ekf.world_T_imu.copy())
        covs.append(ekf.pose_covariance)
        filters.append(ekf)

    res = run_inertial(scene.sequence, Config().with_assignments(["estimator.window=13"]), observer=observe)
    settled = filters[-1].window.settled
    assert sorted(f for f, _, _ in settled) == list(range(scene.sequence.num_steps))
    for frame, pose, block in settled:
        assert np.array_equal(res.world_T_imu[frame], pose)
        np.testing.assert_allclose(res.pose_covariance[frame], body_pose_covariance(pose, block), rtol=1e-10, atol=1e-18)
    for k in range(1, len(covs)):  # in the filter's own coordinates, the left perturbation of each pose (I7 undone)
        A, B = se3.adjoint(filtered[k]), se3.adjoint(res.world_T_imu[k])
        gain = A @ covs[k] @ A.T - B @ res.pose_covariance[k] @ B.T
        assert np.linalg.eigvalsh(gain).min() > -1e-9 * np.abs(covs[k]).max(), k
    assert not np.allclose(res.world_T_imu, np.array(filtered))
    t, truth = scene.sequence.time_stamps, scene.world_T_imu_true
    settled_ate = trajectory_errors(t, res.world_T_imu, t, truth).ate_rmse
    filtered_ate = trajectory_errors(t, np.array(filtered), t, truth).ate_rmse
    assert settled_ate < filtered_ate, (settled_ate, filtered_ate)


def test_a_run_says_what_it_does_with_the_window():
    """The window is a real IMU's SLAM run's, by default: such a run says it holds the clones; a
    velocity run and a mapping run keep their landmarks, and say so where the option was set to
    another size; 0 (landmarks in the state) and the default on such runs say nothing."""
    from vislam.backend.estimator.window import window_in_use, window_text

    default = Config()
    assert window_in_use(default, inertial=True) and "13 pose clones" in window_text(default, inertial=True)
    assert not window_in_use(default, inertial=False) and window_text(default, inertial=False) is None
    mapping = default.with_assignments(["estimator.mode=mapping"])
    assert not window_in_use(mapping, inertial=True) and window_text(mapping, inertial=True) is None
    other = Config().with_assignments(["estimator.window=20"])
    assert "20 pose clones" in window_text(other, inertial=True)
    assert "a velocity run keeps its landmarks" in window_text(other, inertial=False)
    assert "a mapping run keeps its landmarks" in window_text(other.with_assignments(["estimator.mode=mapping"]),
                                                              inertial=True)
    off = Config().with_assignments(["estimator.window=0"])
    assert not window_in_use(off, inertial=True)
    assert window_text(off, inertial=True) is None and window_text(off, inertial=False) is None


def test_plan_use_picks_ended_long_and_oldest_tracks_by_track_oldest_first():
    """(W7) track 1 ended (at the last frame, not this one); track 2 reached its segment's length
    (size - id mod stagger = 5 - 2 % 2 = 5 observations); track 3 was seen in the oldest clone of a
    full window; track 4 goes on, short and younger: left. Rows by track, each oldest first."""
    from vislam.backend.estimator.window import plan_use

    ids = np.array([2, 1, 3, 2, 1, 4, 2, 2, 4, 2, 4], dtype=np.int64)
    slots = np.array([0, 0, 0, 1, 1, 1, 2, 3, 3, 4, 4], dtype=np.int64)
    last = np.array([1, 2, 4], dtype=np.int64)
    current = np.array([2, 4], dtype=np.int64)
    rows, start, count, left = plan_use(ids, slots, last, current, True, 5, 2)
    assert ids[rows].tolist() == [1, 1, 2, 2, 2, 2, 2, 3]
    assert slots[rows].tolist() == [0, 1, 0, 1, 2, 3, 4, 0]
    assert start.tolist() == [0, 2, 7] and count.tolist() == [2, 5, 1] and left == 1
    rows, start, count, left = plan_use(ids, slots, last, current, False, 6, 2)  # not full, longer segments
    assert ids[rows].tolist() == [1, 1] and left == 3
