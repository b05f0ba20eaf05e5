"""Tests of the synthetic track errors (vislam.synth.track_errors) and the scene grid (vislam.synth.grid):
each effect alone is measured back from the observations against the scene's ground truth; the
defaults leave every scene as it was; the files and the command carry the true values."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pickle

import numpy as np
import pytest
from scipy import stats

from helpers import assert_same_scene_arrays
from vislam.backend.data.npz import load_sequence
from vislam.backend.errors import ConfigError
from vislam.backend.geometry import se3
from vislam.backend.run.timing import repeated_steps
from vislam.synth import grid
from vislam.synth.scene import Scene, SceneConfig, SceneFactory, make_scene, write_scene
from vislam.synth.track_errors import FAST, GOOD, JUMP, KITTI_LIKE, PRESETS, TrackErrors
from vislam.tools.cli import main

STEPS = 300
FX = 718.856  # px, the default rig's focal length


def obs_steps(seq) -> np.ndarray:
    return np.repeat(np.arange(seq.num_steps), np.diff(seq.obs_ptr))


def projected(scene: Scene, world_T_imu: np.ndarray, jitter: np.ndarray | None = None) -> np.ndarray:
    """(L,4) the exact pixels of each observation's point from the poses (N,4,4), jittered by (N,6) xi."""
    seq = scene.sequence
    cam_T_world = se3.inverse(seq.imu_T_cam) @ se3.inverse(world_T_imu)
    if jitter is not None:
        cam_T_world = se3.exp_se3_batch(jitter) @ cam_T_world
    T = cam_T_world[obs_steps(seq)]
    q = np.einsum("nij,nj->ni", T[:, :3, :3], scene.landmark_positions[seq.obs_ids]) + T[:, :3, 3]
    return scene.config.calibration.camera.project(q)


def scene_with(steps: int = STEPS, seed: int = 5, **errors) -> Scene:
    return make_scene(SceneConfig(steps=steps, seed=seed, track_errors=TrackErrors(**errors)))


def track_slopes(scene: Scene, residual: np.ndarray, min_length: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """(ids, slopes (T,2) px/step): the least-squares slope of each track's left-image residual over
    its age, for tracks of at least ``min_length`` observations (no repeats: age = step - first step)."""
    seq = scene.sequence
    ids, steps = seq.obs_ids, obs_steps(seq)
    first = np.full(seq.num_features, seq.num_steps)
    np.minimum.at(first, ids, steps)
    age = (steps - first[ids]).astype(float)
    count = np.bincount(ids, minlength=seq.num_features).astype(float)
    keep = count >= min_length
    mean_age = np.bincount(ids, age, minlength=seq.num_features) / np.maximum(count, 1)
    da = age - mean_age[ids]
    saa = np.bincount(ids, da * da, minlength=seq.num_features)
    slopes = np.stack([np.bincount(ids, da * residual[:, c], minlength=seq.num_features) for c in (0, 1)], axis=1)
    return np.flatnonzero(keep), slopes[keep] / saa[keep, None]


# ------------------------------------------------------------------ defaults and streams

#: make_scene(SceneConfig(steps=60, seed=4)) as the scenes were before track errors existed: sha256
#: (16 hex) of obs_ids and obs_ptr, the sum of obs_pixels, the number of observations
DEFAULT_SCENE_PRINT = ("46f8e864c68034fd", 7173253.638935158, 4842)

def assert_identical(a: Scene, b: Scene) -> None:
    assert_same_scene_arrays(a, b)
    assert a.sequence.tracker == b.sequence.tracker


def test_default_scene_is_as_before():
    """The default scene (no track errors) has the observations it had before track errors existed."""
    seq = make_scene(SceneConfig(steps=60, seed=4)).sequence
    digest = hashlib.sha256(seq.obs_ids.tobytes() + seq.obs_ptr.tobytes()).hexdigest()[:16]
    assert (digest, seq.num_observations) == (DEFAULT_SCENE_PRINT[0], DEFAULT_SCENE_PRINT[2])
    np.testing.assert_allclose(seq.obs_pixels.sum(), DEFAULT_SCENE_PRINT[1], rtol=1e-12)


@pytest.mark.parametrize("scenario", ["street", "aerial"])
def test_all_off_track_errors_are_bit_identical_to_the_default(scenario):
    """Explicit all-off TrackErrors, with any shape parameters of the switched-off effects, give the
    default scene array for array; its truth is empty and its tracker is "synthetic"."""
    base = SceneConfig(scenario=scenario, steps=120, seed=6, outlier_share=0.05, pixel_sigma=0.3)
    default = make_scene(base)
    shapes = TrackErrors(pixel_sigma=0.3, outlier_share=0.05, drift_median=0.3, drift_log_sigma=2.0, bad_jump=9.0,
                         bad_drift=3.0, jitter_correlation=0.9)
    for errors in (TrackErrors(pixel_sigma=0.3, outlier_share=0.05), shapes):
        assert_identical(make_scene(dataclasses.replace(base, track_errors=errors)), default)
    truth = default.track_errors
    assert default.sequence.tracker == "synthetic" and not truth.repeated.any()
    np.testing.assert_array_equal(truth.world_T_imu_content, default.world_T_imu_true)
    assert not (truth.jitter.any() or truth.drift_velocity.any() or truth.bad.any() or truth.jump.any())
    assert np.all(truth.jump_step == -1) and truth.bad.shape == default.landmark_ids.shape


def test_drift_changes_no_other_draw():
    """Drift draws from its own streams: the first observation of every track (age 0, no offset
    yet), the ids that start there, the IMU and the geometry are those of the scene without drift."""
    plain = scene_with(steps=150, pixel_sigma=0.25)
    drift = scene_with(steps=150, pixel_sigma=0.25, drift_share=0.7, drift_walk=0.05, bad_share=0.05)
    for name in ("world_T_imu_true", "landmark_positions", "landmark_point_index"):
        np.testing.assert_array_equal(getattr(plain, name), getattr(drift, name))
    for name in ("linear_velocity", "angular_velocity"):
        np.testing.assert_array_equal(getattr(plain.sequence, name), getattr(drift.sequence, name))

    def firsts(scene):
        seq = scene.sequence
        _, where = np.unique(seq.obs_ids, return_index=True)  # CSR is sorted by step: first occurrence
        return seq.obs_pixels[where]

    np.testing.assert_array_equal(firsts(plain), firsts(drift))
    assert drift.sequence.num_observations < plain.sequence.num_observations  # tracks that drift out end early


def test_scene_config_keywords_and_track_errors_agree():
    """pixel_sigma/outlier_share keywords replace track_errors' values and read back (replace() passes
    them on: with_track_errors swaps every error); configs pickle (Monte Carlo workers) and as_dict
    is plain JSON."""
    config = SceneConfig(pixel_sigma=0.7, track_errors=KITTI_LIKE)
    assert config.pixel_sigma == 0.7 == config.track_errors.pixel_sigma
    assert config.track_errors.drift_share == KITTI_LIKE.drift_share
    assert dataclasses.replace(config, pixel_sigma=0.3).track_errors == dataclasses.replace(KITTI_LIKE, pixel_sigma=0.3)
    kept = dataclasses.replace(SceneConfig(pixel_sigma=0.7), track_errors=KITTI_LIKE)
    assert kept.pixel_sigma == 0.7 and kept.track_errors.drift_share == 0.7
    swapped = SceneConfig(pixel_sigma=0.7, outlier_share=0.1).with_track_errors(KITTI_LIKE)
    assert swapped.pixel_sigma == 0.25 and swapped.outlier_share == 0.0 and swapped.track_errors == KITTI_LIKE
    assert dataclasses.replace(swapped, gyro_bias=(0.0, 0.0, 0.0)).track_errors == KITTI_LIKE
    assert pickle.loads(pickle.dumps(SceneFactory(swapped))) == SceneFactory(swapped)
    data = json.loads(json.dumps(swapped.as_dict()))
    assert data["pixel_sigma"] == 0.25 and data["track_errors"]["repeat_interval"] == 12.0
    assert swapped.filter_config().noise.pixel_sigma == 0.25


def test_scene_factory_draws_the_track_errors_from_the_noise_seed():
    """SceneFactory(config)(s) is make_scene(config, noise_seed=s), track errors included: the geometry
    stays, the drawn errors change with the noise seed."""
    config = SceneConfig(steps=60, seed=3, landmark_density=0.5, track_errors=KITTI_LIKE)
    a, b = SceneFactory(config)(11), make_scene(config, noise_seed=11)
    assert_identical(a, b)
    np.testing.assert_array_equal(a.track_errors.repeated, b.track_errors.repeated)
    c = make_scene(config)
    np.testing.assert_array_equal(a.points, c.points)
    assert not np.array_equal(a.track_errors.repeated, c.track_errors.repeated)


@pytest.mark.parametrize("bad", [
    dict(drift_share=1.5), dict(bad_share=-0.1), dict(pixel_sigma=-1.0), dict(drift_median=0.0),
    dict(repeat_interval=1.0), dict(jitter_correlation=1.0), dict(jitter_rotation=-1e-4), dict(disparity_offset=np.inf),
    dict(drift_walk="0.1"),
])
def test_bad_values_are_refused_naming_the_option(bad):
    (key,) = bad
    with pytest.raises(ConfigError) as exc:
        TrackErrors(**bad)
    assert key in str(exc.value) and "\n" not in str(exc.value)


def test_assignments_are_parsed_as_the_track_errors_table():
    errors = KITTI_LIKE.with_assignments(["drift_share=0.5", "track_errors.repeat_interval=0", "jitter-rotation=1e-4"])
    assert (errors.drift_share, errors.repeat_interval, errors.jitter_rotation) == (0.5, 0.0, 1e-4)
    assert errors.pixel_sigma == 0.25  # the preset's, untouched
    for item, words in (("nope=1", "track_errors.nope"), ("drift_share=lots", "expected a number"),
                        ("drift_share", "expected KEY=VALUE"), ("drift_share=2", "drift_share must be in [0, 1]")):
        with pytest.raises(ConfigError, match=words.replace("[", r"\[").replace("]", r"\]")):
            TrackErrors().with_assignments([item])


def test_kitti_like_preset():
    """The preset's values, and its drift distribution: 70 % of tracks drift, median 0.05 px/step,
    a few % of all tracks faster than 0.5 px/step."""
    assert PRESETS["none"] == TrackErrors() and PRESETS["kitti-like"] is KITTI_LIKE
    assert dataclasses.asdict(KITTI_LIKE) == dict(
        pixel_sigma=0.25, outlier_share=0.0, drift_share=0.7, drift_median=0.05, drift_log_sigma=1.2, drift_walk=0.05,
        bad_share=0.02, bad_jump=5.0, bad_drift=1.0, disparity_offset=-0.5, repeat_interval=12.0, jitter_rotation=2e-4,
        jitter_translation=0.0, jitter_correlation=0.0)
    fast = KITTI_LIKE.drift_share * stats.norm.sf(np.log(0.5 / KITTI_LIKE.drift_median) / KITTI_LIKE.drift_log_sigma)
    assert 0.01 < fast < 0.05


# ------------------------------------------------------------------ each effect alone, measured back


def test_white_noise_alone():
    """Residuals against the exact projection: std pixel_sigma within 5 % on each coordinate, mean ~0."""
    scene = scene_with(pixel_sigma=0.25)
    residual = scene.sequence.obs_pixels - projected(scene, scene.world_T_imu_true)
    assert residual.shape[0] > 10000
    np.testing.assert_allclose(residual.std(axis=0), 0.25, rtol=0.05)
    assert np.abs(residual.mean(axis=0)).max() < 0.01


def test_drift_alone_has_the_configured_heavy_tailed_slopes():
    """Drift without noise: each track's residual is a straight line in its age, the same in both
    images, its slope the recorded velocity; the share of tracks faster than 0.01 px/step is
    drift_share P(speed > 0.01) and the speeds are log-normal (median, 10x-median tail)."""
    errors = dict(pixel_sigma=0.0, drift_share=0.7, drift_median=0.05, drift_log_sigma=1.2)
    scene = scene_with(steps=400, **errors)
    residual = scene.sequence.obs_pixels - projected(scene, scene.world_T_imu_true)
    np.testing.assert_allclose(residual[:, 2:], residual[:, :2], atol=1e-9)  # the stereo match follows the track
    ids, slopes = track_slopes(scene, residual)
    assert ids.size > 800
    np.testing.assert_allclose(slopes, scene.track_errors.drift_velocity[ids], atol=1e-9)
    speed = np.linalg.norm(slopes, axis=1)
    expected = 0.7 * stats.norm.sf(np.log(0.01 / 0.05) / 1.2)  # 0.637
    assert abs(np.mean(speed > 0.01) - expected) < 0.05
    drifting = speed[speed > 1e-9]
    assert abs(drifting.size / speed.size - 0.7) < 0.05
    assert abs(np.median(drifting) / 0.05 - 1.0) < 0.2
    tail = np.mean(drifting > 10 * 0.05)  # log-normal: P(Z > ln 10 / 1.2) = 2.7 %, a Gaussian speed has none
    assert 0.01 < tail < 0.06
    # the whole distribution: ln(speed) is normal (Kolmogorov-Smirnov); tracks that drift out end early,
    # so only short tracks' fastest speeds are a little under-represented
    assert stats.kstest((np.log(drifting) - np.log(0.05)) / 1.2, "norm").statistic < 0.08


def test_random_walk_alone():
    """drift_walk without noise or velocity: the residual's steps within a track are white,
    N(0, drift_walk^2) per coordinate, and the residual's variance grows linearly with age."""
    scene = scene_with(pixel_sigma=0.0, drift_walk=0.05)
    seq = scene.sequence
    residual = seq.obs_pixels - projected(scene, scene.world_T_imu_true)
    order = np.lexsort((obs_steps(seq), seq.obs_ids))
    r, ids = residual[order, :2], seq.obs_ids[order]
    same = ids[1:] == ids[:-1]
    increments = np.diff(r, axis=0)[same]
    assert increments.shape[0] > 10000
    np.testing.assert_allclose(increments.std(axis=0), 0.05, rtol=0.05)
    assert abs(np.corrcoef(increments[1:, 0], increments[:-1, 0])[0, 1]) < 0.05
    first = np.r_[True, ~same]
    age = np.arange(ids.size) - np.maximum.accumulate(np.where(first, np.arange(ids.size), 0))
    np.testing.assert_allclose(r[age == 0], 0.0, atol=1e-9)
    np.testing.assert_allclose(r[age == 8].var() / r[age == 2].var(), 4.0, rtol=0.25)


def test_bad_tracks_alone():
    """bad_share without noise: exactly the recorded bad tracks have errors; a jumping track is exact
    until its recorded jump step and off by its jump after; a fast one drifts at 0.5-1.5 bad_drift."""
    scene = scene_with(pixel_sigma=0.0, bad_share=0.1, bad_jump=5.0, bad_drift=1.0)
    seq, truth = scene.sequence, scene.track_errors
    residual = (seq.obs_pixels - projected(scene, scene.world_T_imu_true))[:, :2]
    steps = obs_steps(seq)
    error = np.zeros(seq.num_features)
    np.maximum.at(error, seq.obs_ids, np.abs(residual).max(axis=1))
    counts = np.bincount(seq.obs_ids, minlength=seq.num_features)
    shown = ((truth.bad == JUMP) & (truth.jump_step >= 0)) | ((truth.bad == FAST) & (counts >= 2))
    np.testing.assert_array_equal(error > 1e-9, shown)
    assert abs(np.mean(truth.bad != GOOD) - 0.1 * np.mean(counts >= 2) - 0.05 * np.mean(counts < 2)) < 0.03
    jumping = truth.jump_step[seq.obs_ids] >= 0
    after = jumping & (steps >= truth.jump_step[seq.obs_ids])
    np.testing.assert_allclose(residual[after], truth.jump[seq.obs_ids[after]], atol=1e-9)
    np.testing.assert_allclose(residual[jumping & ~after], 0.0, atol=1e-9)
    size = np.linalg.norm(truth.jump[truth.bad == JUMP], axis=1)
    assert size.min() >= 2.5 - 1e-9 and size.max() <= 7.5 + 1e-9
    speed = np.linalg.norm(truth.drift_velocity[truth.bad == FAST], axis=1)
    assert speed.min() >= 0.5 - 1e-9 and speed.max() <= 1.5 + 1e-9


def test_disparity_offset_alone():
    """The mean disparity error is beta (d_measured = d_true + beta); the left pixels and vR are unbiased."""
    scene = scene_with(pixel_sigma=0.25, disparity_offset=-1.0)
    z, exact = scene.sequence.obs_pixels, projected(scene, scene.world_T_imu_true)
    disparity_error = (z[:, 0] - z[:, 2]) - (exact[:, 0] - exact[:, 2])
    assert abs(disparity_error.mean() - (-1.0)) < 0.01
    assert np.abs((z - exact)[:, [0, 1, 3]].mean(axis=0)).max() < 0.01
    np.testing.assert_allclose(disparity_error.std(), 0.25 * np.sqrt(2), rtol=0.05)


def test_repeated_frames_alone():
    """Repeats every ~10 steps: the recorded steps hold exactly the previous step's ids and pixels
    (and are what the filter's detector finds); across a repeat the points of step k-1 reprojected
    with the motion k -> k+1 fit step k+1 to the noise, with the true motion k-1 -> k+1 they miss."""
    scene = scene_with(pixel_sigma=0.25, repeat_interval=10)
    seq, truth = scene.sequence, scene.track_errors
    repeats = np.flatnonzero(truth.repeated)
    gaps = np.diff(np.r_[0, repeats])
    assert gaps.min() >= 7 and gaps.max() <= 13 and abs(gaps.mean() - 10) < 1.5
    for k in repeats:
        ids, pixels = seq.observations(k)
        prev_ids, prev_pixels = seq.observations(k - 1)
        np.testing.assert_array_equal(ids, prev_ids)
        np.testing.assert_array_equal(pixels, prev_pixels)
    np.testing.assert_array_equal(repeated_steps(seq), truth.repeated)

    T, C = scene.world_T_imu_true, truth.world_T_imu_content
    cam, imu_T_cam = scene.config.calibration.camera, seq.imu_T_cam
    fits, misses = [], []
    for k in repeats[repeats + 1 < seq.num_steps]:
        # the content misses the motion k-1 -> k: C_{k+1} = C_{k-1} T_k^-1 T_{k+1}
        np.testing.assert_allclose(C[k + 1], C[k - 1] @ se3.inverse(T[k]) @ T[k + 1], atol=1e-9)
        ids_a, za = seq.observations(k - 1)
        ids_b, zb = seq.observations(k + 1)
        _, a, b = np.intersect1d(ids_a, ids_b, return_indices=True)
        points = cam.triangulate(za[a])
        for out, start in ((fits, T[k]), (misses, T[k - 1])):
            M = se3.inverse(imu_T_cam) @ se3.inverse(T[k + 1]) @ start @ imu_T_cam
            z = cam.project(points @ M[:3, :3].T + M[:3, 3])
            out.append(np.median(np.linalg.norm(z[:, :2] - zb[b, :2], axis=1)))
    assert len(fits) >= 25
    assert max(fits) < 0.7 and min(misses) > 2.0


@pytest.mark.parametrize("correlation", [0.0, 0.8])
def test_frame_jitter_alone(correlation):
    """Frame jitter without noise: the pixels are the projections from the recorded jittered poses;
    each frame's mean residual has a std of ~fx sigma (one shift for the whole frame, the spread
    within a frame far smaller) and the lag-1 correlation of the Gauss-Markov process."""
    sigma = 3e-4
    scene = scene_with(pixel_sigma=0.0, jitter_rotation=sigma, jitter_correlation=correlation)
    seq, truth = scene.sequence, scene.track_errors
    np.testing.assert_allclose(seq.obs_pixels, projected(scene, truth.world_T_imu_content, truth.jitter), atol=1e-8)
    np.testing.assert_allclose(truth.jitter[:, 3:].std(axis=0), sigma, rtol=0.1 if correlation == 0 else 0.3)
    np.testing.assert_array_equal(truth.jitter[:, :3], 0.0)
    residual = seq.obs_pixels - projected(scene, scene.world_T_imu_true)
    steps = obs_steps(seq)
    count = np.bincount(steps)
    frame_mean = np.stack([np.bincount(steps, residual[:, c]) / count for c in (0, 1)], axis=1)  # (N,2) u, v
    ratio = frame_mean.std(axis=0) / (FX * sigma)
    assert np.all((0.8 < ratio) & (ratio < 1.4)), ratio  # u: rotation about y moves u by fx (1 + x^2) phi_y
    within = residual[:, 0] - frame_mean[steps, 0]
    assert within.std() < 0.3 * frame_mean[:, 0].std()
    lag1 = np.corrcoef(frame_mean[1:, 0], frame_mean[:-1, 0])[0, 1]
    assert abs(lag1 - correlation) < 0.12


def test_kitti_like_scene_is_loadable_and_its_tracks_drift(tmp_path):
    """All effects at once: the written scene loads as written, its tracker key says its tracks
    drift, and scene.json and track_errors.npz carry the truth."""
    scene = make_scene(SceneConfig(steps=80, seed=2, track_errors=KITTI_LIKE))
    out = write_scene(scene, tmp_path / "scene")
    seq = load_sequence(out / "data.npz", image_size=scene.image_size)
    for name in ("obs_ptr", "obs_ids", "obs_pixels", "linear_velocity"):
        np.testing.assert_array_equal(getattr(seq, name), getattr(scene.sequence, name))
    assert seq.tracker == "synthetic-drifting"
    facts = json.loads((out / "scene.json").read_text())
    assert facts["track_errors"]["repeated_steps"] == np.flatnonzero(scene.track_errors.repeated).tolist()
    assert facts["config"]["track_errors"] == dataclasses.asdict(KITTI_LIKE)
    assert facts["track_errors"]["disparity_offset_px"] == -0.5
    with np.load(out / "track_errors.npz") as f:
        np.testing.assert_array_equal(f["drift_velocity"], scene.track_errors.drift_velocity)
        np.testing.assert_array_equal(f["ids"], scene.landmark_ids)
        assert f["world_T_imu_content"].shape == (80, 4, 4)


# ------------------------------------------------------------------ the command


def test_synth_command_track_errors(tmp_path, capsys):
    """--track-errors with --errors overrides writes the truth and says what was drawn; vislam run
    reads the scene; --render with track errors and bad options are one-line refusals (exit 2)."""
    out = tmp_path / "s"
    assert main(["synth", "--steps", "60", "--track-errors", "kitti-like", "--errors", "drift_share=0.5",
                 "--errors", "jitter_rotation=0", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "scene.json" in printed and "track errors: pixel_sigma=0.25, drift_share=0.5" in printed
    facts = json.loads((out / "scene.json").read_text())
    assert facts["config"]["track_errors"]["drift_share"] == 0.5
    assert facts["config"]["track_errors"]["jitter_rotation"] == 0.0
    assert main(["run", str(out / "data.npz"), "--out", str(tmp_path / "run"), "--quiet"]) == 0
    capsys.readouterr()
    for argv, words in (
        (["--render", "--track-errors", "kitti-like"], "--render: rendered images do not show the track errors"),
        (["--errors", "drift_share=2"], "drift_share must be in [0, 1]"),
        (["--errors", "nope=1"], "track_errors.nope"),
    ):
        assert main(["synth", "--steps", "12", "--out", str(tmp_path / "refused"), *argv]) == 2
        err = capsys.readouterr().err
        assert words in err and err.count("\n") == 1, err
        assert not (tmp_path / "refused").exists()
    with pytest.raises(SystemExit):
        main(["synth", "--steps", "12", "--out", str(tmp_path / "refused"), "--track-errors", "kitti"])
    assert "invalid choice" in capsys.readouterr().err


# ------------------------------------------------------------------ the grid

#: The held-out scenes: pinned, so a change of the grid that moves a scene between parts is deliberate
HELD_OUT = (
    "street-s107-n250-px0.75-drift_on-rep_off-beta-1-out0-jit_off-vel_low-next",
    "street-s108-n350-px0.5-drift_on-rep_on-beta0-out3-jit_on-vel_mid-this",
    "street-s109-n300-px1-drift_off-rep_off-beta-1-out3-jit_on-vel_high-this",
    "street-s110-n200-px0.25-drift_heavy-rep_on-beta-1-out0-jit_off-vel_mid-next",
    "street-s112-n300-px0.75-drift_heavy-rep_on-beta0-out3-jit_on-vel_high-next",
    "aerial-s202-n300-px0.5-drift_on-rep_on-beta-1-out0-jit_on-vel_mid-this",
    "aerial-s209-n200-px0.75-drift_heavy-rep_off-beta-1-out3-jit_on-vel_high-next",
)


def test_grid_names_parts_and_determinism():
    names = [spec.name for spec in grid.GRID]
    assert len(names) >= 16 and len(set(names)) == len(names)
    tuning, held_out = list(grid.scenes("tuning")), list(grid.scenes("held_out"))
    assert tuple(name for name, _ in held_out) == HELD_OUT and len(held_out) >= 6
    assert not {n for n, _ in tuning} & {n for n, _ in held_out}
    assert sorted(n for n, _ in tuning + held_out) == sorted(names)
    assert list(grid.scenes("held_out")) == held_out and list(grid.scenes("tuning")) == tuning
    for spec in grid.GRID:
        assert grid.part_of(spec.name) == spec.part
        config = spec.scene_config()
        assert 200 <= config.steps <= 400 and 0.25 <= config.pixel_sigma <= 1.0
    for part in (tuning, held_out):  # both parts span the scenarios, drift levels, repeats and offsets
        configs = [c for _, c in part]
        assert {c.scenario for c in configs} == {"street", "aerial"}
        assert {c.track_errors.drift_share for c in configs} >= {0.0, 0.7, 0.9}
        assert {c.track_errors.repeat_interval for c in configs} == {0.0, 12.0}
        assert {c.track_errors.disparity_offset for c in configs} == {0.0, -1.0}
        assert {c.track_errors.outlier_share for c in configs} == {0.0, 0.03}
    with pytest.raises(ValueError):
        list(grid.scenes("test"))
    for spec in grid.GRID:  # by its whole name or a prefix naming one scene; none or several refused
        assert grid.spec(spec.name) is spec and grid.spec(spec.name[:11]) is spec
    for name in ("aerial-s2", "street-s999", ""):
        with pytest.raises(ValueError, match="grid scenes, not one"):
            grid.spec(name)
    scene = make_scene(dataclasses.replace(held_out[-1][1], steps=40))
    assert scene.sequence.tracker == "synthetic-drifting" and scene.sequence.num_observations > 1000


def test_random_specs_are_seeded_draws_of_the_levels():
    """grid.random_spec: the same seed gives the same scene; every factor is one of RANDOM_LEVELS; over
    200 seeds every level of every factor is drawn, each about as often as uniform draws make it."""
    specs = [grid.random_spec(seed) for seed in range(1000, 1200)]
    assert specs == [grid.random_spec(seed) for seed in range(1000, 1200)]
    assert len({s.name for s in specs}) == len(specs) and not {s.name for s in specs} & {s.name for s in grid.GRID}
    for key, levels in grid.RANDOM_LEVELS.items():
        drawn = [getattr(s, key) for s in specs]
        assert set(drawn) == set(levels), key
        for level in set(levels):
            expected = len(specs) * levels.count(level) / len(levels)
            assert abs(drawn.count(level) - expected) < 4 * np.sqrt(expected), (key, level)
    scene = make_scene(dataclasses.replace(specs[0].scene_config(), steps=30))
    assert scene.sequence.num_steps == 30
