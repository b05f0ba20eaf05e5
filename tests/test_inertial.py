"""The inertial propagation (backend.estimator.inertial, J1-J7): closed-form motions, the error
transition against finite differences, the noise against Monte Carlo, and the real EuRoC IMU."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vislam.backend.data.inertial import ADIS16448, ImuNoiseDensities, ImuSamples
from vislam.backend.estimator import inertial as ine
from vislam.backend.geometry import se3

G = np.array([0.0, 0.0, -9.81])
QUIET = ImuNoiseDensities(1e-12, 1e-12, 1e-12, 1e-12, "none")


def _mean(R=None, v=None, p=None, bg=None, ba=None) -> ine.InertialMean:
    T = np.eye(4)
    T[:3, :3] = np.eye(3) if R is None else R
    T[:3, 3] = np.zeros(3) if p is None else p
    z = np.zeros(3)
    return ine.InertialMean(T, z.copy() if v is None else np.array(v, float), z.copy() if bg is None else np.array(bg, float),
                            z.copy() if ba is None else np.array(ba, float))


def _samples(t, acc, gyr) -> ImuSamples:
    return ImuSamples(np.asarray(t, float), np.asarray(acc, float), np.asarray(gyr, float))


def _error(X: ine.InertialMean, Xh: ine.InertialMean) -> np.ndarray:
    """(J1) inverted: the error state [rho, phi, db_g, nu, db_a] of X against the estimate Xh."""
    Re = X.world_T_imu[:3, :3] @ Xh.world_T_imu[:3, :3].T
    phi = se3.log_so3(Re)
    Jinv = np.linalg.inv(se3.left_jacobian_so3(phi))
    rho = Jinv @ (X.world_T_imu[:3, 3] - Re @ Xh.world_T_imu[:3, 3])
    nu = Jinv @ (X.velocity - Re @ Xh.velocity)
    return np.concatenate([rho, phi, X.gyro_bias - Xh.gyro_bias, nu, X.accel_bias - Xh.accel_bias])


def test_constant_specific_force_and_rate_match_closed_form():
    """At rest the specific force cancels gravity; a constant body acceleration with no rotation gives
    p = a t^2 / 2; a constant rate gives R = Exp(w t) (J3), whatever the sample rate."""
    t = np.linspace(0.0, 2.0, 401)
    R0 = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    rest = _samples(t, np.tile(R0.T @ -G, (t.size, 1)), np.zeros((t.size, 3)))
    out, _ = ine.propagate(_mean(R=R0), rest, 0.0, 2.0, QUIET, G)
    assert np.abs(out.world_T_imu[:3, 3]).max() < 1e-12 and np.abs(out.velocity).max() < 1e-12

    a_body = np.array([0.5, -0.2, 0.1])
    push = _samples(t, np.tile(a_body - R0.T @ G, (t.size, 1)), np.zeros((t.size, 3)))
    out, _ = ine.propagate(_mean(R=R0, v=[1.0, 0, 0]), push, 0.0, 1.3, QUIET, G)
    a_world = R0 @ a_body
    np.testing.assert_allclose(out.velocity, [1.0, 0, 0] + a_world * 1.3, atol=1e-12)
    np.testing.assert_allclose(out.world_T_imu[:3, 3], np.array([1.0, 0, 0]) * 1.3 + a_world * 1.3**2 / 2, atol=1e-12)

    w = np.array([0.2, -0.5, 1.1])
    spin = _samples(t, np.zeros((t.size, 3)), np.tile(w, (t.size, 1)))
    out, _ = ine.propagate(_mean(R=R0), spin, 0.0, 1.7, QUIET, np.zeros(3))
    np.testing.assert_allclose(out.world_T_imu[:3, :3], R0 @ Rotation.from_rotvec(w * 1.7).as_matrix(), atol=1e-12)


def test_circle_at_constant_speed_is_exact():
    """A body turning at rate w about z with forward speed s (centripetal specific force): the closed
    form (J3) follows the circle exactly at any sample rate (no integration error)."""
    w, s = 0.8, 2.0
    for rate in (10.0, 200.0):
        t = np.arange(0.0, 5.0 + 1e-9, 1.0 / rate)
        acc = np.tile([0.0, s * w, 9.81], (t.size, 1))  # body frame: centripetal to the left, gravity up
        gyr = np.tile([0.0, 0.0, w], (t.size, 1))
        out, _ = ine.propagate(_mean(v=[s, 0, 0]), _samples(t, acc, gyr), 0.0, 5.0, QUIET, G)
        yaw = w * 5.0
        expected = np.array([s / w * np.sin(yaw), s / w * (1 - np.cos(yaw)), 0.0])
        np.testing.assert_allclose(out.world_T_imu[:3, 3], expected, atol=1e-9)
        np.testing.assert_allclose(out.velocity, s * np.array([np.cos(yaw), np.sin(yaw), 0]), atol=1e-9)


def _random_motion(rng, rate=200.0, duration=0.5):
    t = np.arange(0.0, duration + 1e-9, 1.0 / rate)
    f = np.array([0.3, 1.1, 2.3])
    acc = np.stack([np.sin(f[i] * t + i) * 2.0 for i in range(3)], 1) + [0.0, 0.0, 9.81]
    gyr = np.stack([np.cos(f[i] * t * 1.3 + i) * 0.8 for i in range(3)], 1)
    return _samples(t + 0.0, acc, gyr)


@pytest.mark.parametrize("rate", [200.0, 20.0])
def test_error_transition_matches_finite_differences(rate):
    """(J4, J5) Phi against central differences of the mean propagation in the error coordinates (J1):
    perturb the start by each error direction, propagate, measure the error at the end."""
    rng = np.random.default_rng(3)
    imu = _random_motion(rng, rate=rate)
    R0 = Rotation.from_rotvec([0.2, 0.4, -0.3]).as_matrix()
    X0 = _mean(R=R0, v=[1.0, -0.5, 0.3], p=[3.0, -2.0, 1.0], bg=[0.01, -0.02, 0.005], ba=[0.05, 0.02, -0.03])
    end = 0.5
    Xh, prop = ine.propagate(X0, imu, 0.0, end, QUIET, G)
    h = 1e-6
    num = np.zeros((15, 15))
    for j in range(15):
        d = np.zeros(15)
        d[j] = h
        Xp, _ = ine.propagate(ine.retract_inertial(X0, np.zeros((0, 3)), d), imu, 0.0, end, QUIET, G)
        Xm, _ = ine.propagate(ine.retract_inertial(X0, np.zeros((0, 3)), -d), imu, 0.0, end, QUIET, G)
        num[:, j] = (_error(Xp, Xh) - _error(Xm, Xh)) / (2 * h)
    # the bias columns are linearized at each interval's midpoint: second order in dt
    tol = 1e-5 if rate == 200.0 else 1e-3
    np.testing.assert_allclose(prop.Phi, num, atol=tol * max(1.0, np.abs(num).max()))
    # and the autonomous block (rho, phi, nu) is exact, independent of the estimate
    blk = np.r_[0:6, 9:12]
    np.testing.assert_allclose(prop.Phi[np.ix_(blk, blk)], num[np.ix_(blk, blk)], atol=1e-6)


def test_noise_matches_monte_carlo():
    """(J5) Q against the spread of 3000 propagations of the true start with noisy samples (white
    noise density/sqrt(dt) per sample, biases walking): error NEES mean 15 within its 99 % band."""
    rng = np.random.default_rng(7)
    rate, end = 100.0, 1.0
    clean = _random_motion(rng, rate=rate, duration=end)
    noise = ImuNoiseDensities(0.05, 0.02, 0.005, 0.001, "test")
    X0 = _mean(v=[1.0, 0.0, 0.0], p=[1.0, 2.0, 0.5])
    Xh, prop = ine.propagate(X0, clean, 0.0, end, noise, G)
    dt = 1.0 / rate
    n = clean.num_samples
    runs = 3000
    errs = np.empty((runs, 15))
    for r in range(runs):
        bg = np.cumsum(rng.standard_normal((n, 3)) * noise.gyroscope_random_walk * np.sqrt(dt), 0)
        ba = np.cumsum(rng.standard_normal((n, 3)) * noise.accelerometer_random_walk * np.sqrt(dt), 0)
        bg -= bg[0]
        ba -= ba[0]
        # the truth moves by the clean samples minus the noise: measured = clean, truth = clean - n - b
        acc = clean.linear_acceleration - rng.standard_normal((n, 3)) * noise.accelerometer_noise_density / np.sqrt(dt) - ba
        gyr = clean.angular_velocity - rng.standard_normal((n, 3)) * noise.gyroscope_noise_density / np.sqrt(dt) - bg
        X, _ = ine.propagate(X0, _samples(clean.time_stamps, acc, gyr), 0.0, end, QUIET, G)
        X.gyro_bias, X.accel_bias = bg[-1], ba[-1]
        errs[r] = _error(X, Xh)
    nees = np.einsum("ri,ij,rj->r", errs, np.linalg.inv(prop.Q), errs)
    band = 15 + 2.58 * np.sqrt(2 * 15 / runs)
    assert abs(nees.mean() - 15) < band - 15, nees.mean()


def test_initialization_at_rest_recovers_tilt_and_its_bias_correlation():
    """(Z1-Z4) synthetic rest: a tilted IMU, a gyro bias and a horizontal accelerometer bias. The gyro
    bias is the mean rate; the estimated attitude is off by exactly the tilt the accelerometer bias fakes,
    and that error is the one the covariance's phi-b_a correlation predicts (phi = C db_a)."""
    from vislam.backend.run.initialization import initialize_at_rest

    rng = np.random.default_rng(11)
    t = np.arange(0.0, 1.5, 0.005)
    R0 = Rotation.from_rotvec([0.3, -0.25, 2.0]).as_matrix()
    b_g = np.array([0.01, -0.02, 0.005])
    b_a = np.array([0.04, -0.03, 0.02])
    acc = np.tile(R0.T @ -G + b_a, (t.size, 1)) + rng.standard_normal((t.size, 3)) * 1e-4
    gyr = np.tile(b_g, (t.size, 1)) + rng.standard_normal((t.size, 3)) * 1e-5
    ini = initialize_at_rest(_samples(t, acc, gyr), 0.0, G)
    assert ini.at_rest
    np.testing.assert_allclose(ini.mean.gyro_bias, b_g, atol=1e-5)
    Rh = ini.mean.world_T_imu[:3, :3]
    # the true attitude in the estimate's (yaw-free) world: same up axis up to the bias's tilt
    up_true = R0.T @ [0, 0, 1.0]
    tilt = np.degrees(np.arccos(up_true @ (Rh.T @ [0, 0, 1.0])))
    assert 0.1 < tilt < 0.5  # |b_a horizontal| / g = 0.29 deg
    # the covariance's prediction of that error (Z4): R_true = Exp(phi) R_hat with phi = C db_a and
    # db_a = b_a - 0; roll and pitch of phi from where the true up axis lies in the estimate's world,
    # Exp(-phi) e_z = R_hat up_true:  phi_x = u_y, phi_y = -u_x
    P = ini.covariance
    C = P[ine.PHI, ine.BA] / P[12, 12]
    u = Rh @ up_true
    np.testing.assert_allclose((C @ b_a)[:2], [u[1], -u[0]], atol=2e-5)
    assert np.all(np.linalg.eigvalsh(P) > -1e-15)


def test_landmark_rows_follow_the_rotation_error():
    """(J6) the block formulas equal the dense F P F^T + G Q G^T with landmark rows zeta' = zeta +
    m^ (phi' - phi); and that row is the first-order change of (J1) for a static landmark whose
    estimate is held while phi changes (finite differences)."""
    rng = np.random.default_rng(5)
    imu = _random_motion(rng, rate=100.0)
    X0 = _mean(R=Rotation.from_rotvec([0.1, 0.2, 0.3]).as_matrix(), v=[1.0, 0, 0], bg=[0.01, 0, 0])
    _, prop = ine.propagate(X0, imu, 0.0, 0.4, ImuNoiseDensities(0.01, 0.02, 0.003, 0.001), G)
    K = 4
    points = rng.normal(size=(K, 3)) * 5
    D = 15 + 3 * K
    A = rng.normal(size=(D, D))
    P = A @ A.T
    L = np.concatenate([se3.hat3(m) for m in points])
    Delta = prop.Phi[3:6].copy()
    Delta[:, 3:6] -= np.eye(3)
    F = np.eye(D)
    F[:15, :15] = prop.Phi
    F[15:, :15] = L @ Delta
    W = np.zeros((D, 15))  # the noise: core w, landmarks L w_phi
    W[:15] = np.eye(15)
    W[15:, 3:6] = L
    dense = F @ P @ F.T + W @ prop.Q @ W.T
    np.testing.assert_allclose(ine.propagate_covariance(P, prop, points), dense, rtol=1e-10, atol=1e-10)
    # zeta' - zeta = m^ dphi: hold m_hat and the true m, change the rotation error by dphi
    m_hat, zeta, phi = points[0], np.zeros(3), np.zeros(3)  # at the linearization point
    E, J = se3.exp_so3_and_left_jacobian(phi)
    m_true = E @ m_hat + J @ zeta
    dphi = np.array([1e-4, 2e-4, -1e-4])
    E2, J2 = se3.exp_so3_and_left_jacobian(phi + dphi)
    zeta2 = np.linalg.solve(J2, m_true - E2 @ m_hat)
    np.testing.assert_allclose(zeta2 - zeta, se3.hat3(m_hat) @ dphi, atol=1e-6)


def test_propagation_follows_the_synthetic_generator():
    """An independent check of the conventions (specific force sign, gravity, body rates): noise-free
    samples of synth.inertial's room flight, propagated from its true state with its true biases, stay
    on its trajectory (2.4 um after 2 s measured: the mean of bounding samples is second order)."""
    from vislam.synth.inertial import frame_times, frame_truth, measure_imu, room

    traj = room(20.0, seed=1, start_at_rest=2.0)
    imu, truth = measure_imu(traj, 200.0, noise=None, seed=1)
    frames = frame_truth(traj, frame_times(imu, 20.0))
    i0, i1 = 40, 80
    X0 = ine.InertialMean(frames.world_T_imu[i0].copy(), frames.velocity[i0].copy(), truth.gyro_bias[0].copy(),
                          truth.accel_bias[0].copy())
    X1, _ = ine.propagate(X0, imu, frames.time_stamps[i0], frames.time_stamps[i1], ADIS16448, G)
    assert np.linalg.norm(X1.world_T_imu[:3, 3] - frames.world_T_imu[i1][:3, 3]) < 1e-4
    assert np.linalg.norm(X1.velocity - frames.velocity[i1]) < 1e-4
    rot = Rotation.from_matrix(X1.world_T_imu[:3, :3].T @ frames.world_T_imu[i1][:3, :3]).magnitude()
    assert rot < 1e-5


def test_interval_knots_interpolate_the_ends_and_serve_only_their_samples():
    """The knots of [t0, t1]: t0, the samples strictly inside, t1, the ends interpolated linearly
    (np.interp, held beyond the record); asked again for the same samples and interval the same
    knots come back, and other samples with the same stamps get their own."""
    interval_knots = ine.interval_knots
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.004, 0.006, 50))
    a, w = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    imu = ImuSamples(t, a, w, None)
    for t0, t1 in ((t[3] + 0.001, t[9] - 0.0005), (t[5], t[11]), (t[0] - 0.01, t[2] + 0.001), (t[47], t[-1] + 0.02)):
        times, acc, gyr = interval_knots(imu, t0, t1)
        inside = (t > t0) & (t < t1)
        np.testing.assert_array_equal(times, np.r_[t0, t[inside], t1])
        for x, got in ((a, acc), (w, gyr)):
            expected = np.stack([np.interp(times, t, x[:, i]) for i in range(3)], axis=1)
            np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)
        assert interval_knots(imu, t0, t1)[1] is acc
        other = ImuSamples(t, a + 1.0, w, None)
        np.testing.assert_allclose(interval_knots(other, t0, t1)[1], acc + 1.0, rtol=0, atol=1e-12)
