"""What a run decides from the data (backend.run.decisions and the tests it runs): each decision
recovers what was planted in a synthetic scene, configured values win, and the record is applied
by OnlineRun as the whole-file run applies it."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from vislam.backend.config import Config
from vislam.backend.errors import HealthWarning
from vislam.backend.evaluation.metrics import trajectory_errors
from vislam.backend.geometry.camera import StereoCamera
from vislam.backend.run import noise
from vislam.backend.run.decisions import WHITE_NOISE, decide
from vislam.backend.run.drift import drift_test
from vislam.backend.run.likelihood import log_likelihood, with_imu
from vislam.backend.run.noise import VelocityCorrection, imu_vs_vision
from vislam.backend.run.online import OnlineRun
from vislam.backend.run.runner import run_sequence
from vislam.backend.run import two_view
from vislam.backend.run.two_view import fit_pairs, tolerances
from vislam.synth.scene import SceneConfig, make_scene
from vislam.synth.track_errors import TrackErrors


def _scene(seed=3, steps=250, **errors):
    return make_scene(SceneConfig(steps=steps, seed=seed, track_errors=TrackErrors(**errors)))


@pytest.fixture(scope="module")
def clean():
    return _scene(pixel_sigma=0.5)


@pytest.fixture(scope="module")
def clean_decisions(clean):
    return decide(clean.sequence, Config())


def test_pixel_noise_is_the_white_noise_on_clean_tracks(clean_decisions):
    """N2: 0.5 px of white noise is measured as 0.5 px (within 5 %), from two-view fits."""
    px = clean_decisions.pixels
    assert px.source == "two-view fits"
    assert px.sigma == pytest.approx(0.5, rel=0.05)


@pytest.mark.parametrize("sigma", [1.0, 1.5])
def test_noisy_pixels_are_measured_whole(sigma):
    """N2 with noisy pixels: 1 and 1.5 px of white noise are measured within 4 %, the stereo rows'
    spread too: the fits' tolerances follow the rows' own spread (fixed, 2 px of row difference is
    1.4 standard deviations of vL - vR at 1 px and left the measured noise 11 % low; a 3 px trim is 2
    standard deviations at 1.5 px)."""
    scene = _scene(seed=5, steps=120, pixel_sigma=sigma)
    px = decide(scene.sequence, Config()).pixels
    assert px.source == "two-view fits"
    assert px.sigma == pytest.approx(sigma, rel=0.04)
    assert px.rows_px == pytest.approx(sigma, rel=0.04)
    assert px.tolerance.rows_px == pytest.approx(4.5 * sigma * np.sqrt(2.0), rel=0.05)
    assert px.as_dict()["row_tolerance_px"] == px.tolerance.rows_px
    assert f"rows agree within {px.tolerance.rows_px:.3g} px" in px.describe()
    trim_said = f"residuals within {px.tolerance.trim_px:.3g} px" in px.describe()
    assert trim_said == (px.tolerance.trim_px > two_view.TRIM_PX)  # said only where the spread widened it


def test_tolerances_follow_the_rows_spread():
    """The fits' tolerances: 2 px of row difference and a 3 px trim where the rows' spread is small
    (real rectified drives, 0.2-0.3 px), |median| + 4.5 robust standard deviations of vL - vR and 3
    per pixel where that is wider; a twentieth of gross mismatches (rows 40 px apart) moves them by
    less than 8 %."""
    rng = np.random.default_rng(0)
    pixels = np.zeros((20000, 4))
    pixels[:, 1] = rng.normal(0.0, 0.25, pixels.shape[0])
    pixels[:, 3] = rng.normal(0.0, 0.25, pixels.shape[0])
    assert tolerances(pixels) == two_view.Tolerances(two_view.ROW_PX, two_view.TRIM_PX)
    pixels[:, 1] = 0.5 + rng.normal(0.0, 1.5, pixels.shape[0])  # rows offset by 0.5 px, 1.5 px noise
    pixels[:, 3] = rng.normal(0.0, 1.5, pixels.shape[0])
    expected = np.array([0.5 + 4.5 * 1.5 * np.sqrt(2.0), 3.0 * 1.5])
    np.testing.assert_allclose(tolerances(pixels).bounds(), expected, rtol=0.03)
    pixels[::20, 3] += rng.uniform(-40.0, 40.0, pixels[::20].shape[0])  # mismatched rows
    np.testing.assert_allclose(tolerances(pixels).bounds(), expected, rtol=0.08)
    assert tolerances(pixels[:5]) == two_view.Tolerances()


def test_clean_tracks_do_not_drift_and_drifting_ones_do(clean_decisions):
    """T1: the residual RMS does not grow with the gap on white noise (ratio within 5 % of 1, no
    drift decided); with drifting tracks it grows and drift is decided."""
    d = clean_decisions.drift
    assert d.source == "test" and not d.drifting
    assert d.ratio == pytest.approx(1.0, abs=0.05)
    drifting = _scene(pixel_sigma=0.3, drift_share=0.7, drift_median=0.15, drift_walk=0.1, bad_share=0.02)
    fits = {g: fit_pairs(drifting.sequence, g, 100, offset=True, min_points=5) for g in (1, 2, 3)}
    ratio, se, gap, _ = drift_test(fits)
    assert ratio > 1.1 + 4 * se and gap in (2, 3)
    assert decide(drifting.sequence, Config()).drift.drifting


def test_imu_noise_from_vision_recovers_the_scene_noise(clean_decisions):
    """N3: the IMU's white noise against the two-view motions is the scene's 0.2 m/s and 0.01 rad/s
    per axis (within 20 %); no lever arm or offset where none was planted."""
    imu = clean_decisions.imu
    assert imu.linear_source == "IMU against vision"
    np.testing.assert_allclose(imu.linear_sigma, 0.2, rtol=0.2)
    np.testing.assert_allclose(imu.angular_sigma, 0.01, rtol=0.2)
    assert not clean_decisions.velocity.active


def test_imu_noise_against_vision_needs_vision_to_be_the_small_part():
    """N3 measures the IMU only where vision is at most a quarter of the scatter: on an aerial scene
    with 0.05 m/s of white velocity noise and heavily drifting tracks, vision is nearly half of it and
    the difference comes out several times the truth; the samples' white noise (N1) is used instead,
    within 20 % of 0.05 m/s, and the record says why."""
    from vislam.synth.grid import random_spec

    spec = random_spec(703)
    assert (spec.scenario, spec.velocity_noise, spec.drift) == ("aerial", "low", "heavy")
    imu = decide(make_scene(spec.scene_config()).sequence, Config()).imu
    assert imu.vision is not None and imu.vision.vision_share > noise.VISION_SHARE_MAX
    assert np.max(imu.vision.linear_sigma) > 2 * 0.05  # what the difference would have said
    assert imu.linear_source.startswith(WHITE_NOISE)
    np.testing.assert_allclose(imu.linear_sigma, 0.05, rtol=0.2)
    assert "against vision not used" in imu.describe()


def test_planted_lever_arm_and_offset_are_found_and_removed(clean):
    """N3: velocities measured at a point 1.5 m left of and 1 m behind the frame the extrinsic defines,
    with a 0.3 m/s offset, give back that lever arm (0.3 m) and offset (0.1 m/s) in x and y, the
    correction is applied, and it brings SLAM back within 25 % of the clean run, while the
    uncorrected velocities are at least 1.5 times worse than the corrected ones."""
    seq = clean.sequence
    r, c = np.array([-1.0, 1.5, 0.0]), np.array([0.3, 0.0, 0.0])
    planted = dataclasses.replace(seq, linear_velocity=seq.linear_velocity + np.cross(seq.angular_velocity, r) + c)
    decisions = decide(planted, Config())
    assert decisions.velocity.active
    np.testing.assert_allclose(decisions.velocity.lever_arm[:2], r[:2], atol=0.3)
    np.testing.assert_allclose(decisions.velocity.offset[:2], c[:2], atol=0.1)
    gt = (seq.time_stamps, clean.world_T_imu_true)
    fixed = run_sequence(planted, decisions=decisions)
    plain = run_sequence(seq)
    ate = trajectory_errors(fixed.time_stamps, fixed.world_T_imu, *gt).ate_rmse
    assert ate <= 1.25 * trajectory_errors(plain.time_stamps, plain.world_T_imu, *gt).ate_rmse
    with pytest.warns(HealthWarning, match="scale disagrees with the IMU's"):  # H4: the IMU's 0.3 m/s is not vision's
        raw = run_sequence(planted, Config().with_assignments(["conventions.velocity_correction=no"]))
    assert trajectory_errors(raw.time_stamps, raw.world_T_imu, *gt).ate_rmse > 1.5 * ate
    assert raw.stats.scale.failed and raw.stats.scale.scale > 1.0 and not fixed.stats.scale.failed


def test_velocity_correction_is_the_lever_arm_formula():
    """v <- v - w x r - c, row by row."""
    corr = VelocityCorrection(np.array([1.0, 2.0, 3.0]), np.array([0.1, 0.2, 0.3]))
    v, w = np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 1.0]])
    np.testing.assert_allclose(corr.correct(v, w), v - np.cross(w, [1.0, 2.0, 3.0]) - [0.1, 0.2, 0.3])


def test_too_few_tracks_leave_the_imu_to_the_likelihood():
    """With a handful of tracks a step N3 has no pairs; the IMU noise is chosen by the innovation
    likelihood (L2), and the chosen linear sigma is within a factor 3 of the true 0.2 m/s."""
    sparse = make_scene(SceneConfig(steps=200, seed=4, landmark_density=0.04, track_errors=TrackErrors(pixel_sigma=0.5)))
    decisions = decide(sparse.sequence, Config())
    assert decisions.imu.vision is None
    assert decisions.imu.linear_source == "innovation likelihood"
    assert 0.2 / 3 <= np.median(decisions.imu.linear_sigma) <= 0.2 * 3


def test_likelihood_prefers_the_true_imu_noise(clean, clean_decisions):
    """L2: the Student-t innovation likelihood is higher at the true 0.2 m/s than at 0.02 or 2 m/s."""
    scores = {s: log_likelihood(clean.sequence, with_imu(clean_decisions, linear_sigma=np.full(3, s)), Config(),
                                steps=150)[0] for s in (0.02, 0.2, 2.0)}
    assert scores[0.2] > scores[0.02] and scores[0.2] > scores[2.0]


def test_likelihood_trials_do_not_warn_for_the_users_run(clean, clean_decisions):
    """A trial run of L2 is not the user's run: its health episodes (here a pixel noise 40 times too
    large, NIS far below 4) are collected, not raised as HealthWarnings."""
    import dataclasses
    import warnings

    from vislam.backend.errors import HealthWarning

    loose = dataclasses.replace(clean_decisions, pixels=dataclasses.replace(clean_decisions.pixels, sigma=20.0))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        score, tested = log_likelihood(clean.sequence, loose, Config(), steps=150)
    assert tested > 0 and np.isfinite(score)
    assert not [w for w in caught if issubclass(w.category, HealthWarning)]
    # the same decisions in a run of its own do warn: the trial above had an episode to keep quiet
    from vislam.backend.run.online import OnlineRun
    from vislam.backend.geometry.camera import StereoCamera

    run = OnlineRun(StereoCamera(clean.sequence.K, clean.sequence.baseline), loose, Config())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for k, step in enumerate(clean.sequence.steps()):
            if k >= 150:
                break
            run.step(*step)
    run.ekf.close()
    assert [w for w in caught if issubclass(w.category, HealthWarning)]


def test_likelihood_search_stops_two_candidates_past_its_peak():
    """L2's search over a noise's factors: it stops once two candidates in a row fall below the best
    before them, not at a single dip."""
    from vislam.backend.run.decisions import _past_the_peak

    assert not _past_the_peak([-3.0, -2.0, -1.0])
    assert not _past_the_peak([-3.0, -2.0, -2.5])  # one below the peak
    assert not _past_the_peak([-3.0, -2.0, -2.5, -1.5])  # a dip, then higher
    assert _past_the_peak([-3.0, -2.0, -2.5, -2.1])
    assert not _past_the_peak([-2.0, -2.0, -2.0])  # ties are not below
    # over 300 observations a candidate is below the best only by more than 2 log-likelihood units in all
    flat = [-4.38811, -4.38821, -4.38870]  # ece276a2019_0042 at pixel_sigma 1.55: 0.03 and 0.18 units below
    assert _past_the_peak(flat) and not _past_the_peak(flat, 300)
    assert _past_the_peak([-4.38811, -4.39811, -4.39911], 300)  # 3.0 and 3.3 units below
    assert not _past_the_peak([-4.38811, -4.39811, -4.38911], 300)  # the last within 0.3 units


def test_hold_error_is_left_out_where_the_truth_moves_by_the_held_samples():
    """The project's velocity-model scenes move by exactly the held twists (piecewise constant), so
    holding a sample costs nothing there: on a grid scene whose IMU noise comes from the white noise
    alone (vision dominates the comparison, N1), the innovation likelihood (L2) compares the hold
    floor (N4) with none and keeps none; the numbers are in the record. (On continuous motion it keeps
    the floor: ``test_kitti_raw.py::test_exact_velocities_cost_what_holding_them_over_a_step_costs``.)"""
    from vislam.synth.grid import scenes

    spec = next(sc for name, sc in scenes("tuning") if "s207" in name)
    seq = make_scene(spec).sequence
    imu = decide(seq, Config()).imu
    assert np.any(imu.hold_angular > imu.white_angular)  # a floor would bind ...
    table = imu.likelihood
    assert table["white noise (N1)"] > table["at least the hold error (N4)"]  # ... and is less likely
    np.testing.assert_array_equal(imu.angular_sigma, np.maximum(imu.white_angular, 1e-7))
    assert "N4 less likely" in imu.angular_source and "(N4)" not in imu.angular_source


def test_configured_values_win(clean):
    """noise.pixel_sigma and the IMU sigmas set in the configuration are used as given."""
    config = Config().with_assignments(["noise.pixel_sigma=0.8", "noise.linear_velocity_sigma=0.3",
                                        "noise.angular_velocity_sigma=0.02", "drift.track_drift=yes"])
    d = decide(clean.sequence, config)
    assert d.pixels.sigma == 0.8 and d.pixels.source == "configured"
    np.testing.assert_array_equal(d.imu.linear_sigma, 0.3)
    np.testing.assert_array_equal(d.imu.angular_sigma, 0.02)
    assert d.drift.drifting and d.drift.source == "configured"
    filt = d.config_for(config)
    assert filt.noise.pixel_sigma == 0.8 and str(filt.drift.track_drift) == "yes"


def test_record_is_serializable_and_says_each_decision(clean_decisions):
    """as_dict() is JSON; describe() has a line for each decision with its numbers."""
    json.dumps(clean_decisions.as_dict())
    text = clean_decisions.describe()
    for word in ("extrinsic", "stereo disparity offset", "IMU velocities", "IMU noise", "pixel noise", "track drift"):
        assert word in text


def test_online_run_with_the_decisions_is_the_whole_file_run(clean, clean_decisions):
    """OnlineRun stepped by hand with decide()'s record gives run_sequence's trajectory exactly."""
    seq = clean.sequence
    run = OnlineRun(StereoCamera(seq.K, seq.baseline), clean_decisions, Config())
    for step in seq.steps():
        run.step(*step)
    whole = run_sequence(seq, decisions=clean_decisions)
    np.testing.assert_allclose(run.result().world_T_imu, whole.world_T_imu, atol=1e-12)
