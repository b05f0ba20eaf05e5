"""The IMU velocities: velocity timing and dead reckoning (``backend.estimator.propagation``),
white-noise estimation (``backend.run.noise``) and the IMU noise a run decides (``backend.run.decisions``)."""

from __future__ import annotations

import numpy as np
import pytest

from vislam.backend.geometry import se3
from vislam.backend.estimator.propagation import dead_reckoning, step_velocities
from vislam.backend.config import Config
from vislam.backend.run.decisions import decide
from vislam.backend.run.noise import estimate_white_noise, hold_error


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


def test_hold_error_by_hand_and_against_the_exact_step_mean():
    """(N4) a ramp x_k = a k dt holds each sample a dt/2 off its step's mean: exactly that RMS; a
    constant holds nothing; and on a smooth vehicle-like signal the RMS of (step mean - sample at
    the step start), integrated finely, is what N4 says within 5 % (both timings)."""
    dt = 0.1
    ramp = np.outer(np.arange(50) * dt, [2.0, -1.0, 0.0])
    np.testing.assert_allclose(hold_error(ramp), [0.1, 0.05, 0.0], rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(hold_error(np.ones((10, 3))), np.zeros(3))
    np.testing.assert_array_equal(hold_error(np.ones((1, 3))), np.zeros(3))
    fine = 50
    t = np.arange(300 * fine + 1) * (dt / fine)
    signal = np.stack([8.0 + 2.0 * np.sin(0.7 * t), 0.5 * np.cos(0.4 * t), 0.2 * np.sin(1.3 * t + 1.0)], axis=1)
    samples = signal[::fine]
    means = np.array([np.trapezoid(signal[k * fine:(k + 1) * fine + 1], dx=dt / fine, axis=0) / dt for k in range(300)])
    for held in (samples[:-1], samples[1:]):  # the timings "this" and "next"
        np.testing.assert_allclose(np.sqrt(np.mean((means - held) ** 2, axis=0)), hold_error(samples), rtol=0.05)


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


@pytest.fixture(scope="module")
def short_scene():
    from vislam.synth.scene import SceneConfig, make_scene

    return make_scene(SceneConfig(steps=60, seed=4)).sequence


def test_imu_noise_configured_wins_else_the_white_noise(short_scene):
    """The IMU noise a run decides (``backend.run.decisions.decide``) where vision cannot measure it
    (dead reckoning uses no vision): each configured sigma is used as given, per axis and on its own;
    an unset one is the white noise of the whole stream's samples (N1, ``imu_velocities``), with no
    floor: clean velocities give their own (tiny) white noise, not a hand-set minimum."""
    rng = np.random.default_rng(4)
    lin = smooth_signal() + rng.normal(0.0, 0.3, (3000, 3))
    ang = smooth_signal() * 0.01 + rng.normal(0.0, 0.02, (3000, 3))
    dead = {"estimator.mode": "dead-reckoning"}

    def imu(values, velocities=(lin, ang)):
        return decide(short_scene, Config.from_values({**dead, **values}), velocities).imu

    configured = imu({"noise.linear_velocity_sigma": 0.5, "noise.angular_velocity_sigma": 0.01})
    assert configured.linear_source == configured.angular_source == "configured"
    np.testing.assert_array_equal(configured.linear_sigma, np.full(3, 0.5))
    np.testing.assert_array_equal(configured.angular_sigma, np.full(3, 0.01))

    estimated = imu({})
    assert estimated.linear_source == estimated.angular_source == "white noise of the samples"
    assert estimated.vision is None and not estimated.likelihood
    np.testing.assert_array_equal(estimated.white_linear, estimate_white_noise(lin))  # the whole stream's (N1)
    np.testing.assert_array_equal(estimated.white_angular, estimate_white_noise(ang))
    np.testing.assert_array_equal(estimated.linear_sigma, estimated.white_linear)  # used as measured
    np.testing.assert_array_equal(estimated.angular_sigma, estimated.white_angular)
    np.testing.assert_allclose(estimated.linear_sigma, 0.3, rtol=0.1)
    np.testing.assert_allclose(estimated.angular_sigma, 0.02, rtol=0.1)

    mixed = imu({"noise.angular_velocity_sigma": 0.01})
    assert (mixed.linear_source, mixed.angular_source) == ("white noise of the samples", "configured")
    np.testing.assert_array_equal(mixed.linear_sigma, estimated.linear_sigma)
    np.testing.assert_array_equal(mixed.angular_sigma, np.full(3, 0.01))
    assert set(mixed.as_dict()) >= {"linear_velocity_sigma", "angular_velocity_sigma", "linear_decided_by",
                                    "angular_decided_by", "white_noise_linear", "white_noise_angular"}

    # clean samples: their white noise is tiny, and what holding them over a step costs (N4) is the
    # floor, measured from their own changes (no hand floor: far below a hand-set 0.05 m/s)
    clean = imu({}, (smooth_signal(), smooth_signal()))
    np.testing.assert_array_equal(clean.white_linear, estimate_white_noise(smooth_signal()))
    assert np.all(clean.white_linear < 1e-3)
    np.testing.assert_array_equal(clean.linear_sigma, np.maximum(clean.white_linear, hold_error(smooth_signal())))
    np.testing.assert_array_equal(clean.hold_linear, hold_error(smooth_signal()))
    assert "(N4)" in clean.linear_source and np.all(clean.linear_sigma < 0.02)
    # noisy samples: their white noise exceeds the hold error, so N1 stands alone
    np.testing.assert_array_equal(estimated.linear_sigma, estimated.white_linear)
    assert np.all(estimated.hold_linear < estimated.white_linear)
    # without imu_velocities: the sequence's own samples
    own = decide(short_scene, Config.from_values(dead)).imu
    np.testing.assert_array_equal(own.white_linear, estimate_white_noise(short_scene.linear_velocity))
