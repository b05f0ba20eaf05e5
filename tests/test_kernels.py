"""The compiled kernels of the EKF step (backend.kernels) against dense textbook formulas."""

from __future__ import annotations

import numpy as np
import pytest

from backend import invariant, kernels, se3
from backend.ekf import CORE

SIGMA2 = 1.7  # pixel variance


def _spd(rng, n: int, scale: float = 1.0) -> np.ndarray:
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T / n + 0.1 * np.eye(n))


def _dense_H(H_x: np.ndarray, H_m: np.ndarray, slots: np.ndarray, D: int) -> np.ndarray:
    H = np.zeros((3 * slots.size, D))
    for i, s in enumerate(slots):
        H[3 * i : 3 * i + 3, :6] = H_x[3 * i : 3 * i + 3]
        H[3 * i : 3 * i + 3, CORE + 3 * s : CORE + 3 * s + 3] = H_m[i]
    return H


def _problem(rng, n_landmarks: int = 12, k: int = 8):
    D = CORE + 3 * n_landmarks
    P = _spd(rng, D, 0.1)
    slots = np.sort(rng.choice(n_landmarks, k, replace=False))
    H_x = rng.normal(size=(3 * k, 6)) * 30.0
    H_m = rng.normal(size=(k, 3, 3)) * 30.0
    return P, slots, H_x, H_m


def _prediction_problem(rng, K: int):
    """P over pose, bias and K landmarks, a pose, a twist, K world points, dt, the twist noise q and a
    bias random-walk variance."""
    P = _spd(rng, CORE + 3 * K)
    mu = se3.exp_se3(rng.normal(size=6))
    twist = rng.normal(size=6) * 0.1
    points = rng.normal(size=(K, 3)) * 10.0
    return P, mu, twist, points, 0.1, rng.uniform(0.01, 0.1, 6), 3e-7


@pytest.mark.parametrize("bias", [True, False])
def test_predict_invariant_equals_dense_propagation(bias):
    """(I2): P <- F P F^T + G Q G^T with F = I + g e_b^T, G = [G_pose; m_i^ R_phi] diag(q)."""
    rng = np.random.default_rng(1)
    K = 7
    D = CORE + 3 * K
    P, mu, twist, points, dt, q, walk = _prediction_problem(rng, K)
    G_pose, G_lm = invariant.noise_jacobian(mu, twist, points)
    G = np.zeros((D, 6))
    G[:6] = G_pose
    G[CORE:] = G_lm.reshape(-1, 6)
    F = np.eye(D)
    if bias:
        F[:, 6:9] += -dt * G[:, 3:6]
    expected = F @ P @ F.T + G @ np.diag(q**2) @ G.T
    if bias:
        expected[6:9, 6:9] += walk * np.eye(3)
    pose, R_phi = invariant.noise_jacobian_pose(mu, twist)
    out = P.copy()
    kernels.predict_invariant_inplace(out, pose, R_phi, points, q, dt, bias, walk)
    np.testing.assert_allclose(out, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
    assert np.array_equal(out, out.T)


@pytest.mark.parametrize("angle", [0.0, 1e-7, 0.05, 0.3, 2.5])
def test_compiled_se3_matches_backend_se3(angle):
    """The compiled single-pose exp and J_r (both sides of the Taylor switch) equal backend.se3's."""
    rng = np.random.default_rng(2)
    axis = rng.normal(size=3)
    xi = np.concatenate([rng.normal(size=3), angle * axis / np.linalg.norm(axis)])
    T, J_l = kernels._exp_se3_parts(xi)
    np.testing.assert_allclose(T, se3.exp_se3(xi), rtol=0, atol=1e-14)
    np.testing.assert_allclose(J_l, se3.left_jacobian_so3(xi[3:]), rtol=0, atol=1e-14)
    np.testing.assert_allclose(kernels._right_jacobian_se3(xi), se3.right_jacobian_se3(xi), rtol=0, atol=1e-13)


def test_predict_step_is_mean_propagation_then_invariant_covariance():
    """One compiled prediction = mu exp(tau u^), the landmark walk on the landmark diagonal, then (I2)
    with backend.invariant's noise Jacobian at the propagated pose."""
    rng = np.random.default_rng(3)
    K = 5
    D = CORE + 3 * K
    P, mu, twist, points, dt, q, walk = _prediction_problem(rng, K)
    lm_walk = 2e-4
    mu_next = mu @ se3.exp_se3(twist)
    expected = P.copy()
    expected[np.arange(CORE, D), np.arange(CORE, D)] += lm_walk
    kernels.predict_invariant_inplace(expected, *invariant.noise_jacobian_pose(mu_next, twist), points, q, dt, True, walk)
    out = P.copy()
    pose = kernels.predict_invariant_step(mu, out, points, twist, q, dt, True, walk, lm_walk)
    np.testing.assert_allclose(pose, mu_next, rtol=0, atol=1e-13)
    np.testing.assert_allclose(out, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())


def test_retract_invariant_equals_backend_invariant():
    """(I5) compiled: the pose and the world points after exp(dx) X_hat, as backend.invariant.retract."""
    rng = np.random.default_rng(4)
    K = 6
    mu = se3.exp_se3(rng.normal(size=6))
    points = rng.normal(size=(K, 3)) * 10.0
    dx = rng.normal(size=CORE + 3 * K) * 0.05
    pose_expected, points_expected = invariant.retract(mu, points, dx[:6], dx[CORE:])
    moved = points.copy()
    pose = kernels.retract_invariant_inplace(mu, moved, dx)
    np.testing.assert_allclose(pose, pose_expected, rtol=0, atol=1e-13)
    np.testing.assert_allclose(moved, points_expected, rtol=0, atol=1e-12)


def test_innovation_covariance_equals_dense_products():
    rng = np.random.default_rng(2)
    P, slots, H_x, H_m = _problem(rng)
    residual = rng.normal(size=(slots.size, 3))
    off_row = rng.normal(size=slots.size)
    HP, S, nis = kernels.innovation_covariance(P, H_x, H_m, slots, SIGMA2, residual, off_row)
    H = _dense_H(H_x, H_m, slots, P.shape[0])
    S_ref = H @ P @ H.T + SIGMA2 * np.eye(H.shape[0])
    np.testing.assert_allclose(HP, H @ P, rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(S, S_ref, rtol=1e-12, atol=1e-9)
    assert np.array_equal(S, S.T)
    for i in range(slots.size):
        block = S_ref[3 * i : 3 * i + 3, 3 * i : 3 * i + 3]
        expected = residual[i] @ np.linalg.solve(block, residual[i]) + off_row[i] ** 2 / SIGMA2
        assert nis[i] == pytest.approx(expected, rel=1e-10)


@pytest.mark.parametrize("pose", [True, False])
def test_innovation_invariant_is_observation_then_products(pose):
    """The fused call = observe_invariant from cam_T_imu world_T_imu^-1, then innovation_covariance."""
    rng = np.random.default_rng(8)
    n = 9
    P = _spd(rng, CORE + 3 * n, 0.1)
    mu, cam_T_imu = se3.exp_se3(rng.normal(size=6) * 0.3), se3.exp_se3(rng.normal(size=6) * 0.3)
    world_T_cam = mu @ se3.inverse(cam_T_imu)
    p_cam = np.column_stack([rng.uniform(-5, 5, n), rng.uniform(-2, 2, n), rng.uniform(5, 30, n)])
    theta = p_cam @ world_T_cam[:3, :3].T + world_T_cam[:3, 3]
    theta[-1] = world_T_cam[:3, 3] - 5.0 * world_T_cam[:3, 2]  # behind the camera
    slots = np.array([8, 1, 4, 6], dtype=np.int64)
    pixels = rng.uniform(100, 600, (slots.size, 4))
    cam = (700.0, 690.0, 610.0, 180.0, 0.54)
    expected = list(kernels.observe_invariant(theta[slots], cam_T_imu @ se3.inverse(mu), *cam, pixels))
    if not pose:
        expected[2][:] = 0.0
    residual, off_row, H_x, H_m, in_front = expected
    HP, S, nis = kernels.innovation_covariance(P, H_x, H_m, slots, SIGMA2, residual, off_row)
    out = kernels.innovation_invariant(P, theta, slots, mu, cam_T_imu, *cam, pixels, SIGMA2, pose)
    assert not out[-1][0] and out[-1][1:].all()  # slot 8 is behind the camera
    for got, want in zip(out, (residual, off_row, H_x, H_m, HP, S, nis, in_front)):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)


def test_gather_and_augment_are_the_block_formulas():
    rng = np.random.default_rng(3)
    D = CORE + 3 * 10
    P = _spd(rng, D)
    keep = np.sort(rng.choice(D, 20, replace=False))
    G = kernels.gather_symmetric(P, keep)
    assert G.flags.c_contiguous
    np.testing.assert_array_equal(G, P[np.ix_(keep, keep)])

    n = 4
    J_xi = rng.normal(size=(3 * n, 6))
    J_z = rng.normal(size=(n, 3, 4))
    out = kernels.augment(P, J_xi, J_z, SIGMA2)
    cross = J_xi @ P[:6]
    block = J_xi @ P[:6, :6] @ J_xi.T
    for i in range(n):
        block[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] += SIGMA2 * J_z[i] @ J_z[i].T
    expected = np.block([[P, cross.T], [cross, block]])
    np.testing.assert_allclose(out, expected, rtol=1e-12, atol=1e-12)
    assert np.array_equal(out, out.T) and out.flags.c_contiguous


def test_gather_landmarks_keeps_pose_bias_and_the_kept_slots():
    rng = np.random.default_rng(5)
    P = _spd(rng, CORE + 3 * 6)
    keep = np.array([1, 4, 5])
    cols = np.concatenate([np.arange(CORE), (CORE + 3 * keep[:, None] + np.arange(3)).ravel()])
    np.testing.assert_array_equal(kernels.gather_landmarks(P, keep), P[np.ix_(cols, cols)])


@pytest.mark.parametrize("pose", [True, False])
def test_initialize_invariant_is_triangulation_then_augmentation(pose):
    """One compiled call = backend.landmarks.initialize (xyz, unscented mean), (I4) J_xi = [I 0]
    (zero with poses held fixed) and the augmentation."""
    from backend.camera import StereoCamera
    from backend.landmarks import initialize

    rng = np.random.default_rng(6)
    camera = StereoCamera(np.array([[718.0, 0, 607.0], [0, 718.0, 185.0], [0, 0, 1]]), 0.54)
    p_cam = np.column_stack([rng.uniform(-8, 8, 5), rng.uniform(-2, 2, 5), rng.uniform(4, 40, 5)])
    pixels = camera.project(p_cam) + rng.normal(size=(5, 4)) * 0.3
    mu, imu_T_cam = se3.exp_se3(rng.normal(size=6)), se3.exp_se3(rng.normal(size=6) * 0.3)
    P = _spd(rng, CORE + 3 * 2)
    theta, _, J_z, _ = initialize("xyz", camera, pixels, mu, imu_T_cam, 1.3)
    J_xi = np.zeros((15, 6))
    if pose:
        J_xi[:, :3] = np.tile(np.eye(3), (5, 1))
    expected = kernels.augment(P, J_xi, np.ascontiguousarray(J_z), SIGMA2)
    out, points = kernels.initialize_invariant(P, pixels, mu, imu_T_cam, camera.fx, camera.fy, camera.cx, camera.cy,
                                               camera.baseline, 1.3, SIGMA2, pose)
    np.testing.assert_allclose(points, theta, rtol=0, atol=1e-11)
    np.testing.assert_allclose(out, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
    assert np.array_equal(out, out.T)


def test_one_point_ransac_hypotheses_are_single_observation_updates():
    """Hypothesis j is the EKF update with observation j alone; the winner's supporters come back.
    Only the translation is uncertain, so each observation (3 rows) can explain it: 6 observations
    agree with one translation error and 3 with another, and the 6 win."""
    rng = np.random.default_rng(4)
    _, slots, H_x, H_m = _problem(rng, n_landmarks=12, k=9)
    D = CORE + 3 * 12
    P = np.diag(np.r_[np.ones(3), np.full(D - 3, 1e-8)])
    H = _dense_H(H_x, H_m, slots, D)
    residual = (H[:, :3] @ np.array([0.3, -0.2, 0.1])).reshape(-1, 3)
    residual[6:] = (H[:, :3] @ np.array([-0.2, 0.4, 0.3])).reshape(-1, 3)[6:]
    off_row = np.zeros(slots.size)
    HP, S, _ = kernels.innovation_covariance(P, H_x, H_m, slots, SIGMA2, residual, off_row)
    threshold = 1.0
    candidates = np.ones(slots.size, dtype=bool)
    inliers = kernels.one_point_ransac(S, residual, off_row, candidates, SIGMA2, threshold)

    # reference: every hypothesis as an explicit single-observation EKF update
    support = []
    for j in range(slots.size):
        Hj = H[3 * j : 3 * j + 3]
        dx = P @ Hj.T @ np.linalg.solve(Hj @ P @ Hj.T + SIGMA2 * np.eye(3), residual[j])
        err = np.linalg.norm(residual - (H @ dx).reshape(-1, 3), axis=1)
        support.append(err <= threshold)
    counts = [s.sum() for s in support]
    best = support[int(np.argmax(counts))]
    np.testing.assert_array_equal(inliers, best)
    assert inliers[:6].all() and not inliers[6:].any()


def test_rescue_test_is_the_gate_after_the_inlier_update():
    """(U3): the rest's residual and covariance after the update with the inliers, to first order."""
    rng = np.random.default_rng(5)
    P, slots, H_x, H_m = _problem(rng, n_landmarks=12, k=8)
    D = P.shape[0]
    H = _dense_H(H_x, H_m, slots, D)
    residual = rng.normal(size=(slots.size, 3)) * 3.0
    residual[7] *= 20.0  # one of the rest fails the gate
    off_row = rng.normal(size=slots.size)
    _, S, _ = kernels.innovation_covariance(P, H_x, H_m, slots, SIGMA2, residual, off_row)
    inlier = np.array([1, 1, 0, 1, 1, 0, 1, 0], dtype=bool)
    ri = (3 * np.flatnonzero(inlier)[:, None] + np.arange(3)).ravel()
    rr = (3 * np.flatnonzero(~inlier)[:, None] + np.arange(3)).ravel()
    L = np.linalg.cholesky(S[np.ix_(ri, ri)])
    w = np.linalg.solve(L, residual[inlier].ravel())
    X = np.linalg.solve(L, S[np.ix_(rr, ri)].T)
    gate = 9.0
    ok = kernels._rescue_test(X, w, S, np.flatnonzero(~inlier), residual, off_row, SIGMA2, gate)

    Hi = H[ri]
    K = P @ Hi.T @ np.linalg.inv(S[np.ix_(ri, ri)])
    P_post = P - K @ Hi @ P
    r_post = residual.ravel() - H @ (K @ residual[inlier].ravel())
    expected = []
    for j in np.flatnonzero(~inlier):
        Hj = H[3 * j : 3 * j + 3]
        Sj = Hj @ P_post @ Hj.T + SIGMA2 * np.eye(3)
        rj = r_post[3 * j : 3 * j + 3]
        expected.append(rj @ np.linalg.solve(Sj, rj) + off_row[j] ** 2 / SIGMA2 <= gate)
    np.testing.assert_array_equal(ok, expected)
    assert ok.tolist() == [True, True, False]


def test_joint_update_with_rescue_equals_dense_update_over_kept_rows():
    """(U2, U3): the compiled update with the inliers and the rescued rest equals the textbook
    update K = P H^T S^-1, P+ = P - K S K^T, dx = K r over exactly those observations."""
    rng = np.random.default_rng(8)
    P, slots, H_x, H_m = _problem(rng, n_landmarks=12, k=8)
    D = P.shape[0]
    H = _dense_H(H_x, H_m, slots, D)
    residual = rng.normal(size=(slots.size, 3)) * 3.0
    residual[7] *= 20.0  # fails the rescue gate
    off_row = rng.normal(size=slots.size)
    HP, S, _ = kernels.innovation_covariance(P, H_x, H_m, slots, SIGMA2, residual, off_row)
    inlier = np.array([1, 1, 0, 1, 1, 0, 1, 0], dtype=bool)
    rest = ~inlier
    rest[2] = False  # not a candidate (gated before): neither used nor tested
    out = P.copy()
    status, dx, used = kernels.joint_update_inplace(out, HP, S, residual, off_row, inlier, rest, SIGMA2, 9.0)
    assert status == 0
    assert used.tolist() == [True, True, False, True, True, True, True, False]
    rows = (3 * np.flatnonzero(used)[:, None] + np.arange(3)).ravel()
    Hu = H[rows]
    Su = Hu @ P @ Hu.T + SIGMA2 * np.eye(rows.size)
    K = np.linalg.solve(Su, Hu @ P).T
    expected = P - K @ Su @ K.T
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-10 * np.abs(P).max())
    assert np.array_equal(out, out.T)
    np.testing.assert_allclose(dx, K @ residual[used].ravel(), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("persistent", [0, 2])
def test_select_and_update_is_gate_ransac_count_then_joint_update(persistent):
    """The fused step = chi-square gate, 1-point RANSAC, the rejection count (tracks at the limit are
    not rescued), the joint update, and the gated-run counts, each as the separate kernels do them."""
    rng = np.random.default_rng(10)
    P, slots, H_x, H_m = _problem(rng, n_landmarks=12, k=8)
    residual = rng.normal(size=(slots.size, 3)) * 2.0
    residual[[1, 5]] += 15.0  # two that agree with each other, not with the rest
    residual[3] *= 40.0  # gated
    off_row = rng.normal(size=slots.size)
    HP, S, nis = kernels.innovation_covariance(P, H_x, H_m, slots, SIGMA2, residual, off_row)
    in_front = np.ones(slots.size, dtype=bool)
    in_front[6] = False
    gate = 13.28
    runs0 = rng.integers(0, 3, 12)
    gated0 = rng.integers(0, 3, 12)
    # the separate kernels
    use = in_front & (nis <= gate)
    inlier = kernels.one_point_ransac(S, residual, off_row, use, SIGMA2, 2.0)
    rest = use & ~inlier
    runs = runs0.copy()
    if persistent:
        rest &= ~kernels.count_rejections_inplace(runs, slots, rest, persistent)
    expected_P = P.copy()
    _, expected_dx, expected_used = kernels.joint_update_inplace(expected_P, HP, S, residual, off_row, inlier, rest,
                                                                 SIGMA2, gate)
    expected_gated = gated0.copy()
    expected_gated[slots] = np.where(expected_used, 0, gated0[slots] + 1)
    # fused
    out_P, out_runs, out_gated = P.copy(), runs0.copy(), gated0.copy()
    status, dx, used = kernels.select_and_update_inplace(out_P, HP, S, residual, off_row, nis, in_front, slots, gate,
                                                         2.0, SIGMA2, out_runs, persistent, out_gated)
    assert status == 0 and not used[3] and not used[6]
    assert used.tolist() == expected_used.tolist()
    np.testing.assert_array_equal(out_P, expected_P)
    np.testing.assert_array_equal(dx, expected_dx)
    np.testing.assert_array_equal(out_runs, runs)
    np.testing.assert_array_equal(out_gated, expected_gated)
    if persistent:
        assert (out_runs != runs0).any()


def test_joint_update_refuses_an_indefinite_innovation_covariance():
    rng = np.random.default_rng(9)
    P, slots, H_x, H_m = _problem(rng, n_landmarks=6, k=4)
    residual, off_row = rng.normal(size=(4, 3)), rng.normal(size=4)
    HP, S, _ = kernels.innovation_covariance(P, H_x, H_m, slots, SIGMA2, residual, off_row)
    S[3, 3] = -1.0
    out = P.copy()
    status, dx, used = kernels.joint_update_inplace(out, HP, S, residual, off_row, np.ones(4, dtype=bool),
                                                    np.zeros(4, dtype=bool), SIGMA2, 9.0)
    assert status > 0 and not used.any() and not dx.any()
    assert np.array_equal(out, P)  # the prior is kept


def test_mirror_lower_copies_the_lower_triangle():
    rng = np.random.default_rng(6)
    A = rng.normal(size=(7, 7))
    B = A.copy()
    kernels.mirror_lower_inplace(B)
    np.testing.assert_array_equal(np.tril(B), np.tril(A))
    assert np.array_equal(B, B.T)


_NO_LAZY_COMPILE = r"""
import json, sys, warnings
sys.path.insert(0, "tests")
warnings.simplefilter("ignore")
from backend import camera, conventions, kernels, timing
from backend.config import FilterConfig
from backend.pipeline import run_sequence
from test_ekf import make_drive, to_sequence

def counts():
    out = {n: len(f.signatures) for n, f in vars(kernels).items()
           if hasattr(f, "signatures") and n[0] != "_" and f.py_func.__module__ == kernels.__name__}
    out["camera._triangulate_rows"] = len(camera._triangulate_rows.signatures)
    out["conventions._left_errors"] = len(conventions._left_errors.signatures)
    out["timing._repeats_sorted"] = len(timing._repeats_sorted.signatures)
    return out

import backend.pipeline as pipeline
at_setup = []  # what is compiled when the first convention test starts
prepare = pipeline.prepare
pipeline.prepare = lambda seq, config: (at_setup.append(counts()), prepare(seq, config))[1]
runs = [run_sequence(to_sequence(make_drive(40, seed=1)), config)
        for config in (FilterConfig(), FilterConfig(mode="mapping"), FilterConfig(error_model="body"))]
reported = [r.stats.kernel_seconds == kernels.warm_up_seconds() > 0 for r in runs]
print(json.dumps([at_setup[0], counts(), reported]))
"""


def test_warm_up_compiles_what_the_filter_calls():
    """Every kernel signature a run needs is compiled (or loaded) by ``warm_up`` before the run's
    convention test, so neither the setup nor a step pays for it; in a fresh process, as other
    tests call kernels too."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", _NO_LAZY_COMPILE], cwd=root, capture_output=True, text=True,
                         check=True)
    before, after, reported = json.loads(out.stdout.strip().splitlines()[-1])
    assert len(before) >= 9 and all(n >= 1 for n in before.values())  # all loaded before the convention test
    assert after == before
    assert reported == [True, True, True]  # each run reports the process's warm-up, apart from its timing


def test_warm_up_says_so_when_it_takes_a_while(monkeypatch):
    """The command line's notice (``slow_notice``) fires when warming up outlasts ``NOTICE_AFTER``."""
    import threading

    called = threading.Event()
    monkeypatch.setattr(kernels, "_warm", False)
    monkeypatch.setattr(kernels, "NOTICE_AFTER", 0.0)
    monkeypatch.setattr(kernels, "slow_notice", called.set)
    monkeypatch.setattr(kernels, "_call_every_kernel", lambda: called.wait(5.0))  # busy until the notice came
    assert kernels.warm_up() > 0.0 and called.is_set()
    assert kernels.warm_up() == 0.0  # once per process


def test_plan_update_routes_observations_and_expires_landmarks():
    """Slots of the observed ids, unseen tracks leaving, and with re-anchoring the landmarks seen
    beyond their limit leaving too (their observations restart the track)."""
    state_ids = np.array([10, 3, 7])
    order = np.argsort(state_ids)
    ids = np.array([7, 10, 42])
    np.testing.assert_array_equal(kernels.slots_of(ids, state_ids[order], order), [2, 0, -1])
    counts, limits = np.array([1, 3, 2]), np.array([5, 3, 2])
    slots, leaving, ended, restart, expired = kernels.plan_update(ids, state_ids[order], order, counts, limits, True,
                                                                  False)
    np.testing.assert_array_equal(slots, [2, 0, -1])
    assert leaving.tolist() == [False, True, True]  # id 3 not seen; id 7 seen a third time, limit 2
    assert ended.tolist() == [False, True, False]
    assert restart.tolist() == [True, False, False] and expired == 1
    np.testing.assert_array_equal(counts, [2, 3, 3])
    counts = np.array([1, 3, 2])
    _, leaving, ended, restart, expired = kernels.plan_update(ids, state_ids[order], order, counts, limits, False,
                                                              True)
    assert not leaving.any() and not ended.any() and not restart.any() and expired == 0  # full state: none leaves
    np.testing.assert_array_equal(counts, [1, 3, 2])


def test_admit_landmarks_filters_by_disparity_and_depth_and_staggers_first_counts():
    """New features start landmarks where disparity > min and depth fx b / d <= max; the limit is the
    far one below the far disparity; a track's first landmark starts at 1 + id mod limit, a
    re-anchored one (restart) at 1."""
    ids = np.array([7, 8, 9, 10, 11])
    d = np.array([0.5, 3.0, 20.0, 2.0, 40.0])  # disparity, px
    pixels = np.column_stack([500.0 + d, np.full(5, 200.0), np.full(5, 500.0), np.full(5, 200.0)])
    restart = np.array([False, False, True, False, False])
    ok, counts, limits = kernels.admit_landmarks(ids, pixels, restart, 1.0, 100.0, 250.0, True, 6.0, 3, 25)
    np.testing.assert_array_equal(ok, [1, 2, 4])  # 0.5 px: too small; 2 px: 125 m > 100 m
    np.testing.assert_array_equal(limits, [25, 3, 3])
    np.testing.assert_array_equal(counts, [1 + 8 % 25, 1, 1 + 11 % 3])
    _, counts, _ = kernels.admit_landmarks(ids, pixels, restart, 1.0, np.inf, 350.0, False, 6.0, 3, 25)
    assert (counts == 1).all()  # no re-anchoring: no stagger


def test_plan_removal_index_arrays():
    mask = np.array([True, False, True, True, False])
    ended = np.array([True, False, False, False, False])
    runs = np.array([2, 0, 3, 0, 1])
    removed, keep, remap, counted = kernels.plan_removal(mask, ended, runs)
    np.testing.assert_array_equal(removed, [0, 2, 3])
    np.testing.assert_array_equal(keep, [1, 4])
    np.testing.assert_array_equal(remap, [-1, 0, -1, -1, 1])
    np.testing.assert_array_equal(counted, [2])  # slot 0 ended, slot 3 has no run
    np.testing.assert_array_equal(kernels.plan_removal(mask, np.zeros(0, dtype=bool), runs)[3], [0, 2])
