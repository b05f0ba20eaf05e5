"""The rotation of the IMU samples' frame (N6 of ``backend.run.noise``, V4 of
``backend.estimator.lever_arm``): its columns of the prediction against finite differences, N6's
estimate of a planted rotation, the prior the decision gives, and a planted rotation the tracks
cannot measure held by the covariance."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from vislam.backend.config import Config
from vislam.backend.errors import HealthWarning
from vislam.backend.estimator.layout import CORE, LEVER_ROWS
from vislam.backend.estimator.lever_arm import consider_information, twist_columns
from vislam.backend.estimator.state import FilterState
from vislam.backend.evaluation.consistency import trajectory_nees
from vislam.backend.geometry import se3
from vislam.backend.run.decisions import decide
from vislam.backend.run.noise import ROTATION_PRIOR_RAD
from vislam.backend.run.runner import run_sequence
from vislam.synth.scene import SceneConfig, make_scene
from test_lever_arm import pose_error


def _rotated(seq, theta):
    """``seq`` with its samples given in a frame turned by exp(theta^) from the IMU's: u_file = R^T u."""
    R = se3.exp_so3_and_left_jacobian(np.asarray(theta, dtype=float))[0]
    return dataclasses.replace(seq, linear_velocity=seq.linear_velocity @ R, angular_velocity=seq.angular_velocity @ R)


@pytest.mark.parametrize("model", ["invariant", "body"])
def test_the_rotations_columns_are_the_derivative_of_the_step(model):
    """(V4): samples in a frame turned by theta move the predicted pose by G E_theta theta to first
    order, E_theta = -[(tau v)^; (tau omega)^] (the body's twist is R u); central differences of the
    exact step over theta = 1e-6 rad, both error models; the lever arm's columns come first."""
    rng = np.random.default_rng(8)
    mu = se3.exp_se3(rng.normal(size=6))
    u, tau = np.array([9.0, 0.4, -0.2, 0.05, -0.12, 0.4]), 0.1
    T_hat = mu @ se3.exp_se3(tau * u)
    J_r = se3.right_jacobian_se3(tau * u)
    G = se3.adjoint(T_hat) @ J_r if model == "invariant" else J_r
    columns = twist_columns(tau * u, rotation=True)
    np.testing.assert_array_equal(columns[:, :LEVER_ROWS], twist_columns(tau * u))
    expected = G @ columns[:, LEVER_ROWS:]
    h = 1e-6
    fd = np.zeros((6, 3))
    for i in range(3):
        d = np.zeros(3)
        d[i] = h
        ends = []
        for s in (1.0, -1.0):
            R = se3.exp_so3_and_left_jacobian(s * d)[0]
            ends.append(mu @ se3.exp_se3(tau * np.r_[R @ u[:3], R @ u[3:]]))
        fd[:, i] = (pose_error(model, ends[0], T_hat) - pose_error(model, ends[1], T_hat)) / (2 * h)
    assert np.abs(expected).max() > 0.1
    np.testing.assert_allclose(fd, expected, rtol=0, atol=1e-7)


def test_n6_measures_a_planted_rotation():
    """(N6): a dense synthetic street whose samples are given in a frame turned by (0.5, 2, -1) deg:
    the estimate lies within 3 standard errors of it on every axis, the standard errors under 1
    deg, significant, and the filter's prior is its second moment (V4); the same street as generated
    gives an estimate within 3 of its standard errors of 0, not significant: no rotation carried."""
    seq = make_scene(SceneConfig(scenario="street", steps=300, seed=5)).sequence
    planted = np.radians([0.5, 2.0, -1.0])
    for truth, data in ((planted, _rotated(seq, planted)), (np.zeros(3), seq)):
        decisions = decide(data, Config())
        v = decisions.imu.vision
        assert v is not None
        se = np.sqrt(np.diag(v.rotation_covariance))
        assert se.max() < np.radians(1.0), np.degrees(se)
        assert np.all(np.abs(v.rotation - truth) < 3 * se), (np.degrees(v.rotation), np.degrees(se))
        prior = decisions.lever_covariance_for(Config())
        assert v.rotation_significant() == bool(truth.any()), v.rotation_chi2
        if truth.any():
            np.testing.assert_allclose(decisions.rotation_covariance,
                                       v.rotation_covariance + np.outer(v.rotation, v.rotation), rtol=1e-12)
            assert prior.shape == (6, 6) and not prior[:3, 3:].any()
            np.testing.assert_array_equal(prior[3:, 3:], decisions.rotation_covariance)
        else:
            assert not decisions.rotation_covariance.any()
            np.testing.assert_array_equal(prior, decisions.lever_covariance)


def test_the_rotations_prior_and_its_settings():
    """(V4): N6's prior where the tracks cannot measure the rotation (a sparse street); a configured
    sigma (deg) wins; 0 leaves the lever arm alone (3 rows), a lever arm set to 0 leaves the
    rotation, whose information is then the prior's pseudo-inverse; an estimated lever arm carries
    no rotation."""
    sparse = decide(make_scene(SceneConfig(scenario="street", steps=120, seed=5, landmark_density=0.03)).sequence,
                    Config())
    assert sparse.imu.vision is None
    np.testing.assert_array_equal(sparse.rotation_covariance, ROTATION_PRIOR_RAD**2 * np.eye(3))
    prior = sparse.lever_covariance_for(Config().with_assignments(["noise.imu_rotation_sigma=2"]))
    np.testing.assert_allclose(prior[3:, 3:], np.radians(2.0)**2 * np.eye(3), rtol=1e-12)
    assert sparse.lever_covariance_for(Config().with_assignments(["noise.imu_rotation_sigma=0"])).shape == (3, 3)
    assert sparse.lever_covariance_for(Config().with_assignments(["estimator.estimate_lever_arm=true"])).shape == (3, 3)
    rotation_only = sparse.lever_covariance_for(Config().with_assignments(["noise.lever_arm_sigma=0"]))
    assert rotation_only.shape == (6, 6) and not rotation_only[:3].any()
    info = consider_information(rotation_only)
    np.testing.assert_allclose(rotation_only @ info @ rotation_only, rotation_only, atol=1e-15)
    st = FilterState(core=CORE + 6, lever_row=CORE, lever_considered=True, lever_information=info)
    assert st.lever_dim == 6 and list(st.considered_rows()) == list(range(CORE, CORE + 6))
    assert not st.estimated(True, True)[CORE:CORE + 6].any()


def test_a_rotation_the_tracks_cannot_measure_is_held_by_the_covariance():
    """A sparse synthetic street (N6 untested) with clean samples (0.01 m/s, 0.001 rad/s, as
    ece276a2019_0042's) given in a frame turned 3 deg in pitch and 1 in roll (a level frame on a
    slope), the lever arm left out of both runs: the run with
    the rotation carries N6's prior (V4) and its position NEES mean stays <= 9, where the same run
    without it is overconfident (> 9); the trajectory is the same (V2)."""
    scene = make_scene(SceneConfig(scenario="street", steps=250, seed=7, landmark_density=0.05,
                                   linear_sigma=0.01, angular_sigma=0.001))
    seq = _rotated(scene.sequence, np.radians([1.0, 3.0, 0.0]))
    gt = (seq.time_stamps, scene.world_T_imu_true)
    runs = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", HealthWarning)
        for name, sets in (("default", []), ("none", ["noise.imu_rotation_sigma=0"])):
            runs[name] = run_sequence(seq, Config().with_assignments(sets + ["noise.lever_arm_sigma=0"]))
    assert runs["default"].decisions.imu.vision is None
    assert runs["default"].lever_arm.rotation_prior_sigma_deg == pytest.approx([3.0] * 3)
    assert runs["none"].lever_arm is None
    np.testing.assert_allclose(runs["default"].world_T_imu, runs["none"].world_T_imu, rtol=0, atol=1e-9)
    nees = {k: trajectory_nees(r.time_stamps, r.world_T_imu, r.pose_covariance, *gt).position.mean
            for k, r in runs.items()}
    assert nees["default"] <= 9.0 < nees["none"], nees
