"""The compiled kernels of the EKF step (``backend.estimator.covariance``, ``.tracks``, ``.update``,
``.invariant``) against dense textbook formulas and readable numpy references."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vislam.backend import compiled
from vislam.backend.estimator import covariance, invariant, tracks, update
from vislam.backend.estimator.layout import CORE
from vislam.backend.estimator.state import FilterState
from vislam.backend.estimator.state_helper import NewLandmarks, StateHelper
from vislam.backend.geometry import se3
from test_se3 import _exp_se3_and_left_jacobian_jit, _right_jacobian_se3_jit

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


# ----------------------------------------------------------------------------------------------
# readable references (Barfoot, "State Estimation for Robotics", ch. 7): power series and block
# formulas, independent of the closed forms and Taylor switches of ``backend.geometry.se3``


def _hat(w: np.ndarray) -> np.ndarray:
    """w^ with w^ v = w x v."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _hat_se3(xi: np.ndarray) -> np.ndarray:
    """xi^ = [[phi^, rho], [0, 0]] of xi = [rho, phi]."""
    out = np.zeros((4, 4))
    out[:3, :3] = _hat(xi[3:])
    out[:3, 3] = xi[:3]
    return out


def _curly_hat(xi: np.ndarray) -> np.ndarray:
    """xi^curly = [[phi^, rho^], [0, phi^]], the adjoint action of the Lie algebra."""
    out = np.zeros((6, 6))
    out[:3, :3] = out[3:, 3:] = _hat(xi[3:])
    out[:3, 3:] = _hat(xi[:3])
    return out


def _series(A: np.ndarray, shift: int) -> np.ndarray:
    """sum_n A^n / (n + shift)! over 80 terms: exp (shift 0) or J_l (shift 1)."""
    out = np.zeros_like(A)
    term = np.eye(A.shape[0])
    for n in range(80):
        out = out + term / math.factorial(n + shift)
        term = term @ A
    return out


def _exp_se3(xi: np.ndarray) -> np.ndarray:
    """exp(xi^) as the power series of the matrix exponential."""
    return _series(_hat_se3(xi), 0)


def _left_jacobian_so3(phi: np.ndarray) -> np.ndarray:
    """J_l(phi) = sum (phi^)^n / (n+1)!."""
    return _series(_hat(phi), 1)


def _right_jacobian_se3(xi: np.ndarray) -> np.ndarray:
    """J_r(xi) = J_l(-xi) = sum (-xi^curly)^n / (n+1)!."""
    return _series(-_curly_hat(xi), 1)


def _adjoint(T: np.ndarray) -> np.ndarray:
    """Ad(T) = [[R, p^ R], [0, R]] (eq. 7.48)."""
    A = np.zeros((6, 6))
    A[:3, :3] = A[3:, 3:] = T[:3, :3]
    A[:3, 3:] = _hat(T[:3, 3]) @ T[:3, :3]
    return A


def _noise_jacobian_pose(world_T_imu_next: np.ndarray, twist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pose part of G J_r(twist) in (I2) of ``backend.estimator.invariant``: the pose rows
    Ad(mu_next) J_r(twist) (6,6), and R_phi = R_next J_r[3:6] (3,6), the world-frame rotation error
    per unit twist error."""
    J = _right_jacobian_se3(twist)
    return _adjoint(world_T_imu_next) @ J, world_T_imu_next[:3, :3] @ J[3:6]


def _noise_jacobian(world_T_imu_next: np.ndarray, twist: np.ndarray, points: np.ndarray):
    """G J_r(twist) of (I2): pose rows (6,6) and landmark rows m_i^ R_phi (K,3,6)."""
    pose, R_phi = _noise_jacobian_pose(world_T_imu_next, twist)
    return pose, np.array([_hat(m) @ R_phi for m in points]).reshape(-1, 3, 6)


def _dense_invariant_prediction(P, mu, twist, points, dt, q, walk, core=CORE, bias=True, lever_row=None):
    """(I2) built densely: F P F^T + G Q G^T with G = [G_pose; m_i^ R_phi] (the landmark rows after
    ``core``), F = I + G E_b e_b^T where ``bias`` (E_b = -tau [0; I]) and + G E_r e_r^T on the lever
    arm's rows from ``lever_row`` (V1 of ``backend.estimator.lever_arm``), the bias walk on its rows."""
    from vislam.backend.estimator.lever_arm import twist_columns

    D = P.shape[0]
    G_pose, G_lm = _noise_jacobian(mu, twist, points)
    G = np.zeros((D, 6))
    G[:6] = G_pose
    G[core:] = G_lm.reshape(-1, 6)
    F = np.eye(D)
    if bias:
        F[:, 6:9] += -dt * G[:, 3:6]
    if lever_row is not None:
        F[:, lever_row:lever_row + 3] += G @ twist_columns(twist)
    expected = F @ P @ F.T + G @ np.diag(q**2) @ G.T
    if bias:
        expected[6:9, 6:9] += walk * np.eye(3)
    return expected


def _retract(world_T_imu: np.ndarray, points: np.ndarray, d_pose: np.ndarray, d_points: np.ndarray):
    """(I5) exp(dx) X_hat: pose exp(d_pose^) world_T_imu, landmarks m <- R_d m + J_l(phi) zeta."""
    E = _exp_se3(d_pose)
    J = _left_jacobian_so3(d_pose[3:])
    return E @ world_T_imu, points @ E[:3, :3].T + d_points.reshape(-1, 3) @ J.T


@pytest.mark.parametrize("bias", [True, False])
def test_predict_invariant_equals_dense_propagation(bias):
    """(I2): P <- F P F^T + G Q G^T with F = I + g e_b^T, G = [G_pose; m_i^ R_phi] diag(q)."""
    rng = np.random.default_rng(1)
    K = 7
    D = CORE + 3 * K
    P, mu, twist, points, dt, q, walk = _prediction_problem(rng, K)
    assert P.shape == (D, D)
    expected = _dense_invariant_prediction(P, mu, twist, points, dt, q, walk, bias=bias)
    pose, R_phi = _noise_jacobian_pose(mu, twist)
    out = P.copy()
    invariant.predict_covariance_inplace(out, pose, R_phi, points, q, dt, bias, walk, -1, np.zeros(3))
    np.testing.assert_allclose(out, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
    assert np.array_equal(out, out.T)


@pytest.mark.parametrize("angle", [0.0, 1e-7, 0.05, 0.3, 2.5])
def test_compiled_se3_matches_backend_se3(angle):
    """``backend.geometry.se3``'s exp (with its J_l) and J_r compiled, as the kernels call them, equal
    the same functions run by Python, on both sides of the Taylor switch; and both equal the power
    series."""
    rng = np.random.default_rng(2)
    axis = rng.normal(size=3)
    xi = np.concatenate([rng.normal(size=3), angle * axis / np.linalg.norm(axis)])
    T, J_l = _exp_se3_and_left_jacobian_jit(xi)
    J_r = _right_jacobian_se3_jit(xi)
    np.testing.assert_allclose(T, se3.exp_se3(xi), rtol=0, atol=1e-14)
    np.testing.assert_allclose(J_l, se3.left_jacobian_so3(xi[3:]), rtol=0, atol=1e-14)
    np.testing.assert_allclose(J_r, se3.right_jacobian_se3(xi), rtol=0, atol=1e-13)
    np.testing.assert_allclose(T, _exp_se3(xi), rtol=0, atol=1e-13)
    np.testing.assert_allclose(J_l, _left_jacobian_so3(xi[3:]), rtol=0, atol=1e-13)
    np.testing.assert_allclose(J_r, _right_jacobian_se3(xi), rtol=0, atol=1e-13)


def test_predict_step_is_mean_propagation_then_invariant_covariance():
    """One prediction = the compiled mean mu exp(tau u^) with the noise Jacobian Ad(mu_next) J_r(twist)
    at the propagated pose, then StateHelper.propagate: (I2) and the landmark walk on the landmark
    diagonal."""
    rng = np.random.default_rng(3)
    K = 5
    D = CORE + 3 * K
    P, mu, twist, points, dt, q, walk = _prediction_problem(rng, K)
    lm_walk = 2e-4
    mu_next = mu @ _exp_se3(twist)
    expected = P.copy()
    invariant.predict_covariance_inplace(expected, *_noise_jacobian_pose(mu_next, twist), points, q, dt, True, walk, -1,
                                         np.zeros(3))
    expected[np.arange(CORE, D), np.arange(CORE, D)] += lm_walk
    pose, G_pose = invariant.predict_step(mu, twist)
    np.testing.assert_allclose(pose, mu_next, rtol=0, atol=1e-13)
    np.testing.assert_allclose(G_pose, _noise_jacobian_pose(mu_next, twist)[0], rtol=0, atol=1e-12)
    state = FilterState(mu=pose)
    state.append_landmarks(np.arange(K), points, np.ones(K, dtype=np.int64), np.full(K, 10))
    state.P = P.copy()
    StateHelper.propagate(state, invariant.InvariantTransition(G_pose, points, q, dt, True, walk), lm_walk)
    np.testing.assert_allclose(state.P, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
    assert np.array_equal(state.P, state.P.T)


def test_retract_invariant_equals_the_group_update():
    """(I5) compiled: the pose and the world points after exp(dx) X_hat, i.e. pose exp(d_pose^) mu
    and m <- R_d m + J_l(phi) zeta."""
    rng = np.random.default_rng(4)
    K = 6
    mu = se3.exp_se3(rng.normal(size=6))
    points = rng.normal(size=(K, 3)) * 10.0
    dx = rng.normal(size=CORE + 3 * K) * 0.05
    pose_expected, points_expected = _retract(mu, points, dx[:6], dx[CORE:])
    moved = points.copy()
    pose = invariant.retract_inplace(mu, moved, dx)
    np.testing.assert_allclose(pose, pose_expected, rtol=0, atol=1e-13)
    np.testing.assert_allclose(moved, points_expected, rtol=0, atol=1e-12)


def test_innovation_covariance_equals_dense_products():
    rng = np.random.default_rng(2)
    P, slots, H_x, H_m = _problem(rng)
    residual = rng.normal(size=(slots.size, 3))
    off_row = rng.normal(size=slots.size)
    HP, S, nis = update.innovation_covariance(P, H_x, H_m, slots, SIGMA2, residual, off_row)
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
    """The fused call = ``invariant.observe`` from cam_T_imu world_T_imu^-1, then
    ``update.innovation_covariance``."""
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
    expected = list(invariant.observe(theta[slots], cam_T_imu @ se3.inverse(mu), *cam, pixels))
    if not pose:
        expected[2][:] = 0.0
    residual, off_row, H_x, H_m, in_front = expected
    HP, S, nis = update.innovation_covariance(P, H_x, H_m, slots, SIGMA2, residual, off_row)
    out = invariant.innovation(P, theta, slots, mu, cam_T_imu, *cam, pixels, SIGMA2, pose)
    assert not out[-1][0] and out[-1][1:].all()  # slot 8 is behind the camera
    for got, want in zip(out, (residual, off_row, H_x, H_m, HP, S, nis, in_front)):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)


def test_gather_and_augment_are_the_block_formulas():
    rng = np.random.default_rng(3)
    D = CORE + 3 * 10
    P = _spd(rng, D)
    keep = np.sort(rng.choice(D, 20, replace=False))
    G = covariance.gather_symmetric(P, keep)
    assert G.flags.c_contiguous
    np.testing.assert_array_equal(G, P[np.ix_(keep, keep)])

    n = 4
    J_xi = rng.normal(size=(3 * n, 6))
    J_z = rng.normal(size=(n, 3, 4))
    out = covariance.augment(P, J_xi, J_z, SIGMA2)
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
    np.testing.assert_array_equal(covariance.gather_landmarks(P, keep), P[np.ix_(cols, cols)])


@pytest.mark.parametrize("pose", [True, False])
def test_initialize_invariant_is_triangulation_then_augmentation(pose):
    """One compiled call = ``backend.estimator.landmarks.initialize`` (xyz, unscented mean) and (I4)
    J_xi = [I 0] (zero with poses held fixed); StateHelper.augment then adds them by (A1)."""
    from vislam.backend.geometry.camera import StereoCamera
    from vislam.backend.estimator.landmarks import initialize

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
    expected = covariance.augment(P, J_xi, np.ascontiguousarray(J_z), SIGMA2)
    points, J_xi_out, J_z_out = invariant.initialize(pixels, mu @ imu_T_cam, camera.fx, camera.fy, camera.cx,
                                                     camera.cy, camera.baseline, 1.3, pose)
    np.testing.assert_allclose(points, theta, rtol=0, atol=1e-11)
    np.testing.assert_array_equal(J_xi_out, J_xi)
    np.testing.assert_allclose(J_z_out, J_z, rtol=1e-12, atol=1e-12 * np.abs(J_z).max())
    state = FilterState()  # two landmarks in the state already
    state.append_landmarks(np.arange(2), rng.normal(size=(2, 3)), np.ones(2, dtype=np.int64), np.full(2, 10))
    state.P = P.copy()
    StateHelper.augment(state, np.arange(2, 7), NewLandmarks(points, None, J_xi_out, J_z_out), SIGMA2,
                        np.ones(5, dtype=np.int64), np.full(5, 10))
    np.testing.assert_allclose(state.P, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
    assert np.array_equal(state.P, state.P.T) and state.num_landmarks == 7


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
    HP, S, _ = update.innovation_covariance(P, H_x, H_m, slots, SIGMA2, residual, off_row)
    threshold = 1.0
    candidates = np.ones(slots.size, dtype=bool)
    inliers = update.one_point_ransac(S, residual, off_row, candidates, SIGMA2, threshold)

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
    _, S, _ = update.innovation_covariance(P, H_x, H_m, slots, SIGMA2, residual, off_row)
    inlier = np.array([1, 1, 0, 1, 1, 0, 1, 0], dtype=bool)
    ri = (3 * np.flatnonzero(inlier)[:, None] + np.arange(3)).ravel()
    rr = (3 * np.flatnonzero(~inlier)[:, None] + np.arange(3)).ravel()
    L = np.linalg.cholesky(S[np.ix_(ri, ri)])
    w = np.linalg.solve(L, residual[inlier].ravel())
    X = np.linalg.solve(L, S[np.ix_(rr, ri)].T)
    gate = 9.0
    ok = update._rescue_test(X, w, S, rr, residual, off_row, SIGMA2, gate)

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
    HP, S, _ = update.innovation_covariance(P, H_x, H_m, slots, SIGMA2, residual, off_row)
    inlier = np.array([1, 1, 0, 1, 1, 0, 1, 0], dtype=bool)
    rest = ~inlier
    rest[2] = False  # not a candidate (gated before): neither used nor tested
    out = P.copy()
    status, dx, used = update.joint_update_inplace(out, HP, S, residual, off_row, inlier, rest, SIGMA2, 9.0)
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
    HP, S, nis = update.innovation_covariance(P, H_x, H_m, slots, SIGMA2, residual, off_row)
    in_front = np.ones(slots.size, dtype=bool)
    in_front[6] = False
    gate = 13.28
    runs0 = rng.integers(0, 3, 12)
    gated0 = rng.integers(0, 3, 12)
    # the separate kernels
    use = in_front & (nis <= gate)
    inlier = update.one_point_ransac(S, residual, off_row, use, SIGMA2, 2.0)
    rest = use & ~inlier
    runs = runs0.copy()
    if persistent:
        rest &= ~update.count_rejections_inplace(runs, slots, rest, persistent)
    expected_P = P.copy()
    _, expected_dx, expected_used = update.joint_update_inplace(expected_P, HP, S, residual, off_row, inlier, rest,
                                                                SIGMA2, gate)
    expected_gated = gated0.copy()
    expected_gated[slots] = np.where(expected_used, 0, gated0[slots] + 1)
    # fused
    out_P, out_runs, out_gated = P.copy(), runs0.copy(), gated0.copy()
    status, dx, used = update.select_and_update_inplace(out_P, HP, S, residual, off_row, nis, in_front, slots, gate,
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
    HP, S, _ = update.innovation_covariance(P, H_x, H_m, slots, SIGMA2, residual, off_row)
    S[3, 3] = -1.0
    out = P.copy()
    status, dx, used = update.joint_update_inplace(out, HP, S, residual, off_row, np.ones(4, dtype=bool),
                                                   np.zeros(4, dtype=bool), SIGMA2, 9.0)
    assert status > 0 and not used.any() and not dx.any()
    assert np.array_equal(out, P)  # the prior is kept


def test_block_rows_are_numpys_rows_of_the_masked_observations():
    """``update._block_rows``: the rows 3 i .. 3 i + 2 of each observation i where the mask holds, as
    numpy's flatnonzero gives them, for random masks (none, all, and in between)."""
    rng = np.random.default_rng(11)
    for k in [0, 1, 2, 5, 17, 64]:
        for p in [0.0, 0.3, 0.7, 1.0]:
            mask = rng.random(k) < p
            expected = (3 * np.flatnonzero(mask)[:, None] + np.arange(3)).ravel()
            rows = update._block_rows(mask)
            assert rows.dtype == np.int64
            np.testing.assert_array_equal(rows, expected)


def test_mirror_lower_copies_the_lower_triangle():
    rng = np.random.default_rng(6)
    A = rng.normal(size=(7, 7))
    B = A.copy()
    covariance.mirror_lower_inplace(B)
    np.testing.assert_array_equal(np.tril(B), np.tril(A))
    assert np.array_equal(B, B.T)


_NO_LAZY_COMPILE = r"""
import json, sys, warnings
sys.path.insert(0, "tests")
warnings.simplefilter("ignore")
from vislam.backend import compiled
from vislam.backend.config import Config
from vislam.backend.estimator import covariance, invariant, linalg, tracks, update
from vislam.backend.geometry import camera
from vislam.backend.run import conventions, runner, timing
from vislam.backend.run.runner import run_sequence
from test_ekf import make_drive, to_sequence

def counts():
    out = {}
    for module in (covariance, tracks, update, invariant, linalg):
        for n, f in vars(module).items():
            if hasattr(f, "signatures") and n[0] != "_" and f.py_func.__module__ == module.__name__:
                out[module.__name__.rsplit(".", 1)[1] + "." + n] = len(f.signatures)
    out["camera.triangulate_rows"] = len(camera.triangulate_rows.signatures)
    out["conventions._left_errors"] = len(conventions._left_errors.signatures)
    out["timing._repeats_sorted"] = len(timing._repeats_sorted.signatures)
    return out

at_setup = []  # what is compiled, and which warm-ups ran, when the first convention test starts
decide = runner.decide
def spy(seq, config):
    at_setup.append((counts(), len(compiled._registered), len(compiled._done & set(compiled._registered))))
    return decide(seq, config)
runner.decide = spy
runs = [run_sequence(to_sequence(make_drive(40, seed=1)), config)
        for config in (Config(), Config.from_values({"estimator.mode": "mapping"}),
                       Config.from_values({"estimator.error_model": "body"}))]
reported = [r.stats.kernel_seconds == compiled.warm_up_seconds() > 0 for r in runs]
before, registered, done = at_setup[0]
inertial_only = [f for f in compiled._registered if compiled._only.get(f) in ("inertial", "window")]
print(json.dumps([before, counts(), reported, registered, done, len(at_setup), len(inertial_only),
                  any(f in compiled._done for f in inertial_only)]))
"""


def test_warm_up_compiles_what_the_filter_calls():
    """Every kernel signature a run needs is compiled (or loaded) by ``compiled.warm_up`` before the
    run's convention test, so neither the setup nor a step pays for it, and a velocity run warms up
    none of the kernels registered for a real IMU's runs only; a kernel that only other kernels call
    is not loaded on its own (it is compiled into their caches); in a fresh process, as other
    tests call kernels too. The kernels are the jitted functions of ``backend.estimator.covariance``,
    ``.tracks``, ``.update``, ``.invariant`` and ``.linalg``, ``geometry.camera.triangulate_rows``,
    ``run.conventions._left_errors`` and ``run.timing._repeats_sorted``."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", _NO_LAZY_COMPILE], cwd=root, capture_output=True, text=True,
                         check=False)
    assert out.returncode == 0, out.stderr
    before, after, reported, registered, done, decisions, inertial_only, inertial_done = json.loads(
        out.stdout.strip().splitlines()[-1])
    assert decisions == 3  # each run decided its conventions
    assert inertial_only >= 1 and not inertial_done  # a velocity run compiles no kernel only a real IMU's run calls
    assert registered >= 8 and done == registered - inertial_only  # every other module's warm-up ran
    for module in ("covariance", "tracks", "update", "invariant"):
        assert any(name.startswith(module + ".") and n >= 1 for name, n in before.items())
    # linalg's kernels run inside the others only (compiled into their caches): not loaded on their own
    assert any(name.startswith("linalg.") for name in before)
    assert not any(n for name, n in before.items() if name.startswith("linalg."))
    assert sum(n >= 1 for n in before.values()) >= 9  # loaded before the convention test
    assert after == before  # and nothing more by the runs: none compiled or loaded a kernel mid-way
    assert reported == [True, True, True]  # each run reports the process's warm-up, apart from its timing


_NO_LAZY_COMPILE_INERTIAL = r"""
import json, warnings
warnings.simplefilter("ignore")
from vislam.backend import compiled
from vislam.backend.estimator import covariance, inertial, invariant, linalg, tracks, update
from vislam.backend.run.inertial import run_inertial
from vislam.synth.inertial_scene import InertialSceneConfig, make_inertial_scene

def counts():
    return {m.__name__ + "." + n: len(f.signatures) for m in (covariance, inertial, invariant, linalg, tracks, update)
            for n, f in vars(m).items() if hasattr(f, "signatures") and f.py_func.__module__ == m.__name__}

compiled.warm_up(inertial=True)
before = counts()
run_inertial(make_inertial_scene(InertialSceneConfig(duration=6.0)).sequence)
after = counts()
print(json.dumps([before, after]))
"""


def test_warm_up_compiles_what_an_inertial_run_calls():
    """A real IMU's run finds every kernel signature it calls compiled (or loaded) by
    ``compiled.warm_up(inertial=True)``: none is compiled in the middle of the run (in a fresh process)."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    out = subprocess.run([sys.executable, "-c", _NO_LAZY_COMPILE_INERTIAL], cwd=Path(__file__).resolve().parents[1],
                         capture_output=True, text=True, check=False)
    assert out.returncode == 0, out.stderr
    before, after = json.loads(out.stdout.strip().splitlines()[-1])
    assert before["vislam.backend.estimator.inertial.integrate_kernel"] >= 1
    assert after == before, {k: (before.get(k), v) for k, v in after.items() if before.get(k) != v}


_WINDOW_KERNELS = r"""
import json, warnings
warnings.simplefilter("ignore")
from vislam.backend import compiled
from vislam.backend.config import Config
from vislam.backend.estimator import window
from vislam.backend.run.inertial import run_inertial
from vislam.synth.inertial_scene import InertialSceneConfig, make_inertial_scene

def counts():
    return {n: len(f.signatures) for n, f in vars(window).items()
            if hasattr(f, "signatures") and f.py_func.__module__ == window.__name__}

windowed = [f for f in compiled._registered if compiled._only.get(f) == "window"]
compiled.warm_up(inertial=True)
landmarks_only = any(f in compiled._done for f in windowed)
compiled.warm_up(inertial=True, window=True)
before = counts()
run_inertial(make_inertial_scene(InertialSceneConfig(duration=4.0)).sequence, Config().with_assignments(["estimator.window=13"]))
print(json.dumps([len(windowed), landmarks_only, all(f in compiled._done for f in windowed), before, counts()]))
"""


def test_the_window_kernels_are_warmed_up_for_a_window_run_only():
    """A real IMU's run with landmarks does not compile the sliding window's kernels (registered
    ``only="window"``); a window run's warm-up does, and the run then compiles none mid-way (in a
    fresh process)."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    out = subprocess.run([sys.executable, "-c", _WINDOW_KERNELS], cwd=Path(__file__).resolve().parents[1],
                         capture_output=True, text=True, check=False)
    assert out.returncode == 0, out.stderr
    registered, landmarks_only, warmed, before, after = json.loads(out.stdout.strip().splitlines()[-1])
    assert registered >= 1 and not landmarks_only and warmed
    assert before["_feature_terms"] >= 1
    assert after == before, {k: (before.get(k), v) for k, v in after.items() if before.get(k) != v}


_WINDOW_RUN_ALONE = r"""
import json, sys, warnings
warnings.simplefilter("ignore")
from vislam.backend import compiled
from vislam.backend.config import Config
from vislam.backend.run.inertial import run_inertial
from vislam.synth.inertial_scene import InertialSceneConfig, make_inertial_scene

def counts():
    return {f"{m}.{n}": len(f.signatures) for m, mod in list(sys.modules.items()) if m.startswith("vislam.")
            for n, f in vars(mod).items() if hasattr(f, "signatures") and getattr(f, "py_func", None) is not None
            and f.py_func.__module__ == m}

compiled.warm_up(inertial=True, window=True)
kinds = sorted({compiled._only.get(f, "every run") for f in compiled._done})
skipped = sorted({compiled._only[f] for f in compiled._registered if f not in compiled._done})
before = counts()
res = run_inertial(make_inertial_scene(InertialSceneConfig(duration=4.0)).sequence, Config())
print(json.dumps([kinds, skipped, before, counts(), res.stats.filter_seconds > 0]))
"""


def test_a_window_run_compiles_only_what_it_uses():
    """A real IMU's run with the default window warms up the kernels of every run, a real IMU's and the
    window's, not the landmark filter's or the velocity runs' (about 17 s of compiling after an
    install), and the run then calls no kernel it did not warm up (in a fresh process)."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    out = subprocess.run([sys.executable, "-c", _WINDOW_RUN_ALONE], cwd=Path(__file__).resolve().parents[1],
                         capture_output=True, text=True, check=False)
    assert out.returncode == 0, out.stderr
    kinds, skipped, before, after, ran = json.loads(out.stdout.strip().splitlines()[-1])
    assert ran and kinds == ["every run", "inertial", "window"] and skipped == ["landmarks", "velocity"]
    assert not any(k.startswith("vislam.backend.estimator.update.") and v for k, v in before.items())
    assert after == before, {k: (before.get(k), v) for k, v in after.items() if before.get(k) != v}


def test_warm_up_says_so_when_it_takes_a_while(monkeypatch):
    """``compiled.warm_up(notice)`` calls ``notice`` when warming up outlasts ``NOTICE_AFTER``; it
    runs each registered warm-up once per process."""
    import threading

    called = threading.Event()

    def slow():
        called.wait(5.0)  # busy until the notice came

    monkeypatch.setattr(compiled, "_registered", [slow])
    monkeypatch.setattr(compiled, "_done", set())
    monkeypatch.setattr(compiled, "_seconds", compiled._seconds)  # restored afterwards
    monkeypatch.setattr(compiled, "NOTICE_AFTER", 0.0)
    assert compiled.warm_up(notice=called.set) > 0.0 and called.is_set()
    assert compiled._done == {slow}
    assert compiled.warm_up(notice=called.set) == 0.0  # once per process


def test_run_says_compiling_when_warm_up_takes_a_while(monkeypatch):
    """A run passes its ``say`` to the warm-up: a slow warm-up says ``runner.COMPILING``, once."""
    import threading

    from vislam.backend.run import runner
    from vislam.synth.scene import SceneConfig, make_scene

    said = threading.Event()
    messages = []

    def say(text):
        messages.append(text)
        if text == runner.COMPILING:
            said.set()

    def slow():
        said.wait(5.0)

    compiled.warm_up()  # the real kernels: loaded before the registry is replaced
    monkeypatch.setattr(compiled, "_registered", [slow])
    monkeypatch.setattr(compiled, "_done", set())
    monkeypatch.setattr(compiled, "_seconds", compiled._seconds)
    monkeypatch.setattr(compiled, "NOTICE_AFTER", 0.0)
    seq = make_scene(SceneConfig(steps=20, seed=1)).sequence
    runner.run_sequence(seq, say=say)
    assert said.is_set() and messages.count(runner.COMPILING) == 1
    assert compiled._done == {slow}


def test_plan_update_routes_observations_and_expires_landmarks():
    """Slots of the observed ids, unseen tracks leaving, and with re-anchoring the landmarks seen
    beyond their limit leaving too (their observations restart the track)."""
    state_ids = np.array([10, 3, 7])
    order = np.argsort(state_ids)
    ids = np.array([7, 10, 42])
    np.testing.assert_array_equal(tracks.slots_of(ids, state_ids[order], order), [2, 0, -1])
    counts, limits = np.array([1, 3, 2]), np.array([5, 3, 2])
    slots, leaving, ended, restart, expired = tracks.plan_update(ids, state_ids[order], order, counts, limits, True,
                                                                 False)
    np.testing.assert_array_equal(slots, [2, 0, -1])
    assert leaving.tolist() == [False, True, True]  # id 3 not seen; id 7 seen a third time, limit 2
    assert ended.tolist() == [False, True, False]
    assert restart.tolist() == [True, False, False] and expired == 1
    np.testing.assert_array_equal(counts, [2, 3, 3])
    counts = np.array([1, 3, 2])
    _, leaving, ended, restart, expired = tracks.plan_update(ids, state_ids[order], order, counts, limits, False,
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
    ok, counts, limits = tracks.admit_landmarks(ids, pixels, restart, 1.0, 100.0, 250.0, True, 6.0, 3, 25)
    np.testing.assert_array_equal(ok, [1, 2, 4])  # 0.5 px: too small; 2 px: 125 m > 100 m
    np.testing.assert_array_equal(limits, [25, 3, 3])
    np.testing.assert_array_equal(counts, [1 + 8 % 25, 1, 1 + 11 % 3])
    _, counts, _ = tracks.admit_landmarks(ids, pixels, restart, 1.0, np.inf, 350.0, False, 6.0, 3, 25)
    assert (counts == 1).all()  # no re-anchoring: no stagger


def test_plan_removal_index_arrays():
    mask = np.array([True, False, True, True, False])
    ended = np.array([True, False, False, False, False])
    runs = np.array([2, 0, 3, 0, 1])
    removed, keep, remap, counted = tracks.plan_removal(mask, ended, runs)
    np.testing.assert_array_equal(removed, [0, 2, 3])
    np.testing.assert_array_equal(keep, [1, 4])
    np.testing.assert_array_equal(remap, [-1, 0, -1, -1, 1])
    np.testing.assert_array_equal(counted, [2])  # slot 0 ended, slot 3 has no run
    np.testing.assert_array_equal(tracks.plan_removal(mask, np.zeros(0, dtype=bool), runs)[3], [0, 2])


def test_slots_of_and_plan_removal_match_numpy():
    """tracks.slots_of (a bisection) and plan_removal (counted index arrays) give what numpy's
    searchsorted and flatnonzero give, on random ids and masks, empty ones included."""
    rng = np.random.default_rng(7)
    for n, m in [(0, 0), (0, 4), (5, 0), (1, 3), (40, 25), (300, 200)]:
        ids_sorted = np.sort(rng.choice(1000, n, replace=False)).astype(np.int64)
        order = rng.permutation(n).astype(np.int64)
        ids = np.concatenate([rng.choice(ids_sorted, min(m, n)), rng.integers(-5, 1005, m)]).astype(np.int64)
        pos = np.minimum(np.searchsorted(ids_sorted, ids), max(n - 1, 0))
        found = (ids_sorted[pos] == ids) if n else np.zeros(ids.size, dtype=bool)
        expected = np.where(found, order[pos] if n else -1, -1)
        np.testing.assert_array_equal(tracks.slots_of(ids, ids_sorted, order), expected)

        mask = rng.random(n) < 0.3
        ended = rng.random(n) < 0.5
        run = rng.integers(0, 3, n).astype(np.int64)
        for ended_arg in (ended, np.zeros(0, dtype=np.bool_)):
            removed, keep, remap, counted = tracks.plan_removal(mask, ended_arg, run)
            np.testing.assert_array_equal(removed, np.flatnonzero(mask))
            np.testing.assert_array_equal(keep, np.flatnonzero(~mask))
            expected_remap = np.full(n, -1)
            expected_remap[~mask] = np.arange(keep.size)
            np.testing.assert_array_equal(remap, expected_remap)
            goes_on = ~ended_arg[removed] if ended_arg.size else np.ones(removed.size, dtype=bool)
            np.testing.assert_array_equal(counted, removed[(run[removed] > 0) & goes_on])
