"""The error model of real tracks, decided on the tracks: pixel noise growing with disparity (N5 of
``backend.run.noise``), the tracks' pixel random walk and its calibration (T3, T4 of
``backend.run.drift``), each landmark's walk by its depth (R3 of ``backend.estimator.ekf``), the
per-track test of the innovations (R4 of ``backend.estimator.tracks``), observations of unequal
noise in the compiled update (U6 of ``backend.estimator.update``) and Huber's weights (U8).

Each recovers what is planted in a synthetic scene, or equals the textbook formula it replaces."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vislam.backend.config import Config
from vislam.backend.estimator import update
from vislam.backend.estimator.ekf import VisualInertialEKF
from vislam.backend.run.decisions import DRIFT_GAPS, PAIRS_GAP1, PAIRS_LONGER, decide
from vislam.backend.run.drift import DRIFT_Z, NOISE_MIN_POINTS, growth_tests
from vislam.backend.run.noise import disparity_noise, with_disparity_noise, pixel_noise, gap_statistics
from vislam.backend.run.two_view import fit_pairs
from vislam.synth.scene import SceneConfig, make_scene
from vislam.synth.track_errors import TrackErrors
from test_ekf import CAMERA, IMU_T_CAM, NOISE, bare_config
from test_kernels import SIGMA2, _dense_H, _problem


def _scene(scenario="street", seed=3, steps=300, **errors):
    return make_scene(SceneConfig(scenario=scenario, steps=steps, seed=seed, track_errors=TrackErrors(**errors)))


# ---------------------------------------------------------------------------------------------- T3, T4
@pytest.mark.parametrize("scenario", ["street", "aerial"])
@pytest.mark.parametrize("walk", [0.2, 0.4])
def test_the_walk_of_random_walk_tracks_is_found(scenario, walk):
    """(T1-T4): tracks whose pixels random-walk walk^2 px^2 a step are found drifting, the walk is
    measured at the shortest gap (2, where the growth is already significant), and at their median
    disparity it is within 25 % of the planted one, on streets and aerial scenes alike (whose
    two-view fits absorb different shares of a walk: T4 measures it, 3.2-4.5 on streets, 2.3-3.2 on
    aerial scenes)."""
    seq = _scene(scenario, pixel_sigma=0.3, drift_walk=walk).sequence
    drift = decide(seq, Config()).drift
    assert drift.drifting and drift.source == "test" and drift.walk_gap == 2
    d = np.median(seq.obs_pixels[:, 0] - seq.obs_pixels[:, 2])
    q = drift.walk + drift.walk_per_disparity * d
    assert q == pytest.approx(walk**2, rel=0.25)
    assert (3.2 <= drift.walk_growth <= 4.5) if scenario == "street" else (2.3 <= drift.walk_growth <= 3.2)


def test_a_slow_walk_is_found_at_the_long_gap():
    """(T1, T3): a walk too slow for gaps 2-3 to show under 0.3 px of white noise (growth below 4
    standard errors there) is found at gap 10, and its walk is measured there: within a factor 2 of
    the planted one (the re-fits of T4 at gap 10 count more of a walk as absorbed than these tracks
    show: 1.4-1.8 times the planted walk on streets and aerial scenes, the safe side)."""
    seq = _scene(seed=4, pixel_sigma=0.3, drift_walk=0.08).sequence
    fits = {g: fit_pairs(seq, g, PAIRS_GAP1 if g == 1 else PAIRS_LONGER, offset=True, min_points=NOISE_MIN_POINTS)
            for g in DRIFT_GAPS}
    tests, _ = growth_tests(fits)
    assert all((tests[h][0] - 1.0) / tests[h][1] < DRIFT_Z for h in (2, 3))
    drift = decide(seq, Config()).drift
    assert drift.drifting and drift.gap == 10 and drift.walk_gap == 10
    d = np.median(seq.obs_pixels[:, 0] - seq.obs_pixels[:, 2])
    assert 0.08**2 <= drift.walk + drift.walk_per_disparity * d <= 2 * 0.08**2


def test_tracks_without_drift_get_no_walk():
    """White noise alone: no drift decided (T1), no walk, and the filter's pixel noise is the gap-1 one."""
    decisions = decide(_scene(pixel_sigma=0.5).sequence, Config())
    assert not decisions.drift.drifting
    assert decisions.drift.walk == 0.0 and decisions.drift.walk_per_disparity == 0.0
    config = decisions.config_for(Config())
    assert config.drift.pixel_walk == 0.0 and config.drift.pixel_walk_per_disparity == 0.0
    assert decisions.pixels.used_gaps == 1


def test_a_measured_walk_replaces_the_pooled_pixel_noise():
    """With a measured walk (T3) the pixel noise is the gap-1 one (the walk carries the growth beyond
    it); with a configured constant walk it is pooled over the gaps a landmark lives through."""
    seq = _scene(pixel_sigma=0.3, drift_walk=0.3).sequence
    measured = decide(seq, Config())
    assert measured.drift.walk > 0 and measured.pixels.used_gaps == 1
    constant = decide(seq, Config().with_assignments(["drift.landmark_random_walk=0.05"]))
    assert constant.pixels.used_gaps == 3 and constant.pixels.sigma > measured.pixels.sigma
    assert "0.05 m/sqrt(s) (configured)" in constant.describe(Config().with_assignments(["drift.landmark_random_walk=0.05"]))


# ---------------------------------------------------------------------------------------------- N5
def _with_disparity_noise(seq, per_disparity: float, seed: int = 0):
    """``seq`` with white noise of variance per_disparity * d added to each coordinate of every
    observation of disparity d (each observation's own draw)."""
    rng = np.random.default_rng(seed)
    z = seq.obs_pixels.copy()
    d = np.maximum(z[:, 0] - z[:, 2], 0.0)
    z += rng.normal(size=z.shape) * np.sqrt(per_disparity * d)[:, None]
    return dataclasses.replace(seq, obs_pixels=z)


def test_pixel_noise_growing_with_disparity_is_found():
    """(N5): noise of variance 0.04 + 0.01 d px^2 per coordinate is found growing, its slope within
    25 % and its intercept within 0.02 px^2; white noise alone is found not growing; the filter's
    sigma_i^2 = f (a + b d_i) averages the pooled noise at the fits' mean disparity."""
    base = _scene(pixel_sigma=0.2).sequence
    white = disparity_noise(fit_pairs(base, 1, 300, offset=True, min_points=5))
    assert white is not None and not white.growth
    seq = _with_disparity_noise(base, 0.01)
    fits = fit_pairs(seq, 1, 300, offset=True, min_points=5)
    test = disparity_noise(fits)
    assert test.growth and test.slope > 10 * test.slope_se
    assert test.slope == pytest.approx(0.01, rel=0.25)
    assert test.intercept == pytest.approx(0.04, abs=0.02)
    pooled = pixel_noise(seq, gap_statistics({1: fits}), 1, None)
    pixels = with_disparity_noise(pooled, test, None)
    assert pixels.variance(np.array([test.mean_disparity]))[0] == pytest.approx(pooled.sigma**2, rel=1e-9)
    assert pixels.variance_per_disparity > 0 and pixels.sigma < pooled.sigma
    decisions = decide(seq, Config())
    assert decisions.pixels.variance_per_disparity > 0
    assert decisions.config_for(Config()).noise.pixel_variance_per_disparity == decisions.pixels.variance_per_disparity
    assert "grows with disparity" in decisions.describe()


def test_configured_pixel_noise_is_white_unless_its_slope_is_configured():
    """A configured pixel sigma is used alone; a configured slope is used with it."""
    seq = _with_disparity_noise(_scene(pixel_sigma=0.2).sequence, 0.01)
    alone = decide(seq, Config().with_assignments(["noise.pixel_sigma=0.5"]))
    assert alone.pixels.sigma == 0.5 and alone.pixels.variance_per_disparity == 0.0
    both = decide(seq, Config().with_assignments(["noise.pixel_sigma=0.5", "noise.pixel_variance_per_disparity=0.02"]))
    assert both.pixels.sigma == 0.5 and both.pixels.variance_per_disparity == 0.02


# ---------------------------------------------------------------------------------------------- U6
def _whitened_problem(seed: int, k: int):
    """(P, dense H (3k,D), residual (k,3), off_row (k,), each observation's variance (k,), the
    innovation formed with R = SIGMA2 I and whitened to those variances) of a random problem."""
    rng = np.random.default_rng(seed)
    P, slots, H_x, H_m = _problem(rng, n_landmarks=10, k=k)
    H = _dense_H(H_x, H_m, slots, P.shape[0])
    residual = rng.normal(size=(slots.size, 3)) * 2.0
    off_row = rng.normal(size=slots.size)
    obs_var = SIGMA2 * rng.uniform(0.3, 4.0, slots.size)
    HP, S, nis = update.innovation_covariance(P, H_x, H_m, slots, SIGMA2, residual, off_row)
    inn = update.whiten(update.Innovation(residual, off_row, H_x, H_m, HP, S, nis, np.ones(slots.size, bool)),
                        obs_var, SIGMA2)
    return P, H, residual, off_row, obs_var, inn


def test_whitening_gives_the_update_with_each_observations_own_variance():
    """(U6): an innovation formed with R = ref I and whitened to obs_var gives the textbook update
    with R_i = obs_var_i I (P, dx) and the NIS r^T S_ii^-1 r + off^2 / obs_var_i of S = H P H^T + R."""
    P, H, residual, off_row, obs_var, inn = _whitened_problem(4, k=7)
    slots = np.arange(residual.shape[0])
    S_true = H @ P @ H.T + np.diag(np.repeat(obs_var, 3))
    for i in range(slots.size):
        b = slice(3 * i, 3 * i + 3)
        expected = residual[i] @ np.linalg.solve(S_true[b, b], residual[i]) + off_row[i] ** 2 / obs_var[i]
        assert inn.nis[i] == pytest.approx(expected, rel=1e-10)
    out = P.copy()
    everyone = np.ones(slots.size, dtype=bool)
    status, dx, used = update.joint_update_inplace(out, inn.HP, inn.S, inn.residual, inn.off_row, everyone,
                                                   ~everyone, SIGMA2, 1e9)
    assert status == 0 and used.all()
    K = np.linalg.solve(S_true, H @ P).T
    np.testing.assert_allclose(out, P - K @ S_true @ K.T, rtol=0, atol=1e-10 * np.abs(P).max())
    np.testing.assert_allclose(dx, K @ residual.ravel(), rtol=1e-9, atol=1e-12)


def test_the_likelihood_of_a_whitened_innovation_is_that_of_its_own_variances():
    """(L1 with U6): the log-likelihood of a whitened innovation equals the formula on S_true's
    blocks and each observation's own variance."""
    P, H, residual, off_row, obs_var, inn = _whitened_problem(5, k=6)
    slots = np.arange(residual.shape[0])
    ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, bare_config(), NOISE)
    total, tested = ekf._log_likelihood(inn, SIGMA2)
    S_true = H @ P @ H.T + np.diag(np.repeat(obs_var, 3))
    nu = 4.0
    expected = 0.0
    for i in range(slots.size):
        b = slice(3 * i, 3 * i + 3)
        n = residual[i] @ np.linalg.solve(S_true[b, b], residual[i]) + off_row[i] ** 2 / obs_var[i]
        expected += -0.5 * ((nu + 4) * np.log1p(n / nu) + np.linalg.slogdet(S_true[b, b])[1] + np.log(obs_var[i]))
    assert tested == slots.size and total == pytest.approx(expected, rel=1e-10)


# ---------------------------------------------------------------------------------------------- U8
def test_huber_weights_inflate_the_variance_between_threshold_and_gate():
    """(U8): factor 1 up to the threshold, sqrt(NIS / threshold) above it (Huber's c / d on the
    Mahalanobis distance d), 1 beyond the gate (gated anyway); None where no observation exceeds
    the threshold."""
    threshold, gate = 9.0, 18.0
    nis = np.array([0.5, 9.0, 12.0, 16.0, 18.0, 30.0])
    np.testing.assert_allclose(update.huber_inflation(nis, threshold, gate),
                               [1.0, 1.0, np.sqrt(12.0 / 9.0), 4.0 / 3.0, np.sqrt(2.0), 1.0])
    assert update.huber_inflation(np.array([0.1, 8.9, 40.0]), threshold, gate) is None


def test_huber_weights_leave_the_reported_nis_and_change_the_update_of_an_outlying_observation():
    """(U8) in the filter: one landmark's second observation moved sideways by 7 px, the others
    exact, so the step's NIS sum is that observation's, between the Huber threshold (chi-square 4
    dof, 0.95: 9.49) and the gate (0.999: 18.47): the NIS sum the health check reads is the same
    with Huber's weights as without (the noise model's), every observation is still used, and the
    pose moves less toward the moved one with the weights than without."""
    rng = np.random.default_rng(3)
    depths = rng.uniform(6.0, 30.0, 12)
    pixels = _points_at_depths(depths)
    pixels[:, 1] += rng.uniform(-60.0, 60.0, depths.size)
    pixels[:, 3] = pixels[:, 1]
    ids = np.arange(depths.size)
    moved = pixels.copy()
    moved[0, [0, 2]] += 7.0
    base = {"noise.pixel_sigma": 0.3, "drift.track_drift": "no", "update.ransac_threshold_px": 0.0}

    def second_step(values: dict):
        ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, bare_config({**base, **values}), NOISE)
        ekf.update(ids, pixels)
        ekf.predict(0.1, np.zeros(3), np.zeros(3))
        stats = ekf.update(ids, moved)
        return stats, ekf.world_T_imu[:3, 3].copy()

    plain, moved_plain = second_step({})
    huber, moved_huber = second_step({"update.huber_probability": 0.95})
    assert plain.used == huber.used == ids.size
    assert 9.49 < plain.nis_sum < 18.47
    assert huber.nis_sum == pytest.approx(plain.nis_sum, rel=1e-12)
    assert 0.0 < np.linalg.norm(moved_huber) < np.linalg.norm(moved_plain)


def test_huber_probability_is_checked():
    """``update.huber_probability`` is 0 (off) or a probability in (0.5, 1)."""
    from vislam.backend.errors import ConfigError

    assert Config().update.huber_probability == 0.0
    for bad in ("1.0", "0.3", "-0.1"):
        with pytest.raises(ConfigError, match="huber_probability"):
            Config().with_assignments([f"update.huber_probability={bad}"])


# ---------------------------------------------------------------------------------------------- R4
def test_whitened_residuals_are_the_nis_square_roots_of_the_blocks():
    """(R4): e_i = L_i^-1 r_i with S_ii = L_i L_i^T, so |e_i|^2 = r_i^T S_ii^-1 r_i, for the rows asked."""
    P, H, residual, off_row, obs_var, inn = _whitened_problem(6, k=5)
    rows = np.array([0, 2, 4])
    e = update.whitened_residuals(inn.S, inn.residual, rows)
    for j, i in enumerate(rows):
        b = slice(3 * i, 3 * i + 3)
        assert e[j] @ e[j] == pytest.approx(inn.residual[i] @ np.linalg.solve(inn.S[b, b], inn.residual[i]), rel=1e-10)
        np.testing.assert_allclose(np.linalg.cholesky(inn.S[b, b]) @ e[j], inn.residual[i], rtol=1e-10)


def test_the_track_test_rejects_a_biased_track_and_holds_its_false_alarm_rate():
    """(R4): a track whose whitened innovations are (3, 0, 0) each time is rejected at its third
    observation (T = 81 / 3 = 27 > chi2_3^-1(0.999) = 16.27), not before (n_min = 3), and stays out;
    on tracks of white N(0, I3) innovations T ~ chi2(3), so the share rejected at the third
    observation is p (20000 tracks, p = 0.01: 200 expected, 4 standard deviations allowed)."""
    from vislam.backend.estimator.tracks import TrackTest

    test = TrackTest(0.001, 3)
    ids = np.array([5, 9])
    for n in range(1, 4):
        out = test.add(ids, np.array([[3.0, 0.0, 0.0], [0.1, -0.2, 0.0]]))
        assert out.tolist() == [n == 3, False]
    assert test.admitted(np.array([9, 5, 11])).tolist() == [True, False, True] and test.rejected.sum() == 1

    rng = np.random.default_rng(0)
    white = TrackTest(0.01, 3)
    tracks = np.arange(20000)
    rejected = [white.add(tracks, rng.normal(size=(tracks.size, 3))) for _ in range(3)]
    assert not rejected[0].any() and not rejected[1].any()
    assert abs(int(rejected[2].sum()) - 200) < 4 * np.sqrt(200)


@pytest.mark.parametrize("seed", [3, 4])
def test_the_track_test_rejects_the_fast_drifting_tracks(seed):
    """(R4) in a run: on a street with 6 % bad tracks (half of them drifting 0.5-1.5 px a step) among
    tracks of 0.3 px white noise, the tracks the test rejects are mostly the fast ones (>= 80 %), it
    rejects at most 0.2 % of the good tracks, and the run says how many it rejected (summary.json and
the screen; nothing on the screen where it rejected none)."""
    from vislam.backend.run.runner import run_sequence
    from vislam.synth.track_errors import FAST, GOOD
    from vislam.tools.report import format_summary, summary_dict

    scene = _scene(seed=seed, steps=250, pixel_sigma=0.3, bad_share=0.06, bad_drift=1.0)
    seen = {}
    result = run_sequence(scene.sequence, Config().with_assignments(["drift.track_test_probability=0.001"]),
                          observer=lambda k, ekf, stats: seen.update(ekf=ekf))
    rejected = np.flatnonzero(seen["ekf"].track_test.rejected)
    kind = scene.track_errors.bad[rejected]
    assert rejected.size == result.stats.tracks_rejected > 0
    assert (kind == FAST).mean() >= 0.8
    assert (kind == GOOD).sum() <= 0.002 * (scene.track_errors.bad == GOOD).sum()
    summary = summary_dict(result, "scene")
    assert summary["landmarks"]["tracks_rejected_by_test"] == rejected.size
    assert f"the per-track test rejected {rejected.size} tracks" in format_summary(summary)
    summary["landmarks"]["tracks_rejected_by_test"] = 0
    assert "per-track test" not in format_summary(summary)


def test_the_track_test_is_off_by_default_and_checked():
    """``drift.track_test_probability`` is 0 (off: no test object in the filter) or a tail
    probability in (0, 0.5); its minimum number of observations at least 1."""
    from vislam.backend.errors import ConfigError

    ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, bare_config(), NOISE)
    assert ekf.track_test is None
    for bad in ("drift.track_test_probability=0.5", "drift.track_test_probability=-0.01",
                "drift.track_test_min_observations=0"):
        with pytest.raises(ConfigError, match="track_test"):
            Config().with_assignments([bad])


# ---------------------------------------------------------------------------------------------- R3
def _points_at_depths(depths):
    """Stereo pixels (n,4) of points straight ahead of the camera at ``depths`` (m), a little apart."""
    fx, cx, cy, b = CAMERA.fx, CAMERA.cx, CAMERA.cy, CAMERA.baseline
    z = np.asarray(depths, dtype=float)
    u = cx + 40.0 * np.arange(z.size)
    return np.column_stack([u, np.full(z.size, cy), u - fx * b / z, np.full(z.size, cy)])


def test_a_landmarks_walk_follows_its_depth():
    """(R3): one step later a landmark's variance has grown by (z/fx)^2 q_0 + q_d b z / fx per axis
    more than without the walk (z its depth in the camera); a configured constant walk q adds
    q^2 dt to every landmark alike."""
    depths = [4.0, 15.0, 60.0]
    pixels = _points_at_depths(depths)
    ids = np.arange(len(depths))
    q0, qd, dt = 0.05, 0.004, 0.1
    common = {"drift.track_drift": "yes", "drift.reanchor_observations": 0, "drift.reanchor_far_observations": 0,
              "estimator.error_model": "body", "landmarks.unbiased_triangulation": False}

    def landmark_variances(values: dict) -> np.ndarray:
        ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, bare_config({**common, **values}), NOISE)
        ekf.update(ids, pixels)
        ekf.predict(dt, np.zeros(3), np.zeros(3))
        c = ekf.state.core
        return np.diag(ekf.state.P)[c:].reshape(-1, 3)

    still = landmark_variances({"drift.pixel_walk": 0.0, "drift.pixel_walk_per_disparity": 0.0})
    walked = landmark_variances({"drift.pixel_walk": q0, "drift.pixel_walk_per_disparity": qd})
    cam_T_world = np.linalg.inv(IMU_T_CAM)  # the first pose is the world
    ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, bare_config(common), NOISE)
    ekf.update(ids, pixels)
    z = ekf.state.theta @ cam_T_world[2, :3] + cam_T_world[2, 3]
    np.testing.assert_allclose(z, depths, rtol=1e-9)  # the landmarks are where the pixels put them
    expected = (z / CAMERA.fx) ** 2 * q0 + qd * CAMERA.baseline * z / CAMERA.fx
    np.testing.assert_allclose(walked - still, np.repeat(expected[:, None], 3, axis=1), rtol=1e-6)
    constant = landmark_variances({"drift.landmark_random_walk": 0.05})
    np.testing.assert_allclose(constant - still, 0.05**2 * dt, rtol=1e-6)


def test_a_configured_walk_wins_and_is_said_to_be():
    """``drift.pixel_walk`` / ``drift.pixel_walk_per_disparity`` set: the filter takes them as given,
    the one left unset is measured, and the record says which."""
    seq = _scene(pixel_sigma=0.3, drift_walk=0.3).sequence
    measured = decide(seq, Config()).drift
    config = Config().with_assignments(["drift.pixel_walk=0.02"])
    part = decide(seq, config)
    assert part.drift.walk == 0.02 and part.drift.walk_per_disparity == measured.walk_per_disparity
    assert part.drift.walk_configured == (True, False)
    assert part.config_for(config).drift.pixel_walk == 0.02
    assert "configured where set" in part.describe(part.config_for(config))
    both = decide(seq, Config().with_assignments(["drift.pixel_walk=0.02", "drift.pixel_walk_per_disparity=0"]))
    assert (both.drift.walk, both.drift.walk_per_disparity) == (0.02, 0.0) and not np.isfinite(both.drift.walk_growth)
    assert "a step (configured)" in both.describe(both.config_for(Config()))
