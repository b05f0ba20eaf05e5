"""The right-invariant error model (backend.estimator.invariant, estimator.error_model = "invariant"):
every Jacobian against finite differences of the error definition (I1), the compiled prediction and
correction against readable reference implementations of (I2) and (I5), and the structural property
the model exists for.

Error of an estimate (mu, m_hat) against a truth (T, m):  E = X X_hat^-1, i.e.
(rho, phi) = log(T mu^-1) and zeta = J_l(phi)^-1 (m - exp(phi^) m_hat).
"""

from __future__ import annotations

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from vislam.backend.config import Config
from vislam.backend.estimator import invariant
from vislam.backend.estimator.body import BodyModel
from vislam.backend.estimator.ekf import ImuNoise, VisualInertialEKF
from vislam.backend.estimator.invariant import InvariantModel
from vislam.backend.estimator.layout import BIAS, CORE, POSE
from vislam.backend.estimator.state import FilterState
from vislam.backend.geometry import se3
from helpers import THREE_ROWS, numeric_jacobian, observation_model, slots_of
from test_ekf import CAMERA, IMU_T_CAM, NOISE, bare_config, homogeneous, random_pose, random_spd, rel_err

CONFIG = bare_config({"estimator.error_model": "invariant", "landmarks.parametrization": "xyz",
                      "drift.landmark_random_walk": 0.05})  # a constant walk: test_prediction_without_noise_is_the_identity


@pytest.fixture(autouse=True)
def _single_blas_thread():
    with threadpool_limits(limits=1):
        yield


def pose_error(T: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """(rho, phi) of T = exp(xi^) mu."""
    return se3.log_se3(T @ se3.inverse(mu))


def landmark_error(m: np.ndarray, m_hat: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """zeta of (I1): m = exp(phi^) m_hat + J_l(phi) zeta."""
    R, J_l = se3.exp_so3_and_left_jacobian(phi)
    return np.linalg.solve(J_l, m - R @ m_hat)


# ---------------------------------------------------------------- reference implementations
def noise_jacobian(world_T_imu_next: np.ndarray, twist: np.ndarray, points: np.ndarray):
    """G J_r(twist) of (I2): how a body-twist error d (6,) moves the error state,
    xi_{k+1} = xi_k + [pose rows; landmark rows] @ d.

    Pose rows G_pose = Ad(mu_next) J_r(twist) (6,6); with R_phi = R_next J_r[3:6], the world-frame
    rotation error per unit twist error, landmark i's rows are m_i^ R_phi (3,6).
    Returns (G_pose (6,6), landmark rows (K,3,6)).
    """
    J = se3.right_jacobian_se3(twist)
    G_pose = se3.adjoint(world_T_imu_next) @ J
    R_phi = world_T_imu_next[:3, :3] @ J[3:6]
    G_lm = np.array([se3.hat3(m) @ R_phi for m in np.asarray(points, dtype=float)]).reshape(-1, 3, 6)
    return G_pose, G_lm


def retract(world_T_imu: np.ndarray, points: np.ndarray, d_pose: np.ndarray, d_points: np.ndarray):
    """(I5): exp(dx) X_hat for the pose (4,4) and the landmarks (K,3), as new copies:
    E = exp(d_pose^), pose = E mu, m <- R_d m + J_l(phi) zeta."""
    R_d, J_l = se3.exp_so3_and_left_jacobian(d_pose[3:])
    E = np.eye(4)  # exp(d_pose^) (Barfoot eq. 7.39) from the same R_d and J_l
    E[:3, :3] = R_d
    E[:3, 3] = J_l @ d_pose[:3]
    pts = np.asarray(points) @ R_d.T + np.asarray(d_points).reshape(-1, 3) @ J_l.T
    return E @ world_T_imu, pts


def _filter(mu0, bias=np.zeros(3), estimate_bias=True, noise=NOISE) -> VisualInertialEKF:
    config = CONFIG.with_values({"estimator.estimate_gyro_bias": estimate_bias})
    ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, config, noise, world_T_imu=mu0)
    ekf.state.gyro_bias = np.array(bias, dtype=float)
    return ekf


def test_config_refuses_invariant_with_inverse_depth():
    from vislam.backend.errors import ConfigError

    with pytest.raises(ConfigError, match="error_model"):
        Config.from_values({"estimator.error_model": "invariant", "landmarks.parametrization": "inverse-depth"})


def test_prediction_leaves_the_error_unchanged_and_adds_mapped_noise():
    """(I2): with no noise the error is autonomous (F = I); the noise enters through G."""
    rng = np.random.default_rng(1)
    mu0 = random_pose(rng)
    dt, v, w = 0.4, np.array([7.0, 0.4, -0.2]), np.array([0.3, -0.2, 0.8])
    twist = dt * np.concatenate([v, w])
    ekf = _filter(mu0, estimate_bias=False)
    P0 = random_spd(rng, 6, 1e-3)
    ekf.state.P[POSE, POSE] = P0
    ekf.predict(dt, v, w)
    mu1 = ekf.world_T_imu
    # exact, not only to first order: exp(x) mu0 step (mu0 step)^-1 = exp(x)
    x = rng.multivariate_normal(np.zeros(6), P0)
    np.testing.assert_allclose(pose_error(se3.exp_se3(x) @ mu0 @ se3.exp_se3(twist), mu1), x, atol=1e-10)

    J_fd = numeric_jacobian(lambda n: pose_error(mu0 @ se3.exp_se3(twist + n), mu1), np.zeros(6), 1e-7)
    G_pose, _ = noise_jacobian(mu1, twist, np.zeros((0, 3)))
    assert rel_err(G_pose, J_fd) < 1e-6
    Q = np.diag(np.concatenate([NOISE.linear_sigma**2, NOISE.angular_sigma**2]) * dt * dt)
    np.testing.assert_allclose(ekf.state.P[POSE, POSE], P0 + G_pose @ Q @ G_pose.T, rtol=1e-10, atol=1e-18)


def test_noise_moves_landmark_errors_with_the_rotation():
    """(I2) landmark rows: a static landmark's zeta changes by m_hat^ phi when the pose error turns by phi;
    the compiled prediction (invariant.predict_step) adds G Q G^T with exactly those rows."""
    rng = np.random.default_rng(2)
    mu0 = random_pose(rng)
    twist = 0.3 * np.array([6.0, 0.2, 0.1, 0.2, -0.4, 0.7])
    mu1 = mu0 @ se3.exp_se3(twist)
    points = rng.normal(0.0, 20.0, (3, 3))
    G_pose, G_lm = noise_jacobian(mu1, twist, points)
    for i, m in enumerate(points):  # truth = estimate for the landmark; only the pose noise n differs

        def zeta(n, m=m):
            phi = pose_error(mu0 @ se3.exp_se3(twist + n), mu1)[3:]
            return landmark_error(m, m, phi)

        assert rel_err(G_lm[i], numeric_jacobian(zeta, np.zeros(6), 1e-7)) < 1e-6

    # the compiled prediction from a zero covariance, no bias state: P = G diag(q^2) G^T
    dt, q = 0.3, np.array([0.2, 0.2, 0.2, 0.01, 0.02, 0.03]) * 0.3
    P = np.zeros((CORE + 3 * len(points), CORE + 3 * len(points)))
    mu_next, G_pose_next = invariant.predict_step(mu0, twist)
    np.testing.assert_allclose(mu_next, mu1, rtol=0, atol=1e-12)
    P = invariant.InvariantTransition(G_pose_next, points, q, dt, False, 0.0).apply(P)
    G = np.zeros((P.shape[0], 6))
    G[POSE] = G_pose
    G[CORE:] = G_lm.reshape(-1, 6)
    np.testing.assert_allclose(P, G @ np.diag(q * q) @ G.T, rtol=1e-10, atol=1e-18)
    assert np.all(P[BIAS] == 0.0) and np.abs(P[CORE:, CORE:]).max() > 0.0


def test_gyro_bias_jacobian_and_cross_covariance():
    rng = np.random.default_rng(3)
    mu0 = random_pose(rng)
    sigma_b, bias0 = 0.01, np.array([0.002, -0.004, 0.003])
    dt, v, w = 0.4, np.array([7.0, 0.3, -0.1]), np.array([0.2, -0.5, 0.9])
    ekf = _filter(mu0, bias0)
    ekf.state.P[:] = 0.0
    ekf.state.P[BIAS, BIAS] = sigma_b**2 * np.eye(3)
    ekf.predict(dt, v, w)
    mu1 = ekf.world_T_imu.copy()

    def error(delta):  # the true bias is bias0 + delta
        return pose_error(mu0 @ se3.exp_se3(dt * np.concatenate([v, w - bias0 - delta])), mu1)

    J_fd = numeric_jacobian(error, np.zeros(3), 1e-7)
    P = ekf.state.P
    assert rel_err(P[POSE, BIAS], J_fd * sigma_b**2) < 1e-5
    np.testing.assert_allclose(P[BIAS, POSE], P[POSE, BIAS].T, rtol=0, atol=0)


def _filter_with_landmarks(rng):
    mu0 = random_pose(rng)
    ekf = _filter(mu0)
    ekf.state.P[:CORE, :CORE] = random_spd(rng, CORE, 1e-4)
    p_cam = np.array([[2.0, -1.0, 15.0], [-6.0, 0.5, 8.0], [0.3, 1.2, 35.0], [9.0, -2.0, 22.0]])
    ids = np.array([3, 7, 8, 20])
    assert ekf.update(ids, CAMERA.project(p_cam)).initialized == 4
    ekf.predict(0.1, np.array([2.0, 0.1, 0.0]), np.array([0.02, -0.01, 0.05]))
    return ekf, ids, p_cam


def _pixels(T: np.ndarray, m: np.ndarray) -> np.ndarray:
    q = se3.inverse(IMU_T_CAM) @ se3.inverse(T) @ homogeneous(m)
    return CAMERA.Ks @ (q / q[2])


def test_observation_jacobians_against_the_retraction():
    """(I3) against finite differences of z(exp(dx) X_hat) with the retraction (I1)/(I5)."""
    rng = np.random.default_rng(4)
    ekf, ids, _ = _filter_with_landmarks(rng)
    slots = slots_of(ekf, ids)
    z_meas = np.array([_pixels(ekf.world_T_imu, m) for m in ekf.state.theta[slots]]) + 2.0
    residual, _, H_xi, H_m, in_front = observation_model(ekf, slots, z_meas)
    assert in_front.all()
    for k, slot in enumerate(slots):
        others = np.zeros((ekf.num_active, 3))

        def z_of(d_pose, d_lm, slot=slot):
            pts = others.copy()
            pts[slot] = d_lm
            T, m = retract(ekf.world_T_imu, ekf.state.theta, d_pose, pts)
            return _pixels(T, m[slot])

        np.testing.assert_allclose(residual[k], THREE_ROWS @ (z_meas[k] - z_of(np.zeros(6), np.zeros(3))), atol=1e-8)
        J_pose = numeric_jacobian(lambda d: z_of(d, np.zeros(3)), np.zeros(6), 1e-6)
        J_lm = numeric_jacobian(lambda d: z_of(np.zeros(6), d), np.zeros(3), 1e-6)
        assert rel_err(H_xi[k], THREE_ROWS @ J_pose) < 1e-5
        assert rel_err(H_m[k], THREE_ROWS @ J_lm) < 1e-5


def test_global_rotation_and_translation_are_unobservable_at_any_estimate():
    """The reason for the invariant error: moving the whole world (pose and landmarks) changes no
    prediction, and H says so exactly at every estimate: no rotation column, rho = -zeta."""
    rng = np.random.default_rng(5)
    ekf, ids, _ = _filter_with_landmarks(rng)
    for _ in range(3):  # several linearization points
        ekf.state.mu = random_pose(rng, angle=0.3, spread=2.0) @ ekf.state.mu
        slots = slots_of(ekf, ids)
        _, _, H_xi, H_m, _ = observation_model(ekf, slots, np.zeros((ids.size, 4)))
        assert np.all(H_xi[:, :, 3:6] == 0.0)
        np.testing.assert_allclose(H_xi[:, :, :3] + H_m, 0.0, atol=1e-12)
        assert np.abs(H_m).max() > 1.0


def test_initialization_and_map_covariance():
    """(I4) and (I6): the map covariance of a new landmark equals J P J^T + J_z R J_z^T of the world
    point m = exp(xi^) mu T_ic g(z), whatever the coordinates the state keeps it in."""
    rng = np.random.default_rng(6)
    mu0 = random_pose(rng)
    sigma_pix = 0.8
    config = CONFIG.with_values({"noise.pixel_sigma": sigma_pix,
                                 "landmarks.unbiased_triangulation": False})  # mean shift: test_camera
    ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, config, NOISE, world_T_imu=mu0)
    P_core = random_spd(rng, CORE, 1e-3)
    ekf.state.P[:] = P_core
    p_cam = np.array([[2.0, -1.0, 15.0], [-6.0, 0.5, 8.0], [0.3, 1.2, 35.0]])
    z = CAMERA.project(p_cam) + rng.normal(0.0, 0.5, (3, 4))
    ids = np.array([4, 10, 11])
    assert ekf.update(ids, z).initialized == 3

    def world(d, zi):
        return (se3.exp_se3(d) @ mu0 @ IMU_T_CAM @ homogeneous(CAMERA.triangulate(zi)))[:3]

    map_ids, map_pos, map_cov = ekf.landmark_map()
    np.testing.assert_array_equal(map_ids, ids)
    for i, zi in enumerate(z):
        J_xi = numeric_jacobian(lambda d: world(d, zi), np.zeros(6), 1e-6)
        J_z = numeric_jacobian(lambda zz: world(np.zeros(6), zz), zi, 1e-4)
        expected = J_xi @ P_core[POSE, POSE] @ J_xi.T + sigma_pix**2 * J_z @ J_z.T
        np.testing.assert_allclose(map_pos[i], world(np.zeros(6), zi), atol=1e-10)
        assert rel_err(map_cov[i], expected) < 1e-4
        # and the state's zeta: cross covariance with the pose and bias is that of rho (I4)
        cols = CORE + 3 * slots_of(ekf, ids[i : i + 1])[0] + np.arange(3)
        np.testing.assert_allclose(ekf.state.P[cols, :CORE], P_core[:3, :], rtol=1e-12, atol=1e-18)


def test_body_pose_covariance_is_the_adjoint_map():
    """(I7): mu^-1 exp(xi^) mu = exp((Ad(mu^-1) xi)^) exactly, so samples give the same covariance."""
    rng = np.random.default_rng(7)
    mu = random_pose(rng)
    P = random_spd(rng, 6, 1e-3)
    xi = rng.multivariate_normal(np.zeros(6), P, size=500)
    body = np.array([se3.log_se3(se3.inverse(mu) @ se3.exp_se3(x) @ mu) for x in xi])
    expected = invariant.body_pose_covariance(mu, xi.T @ xi / len(xi))
    np.testing.assert_allclose(body.T @ body / len(body), expected, rtol=0, atol=1e-10 * np.abs(expected).max())
    ekf = _filter(mu)
    ekf.state.P[POSE, POSE] = P
    np.testing.assert_allclose(ekf.pose_covariance, invariant.body_pose_covariance(mu, P), rtol=1e-14, atol=0)
    # N poses at once: each the one pose's
    mus = np.array([mu, random_pose(rng), random_pose(rng)])
    Ps = np.array([P, random_spd(rng, 6, 1e-3), random_spd(rng, 6, 1e-2)])
    batch = invariant.body_pose_covariance(mus, Ps)
    for k in range(3):
        A = se3.adjoint(se3.inverse(mus[k]))
        np.testing.assert_allclose(batch[k], A @ Ps[k] @ A.T, rtol=1e-12, atol=1e-18)


def test_correction_is_the_group_exponential():
    """(I5): retract with (rho, phi, zeta) gives back exactly that error, by the definition (I1), both the
    reference and the compiled correction (invariant.retract_inplace, which skips the bias rows of dx)."""
    rng = np.random.default_rng(8)
    mu = random_pose(rng)
    points = rng.normal(0.0, 10.0, (4, 3))
    d_pose = np.concatenate([rng.normal(0, 0.5, 3), rng.normal(0, 0.3, 3)])
    d_pts = rng.normal(0.0, 0.5, (4, 3))
    T, m = retract(mu, points, d_pose, d_pts)
    np.testing.assert_allclose(pose_error(T, mu), d_pose, atol=1e-10)
    for i in range(4):
        np.testing.assert_allclose(landmark_error(m[i], points[i], d_pose[3:]), d_pts[i], atol=1e-10)

    dx = np.concatenate([d_pose, rng.normal(0.0, 0.1, 3), d_pts.ravel()])  # [rho, phi, bias, zeta_1 .. zeta_4]
    m_compiled = points.copy()
    T_compiled = invariant.retract_inplace(mu, m_compiled, dx)
    np.testing.assert_allclose(pose_error(T_compiled, mu), d_pose, atol=1e-10)
    for i in range(4):
        np.testing.assert_allclose(landmark_error(m_compiled[i], points[i], d_pose[3:]), d_pts[i], atol=1e-10)
    np.testing.assert_allclose(T_compiled, T, rtol=0, atol=1e-12)
    np.testing.assert_allclose(m_compiled, m, rtol=0, atol=1e-12)


def test_prediction_keeps_covariance_symmetric_with_landmarks():
    rng = np.random.default_rng(9)
    ekf, _, _ = _filter_with_landmarks(rng)
    for _ in range(20):
        ekf.predict(0.1, np.array([8.0, 0.1, 0.0]), np.array([0.01, 0.02, 0.3]))
        assert np.array_equal(ekf.state.P, ekf.state.P.T)
    assert np.linalg.eigvalsh(ekf.state.P).min() > 0.0


def test_prediction_without_noise_is_the_identity():
    """No velocity noise and no bias uncertainty: F = I, so only the random walks of the bias and
    of the landmarks are added."""
    rng = np.random.default_rng(10)
    tiny = ImuNoise(np.zeros(3), np.zeros(3))
    ekf, _, _ = _filter_with_landmarks(rng)
    ekf.imu_noise = tiny
    ekf.state.P[BIAS, :] = 0.0
    ekf.state.P[:, BIAS] = 0.0
    before = ekf.state.P.copy()
    ekf.predict(0.1, np.array([8.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.2]))
    before[np.arange(6, 9), np.arange(6, 9)] += CONFIG.noise.gyro_bias_random_walk**2 * 0.1
    landmarks = np.arange(CORE, before.shape[0])
    assert landmarks.size and CONFIG.drift.landmark_random_walk > 0
    before[landmarks, landmarks] += CONFIG.drift.landmark_random_walk**2 * 0.1
    np.testing.assert_allclose(ekf.state.P, before, rtol=0, atol=1e-20)


def test_error_models_agree_on_world_landmarks_and_pose_covariance():
    """For the same mean and P, InvariantModel and BodyModel report the same world positions of xyz
    landmarks (the parameters); the covariances are each model's: the invariant one that of
    dm = zeta - m_hat^ phi (I6, against finite differences of (I1)), the body one P's 3x3 blocks.
    Both pose_covariance are the right-perturbation covariance: P_pose for the body model,
    Ad(mu^-1) P_pose Ad(mu^-1)^T for the invariant one (I7, against finite differences of
    log(mu^-1 exp(x^) mu))."""
    rng = np.random.default_rng(11)
    mu = random_pose(rng)
    n = 4
    theta = rng.normal(0.0, 10.0, (n, 3))
    P = random_spd(rng, CORE + 3 * n, 1e-2)
    state = FilterState(mu=mu)
    state.append_landmarks(np.array([8, 2, 5, 11]), theta, np.ones(n, dtype=np.int64), np.full(n, 10))
    state.P = P  # a given covariance over the pose, bias and the 4 landmarks
    inv = InvariantModel(CAMERA, IMU_T_CAM, "xyz", True, True)
    body = BodyModel(CAMERA, IMU_T_CAM, "xyz", True, True, first_estimate_jacobians=False)
    slots = np.array([2, 0, 3])

    pos_inv, cov_inv, finite_inv = inv.world_landmarks(state, slots)
    pos_body, cov_body, finite_body = body.world_landmarks(state, slots)
    np.testing.assert_array_equal(pos_inv, pos_body)
    np.testing.assert_array_equal(pos_inv, theta[slots])
    assert finite_inv.all() and finite_body.all()
    for i, s in enumerate(slots):
        block = CORE + 3 * s + np.arange(3)
        np.testing.assert_array_equal(cov_body[i], P[np.ix_(block, block)])

        def world(e, m_hat=theta[s]):  # m of (I1) for the error e = (rho, phi, zeta)
            R, J_l = se3.exp_so3_and_left_jacobian(e[3:6])
            return R @ m_hat + J_l @ e[6:9]

        J = numeric_jacobian(world, np.zeros(9), 1e-6)
        idx = np.concatenate([np.arange(6), block])
        assert rel_err(cov_inv[i], J @ P[np.ix_(idx, idx)] @ J.T) < 1e-6
        np.testing.assert_array_equal(cov_inv[i], cov_inv[i].T)
    assert rel_err(cov_inv, cov_body) > 0.1  # the two models' P mean different errors

    np.testing.assert_array_equal(body.pose_covariance(state), P[POSE, POSE])
    J_body = numeric_jacobian(lambda x: se3.log_se3(se3.inverse(mu) @ se3.exp_se3(x) @ mu), np.zeros(6), 1e-6)
    expected = J_body @ P[POSE, POSE] @ J_body.T
    assert rel_err(inv.pose_covariance(state), expected) < 1e-6
    A = se3.adjoint(se3.inverse(mu))
    np.testing.assert_allclose(inv.pose_covariance(state), A @ P[POSE, POSE] @ A.T, rtol=0,
                               atol=1e-12 * np.abs(expected).max())
