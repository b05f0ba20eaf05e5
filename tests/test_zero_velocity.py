"""Zero-velocity updates (``backend.estimator.zero_velocity``, Z6-Z9): each test's statistic against
its distribution at rest, the Jacobians against finite differences, the update against the Joseph
form, and runs of flights that start at rest or in motion."""

from __future__ import annotations

import numpy as np
import pytest

from vislam.backend.config import Config
from vislam.backend.data.inertial import ImuNoiseDensities, ImuSamples
from vislam.backend.estimator.inertial import BA, BG, CORE_INERTIAL, NU, PHI, InertialMean, retract_inertial
from vislam.backend.estimator.state import FilterState
from vislam.backend.estimator.state_helper import StateHelper
from vislam.backend.estimator.zero_velocity import (flow_rest_statistic, imu_rest_statistic, median_threshold,
                                                    rest_jacobian, translation_covariance, velocity_jacobian)
from vislam.backend.geometry import se3
from vislam.backend.geometry.camera import StereoCamera
from vislam.backend.run.inertial import run_inertial
from vislam.synth.inertial_scene import InertialSceneConfig, make_inertial_scene
from vislam.tools.report import format_summary

GRAVITY = np.array([0.0, 0.0, -9.81])
NOISE = ImuNoiseDensities(2e-3, 3e-3, 1.7e-4, 2e-5)


def _mean(rng) -> InertialMean:
    T = se3.exp_se3(np.r_[rng.normal(0, 1, 3), rng.normal(0, 0.5, 3)])
    return InertialMean(T, rng.normal(0, 1, 3), rng.normal(0, 0.01, 3), rng.normal(0, 0.1, 3))


@pytest.mark.parametrize("k", [5, 20, 101])
def test_the_median_threshold_is_exceeded_with_the_gate_probability(k):
    """(Z6) the median of k chi2_4 draws exceeds x_k in 1 - p of draws (p = 0.99; 40000 draws: 1 %
    within +-0.2 points, 4 standard errors)."""
    rng = np.random.default_rng(k)
    d = rng.chisquare(4, size=(40000, k))
    m = (k + 1) // 2 - 1
    medians = np.partition(d, m, axis=1)[:, m]
    share = np.mean(medians > median_threshold(k, 0.99))
    assert abs(share - 0.01) < 0.002


def test_the_flow_statistic_pairs_the_tracks_by_id():
    """(Z6) the tracks of both frames, matched by id whatever their order; their moves squared over
    2 sigma^2, the ceil(k/2)-th smallest; too few tracks: no median."""
    last_ids = np.array([3, 5, 7, 9, 11, 13])
    last = np.arange(24, dtype=float).reshape(6, 4)
    ids = np.array([20, 13, 11, 9, 7, 5])
    moves = {13: 0.1, 11: 0.5, 9: 0.2, 7: 0.4, 5: 0.3}  # each pixel of the track moves this much
    pixels = np.zeros((6, 4))
    for row, i in enumerate(ids):
        if i in moves:
            pixels[row] = last[list(last_ids).index(i)] + moves[i]
    median, rows = flow_rest_statistic(last_ids, last, ids, pixels, 0.25)
    d = sorted(4 * m**2 / 0.5 for m in moves.values())
    assert median == pytest.approx(d[2])
    assert sorted(ids[rows]) == [5, 7, 9, 11, 13]
    few, rows = flow_rest_statistic(last_ids, last, ids[:3], pixels[:3], 0.25)
    assert np.isnan(few) and rows.size == 2  # tracks 13 and 11


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_median_of_the_flow_is_numpys(seed):
    """(Z6) the compiled selection gives numpy's ceil(k/2)-th smallest, ties and odd or even k alike."""
    rng = np.random.default_rng(seed)
    for k in (5, 6, 17, 120):
        ids = rng.permutation(400)[:k].astype(np.int64)
        last = rng.normal(size=(k, 4))
        moved = last + np.round(rng.normal(size=(k, 4)), 1)  # rounded: equal moves happen
        order = rng.permutation(k)
        median, rows = flow_rest_statistic(ids, last, ids[order], moved[order], 0.5)
        d = np.sum((moved - last) ** 2, axis=1)
        assert median == pytest.approx(np.sort(d)[(k + 1) // 2 - 1])
        assert np.array_equal(np.sort(rows), np.arange(k))


def _samples_at_rest(rng, mean: InertialMean, seconds: float, rate: float, noise: ImuNoiseDensities,
                     accel=np.zeros(3)) -> ImuSamples:
    t = np.arange(0.0, seconds, 1.0 / rate)
    R = mean.world_T_imu[:3, :3]
    d = noise.discrete(1.0 / rate)
    w = mean.gyro_bias + rng.normal(0, d["gyroscope"], (t.size, 3))
    a = R.T @ (accel - GRAVITY) + mean.accel_bias + rng.normal(0, d["accelerometer"], (t.size, 3))
    return ImuSamples(t, a, w, noise)


def test_the_imu_statistic_is_chi2_at_rest_and_large_when_accelerating():
    """(Z7) from the true state, the statistic of 200 Hz samples at rest over 0.05 s intervals is
    chi2 with 6n degrees of freedom (mean 6n within 3 %, 1 % beyond the 0.99 quantile within 1 point);
    an acceleration of 0.3 m/s^2 (6x the mean's noise) is beyond it in every interval; a density of zero
    leaves nothing to test against (no degrees of freedom: not still)."""
    from scipy.special import chdtri

    rng = np.random.default_rng(1)
    mean = _mean(rng)
    imu = _samples_at_rest(rng, mean, 100.0, 200.0, NOISE)
    P = np.zeros((CORE_INERTIAL, CORE_INERTIAL))
    stats, dofs = [], []
    for t0 in np.arange(0.0, 99.9, 0.05):
        s, dof = imu_rest_statistic(imu, t0 - 1e-9, t0 + 0.05 - 1e-9, mean.world_T_imu[:3, :3], mean.gyro_bias,
                                    mean.accel_bias, P, NOISE, GRAVITY)
        stats.append(s)
        dofs.append(dof)
    stats, dofs = np.array(stats), np.array(dofs)
    assert np.all(dofs == 60)
    assert abs(stats.mean() / 60 - 1) < 0.03
    assert abs(np.mean(stats > chdtri(60, 0.01)) - 0.01) < 0.01
    silent = ImuNoiseDensities(0.0, 0.0, 1e-3, 0.0)  # no accelerometer noise to test against: not tested
    assert imu_rest_statistic(imu, 0.0, 0.05, mean.world_T_imu[:3, :3], mean.gyro_bias, mean.accel_bias, P, silent,
                              GRAVITY)[1] == 0
    moving = _samples_at_rest(rng, mean, 2.0, 200.0, NOISE, accel=np.array([0.3, 0.0, 0.0]))
    for t0 in np.arange(0.0, 1.9, 0.05):
        s, dof = imu_rest_statistic(moving, t0 - 1e-9, t0 + 0.05 - 1e-9, mean.world_T_imu[:3, :3], mean.gyro_bias,
                                    mean.accel_bias, P, NOISE, GRAVITY)
        assert s > chdtri(dof, 0.001)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_rest_and_velocity_jacobians_against_finite_differences(seed):
    """(Z7, Z8) with the truth X = exp(dx) X_hat (J7), the mean residuals at rest made by the truth and
    taken at the estimate are H_i dx, and the true velocity is v_hat + H_v dx, to first order
    (relative error < 1e-4 for |dx| ~ 1e-5)."""
    rng = np.random.default_rng(seed)
    est = _mean(rng)
    for _ in range(3):
        dx = np.zeros(CORE_INERTIAL)
        dx[:] = rng.normal(0, 1e-5, CORE_INERTIAL)
        true = retract_inertial(est, np.zeros((0, 3)), dx)
        # at rest: w_m = b_g, a_m = -R^T g + b_a (noise-free), residuals at the estimate
        R, R_hat = true.world_T_imu[:3, :3], est.world_T_imu[:3, :3]
        r = np.r_[true.gyro_bias - est.gyro_bias, -R.T @ GRAVITY + true.accel_bias - est.accel_bias + R_hat.T @ GRAVITY]
        H = rest_jacobian(R_hat, GRAVITY, CORE_INERTIAL)
        assert np.linalg.norm(r - H @ dx) < 1e-4 * np.linalg.norm(r)
        dv = true.velocity - est.velocity
        Hv = velocity_jacobian(est.velocity, CORE_INERTIAL)
        assert np.linalg.norm(dv - Hv @ dx) < 1e-4 * np.linalg.norm(dv)
    assert np.all(rest_jacobian(R_hat, GRAVITY, CORE_INERTIAL)[:, NU] == 0)  # rest says nothing of v itself
    assert np.all(velocity_jacobian(est.velocity, CORE_INERTIAL)[:, BG] == 0)
    assert np.all(velocity_jacobian(est.velocity, CORE_INERTIAL)[:, BA] == 0)


def test_the_translation_covariance_is_the_inverse_information_of_the_stereo_projection():
    """(Z8) C_t = 2 sigma^2 (sum_i J_i^T J_i)^-1 with J_i the finite-difference Jacobian of the stereo
    pixels of s_i - t in t (the camera's own projection, S1); tracks without disparity add nothing."""
    rng = np.random.default_rng(4)
    cam = StereoCamera(np.array([[450.0, 0, 370.0], [0, 440.0, 240.0], [0, 0, 1]]), 0.11)
    s = np.c_[rng.uniform(-2, 2, (30, 2)), rng.uniform(1.5, 12, 30)]
    pixels = np.array([cam.project(p) for p in s])
    info = np.zeros((3, 3))
    for p in s:
        J = np.column_stack([(cam.project(p - e * 1e-6) - cam.project(p + e * 1e-6)) / 2e-6 for e in np.eye(3)])
        info += J.T @ J
    C = translation_covariance(pixels, cam, 0.09)
    np.testing.assert_allclose(C, 2 * 0.09 * np.linalg.inv(info), rtol=1e-5)
    far = pixels.copy()
    far[:, 2] = far[:, 0]  # no disparity
    assert translation_covariance(far, cam, 0.09) is None
    both = np.r_[pixels, far[:3]]
    np.testing.assert_allclose(translation_covariance(both, cam, 0.09), C)


def test_update_dense_is_the_joseph_update():
    """(Z9) dx = K r and P <- P - P H^T S^-1 H P equal the Joseph form (I - K H) P (I - K H)^T + K R K^T
    for a state of core and landmark rows, H on the core only."""
    rng = np.random.default_rng(5)
    D = CORE_INERTIAL + 12
    A = rng.normal(size=(D, D))
    P = A @ A.T + np.eye(D)
    H_core = rng.normal(size=(3, CORE_INERTIAL))
    H = np.zeros((3, D))
    H[:, :CORE_INERTIAL] = H_core
    R = np.diag([0.3, 0.5, 0.7])
    r = rng.normal(size=3)
    state = FilterState(mu=np.eye(4), gyro_bias=np.zeros(3), core=CORE_INERTIAL)
    state.P = P.copy()
    dx = StateHelper.update_dense(state, H_core, r, H @ P @ H.T + R)
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
    IKH = np.eye(D) - K @ H
    np.testing.assert_allclose(dx, K @ r, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(state.P, IKH @ P @ IKH.T + K @ R @ K.T, rtol=1e-8, atol=1e-10)
    assert np.array_equal(state.P, state.P.T)


def _stills(scene, **values):
    stills = []
    config = Config().with_values(values) if values else Config()
    res = run_inertial(scene.sequence, config, observer=lambda k, ekf, st: stills.append(bool(st and st.still)))
    return np.array(stills), res


@pytest.fixture(scope="module")
def rest_then_flight():
    return make_inertial_scene(InertialSceneConfig(duration=5.0, seed=2, start_at_rest=2.0), noise_seed=7)


def test_a_flight_standing_still_first_is_found_still_until_it_moves(rest_then_flight):
    """(Z6-Z8) 2 s at rest, then a smooth take-off (the acceleration grows from zero): at least 90 % of the
    40 intervals at rest are still, none later than 0.25 s after the take-off; the run counts them,
    says so, and with ``update.zero_velocity = false`` none is."""
    stills, res = _stills(rest_then_flight)
    t = rest_then_flight.sequence.time_stamps - rest_then_flight.sequence.time_stamps[0]
    assert stills[1:41].mean() >= 0.9
    assert not stills[t > 2.25].any()
    assert res.stats.still_frames == stills.sum()
    summary = {"steps": res.stats.steps, "observations": {"used": 1, "gated_share": 0.0, "still_frames": int(stills.sum())},
               "landmarks": {"mapped": 0, "active_mean": 0.0, "active_max": 0}, "mean_nis_per_observation": 4.0,
               "timing": {"run_seconds": 1.0, "sequence_seconds": 5.0, "real_time_factor": 5.0}}
    assert f"standing still at {stills.sum()} of {res.stats.steps} frames" in format_summary(summary)
    assert "standing still" not in format_summary({**summary, "observations": {**summary["observations"], "still_frames": 0}})
    off, res_off = _stills(rest_then_flight, **{"update.zero_velocity": False})
    assert not off.any() and res_off.stats.still_frames == 0


def test_a_flight_in_motion_is_never_still():
    """A flight moving from its first frame (the room's smooth path, ~1 m/s): no frame is still."""
    scene = make_inertial_scene(InertialSceneConfig(duration=4.0, seed=3, start_at_rest=None), noise_seed=8)
    stills, _ = _stills(scene)
    assert not stills.any()
