"""Tests of vislam.synth.inertial: exact trajectory derivatives, real-IMU samples (specific force and
angular rate) whose integration gives the trajectory back, their noise and bias statistics, the
scenarios' documented ranges, camera frame stamps and reproducibility."""

from __future__ import annotations

import numpy as np
import pytest

from vislam.backend.data.inertial import ADIS16448, ImuNoiseDensities, ImuSamples
from vislam.backend.geometry import se3
from vislam.synth.inertial import (
    ACCEL_BIAS_RANGE,
    GYRO_BIAS_RANGE,
    ROOM_BOX,
    ROOM_FLIGHT_BOX,
    ROOM_MAX_TILT,
    InertialTrajectory,
    Sinusoids,
    frame_times,
    frame_truth,
    measure_imu,
    room,
    street,
)

SCENARIOS = {"room": room, "street": street}
CASES = [(name, seed, rest) for name in SCENARIOS for seed in (0, 1, 2) for rest in (None, 1.5)]
G = np.array([0.0, 0.0, -9.81])


def make(name: str, seed: int, rest=None, duration: float = 60.0) -> InertialTrajectory:
    return SCENARIOS[name](duration, seed, start_at_rest=rest)


def check_times(traj: InertialTrajectory, count: int = 150, seed: int = 0) -> np.ndarray:
    """Random times over the trajectory, plus the ends of the rest and of the ramp (where the warp changes form)."""
    t = np.random.default_rng(seed).uniform(0.01, traj.duration - 0.01, count)
    if traj.start_at_rest is not None:
        knots = np.array([traj.start_at_rest, traj.start_at_rest + traj.ramp])
        inside = traj.start_at_rest + traj.ramp * np.linspace(0.1, 0.9, 9)
        t = np.concatenate([t, knots, knots + 3e-5, knots - 3e-5, inside])
    return np.sort(t)


# ------------------------------------------------------------------ (a) exact derivatives


@pytest.mark.parametrize("name,seed,rest", CASES)
def test_derivatives_match_central_differences(name, seed, rest):
    traj = make(name, seed, rest)
    t = check_times(traj, seed=seed)
    h = 1e-4
    mid, plus, minus = traj.evaluate(t), traj.evaluate(t + h), traj.evaluate(t - h)
    velocity_fd = (plus.position - minus.position) / (2 * h)
    acceleration_fd = (plus.velocity - minus.velocity) / (2 * h)
    np.testing.assert_allclose(mid.velocity, velocity_fd, rtol=0, atol=1e-7)
    np.testing.assert_allclose(mid.acceleration, acceleration_fd, rtol=0, atol=1e-7)
    rates_fd = (plus.angles - minus.angles) / (2 * h)
    np.testing.assert_allclose(mid.angle_rates, rates_fd, rtol=0, atol=5e-8)
    # body rate: R(t-h)^T R(t+h) = exp(2h w^) + O(h^3)
    omega_fd = np.array([se3.log_so3(a.T @ b) for a, b in zip(minus.rotation, plus.rotation)]) / (2 * h)
    np.testing.assert_allclose(mid.angular_velocity, omega_fd, rtol=0, atol=5e-8)  # observed <= 4e-9
    # and the forward difference log(R(t)^T R(t+h)) / h agrees to O(h)
    omega_fwd = np.array([se3.log_so3(a.T @ b) for a, b in zip(mid.rotation, plus.rotation)]) / h
    np.testing.assert_allclose(mid.angular_velocity, omega_fwd, rtol=0, atol=1e-3)
    R = mid.rotation
    np.testing.assert_allclose(R.transpose(0, 2, 1) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)


def test_sinusoids_derivatives():
    f = Sinusoids(0.3, -0.2, [1.0, 0.5], [2.0, 7.0], [0.1, -1.0])
    tau = np.linspace(-3.0, 3.0, 11)
    d = f.derivatives(tau, 3)
    np.testing.assert_allclose(d[0], 0.3 - 0.2 * tau + np.sin(2 * tau + 0.1) + 0.5 * np.sin(7 * tau - 1.0), atol=1e-15)
    np.testing.assert_allclose(d[1], -0.2 + 2 * np.cos(2 * tau + 0.1) + 3.5 * np.cos(7 * tau - 1.0), atol=1e-14)
    np.testing.assert_allclose(d[2], -4 * np.sin(2 * tau + 0.1) - 24.5 * np.sin(7 * tau - 1.0), atol=1e-13)
    assert f.bound == 1.5
    np.testing.assert_array_equal(Sinusoids(2.0)(tau), np.full(tau.shape, 2.0))
    with pytest.raises(ValueError):
        Sinusoids(0.0, 0.0, [1.0], [1.0, 2.0], [0.0])


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_start_at_rest(name):
    traj = make(name, 4, rest=2.0)
    t = np.linspace(0.0, 2.0, 41)
    s = traj.evaluate(t)
    assert np.all(s.velocity == 0) and np.all(s.acceleration == 0) and np.all(s.angular_velocity == 0)
    np.testing.assert_array_equal(s.world_T_imu, np.broadcast_to(s.world_T_imu[0], s.world_T_imu.shape))
    after = traj.evaluate([2.0 + traj.ramp + 1.0])
    assert np.linalg.norm(after.velocity) > 0.1
    # at rest a real accelerometer reads R^T (0, 0, +9.81) and the gyro nothing
    _, truth = measure_imu(traj, duration=2.0, noise=None, bias0_gyro=0.0, bias0_accel=0.0)
    R = truth.world_T_imu[:, :3, :3]
    np.testing.assert_allclose(truth.noise_free.linear_acceleration, np.einsum("kji,j->ki", R, [0.0, 0.0, 9.81]),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(truth.noise_free.linear_acceleration, axis=1), 9.81, atol=1e-12)
    assert np.all(truth.noise_free.angular_velocity == 0)


def test_warp_is_smooth_at_its_knots():
    traj = make("room", 0, rest=1.0)
    for knot in (1.0, 1.0 + traj.ramp):
        tau, dtau, ddtau = traj.warp(np.array([knot - 1e-9, knot, knot + 1e-9]))
        assert np.ptp(dtau) < 1e-8 and np.ptp(ddtau) < 1e-6
    tau, dtau, _ = traj.warp(np.array([1.0 + traj.ramp, 10.0]))
    np.testing.assert_allclose(tau, [0.5 * traj.ramp, 10.0 - 1.0 - 0.5 * traj.ramp], atol=1e-15)
    np.testing.assert_array_equal(dtau, [1.0, 1.0])


# ------------------------------------------------------------------ (b) integration gives the trajectory back


def integrate_rk4(R, p, v, force, rate, dt, g):
    """RK4 of R' = R w^, v' = R f + g, p' = v with steps of 2 dt; samples k, k+1, k+2 give the start,
    midpoint and end of each step. Returns R, p, v at sample 2 * floor((L - 1) / 2)."""

    def f(R, v, k):
        return R @ se3.hat3(rate[k]), R @ force[k] + g, v

    h = 2 * dt
    for k in range(0, force.shape[0] - 2, 2):
        k1 = f(R, v, k)
        k2 = f(R + 0.5 * h * k1[0], v + 0.5 * h * k1[1], k + 1)
        k3 = f(R + 0.5 * h * k2[0], v + 0.5 * h * k2[1], k + 1)
        k4 = f(R + h * k3[0], v + h * k3[1], k + 2)
        R = R + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        p = p + h / 6 * (v + 2 * (v + 0.5 * h * k1[1]) + 2 * (v + 0.5 * h * k2[1]) + (v + h * k3[1]))
        v = v + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        u, _, wt = np.linalg.svd(R)
        R = u @ wt
    return R, p, v


INTEGRATION_CASES = [("room", 0, None), ("room", 1, 1.0), ("street", 0, None), ("street", 2, 1.0)]


@pytest.mark.parametrize("name,seed,rest", INTEGRATION_CASES)
def test_noise_free_samples_integrate_to_the_trajectory(name, seed, rest):
    traj = make(name, seed, rest, duration=8.0)
    start = 0.5
    _, truth = measure_imu(traj, 200.0, duration=5.0, noise=None, bias0_gyro=0.0, bias0_accel=0.0, start=start)
    imu = truth.noise_free
    assert imu.num_samples == 1001 and imu.time_stamps[0] == start and imu.time_stamps[-1] == pytest.approx(5.5)
    T0 = truth.world_T_imu[0]
    R, p, v = integrate_rk4(T0[:3, :3], T0[:3, 3], truth.velocity[0], imu.linear_acceleration, imu.angular_velocity,
                            0.005, G)
    end = traj.evaluate([start + 5.0])
    # far tighter than "a few mm": RK4 over 5 s at 100 Hz misses by ~1e-9 m on these trajectories
    assert np.linalg.norm(p - end.position[0]) < 1e-5
    assert np.linalg.norm(v - end.velocity[0]) < 1e-5
    assert np.linalg.norm(se3.log_so3(end.rotation[0].T @ R)) < 1e-7
    # the sign of gravity matters: integrating with +g misses by metres
    _, p_wrong, _ = integrate_rk4(T0[:3, :3], T0[:3, 3], truth.velocity[0], imu.linear_acceleration,
                                  imu.angular_velocity, 0.005, -G)
    assert np.linalg.norm(p_wrong - end.position[0]) > 100.0


def test_specific_force_method_and_gravity_parameter():
    traj = make("room", 3)
    t = np.linspace(1.0, 9.0, 7)
    s = traj.evaluate(t)
    g = np.array([0.0, 0.0, -9.80665])
    expected = np.einsum("kji,kj->ki", s.rotation, s.acceleration - g)
    np.testing.assert_allclose(traj.specific_force(t, g), expected, atol=1e-14)
    _, truth = measure_imu(traj, 100.0, duration=2.0, noise=None, gravity=g, start=1.0)
    np.testing.assert_allclose(truth.noise_free.linear_acceleration, traj.specific_force(truth.time_stamps, g),
                               atol=1e-13)
    np.testing.assert_array_equal(truth.gravity, g)


# ------------------------------------------------------------------ (c) noise and bias statistics


@pytest.fixture(scope="module")
def room_imu():
    traj = make("room", 5)
    return traj, *measure_imu(traj, 200.0, noise=ADIS16448, seed=11)


def test_white_noise_has_the_discrete_standard_deviation(room_imu):
    _, samples, truth = room_imu
    dt = 1.0 / 200.0
    assert samples.num_samples == 12001
    assert samples.noise is ADIS16448 and isinstance(samples, ImuSamples)
    np.testing.assert_array_equal(samples.time_stamps, truth.time_stamps)
    white_a = samples.linear_acceleration - truth.noise_free.linear_acceleration - truth.accel_bias
    white_g = samples.angular_velocity - truth.noise_free.angular_velocity - truth.gyro_bias
    sigma = ADIS16448.discrete(dt)
    for white, expected in ((white_a, sigma["accelerometer"]), (white_g, sigma["gyroscope"])):
        assert expected == pytest.approx(
            (ADIS16448.accelerometer_noise_density if white is white_a else ADIS16448.gyroscope_noise_density)
            / np.sqrt(dt))
        np.testing.assert_allclose(white.std(axis=0), expected, rtol=0.05)
        assert np.all(np.abs(white.mean(axis=0)) < 5 * expected / np.sqrt(white.shape[0]))
        assert abs(np.corrcoef(white[:-1, 0], white[1:, 0])[0, 1]) < 0.05  # white: no correlation in time


def test_bias_walk_has_the_discrete_step(room_imu):
    _, _, truth = room_imu
    dt = 1.0 / 200.0
    for bias, walk in ((truth.accel_bias, ADIS16448.accelerometer_random_walk),
                       (truth.gyro_bias, ADIS16448.gyroscope_random_walk)):
        steps = np.diff(bias, axis=0)
        np.testing.assert_allclose(steps.std(axis=0), walk * np.sqrt(dt), rtol=0.05)
    b_g, b_a = np.abs(truth.gyro_bias[0]), np.abs(truth.accel_bias[0])
    assert np.all((b_g >= GYRO_BIAS_RANGE[0]) & (b_g <= GYRO_BIAS_RANGE[1]))
    assert np.all((b_a >= ACCEL_BIAS_RANGE[0]) & (b_a <= ACCEL_BIAS_RANGE[1]))


def test_given_biases_and_noise_off():
    traj = make("room", 6, duration=5.0)
    b_g, b_a = [0.01, -0.02, 0.003], [0.05, 0.0, -0.1]
    noisy, truth = measure_imu(traj, 200.0, bias0_gyro=b_g, bias0_accel=b_a, seed=3)
    np.testing.assert_array_equal(truth.gyro_bias[0], b_g)
    np.testing.assert_array_equal(truth.accel_bias[0], b_a)
    # giving the biases changes no other draw: the white noise is the same as with drawn biases
    drawn, truth_drawn = measure_imu(traj, 200.0, seed=3)
    np.testing.assert_allclose(noisy.angular_velocity - truth.gyro_bias, drawn.angular_velocity - truth_drawn.gyro_bias,
                               atol=1e-15)
    clean, truth_clean = measure_imu(traj, 200.0, noise=None, bias0_gyro=b_g, bias0_accel=b_a, seed=3)
    assert clean.noise is None
    np.testing.assert_allclose(clean.angular_velocity, truth_clean.noise_free.angular_velocity + b_g, atol=1e-15)
    np.testing.assert_allclose(clean.linear_acceleration, truth_clean.noise_free.linear_acceleration + b_a, atol=1e-14)
    zeros = ImuNoiseDensities(0.0, 0.0, 0.0, 0.0)
    same, _ = measure_imu(traj, 200.0, noise=zeros, bias0_gyro=b_g, bias0_accel=b_a, seed=3)
    np.testing.assert_array_equal(same.angular_velocity, clean.angular_velocity)
    with pytest.raises(ValueError):
        measure_imu(traj, 0.0)
    with pytest.raises(ValueError):
        measure_imu(traj, 200.0, duration=-1.0)


# ------------------------------------------------------------------ (d) the scenarios' ranges


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_room_stays_in_its_box_with_the_documented_attitude(seed):
    traj = make("room", seed, rest=2.0 if seed % 2 else None)
    s = traj.evaluate(np.arange(0.0, 60.0, 0.01))
    assert np.all(ROOM_BOX[0] <= ROOM_FLIGHT_BOX[0]) and np.all(ROOM_FLIGHT_BOX[1] <= ROOM_BOX[1])
    assert np.all(s.position >= ROOM_FLIGHT_BOX[0]) and np.all(s.position <= ROOM_FLIGHT_BOX[1])
    yaw, pitch, roll = s.angles.T
    for angle in (roll, pitch):
        assert np.abs(angle).max() <= ROOM_MAX_TILT + 1e-12
        assert np.abs(angle).max() >= np.deg2rad(10.0)
    assert abs(yaw[-1] - yaw[0]) >= 2 * np.pi  # at least one full turn a minute
    speed = np.linalg.norm(s.velocity, axis=1)
    assert 1.0 < speed.max() < 2.5
    assert np.linalg.norm(s.acceleration, axis=1).max() < 3.0
    assert np.linalg.norm(s.angular_velocity, axis=1).max() < 1.5


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_street_is_a_car(seed):
    traj = make("street", seed)
    s = traj.evaluate(np.arange(0.0, 60.0, 0.02))
    speed = np.linalg.norm(s.velocity, axis=1)
    assert speed.min() >= 5.0 - 1e-6 and speed.max() <= 12.0 + 1e-6
    np.testing.assert_allclose(s.position[0], 0.0, atol=1e-12)
    # the x axis points along the velocity, up to the small pitch and roll bumps
    along = np.einsum("ki,ki->k", s.rotation[:, :, 0], s.velocity) / speed
    assert np.all(along >= np.cos(np.deg2rad(1.2)))
    yaw, pitch, roll = s.angles.T
    assert np.abs(roll).max() <= np.deg2rad(2.0) + 1e-12 and np.abs(pitch).max() < np.deg2rad(6.0)
    assert np.abs(s.angle_rates[:, 0]).max() <= 0.3
    assert np.abs(np.ptp(s.position[:, 2])) < 3.0


# ------------------------------------------------------------------ camera frames


def test_frame_times_and_truth(room_imu):
    traj, samples, truth = room_imu
    frames = frame_times(samples, 20.0)
    assert frames[0] == samples.time_stamps[0] and frames.size == 1201
    index = np.searchsorted(samples.time_stamps, frames)
    np.testing.assert_array_equal(samples.time_stamps[index], frames)  # bit for bit
    np.testing.assert_array_equal(index, np.arange(0, 12001, 10))
    ft = frame_truth(traj, frames)
    assert ft.num_frames == 1201
    np.testing.assert_array_equal(ft.world_T_imu, truth.world_T_imu[index])
    np.testing.assert_array_equal(ft.velocity, truth.velocity[index])
    np.testing.assert_array_equal(ft.angular_velocity, truth.noise_free.angular_velocity[index])
    shifted = frame_times(samples.time_stamps[3:], 20.0)
    assert shifted[0] == samples.time_stamps[3] and shifted[-1] <= samples.time_stamps[-1]


# ------------------------------------------------------------------ (e) reproducibility


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_reproducible_by_seed(name):
    t = np.linspace(0.0, 10.0, 50)
    a, b, c = make(name, 7, duration=10.0), make(name, 7, duration=10.0), make(name, 8, duration=10.0)
    sa, sb, sc = a.evaluate(t), b.evaluate(t), c.evaluate(t)
    for key in ("world_T_imu", "velocity", "acceleration", "angular_velocity"):
        np.testing.assert_array_equal(getattr(sa, key), getattr(sb, key))
        assert not np.allclose(getattr(sa, key), getattr(sc, key))
    assert a.name == f"{name}:seed7"
    i1, t1 = measure_imu(a, 200.0, seed=3)
    i2, t2 = measure_imu(b, 200.0, seed=3)
    i3, t3 = measure_imu(a, 200.0, seed=4)
    np.testing.assert_array_equal(i1.linear_acceleration, i2.linear_acceleration)
    np.testing.assert_array_equal(i1.angular_velocity, i2.angular_velocity)
    np.testing.assert_array_equal(t1.gyro_bias, t2.gyro_bias)
    assert not np.allclose(i1.linear_acceleration, i3.linear_acceleration)
    assert not np.allclose(t1.accel_bias[0], t3.accel_bias[0])
    np.testing.assert_array_equal(t1.noise_free.linear_acceleration, t3.noise_free.linear_acceleration)


def test_the_commands_bounds_of_an_inertial_scene_are_one_check(tmp_path, capsys):
    """vislam synth and vislam mc refuse the same scenarios and durations, with the same line."""
    from vislam.backend.errors import ConfigError
    from vislam.synth.inertial_scene import MAX_SECONDS, MIN_SECONDS, check_inertial_scene
    from vislam.tools.cli import main

    check_inertial_scene("room", MIN_SECONDS)
    check_inertial_scene("street", MAX_SECONDS)
    for scenario, duration, named in (("aerial", 10.0, "--scenario aerial"), ("room", MIN_SECONDS - 0.5, "--duration"),
                                      ("street", MAX_SECONDS + 1.0, "--duration")):
        with pytest.raises(ConfigError, match=named):
            check_inertial_scene(scenario, duration)
        lines = []
        for command in (["synth"], ["mc", "--runs", "2"]):
            assert main([*command, "--imu", "inertial", "--scenario", scenario, "--duration", str(duration),
                         "--out", str(tmp_path / "x")]) == 2
            lines.append(capsys.readouterr().err.strip())
        assert lines[0] == lines[1] and named in lines[0] and not (tmp_path / "x").exists()


def test_rendered_street_drive_in_the_euroc_layout_runs_end_to_end(tmp_path):
    """`vislam synth --imu inertial --scenario street --render` writes mav0/ that frontend.euroc reads
    back as the scene (samples, truth) and `vislam run` follows to 2 cm, under half of dead
    reckoning's error (4 s, 2 of them at rest)."""
    import json

    from vislam.frontend.euroc import read_euroc
    from vislam.synth.inertial_scene import InertialSceneConfig, make_inertial_scene
    from vislam.tools.cli import main

    out = tmp_path / "s"
    assert main(["synth", "--imu", "inertial", "--scenario", "street", "--duration", "4", "--render", "--out",
                 str(out), "--quiet"]) == 0
    scene = make_inertial_scene(InertialSceneConfig(scenario="street", duration=4.0, seed=0))
    data = read_euroc(out / "mav0")
    assert len(data.frames) == scene.sequence.num_steps and not data.notes
    np.testing.assert_allclose(data.frames.times, scene.sequence.time_stamps, atol=1e-9)
    np.testing.assert_array_equal(data.imu.samples.linear_acceleration, scene.sequence.imu.linear_acceleration)
    np.testing.assert_allclose(data.ground_truth.world_T_imu, scene.world_T_imu_true, atol=1e-12)
    np.testing.assert_allclose(data.ground_truth.accel_bias, scene.accel_bias_true, atol=1e-15)
    assert main(["run", str(out / "mav0"), "--out", str(tmp_path / "r"), "--quiet"]) == 0
    errors = json.loads((tmp_path / "r" / "summary.json").read_text())["errors"]
    assert errors["estimate"]["ate_rmse"] <= 0.02
    assert errors["estimate"]["ate_rmse"] < errors["dead_reckoning"]["ate_rmse"] / 2
    assert main(["synth", "--imu", "inertial", "--scenario", "room", "--render", "--out", str(tmp_path / "x")]) == 2
