"""Repeated frames whose content froze (I8, T2): the landmarks keep their body-frame points, the
covariance propagation is the linearization of that map, and on scenes with repeated frames the
freeze policy tracks the truth where using the repeated pixels does not."""

from __future__ import annotations

import numpy as np
import pytest

from vislam.backend.config import Config
from vislam.backend.errors import HealthWarning
from vislam.backend.estimator.invariant import predict_frozen
from vislam.backend.estimator.layout import CORE
from vislam.backend.evaluation.consistency import trajectory_nees
from vislam.backend.evaluation.metrics import trajectory_errors
from vislam.backend.geometry import se3
from vislam.backend.run.runner import run_sequence
from vislam.backend.run.timing import MotionPrior
from vislam.synth.scene import SceneConfig, make_scene
from vislam.synth.track_errors import TrackErrors


def _invariant_error(T, m, T_hat, m_hat):
    """(rho, phi, bias 0, zeta_i) of (I1): E = X X_hat^-1 with m = exp(phi) m_hat + J_l(phi) zeta."""
    E = T @ se3.inverse(T_hat)
    xi = se3.log_se3(E)
    zeta = np.linalg.solve(se3.left_jacobian_so3(xi[3:]), (m - m_hat @ E[:3, :3].T).T).T
    return np.concatenate([xi, np.zeros(3), zeta.ravel()])


def test_frozen_mean_keeps_body_points():
    """(I8) mean: T^-1 m of every landmark is the same before and after the step; the pose moves by
    exp(twist)."""
    rng = np.random.default_rng(0)
    T = se3.exp_se3(rng.normal(0, 1, 6))
    points = rng.normal(0, 10, (5, 3))
    twist = np.array([1.0, 0.1, 0.0, 0.01, -0.02, 0.05])
    before = (points - T[:3, 3]) @ T[:3, :3]
    mu, _ = predict_frozen(T, points, twist, np.full(6, 1e-3), 0.1, True, 1e-8)
    np.testing.assert_allclose(mu, T @ se3.exp_se3(twist), atol=1e-12)
    np.testing.assert_allclose((points - mu[:3, 3]) @ mu[:3, :3], before, atol=1e-9)


def test_frozen_covariance_is_the_linearized_map():
    """(I8) covariance: sampling the prior error (pose, bias, landmarks) and the twist noise, moving
    pose and landmarks through the exact frozen step and measuring the invariant error after it
    gives the covariance predict_frozen computes (small errors: the linear regime; 20000 samples,
    entries within 10 % of the largest)."""
    rng = np.random.default_rng(1)
    K = 3
    D = CORE + 3 * K
    A = rng.normal(0, 1, (D, D))
    P0 = A @ A.T * 1e-6
    T_hat = se3.exp_se3(np.array([2.0, -1.0, 0.5, 0.1, 0.2, -0.3]))
    m_hat = rng.normal(0, 8, (K, 3))
    twist, q, dt = np.array([1.2, 0.05, -0.02, 0.02, -0.01, 0.04]), np.full(6, 1e-3), 0.1
    P = P0.copy()
    m_new = m_hat.copy()
    mu, transition = predict_frozen(T_hat, m_new, twist, q, dt, True, 0.0)
    P = transition.apply(P)
    L = np.linalg.cholesky(P0)
    errors = []
    for _ in range(20000):
        x = L @ rng.standard_normal(D)
        T = se3.exp_se3(x[:6]) @ T_hat
        E = se3.exp_se3(x[:6])
        J = se3.exp_se3_and_left_jacobian(x[:6])[1]
        m = m_hat @ E[:3, :3].T + (J @ x[CORE:].reshape(K, 3).T).T
        b = x[6:9]
        n = q * rng.standard_normal(6)
        true_twist = twist - dt * np.r_[0, 0, 0, b] - n  # the bias error enters like the gyro's
        T_next = T @ se3.exp_se3(true_twist)
        s = (m - T[:3, 3]) @ T[:3, :3]  # body points, kept
        m_next = s @ T_next[:3, :3].T + T_next[:3, 3]
        e = _invariant_error(T_next, m_next, mu, m_new)
        e[6:9] = b
        errors.append(e)
    C = np.cov(np.array(errors).T)
    np.testing.assert_allclose(C, P, atol=0.1 * np.abs(P).max())


def test_motion_prior_measures_its_own_error():
    """(T2): velocities changing by white steps of 0.05 per axis, an IMU of sigma 0.1: the prior's
    sigma per step is tau * 0.05, on the safe side (between 0.9 and 1.5 times: it adds a standard
    error of its own estimate), and no prior where the IMU is better than it."""
    rng = np.random.default_rng(2)
    prior = MotionPrior(np.full(6, 0.1))
    u = np.zeros(6)
    T = np.eye(4)
    dt = 0.1
    for _ in range(300):
        u = u + rng.normal(0, 0.05, 6)
        T_next = T @ se3.exp_se3(dt * u)
        prior.add(T, T_next, dt, u + rng.normal(0, 0.1, 6), frozen=False)
        T = T_next
    twist, sigma = prior.predict(dt)
    np.testing.assert_allclose(twist, dt * u, atol=1e-9)
    assert np.all(sigma / dt >= 0.9 * 0.05) and np.all(sigma / dt <= 1.5 * 0.05)
    sharp = MotionPrior(np.full(6, 0.01))
    for _ in range(100):
        sharp.add(np.eye(4), se3.exp_se3(dt * rng.normal(0, 1.0, 6)), dt, np.zeros(6), frozen=False)
    assert sharp.predict(dt) is None


def test_motion_prior_is_never_exact_where_the_imu_noise_takes_up_its_differences():
    """(T2) An IMU whose configured sigma (0.1) exceeds the differences it shows to the prior (white
    0.05, the velocity constant): the excess is negative, and the prior's variance is then the
    standard error of the squared differences' mean, not zero: sigma / tau between 0.1 and 1 times
    0.05 on every axis, so a frozen step cannot pin an axis as exactly known."""
    rng = np.random.default_rng(3)
    prior = MotionPrior(np.full(6, 0.1))
    dt = 0.1
    u = rng.normal(0, 0.5, 6)
    for _ in range(200):
        prior.add(np.eye(4), se3.exp_se3(dt * u), dt, u + rng.normal(0, 0.05, 6), frozen=False)
    twist, sigma = prior.predict(dt)
    np.testing.assert_allclose(twist, dt * u, atol=1e-12)
    sq = 0.05**2
    se = np.sqrt(2) * sq / np.sqrt(199)  # the standard error of a mean of 199 squares of N(0, 0.05^2)
    assert np.all(sigma / dt > 0.5 * np.sqrt(se)) and np.all(sigma / dt < 2 * np.sqrt(se))
    assert np.all(sigma / dt > 0.1 * 0.05) and np.all(sigma / dt < 0.05)


@pytest.fixture(scope="module")
def repeats():
    return make_scene(SceneConfig(steps=300, seed=7, track_errors=TrackErrors(pixel_sigma=0.5, repeat_interval=12.0)))


def test_freeze_tracks_the_truth_through_repeated_frames(repeats):
    """On a street with a repeated frame every ~12 steps: using the repeated pixels as frames is
    worse than dead reckoning; freezing them is at least 3 times better than dead reckoning and its
    position NEES mean stays below 3 x 3 (a consistent filter: 3)."""
    seq = repeats.sequence
    gt = (seq.time_stamps, repeats.world_T_imu_true)
    frozen = run_sequence(seq)
    with pytest.warns(HealthWarning, match="scale disagrees with the IMU's"):  # H4: the repeats say the camera stood
        used = run_sequence(seq, Config().with_assignments(["conventions.repeated_frames=use"]))
    assert used.stats.scale.failed and used.stats.scale.scale > 1.0 and not frozen.stats.scale.failed
    ate = {name: trajectory_errors(r.time_stamps, r.world_T_imu, *gt).ate_rmse for name, r in
           (("freeze", frozen), ("use", used))}
    dr = trajectory_errors(frozen.time_stamps, frozen.dead_reckoning, *gt).ate_rmse
    assert frozen.stats.frozen_steps == frozen.decisions.repeated_frames > 10
    assert ate["use"] > dr
    assert ate["freeze"] < dr / 3
    nees = trajectory_nees(frozen.time_stamps, frozen.world_T_imu, frozen.pose_covariance, *gt)
    assert nees.position.mean < 9.0
