"""The IMU velocities: velocity timing and dead reckoning (``backend.estimator.propagation``),
white-noise estimation and the noise decision (``backend.run.noise``)."""

from __future__ import annotations

import numpy as np
import pytest

from vislam.backend.geometry import se3
from vislam.backend.estimator.propagation import dead_reckoning, step_velocities
from vislam.backend.run.noise import decide_imu_noise, estimate_white_noise


def smooth_signal(n: int = 3000, dt: float = 0.1) -> np.ndarray:
    """Vehicle-like velocities: slow variations around a cruise speed, (n,3)."""
    t = np.arange(n) * dt
    return np.stack([8.0 + np.sin(0.3 * t), 0.5 * np.cos(0.11 * t), 0.2 * np.sin(0.05 * t + 1.0)], axis=1)


def test_white_noise_recovered():
    rng = np.random.default_rng(0)
    sigma = 0.3
    est = estimate_white_noise(smooth_signal() + rng.normal(0.0, sigma, (3000, 3)))
    assert est.shape == (3,)
    np.testing.assert_allclose(est, sigma, rtol=0.10)


def test_white_noise_per_axis():
    rng = np.random.default_rng(1)
    sigmas = np.array([0.3, 0.01, 1.0])
    est = estimate_white_noise(smooth_signal() + rng.normal(0.0, 1.0, (3000, 3)) * sigmas)
    np.testing.assert_allclose(est, sigmas, rtol=0.10)


def test_white_noise_of_clean_signal_is_small():
    assert np.all(estimate_white_noise(smooth_signal()) < 0.01)
    assert np.all(estimate_white_noise(np.ones((100, 3))) == 0.0)


def test_white_noise_robust_to_manoeuvres():
    rng = np.random.default_rng(2)
    signal = smooth_signal() + rng.normal(0.0, 0.3, (3000, 3))
    signal[1500:] += 5.0  # a sudden change of speed
    signal[::200] += 20.0  # and a few glitches
    np.testing.assert_allclose(estimate_white_noise(signal), 0.3, rtol=0.10)


def test_white_noise_short_signal():
    np.testing.assert_array_equal(estimate_white_noise(np.ones((4, 3))), np.zeros(3))


def test_step_velocities_select_samples():
    n = 6
    v = np.arange(3 * n, dtype=float).reshape(n, 3)
    w = -v
    v_this, w_this = step_velocities(v, w, "this")
    v_next, w_next = step_velocities(v, w, "next")
    np.testing.assert_array_equal(v_this, v[:-1])
    np.testing.assert_array_equal(w_this, w[:-1])
    np.testing.assert_array_equal(v_next, v[1:])
    np.testing.assert_array_equal(w_next, w[1:])
    assert v_this.shape == v_next.shape == (n - 1, 3)


def test_step_velocities_unknown_index():
    with pytest.raises(KeyError):
        step_velocities(np.zeros((3, 3)), np.zeros((3, 3)), "auto")


def test_dead_reckoning_constant_twist():
    n, dt = 50, 0.1
    u = np.array([8.0, 0.2, -0.1, 0.01, -0.02, 0.15])
    t = np.arange(n) * dt
    poses = dead_reckoning(t, np.tile(u[:3], (n, 1)), np.tile(u[3:], (n, 1)))
    assert poses.shape == (n, 4, 4)
    np.testing.assert_array_equal(poses[0], np.eye(4))
    for k in range(n):
        np.testing.assert_allclose(poses[k], se3.exp_se3(k * dt * u), rtol=0, atol=1e-10)


def test_dead_reckoning_uneven_steps_start_and_bias():
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.05, 0.2, 30))
    u = np.array([5.0, 0.0, 0.3, 0.05, 0.0, -0.2])
    bias = np.array([0.01, -0.02, 0.03])
    T0 = se3.exp_se3(np.array([1.0, 2.0, 3.0, 0.3, -0.2, 0.1]))
    poses = dead_reckoning(t, np.tile(u[:3], (30, 1)), np.tile(u[3:] + bias, (30, 1)), gyro_bias=bias, world_T_imu0=T0)
    for k in range(30):
        np.testing.assert_allclose(poses[k], T0 @ se3.exp_se3((t[k] - t[0]) * u), rtol=0, atol=1e-9)


def test_dead_reckoning_velocity_index():
    n, dt = 5, 0.5
    t = np.arange(n) * dt
    v = np.zeros((n, 3))
    v[:, 0] = np.arange(n, dtype=float)  # speed k at sample k
    w = np.zeros((n, 3))
    this = dead_reckoning(t, v, w, "this")
    nxt = dead_reckoning(t, v, w, "next")
    # "this": x_k = dt * (0 + 1 + ... + k-1); "next": x_k = dt * (1 + ... + k)
    np.testing.assert_allclose(this[:, 0, 3], dt * np.array([0, 0, 1, 3, 6]), atol=1e-12)
    np.testing.assert_allclose(nxt[:, 0, 3], dt * np.array([0, 1, 3, 6, 10]), atol=1e-12)


def test_decide_imu_noise_configured_and_estimated():
    rng = np.random.default_rng(4)
    lin = smooth_signal() + rng.normal(0.0, 0.3, (3000, 3))
    ang = smooth_signal() * 0.01 + rng.normal(0.0, 0.02, (3000, 3))
    configured = decide_imu_noise(lin, ang, 0.5, 0.01, 0.05, 0.002)
    assert configured.source == "configured"
    np.testing.assert_array_equal(configured.linear_sigma, np.full(3, 0.5))
    np.testing.assert_array_equal(configured.angular_sigma, np.full(3, 0.01))
    assert configured.linear_estimated is None and configured.angular_estimated is None

    estimated = decide_imu_noise(lin, ang, None, None, 0.05, 0.002)
    assert estimated.source == "estimated"
    np.testing.assert_array_equal(estimated.linear_sigma, estimated.linear_estimated)  # above the floor: kept
    np.testing.assert_array_equal(estimated.angular_sigma, estimated.angular_estimated)
    np.testing.assert_allclose(estimated.linear_sigma, 0.3, rtol=0.1)
    np.testing.assert_allclose(estimated.angular_sigma, 0.02, rtol=0.1)
    raised = decide_imu_noise(lin, ang, None, None, 0.5, 0.05)  # floors above the white noise
    np.testing.assert_array_equal(raised.linear_sigma, np.full(3, 0.5))
    np.testing.assert_array_equal(raised.angular_sigma, np.full(3, 0.05))

    mixed = decide_imu_noise(lin, ang, None, 0.01, 0.05, 0.002)
    assert mixed.source == "mixed" and mixed.angular_estimated is None
    assert set(mixed.as_dict()) >= {"linear_velocity_sigma", "angular_velocity_sigma", "source"}

    clean = decide_imu_noise(smooth_signal(), smooth_signal(), None, None, 0.05, 0.002)
    np.testing.assert_array_equal(clean.linear_sigma, np.full(3, 0.05))  # the floor remains
