"""The residual lever arm of the IMU's velocities in the filter (V1-V3 of ``backend.estimator.lever_arm``):
its columns of the prediction against finite differences and the dense textbook form, the
considered parameter's sensitivity against the estimate's own derivative, the prior the decision
gives, and a planted lever arm the tracks cannot measure."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from vislam.backend.config import Config
from vislam.backend.errors import HealthWarning
from vislam.backend.estimator import invariant
from vislam.backend.estimator.body import BodyModel
from vislam.backend.estimator.ekf import VisualInertialEKF
from vislam.backend.estimator.layout import CORE, LEVER_ROWS
from vislam.backend.estimator.lever_arm import twist_columns
from vislam.backend.estimator.propagation import ImuNoise
from vislam.backend.estimator.state import FilterState
from vislam.backend.evaluation.consistency import trajectory_nees
from vislam.backend.evaluation.metrics import trajectory_errors
from vislam.backend.geometry import se3
from vislam.backend.geometry.camera import StereoCamera
from vislam.backend.run.decisions import decide
from vislam.backend.run.noise import LEVER_PRIOR_M
from vislam.backend.run.runner import run_sequence
from vislam.synth.scene import SceneConfig, make_scene
from test_kernels import _dense_invariant_prediction, _noise_jacobian_pose, _prediction_problem, _spd

CORE_L = CORE + LEVER_ROWS  # pose, gyro bias, the lever arm


def pose_error(model: str, T: np.ndarray, T_hat: np.ndarray) -> np.ndarray:
    """(6,) the error of ``T`` against ``T_hat`` in ``model``'s form: log(T T_hat^-1) (invariant, I2),
    log(T_hat^-1 T) (body, B1)."""
    return se3.log_se3(T @ se3.inverse(T_hat) if model == "invariant" else se3.inverse(T_hat) @ T)


def _twist_error(v, w, tau, dr):
    """The step's body twist tau [v - w x dr; w] (6,), the velocity measured at a point dr from the frame."""
    return tau * np.r_[v - np.cross(w, dr), w]


@pytest.mark.parametrize("model", ["invariant", "body"])
def test_the_lever_arms_columns_are_the_derivative_of_the_step(model):
    """(V1): a lever arm error dr moves the predicted pose by G E_r dr to first order, E_r =
    -[(tau omega)^; 0]: the invariant error log(T T_hat^-1) with G = Ad(T_hat) J_r (I2), the body
    error log(T_hat^-1 T) with G = J_r (B1); central differences of the exact step over dr = 1e-6 m."""
    rng = np.random.default_rng(4)
    mu = se3.exp_se3(rng.normal(size=6))
    v, w, tau = np.array([9.0, 0.4, -0.2]), np.array([0.05, -0.12, 0.4]), 0.1
    twist = _twist_error(v, w, tau, np.zeros(3))
    T_hat = mu @ se3.exp_se3(twist)
    J_r = se3.right_jacobian_se3(twist)
    G = se3.adjoint(T_hat) @ J_r if model == "invariant" else J_r
    expected = G @ twist_columns(twist)
    h = 1e-6
    fd = np.zeros((6, 3))
    for i in range(3):
        dr = np.zeros(3)
        dr[i] = h
        ends = [mu @ se3.exp_se3(_twist_error(v, w, tau, s * dr)) for s in (1.0, -1.0)]
        fd[:, i] = (pose_error(model, ends[0], T_hat) - pose_error(model, ends[1], T_hat)) / (2 * h)
    assert np.abs(expected).max() > 0.01
    np.testing.assert_allclose(fd, expected, rtol=0, atol=1e-7)


def test_the_estimated_lever_arm_in_the_kernel_is_the_dense_prediction():
    """(I2, V1): the compiled prediction with the lever arm's rows equals F P F^T + G Q G^T with
    F = I + G E_b e_b^T + G E_r e_r^T (the bias's and the lever arm's columns), G = [G_pose; m_i^ R_phi]."""
    rng = np.random.default_rng(5)
    K = 4
    _, mu, twist, points, dt, q, walk = _prediction_problem(rng, K)
    P = _spd(rng, CORE_L + 3 * K)
    expected = _dense_invariant_prediction(P, mu, twist, points, dt, q, walk, core=CORE_L, lever_row=CORE)
    pose, R_phi = _noise_jacobian_pose(mu, twist)
    out = P.copy()
    invariant.predict_covariance_inplace(out, pose, R_phi, points, q, dt, True, walk, CORE, twist[3:6].copy())
    np.testing.assert_allclose(out, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
    assert np.array_equal(out, out.T)


def _scene(seed: int = 5, steps: int = 60, density: float = 1.0, scenario: str = "street"):
    return make_scene(SceneConfig(scenario=scenario, steps=steps, seed=seed, landmark_density=density))


def _filter(seq, sigma_m: float, dr=np.zeros(3), steps: int = 60, error_model: str = "invariant",
            vision: bool = True):
    """The filter alone (no decision) over the first ``steps`` of ``seq`` with the scene's noise, a
    considered lever arm of prior sigma ``sigma_m`` (0: none) and the velocities measured at ``dr``;
    ``vision`` False: no observation is used (the prediction alone)."""
    config = SceneConfig(scenario="street", seed=5).filter_config().with_values(
        {"noise.lever_arm_sigma": sigma_m, "drift.track_drift": "no", "noise.pixel_variance_per_disparity": 0.0,
         "estimator.error_model": error_model})
    ekf = VisualInertialEKF(StereoCamera(seq.K, seq.baseline), seq.imu_T_cam, config,
                            ImuNoise(np.full(3, 0.2), np.full(3, 0.01)))
    prev = None
    for k, (t, v, w, ids, pixels) in enumerate(seq.steps()):
        if k == steps:
            break
        if prev is not None:
            ekf.predict(t - prev[0], prev[1] + np.cross(prev[2], dr), prev[2])
        prev = (t, v, w)
        if vision:
            ekf.update(ids, pixels)
    return ekf


def _sensitivity_against_differences(seq, error_model: str, vision: bool, steps: int):
    """(the world position's sensitivity to the lever arm the considered run holds (3,3), the central
    differences of the estimate of the run without it over dr = +-1e-4 m per axis (3,3)), and the
    two runs' poses (considered, plain)."""
    sigma = 1.0
    considered = _filter(seq, sigma, steps=steps, error_model=error_model, vision=vision)
    plain = _filter(seq, 0.0, steps=steps, error_model=error_model, vision=vision)
    st = considered.state
    r = np.arange(st.lever_row, st.lever_row + LEVER_ROWS)
    np.testing.assert_allclose(st.P[np.ix_(r, r)], sigma**2 * np.eye(3), rtol=1e-12)
    S = st.P[:6][:, r] / sigma**2  # (6,3) d(error) / d(dr)
    p_hat, R_hat = considered.world_T_imu[:3, 3], considered.world_T_imu[:3, :3]
    if error_model == "invariant":  # dp = rho + phi x p (I1)
        expected = S[0:3] + np.cross(S[3:6].T, p_hat).T
    else:  # T = T_hat exp(xi): dp = R_hat rho
        expected = R_hat @ S[0:3]
    h = 1e-4
    fd = np.zeros((3, 3))
    for i in range(3):
        dr = np.zeros(3)
        dr[i] = h
        up = _filter(seq, 0.0, dr, steps, error_model, vision)
        down = _filter(seq, 0.0, -dr, steps, error_model, vision)
        fd[:, i] = (up.world_T_imu[:3, 3] - down.world_T_imu[:3, 3]) / (2 * h)
    # the error is truth - estimate: measuring the velocities dr further moves the estimate by -S dr
    return expected, -fd, considered, plain


@pytest.mark.parametrize("error_model", ["invariant", "body"])
def test_a_considered_lever_arms_sensitivity_is_the_derivative_of_the_prediction(error_model):
    """(V1, V2) without vision: the sensitivity the considered lever arm's column carries through 80
    predictions is the derivative of dead reckoning's pose with respect to where the velocities are
    measured (central differences over dr = +-1e-4 m), to 1e-6 of its norm."""
    seq = _scene(steps=80).sequence
    expected, fd, _, _ = _sensitivity_against_differences(seq, error_model, vision=False, steps=80)
    assert np.linalg.norm(expected) > 0.1
    np.testing.assert_allclose(fd, expected, rtol=0, atol=1e-6 * np.linalg.norm(expected))


def test_a_considered_lever_arm_leaves_the_estimate_and_carries_its_sensitivity():
    """(V2) with vision: with the lever arm considered the estimate is the filter's without it (to
    rounding), its pose covariance larger by S P_rr S^T (positive semi-definite, nonzero), the lever
    arm's own block its prior, and the sensitivity S the derivative of the estimate with respect to
    where the velocities are measured (central differences of the filter without it) to within 10 %
    of its norm on 150 steps of a street (4 % measured: the first-order sensitivity leaves out how
    the gains and Jacobians move with the estimate; a term left out, e.g. new landmarks' columns,
    is of the order of the whole). The invariant error model (the default): the body model's
    first-estimate Jacobians (B3) keep the gain off the estimate's own derivative by design."""
    seq = _scene(steps=150).sequence
    expected, fd, considered, plain = _sensitivity_against_differences(seq, "invariant", vision=True, steps=150)
    np.testing.assert_allclose(considered.world_T_imu, plain.world_T_imu, rtol=0, atol=1e-9)
    extra = considered.pose_covariance - plain.pose_covariance
    assert np.linalg.eigvalsh(0.5 * (extra + extra.T)).min() > -1e-12 and np.trace(extra) > 1e-5
    assert np.linalg.norm(expected) > 0.01  # m per m
    np.testing.assert_allclose(fd, expected, rtol=0, atol=0.1 * np.linalg.norm(expected))


def test_the_prior_is_what_n3_leaves():
    """(V3): N3's prior where the tracks cannot measure the lever arm (a sparse street), the applied
    correction's covariance or the second moment of taking none (a street's height, which its yaw
    does not excite, keeps most of N3's prior); a configured sigma wins; a mapping run carries none."""
    sparse = decide(_scene(density=0.03, steps=120).sequence, Config())
    assert sparse.imu.vision is None
    np.testing.assert_array_equal(sparse.lever_covariance, LEVER_PRIOR_M**2 * np.eye(3))
    dense = decide(_scene(steps=200).sequence, Config())
    v = dense.imu.vision
    assert v is not None and not dense.velocity.active
    np.testing.assert_allclose(dense.lever_covariance, v.covariance[:3, :3] + np.outer(v.lever_arm, v.lever_arm),
                               rtol=1e-12)
    sd = np.sqrt(np.diag(dense.lever_covariance))
    assert sd[:2].max() < 0.25 * LEVER_PRIOR_M < 0.5 * LEVER_PRIOR_M < sd[2] <= LEVER_PRIOR_M
    applied = dataclasses.replace(dense, velocity=dataclasses.replace(dense.velocity, lever_arm=v.lever_arm.copy()))
    assert applied.velocity.active
    np.testing.assert_allclose(applied.lever_covariance, v.covariance[:3, :3], rtol=1e-12)
    no_rotation = ["noise.imu_rotation_sigma=0"]
    np.testing.assert_array_equal(dense.lever_covariance_for(Config().with_assignments(no_rotation)),
                                  dense.lever_covariance)
    assert dense.lever_covariance_for(Config().with_assignments(["noise.lever_arm_sigma=0"] + no_rotation)) is None
    np.testing.assert_array_equal(
        dense.lever_covariance_for(Config().with_assignments(["noise.lever_arm_sigma=0.3"] + no_rotation)),
        0.09 * np.eye(3))
    assert dense.lever_covariance_for(Config().with_assignments(["estimator.mode=mapping"])) is None


def test_a_lever_arm_the_tracks_cannot_measure_is_held_by_the_covariance():
    """A sparse synthetic street (N3 untested) whose velocities are measured 2 m from the IMU frame
    in a turn-rich drive: the default run carries N3's prior (V3) and its position NEES mean stays
    <= 9, where the same run without the lever arm in its covariance is overconfident (> 9); the
    trajectory is the same (V2)."""
    scene = make_scene(SceneConfig(scenario="street", steps=250, seed=7, landmark_density=0.05))
    seq = scene.sequence
    lever = np.array([-1.2, 1.4, 0.6])
    seq = dataclasses.replace(seq, linear_velocity=seq.linear_velocity + np.cross(seq.angular_velocity, lever))
    gt = (seq.time_stamps, scene.world_T_imu_true)
    runs = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", HealthWarning)
        for name, sets in (("default", []), ("none", ["noise.lever_arm_sigma=0", "noise.imu_rotation_sigma=0"])):
            runs[name] = run_sequence(seq, Config().with_assignments(sets))
    assert runs["default"].decisions.imu.vision is None
    assert runs["default"].lever_arm.prior_sigma_m == [LEVER_PRIOR_M] * 3 and runs["none"].lever_arm is None
    np.testing.assert_allclose(runs["default"].world_T_imu, runs["none"].world_T_imu, rtol=0, atol=1e-9)
    nees = {k: trajectory_nees(r.time_stamps, r.world_T_imu, r.pose_covariance, *gt).position.mean
            for k, r in runs.items()}
    ate = trajectory_errors(runs["default"].time_stamps, runs["default"].world_T_imu, *gt).ate_rmse
    assert nees["default"] <= 9.0 < nees["none"], (nees, ate)


def test_the_lever_arm_rows_are_held_and_out_of_the_repair():
    """(V2): the considered rows are held by the update and left out of the positive-definiteness
    repair (H2), which they would fail: P holds the sensitivity there, not a covariance."""
    st = FilterState(core=CORE_L, lever_row=CORE, lever_considered=True)
    mask = st.estimated(True, True)
    assert not mask[CORE:CORE_L].any() and mask[:CORE].all()
    assert list(st.considered_rows()) == [CORE, CORE + 1, CORE + 2]


@pytest.mark.parametrize("path", ["invariant", "invariant-frozen", "body"])
def test_considered_and_estimated_lever_arms_move_its_columns_alike(path):
    """(V1, V2): one prediction moves the lever arm's columns of P the same way whether it is
    estimated (F's columns G E_r) or considered (its sensitivity S <- F S + G E_r), and leaves its own
    block alone; only the estimated one adds its share to the other blocks: for the ordinary step,
    a frozen step (I8, the landmarks' rows too; the IMU's share 0.6 of the linear velocity) and the
    body error model (B1)."""
    rng = np.random.default_rng(6)
    K = 3
    D = CORE_L + 3 * K
    P = _spd(rng, D)
    twist = np.array([1.1, 0.05, -0.03, 0.02, -0.04, 0.3])
    q = np.full(6, 1e-3)
    camera = StereoCamera(np.array([[700.0, 0, 600], [0, 700.0, 180], [0, 0, 1]]), 0.5)
    out = {}
    for considered in (True, False):
        state = FilterState(mu=se3.exp_se3(np.full(6, 0.3)), core=CORE_L, lever_row=CORE,
                            lever_considered=considered)
        state.append_landmarks(np.arange(K), np.random.default_rng(7).normal(0, 10, (K, 3)), np.ones(K, np.int64),
                               np.full(K, 10))
        state.P = P.copy()
        model = (BodyModel if path == "body" else invariant.InvariantModel)(camera, np.eye(4), "xyz", True, True)
        if path == "invariant-frozen":
            transition = model.predict_frozen(state, twist, q, 0.1, 1e-8, np.r_[np.full(3, 0.6), np.ones(3)])
        else:
            transition = model.predict(state, twist, q, 0.1, 1e-8)
        out[considered] = transition.apply(state.P)
    r = slice(CORE, CORE_L)
    np.testing.assert_allclose(out[True][:, r], out[False][:, r], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(out[True][r, r], P[r, r])
    gap = out[False][:CORE, :CORE] - out[True][:CORE, :CORE]
    assert np.abs(gap).max() > 1e-6  # the estimated one's share, the considered one's not
