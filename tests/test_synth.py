"""Tests of the synthetic scenes (vislam.synth): exact trajectories, camera-consistent observations,
tracks, noise statistics, the filter configuration a scene asks for and the file round trip."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from helpers import SEQUENCE_ARRAYS, assert_same_scene_arrays
from vislam.backend.config import Config
from vislam.backend.data.npz import load_sequence
from vislam.backend.data.tum import read_tum
from vislam.backend.errors import ConfigError
from vislam.backend.estimator.propagation import dead_reckoning
from vislam.backend.geometry import se3
from vislam.synth.imu import measure_velocities, stamp_twists
from vislam.synth.observe import kitti_calibration
from vislam.synth.scene import Scene, SceneConfig, make_scene, write_scene
from vislam.synth.trajectories import aerial, street

NOISE_FREE = dict(linear_sigma=0.0, angular_sigma=0.0, gyro_bias=(0.0, 0.0, 0.0), pixel_sigma=0.0)


@pytest.fixture(scope="module")
def default_street() -> Scene:
    return make_scene(SceneConfig())


@pytest.fixture(scope="module", params=["street", "aerial"])
def exact_scene(request) -> Scene:
    return make_scene(SceneConfig(scenario=request.param, steps=300, seed=3, **NOISE_FREE))


def obs_steps(seq) -> np.ndarray:
    return np.repeat(np.arange(seq.num_steps), np.diff(seq.obs_ptr))


def camera_points(scene: Scene) -> np.ndarray:
    """True landmark of each observation (by id) in the camera frame of its step."""
    seq = scene.sequence
    cam_T_world = se3.inverse(seq.imu_T_cam) @ se3.inverse(scene.world_T_imu_true)
    T = cam_T_world[obs_steps(seq)]
    p = scene.landmark_positions[seq.obs_ids]
    return np.einsum("nij,nj->ni", T[:, :3, :3], p) + T[:, :3, 3]


def reprojected(scene: Scene) -> np.ndarray:
    return scene.config.calibration.camera.project(camera_points(scene))


# ------------------------------------------------------------------ reproducibility


def assert_same_scene(a: Scene, b: Scene) -> None:
    for name in ("world_T_imu_true", "twists_true", "landmark_ids", "landmark_positions", "points"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    for name in ("time_stamps", "linear_velocity", "angular_velocity", "obs_ptr", "obs_ids", "obs_pixels"):
        np.testing.assert_array_equal(getattr(a.sequence, name), getattr(b.sequence, name))


@pytest.mark.parametrize("scenario", ["street", "aerial"])
def test_make_scene_is_reproducible(scenario):
    config = SceneConfig(scenario=scenario, steps=200, seed=7, outlier_share=0.05)
    assert_same_scene(make_scene(config), make_scene(dataclasses.replace(config)))
    other = make_scene(dataclasses.replace(config, seed=8))
    assert not np.allclose(make_scene(config).world_T_imu_true, other.world_T_imu_true)
    assert other.sequence.source == f"synthetic:{scenario}:seed8"


def test_noise_settings_do_not_change_the_geometry():
    a = make_scene(SceneConfig(steps=150, seed=2))
    b = make_scene(SceneConfig(steps=150, seed=2, linear_sigma=0.0, pixel_sigma=0.0))
    np.testing.assert_array_equal(a.world_T_imu_true, b.world_T_imu_true)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.sequence.angular_velocity, b.sequence.angular_velocity)


def test_config_is_validated():
    for bad in (
        dict(scenario="city"),
        dict(steps=1),
        dict(velocity_index="last"),
        dict(pixel_sigma=-1.0),
        dict(outlier_share=1.5),
        dict(min_depth=70.0),
        dict(linear_sigma=(0.1, 0.2)),
    ):
        with pytest.raises(ConfigError):
            SceneConfig(**bad)


def test_filter_config_is_the_scenes_noise():
    """The filter is told the scene's pixel noise and the largest axis of its velocity noise; every
    other option keeps its default."""
    config = SceneConfig(pixel_sigma=0.7, linear_sigma=(0.1, 0.3, 0.2), angular_sigma=0.02).filter_config()
    assert isinstance(config, Config)
    assert config.noise.pixel_sigma == 0.7
    assert config.noise.linear_velocity_sigma == 0.3 and isinstance(config.noise.linear_velocity_sigma, float)
    assert config.noise.angular_velocity_sigma == 0.02
    assert config == Config().with_values(
        {"noise.pixel_sigma": 0.7, "noise.linear_velocity_sigma": 0.3, "noise.angular_velocity_sigma": 0.02})
    default = SceneConfig().filter_config()
    assert (default.noise.pixel_sigma, default.noise.linear_velocity_sigma, default.noise.angular_velocity_sigma) == (
        0.5, 0.2, 0.01)


# ------------------------------------------------------------------ trajectories and IMU


@pytest.mark.parametrize("velocity_index", ["this", "next"])
@pytest.mark.parametrize("scenario", ["street", "aerial"])
def test_dead_reckoning_on_noise_free_velocities_is_exact(scenario, velocity_index):
    scene = make_scene(
        SceneConfig(scenario=scenario, steps=400, seed=1, velocity_index=velocity_index, **NOISE_FREE)
    )
    seq = scene.sequence
    poses = dead_reckoning(seq.time_stamps, seq.linear_velocity, seq.angular_velocity, velocity_index)
    np.testing.assert_allclose(poses, scene.world_T_imu_true, rtol=0, atol=1e-9)
    # the other convention drifts away: the stamping really differs
    other = "next" if velocity_index == "this" else "this"
    wrong = dead_reckoning(seq.time_stamps, seq.linear_velocity, seq.angular_velocity, other)
    assert np.abs(wrong[:, :3, 3] - scene.world_T_imu_true[:, :3, 3]).max() > 0.1


def test_next_stamping():
    twists = np.arange(5 * 6, dtype=float).reshape(5, 6)
    nxt = stamp_twists(twists, "next")
    np.testing.assert_array_equal(nxt[1:], twists[:-1])
    np.testing.assert_array_equal(nxt[0], twists[0])
    np.testing.assert_array_equal(stamp_twists(twists, "this"), twists)


def test_street_profile_is_car_like():
    traj = street(1500, 0.1, seed=4)
    v, w = traj.twists[:, :3], traj.twists[:, 3:]
    assert 5.0 <= v[:, 0].min() and v[:, 0].max() <= 12.0
    assert np.abs(v[:, 1:]).max() < 0.1
    assert np.abs(w[:, :2]).max() <= 0.011
    assert 0.1 < np.abs(w[:, 2]).max() <= 0.31  # some real turns, never sharper than ~0.3 rad/s
    # smooth: consecutive twists differ little
    assert np.abs(np.diff(traj.twists, axis=0)).max() < 0.2
    np.testing.assert_array_equal(traj.twists[-1], traj.twists[-2])
    np.testing.assert_array_equal(traj.time_stamps, np.arange(1500) * 0.1)
    for T in traj.world_T_imu[::50]:
        assert se3.is_rigid(T, tol=1e-9)


def test_aerial_profile_is_six_dof():
    traj = aerial(1000, 0.1, seed=4)
    speed = np.linalg.norm(traj.twists[:, :3], axis=1)
    assert 0.7 < speed.min() and speed.max() < 2.5
    rates = np.abs(traj.twists[:, 3:]).max(axis=0)
    assert np.all(rates > 0.15) and np.all(rates <= 0.31)


def test_velocity_noise_and_bias_statistics():
    traj = street(3000, 0.1, seed=0)
    bias = np.array([0.002, -0.002, 0.001])
    imu = measure_velocities(traj.twists, traj.time_stamps, 11, linear_sigma=0.2, angular_sigma=0.01, gyro_bias=bias)
    lin_err = imu.linear_velocity - traj.twists[:, :3]
    ang_err = imu.angular_velocity - traj.twists[:, 3:]
    assert abs(lin_err.std() / 0.2 - 1.0) < 0.1
    assert abs((ang_err - bias).std() / 0.01 - 1.0) < 0.1
    # the bias is in the mean, to ~4 standard errors (0.01 / sqrt(3000) = 1.8e-4)
    np.testing.assert_allclose(ang_err.mean(axis=0), bias, atol=7e-4)
    assert np.abs(lin_err.mean(axis=0)).max() < 0.02
    np.testing.assert_array_equal(imu.gyro_bias, np.broadcast_to(bias, (3000, 3)))


def test_scene_velocity_noise_matches_config():
    scene = make_scene(SceneConfig(steps=2000, seed=5, landmark_density=0.0))
    seq = scene.sequence
    lin_err = seq.linear_velocity - scene.twists_true[:, :3]
    ang_err = seq.angular_velocity - scene.twists_true[:, 3:]
    assert abs(lin_err.std() / 0.2 - 1.0) < 0.1
    assert abs((ang_err - scene.gyro_bias_true).std() / 0.01 - 1.0) < 0.1
    np.testing.assert_allclose(ang_err.mean(axis=0), [0.002, -0.002, 0.001], atol=1e-3)
    assert seq.num_observations == 0


def test_gyro_bias_random_walk():
    traj = street(2000, 0.1, seed=0)
    imu = measure_velocities(
        traj.twists, traj.time_stamps, 3, angular_sigma=0.0, gyro_bias=(0.0, 0.0, 0.0), gyro_bias_walk=1e-3
    )
    steps = np.diff(imu.gyro_bias, axis=0)
    assert abs(steps.std() / (1e-3 * np.sqrt(0.1)) - 1.0) < 0.1
    np.testing.assert_array_equal(imu.gyro_bias[0], 0.0)
    np.testing.assert_allclose(imu.angular_velocity - traj.twists[:, 3:], imu.gyro_bias, atol=1e-15)


# ------------------------------------------------------------------ observations


def test_noise_free_pixels_equal_the_camera_model(exact_scene):
    seq = exact_scene.sequence
    assert seq.num_observations > 1000
    np.testing.assert_allclose(seq.obs_pixels, reprojected(exact_scene), rtol=0, atol=1e-9)


def test_every_observation_is_visible(exact_scene):
    seq = exact_scene.sequence
    width, height = exact_scene.image_size
    z = seq.obs_pixels
    assert np.all(z[:, 0] - z[:, 2] > 0)
    assert np.all((z[:, 0::2] >= 0) & (z[:, 0::2] < width))
    assert np.all((z[:, 1::2] >= 0) & (z[:, 1::2] < height))
    depth = camera_points(exact_scene)[:, 2]
    assert depth.min() >= 2.0 and depth.max() <= 60.0
    # the scene does use the whole depth range
    assert depth.min() < 8.0 and depth.max() > 45.0


def test_noisy_observations_stay_in_the_image(default_street):
    seq = default_street.sequence
    width, height = default_street.image_size
    z = seq.obs_pixels
    assert np.all(z[:, 0] - z[:, 2] > 0)
    assert np.all((z[:, 0::2] >= 0) & (z[:, 0::2] < width) & (z[:, 1::2] >= 0) & (z[:, 1::2] < height))
    depth = camera_points(default_street)[:, 2]
    assert depth.min() >= 2.0 and depth.max() <= 60.0


def test_ids_are_never_reused(default_street):
    seq = default_street.sequence
    steps, ids = obs_steps(seq), seq.obs_ids
    order = np.lexsort((steps, ids))
    s, i = steps[order], ids[order]
    same = i[1:] == i[:-1]
    assert np.all(s[1:][same] == s[:-1][same] + 1)  # one consecutive run per id
    assert np.array_equal(np.unique(ids), default_street.landmark_ids)
    assert seq.num_features == default_street.landmark_ids.size
    # ids increasing within a step, sorted by step (CSR)
    within = steps[1:] == steps[:-1]
    assert np.all(np.diff(ids)[within] > 0)
    # points are seen again under new ids, and the positions follow the point by id
    assert default_street.landmark_point_index.size > np.unique(default_street.landmark_point_index).size
    np.testing.assert_array_equal(
        default_street.landmark_positions, default_street.points[default_street.landmark_point_index]
    )


def test_tracks_are_not_cut_without_a_max_length():
    scene = make_scene(SceneConfig(steps=200, seed=1, mean_track_length=None, pixel_sigma=0.0))
    seq = scene.sequence
    steps = obs_steps(seq)
    # consecutive tracks of one point must be separated by at least one step without it
    first = np.full(seq.num_features, seq.num_steps)
    last = np.full(seq.num_features, -1)
    np.minimum.at(first, seq.obs_ids, steps)
    np.maximum.at(last, seq.obs_ids, steps)
    order = np.lexsort((first, scene.landmark_point_index))
    pts = scene.landmark_point_index[order]
    same = pts[1:] == pts[:-1]
    assert np.all(first[order][1:][same] > last[order][:-1][same] + 1)


def test_pixel_noise_statistics():
    scene = make_scene(SceneConfig(steps=300, seed=9, pixel_sigma=0.5))
    residual = scene.sequence.obs_pixels - reprojected(scene)
    assert residual.shape[0] > 10000
    assert abs(residual.std() / 0.5 - 1.0) < 0.1
    assert np.all(np.abs(residual.std(axis=0) / 0.5 - 1.0) < 0.1)
    assert np.abs(residual.mean(axis=0)).max() < 0.02


def test_outliers():
    scene = make_scene(SceneConfig(steps=200, seed=4, pixel_sigma=0.0, outlier_share=0.1))
    seq = scene.sequence
    assert abs(scene.outlier.mean() - 0.1) < 0.02
    err = np.abs(seq.obs_pixels - reprojected(scene)).max(axis=1)
    assert np.all(err[~scene.outlier] < 1e-9)
    assert np.median(err[scene.outlier]) > 20.0
    z = seq.obs_pixels[scene.outlier]
    width, height = scene.image_size
    assert np.all(z[:, 0] - z[:, 2] > 0)
    assert np.all((z[:, 0::2] >= 0) & (z[:, 0::2] < width) & (z[:, 1::2] >= 0) & (z[:, 1::2] < height))


def test_default_street_coverage(default_street):
    seq = default_street.sequence
    per_step = np.diff(seq.obs_ptr)
    assert seq.num_steps == 500
    assert per_step.min() >= 30
    assert 60 <= np.median(per_step) <= 110
    assert np.median(np.bincount(seq.obs_ids)) >= 8


def test_default_street_calibration(default_street):
    seq = default_street.sequence
    calib = kitti_calibration()
    np.testing.assert_array_equal(seq.K, calib.K)
    assert seq.baseline == 0.537 and default_street.image_size == (1241, 376)
    # the camera looks along the IMU x axis, its x axis is the IMU's -y, its y the IMU's -z
    np.testing.assert_array_equal(seq.imu_T_cam[:3, :3], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    np.testing.assert_array_equal(seq.imu_T_cam[:3, 3], [1.1, -0.3, 0.75])
    assert seq.layout == "2022" and seq.source == "synthetic:street:seed0"


# ------------------------------------------------------------------ files


def test_write_scene_round_trip(tmp_path):
    scene = make_scene(SceneConfig(steps=120, seed=6, outlier_share=0.02))
    out = write_scene(scene, tmp_path / "scene")
    seq = load_sequence(out / "data.npz", image_size=scene.image_size)
    ref = scene.sequence
    assert seq.dropped == {"nonpositive_disparity": 0, "outside_image": 0}
    for name in ("time_stamps", "linear_velocity", "angular_velocity", "K", "imu_T_cam", "obs_ptr", "obs_ids", "obs_pixels"):
        np.testing.assert_array_equal(getattr(seq, name), getattr(ref, name))
    assert seq.num_features == ref.num_features and seq.baseline == ref.baseline
    # also with the image size inferred from K, as the pipeline loads it
    assert load_sequence(out / "data.npz").num_observations == ref.num_observations

    with np.load(out / "landmarks.npz") as lm:
        np.testing.assert_array_equal(lm["ids"], scene.landmark_ids)
        np.testing.assert_array_equal(lm["positions"], scene.landmark_positions)

    from scipy.spatial.transform import Rotation

    rows = np.loadtxt(out / "gt_tum.txt", comments="#")
    assert rows.shape == (120, 8)
    np.testing.assert_allclose(rows[:, 0], ref.time_stamps, atol=1e-6)
    np.testing.assert_allclose(rows[:, 1:4], scene.world_T_imu_true[:, :3, 3], atol=1e-8)
    R = Rotation.from_quat(rows[:, 4:]).as_matrix()
    np.testing.assert_allclose(R, scene.world_T_imu_true[:, :3, :3], atol=1e-8)
    assert np.all(rows[:, 7] >= 0)
    # the ground truth reads back with the TUM reader the commands use (--gt)
    t, poses = read_tum(out / "gt_tum.txt")
    np.testing.assert_allclose(t, ref.time_stamps, rtol=0, atol=1e-6)
    np.testing.assert_allclose(poses[:, :3, 3], scene.world_T_imu_true[:, :3, 3], rtol=0, atol=1e-8)
    np.testing.assert_allclose(poses[:, :3, :3], scene.world_T_imu_true[:, :3, :3], rtol=0, atol=1e-8)
    assert (out / "gt_tum.txt").read_text().startswith(f"# {scene.config.source} ground truth world_T_imu")
    assert sorted(p.name for p in out.iterdir()) == ["data.npz", "gt_tum.txt", "landmarks.npz"]


# ------------------------------------------------------------------ memory bounds and the sparse file layout

import os

import vislam.synth.landmarks as synth_landmarks
import vislam.synth.observe as synth_observe
from vislam.backend.data import npz as npz_module
from vislam.backend.data.npz import save_sequence

def assert_identical_scene(a: Scene, b: Scene) -> None:
    assert_same_scene_arrays(a, b)
    assert a.sequence.num_features == b.sequence.num_features


@pytest.fixture(scope="module")
def small_street() -> Scene:
    return make_scene(SceneConfig(steps=80))


@pytest.mark.parametrize("scenario", ["street", "aerial"])
def test_huge_landmark_density_is_refused_before_allocating(scenario):
    """landmark_density 1e6 over 300 steps raises ConfigError (quickly, before drawing points) naming GiB."""
    with pytest.raises(ConfigError) as exc:
        make_scene(SceneConfig(scenario=scenario, landmark_density=1e6, steps=300))
    message = str(exc.value)
    assert "GiB" in message and "landmark_density" in message and "\n" not in message


@pytest.mark.parametrize("scenario", ["street", "aerial"])
def test_point_budget_follows_max_points(monkeypatch, scenario):
    """A scene whose expected point count exceeds a lowered MAX_POINTS is refused; the default bound lets it through."""
    assert make_scene(SceneConfig(scenario=scenario, steps=80)).points.shape[0] > 100
    monkeypatch.setattr(synth_landmarks, "MAX_POINTS", 100)
    with pytest.raises(ConfigError, match="GiB"):
        make_scene(SceneConfig(scenario=scenario, steps=80))


def test_observation_budget_triggers(monkeypatch, small_street):
    """MAX_OBSERVATIONS lowered below the scene's observations: make_scene raises ConfigError naming GiB and the bound."""
    assert small_street.sequence.num_observations > 1000
    monkeypatch.setattr(synth_observe, "MAX_OBSERVATIONS", 1000)
    with pytest.raises(ConfigError) as exc:
        make_scene(SceneConfig(steps=80))
    assert "GiB" in str(exc.value) and "1,000" in str(exc.value)


def test_observation_budget_sampling_estimate_triggers(monkeypatch, small_street):
    """The estimate from a sample of the points (more points than _SAMPLE_POINTS) refuses a scene whose
    sample alone is under MAX_OBSERVATIONS but whose whole would exceed it ('about ... GiB')."""
    n = small_street.sequence.num_observations  # ~6500 from ~290 points
    monkeypatch.setattr(synth_observe, "_SAMPLE_POINTS", 100)
    monkeypatch.setattr(synth_observe, "MAX_OBSERVATIONS", int(0.6 * n))
    with pytest.raises(ConfigError) as exc:
        make_scene(SceneConfig(steps=80))
    assert str(exc.value).startswith("synthetic scene: about ") and "GiB" in str(exc.value)


@pytest.mark.parametrize("patch", ["bound", "sample"])
def test_scene_under_the_observation_budget_is_unchanged(monkeypatch, small_street, patch):
    """A scene under a lowered MAX_OBSERVATIONS, or built through the sampling estimate (small
    _SAMPLE_POINTS), has exactly the arrays of the unpatched scene."""
    if patch == "bound":
        monkeypatch.setattr(synth_observe, "MAX_OBSERVATIONS", 2 * small_street.sequence.num_observations)
    else:
        monkeypatch.setattr(synth_observe, "_SAMPLE_POINTS", 100)
    assert_identical_scene(make_scene(SceneConfig(steps=80)), small_street)


def _dense_bytes(seq) -> int:
    return 4 * int(seq.num_features) * seq.num_steps * 8


@pytest.mark.parametrize("layout", ["2022", "2019"])
@pytest.mark.parametrize("over", [True, False])
def test_save_sequence_sparse_over_the_dense_limit(tmp_path, monkeypatch, small_street, over, layout):
    """save_sequence(dense=None) writes the sparse keys (obs_ptr, obs_ids, obs_pixels, num_features, no
    features) when 4*M*N*8 bytes exceed DENSE_LIMIT_BYTES, the dense features otherwise (at the limit
    too); both load back to the same observations, time stamps, K, baseline and imu_T_cam."""
    seq = small_street.sequence
    monkeypatch.setattr(npz_module, "DENSE_LIMIT_BYTES", _dense_bytes(seq) - 1 if over else _dense_bytes(seq))
    path = tmp_path / "data.npz"
    save_sequence(seq, path, layout=layout)
    with np.load(path) as f:
        keys = set(f.files)
        if over:
            assert {"obs_ptr", "obs_ids", "obs_pixels", "num_features"} <= keys and "features" not in keys
            assert int(f["num_features"]) == seq.num_features
        else:
            assert "features" in keys and not keys & {"obs_ptr", "obs_ids", "obs_pixels", "num_features"}
            assert f["features"].shape == (4, seq.num_features, seq.num_steps)
    back = load_sequence(path, image_size=small_street.image_size)
    assert back.dropped == {"nonpositive_disparity": 0, "outside_image": 0}
    for name in SEQUENCE_ARRAYS + ("K", "imu_T_cam"):
        np.testing.assert_array_equal(getattr(back, name), getattr(seq, name), err_msg=name)
    assert back.baseline == seq.baseline and back.num_features == seq.num_features
    assert back.layout == layout and back.tracker == seq.tracker
    assert os.listdir(tmp_path) == ["data.npz"]


def test_save_sequence_explicit_dense_overrides_the_limit(tmp_path, monkeypatch, small_street):
    """dense=False writes the sparse layout and dense=True the dense one, whatever DENSE_LIMIT_BYTES says."""
    seq = small_street.sequence
    monkeypatch.setattr(npz_module, "DENSE_LIMIT_BYTES", 1)
    save_sequence(seq, tmp_path / "dense.npz", dense=True)
    monkeypatch.setattr(npz_module, "DENSE_LIMIT_BYTES", 1 << 40)
    save_sequence(seq, tmp_path / "sparse.npz", dense=False)
    with np.load(tmp_path / "dense.npz") as f:
        assert "features" in f.files and "obs_ptr" not in f.files
    with np.load(tmp_path / "sparse.npz") as f:
        assert "obs_ptr" in f.files and "features" not in f.files
    for name in ("dense.npz", "sparse.npz"):
        back = load_sequence(tmp_path / name, image_size=small_street.image_size)
        for key in ("obs_ptr", "obs_ids", "obs_pixels"):
            np.testing.assert_array_equal(getattr(back, key), getattr(seq, key), err_msg=f"{name} {key}")


def test_observation_budget_message_counts_are_plausible(monkeypatch, small_street):
    """The 'observations in all' the refusal names is of the order of the scene's real count (within 10x)."""
    import re

    n = small_street.sequence.num_observations
    monkeypatch.setattr(synth_observe, "MAX_OBSERVATIONS", 1000)
    with pytest.raises(ConfigError) as exc:
        make_scene(SceneConfig(steps=80))
    claimed = float(re.search(r"(\S+) observations in all", str(exc.value)).group(1))
    assert n / 10 <= claimed <= 10 * n, str(exc.value)
