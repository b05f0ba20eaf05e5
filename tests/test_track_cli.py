"""`vislam track` and `vislam run IMAGES_DIR --imu`: pixels to trajectory, end to end."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from vislam.backend.config import Config
from vislam.backend.data.npz import load_sequence
from vislam.frontend.config import TrackerConfig
from vislam.frontend.tracker import StereoTracker
from vislam.tools.cli import main



@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """A rendered synthetic street (80 frames) with its feature file and ground truth."""
    out = tmp_path_factory.mktemp("render") / "street"
    assert main(["synth", "--scenario", "street", "--steps", "80", "--seed", "3", "--out", str(out), "--render"]) == 0
    return out


@pytest.fixture(scope="module")
def tracked(rendered, tmp_path_factory):
    data = tmp_path_factory.mktemp("tracked") / "tracks.npz"
    assert main(["track", str(rendered), "--imu", str(rendered / "data.npz"), "--out", str(data), "--quiet"]) == 0
    return data


def test_track_writes_the_course_layout(rendered, tracked):
    seq = load_sequence(tracked)
    imu = load_sequence(rendered / "data.npz")
    assert seq.num_steps == imu.num_steps == 80
    np.testing.assert_array_equal(seq.time_stamps, imu.time_stamps)  # the IMU file's stamps
    np.testing.assert_array_equal(seq.linear_velocity, imu.linear_velocity)
    np.testing.assert_allclose(seq.imu_T_cam, imu.imu_T_cam, atol=1e-12)
    np.testing.assert_allclose(seq.K, imu.K, atol=1e-6)
    assert seq.baseline == pytest.approx(imu.baseline, abs=1e-9)
    assert seq.num_observations / seq.num_steps >= 100
    assert np.all(seq.obs_pixels[:, 0] - seq.obs_pixels[:, 2] > 0)  # positive disparity
    assert seq.tracker == "vislam"  # so that `vislam run` does not model track drift


def test_images_to_trajectory_beats_dead_reckoning(rendered, tracked, tmp_path):
    """End to end: render, track, run SLAM: ATE <= 1/3 of dead reckoning's."""
    out = tmp_path / "run"
    assert main(["run", str(tracked), "--out", str(out), "--gt", str(rendered / "gt_tum.txt"), "--quiet"]) == 0
    errors = json.loads((out / "summary.json").read_text())["errors"]
    assert errors["estimate"]["ate_rmse"] <= errors["dead_reckoning"]["ate_rmse"] / 3


def test_run_on_an_image_directory_equals_track_then_run(rendered, tracked, tmp_path):
    one = tmp_path / "one"
    assert main(["run", str(rendered), "--imu", str(rendered / "data.npz"), "--out", str(one), "--quiet"]) == 0
    two = tmp_path / "two"
    assert main(["run", str(tracked), "--out", str(two), "--quiet"]) == 0
    a = np.loadtxt(one / "trajectory.txt")
    b = np.loadtxt(two / "trajectory.txt")
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    # the image run's time includes tracking the frames (input_seconds) besides the filter
    timing = json.loads((one / "summary.json").read_text())["timing"]
    assert timing["input_seconds"] > 0 and timing["filter_seconds"] > 0
    assert timing["real_time_factor"] == pytest.approx(timing["sequence_seconds"] / timing["run_seconds"], rel=1e-9)
    # the image run records the front end's options too: summary.json and config.toml have [tracker]
    config = json.loads((one / "summary.json").read_text())["config"]
    assert list(config) == [*Config().tables(), "tracker"]
    assert config["tracker"] == TrackerConfig().as_dict()
    assert config == {**json.loads((two / "summary.json").read_text())["config"], "tracker": config["tracker"]}
    text = (one / "config.toml").read_text()
    assert "\n[tracker]\n" in text
    assert TrackerConfig.load(one / "config.toml") == TrackerConfig()
    assert Config.load(one / "config.toml", foreign=("tracker",)).as_dict() == {
        k: v for k, v in config.items() if k != "tracker"}
    # ... and loads back with --config, into either command
    three = tmp_path / "three"
    assert main(["run", str(tracked), "--out", str(three), "--quiet", "--config", str(one / "config.toml")]) == 0
    np.testing.assert_allclose(np.loadtxt(three / "trajectory.txt"), b, rtol=0, atol=1e-9)
    again = tmp_path / "again.npz"
    assert main(["track", str(rendered), "--imu", str(rendered / "data.npz"), "--out", str(again), "--quiet",
                 "--config", str(one / "config.toml")]) == 0
    np.testing.assert_array_equal(load_sequence(again).obs_pixels, load_sequence(tracked).obs_pixels)


def test_track_refuses_bad_requests(rendered, tracked, tmp_path, capsys):
    # an existing output is not overwritten without --force
    before = tracked.read_bytes()
    assert main(["track", str(rendered), "--imu", str(rendered / "data.npz"), "--out", str(tracked), "--quiet"]) == 2
    assert tracked.read_bytes() == before
    assert "exists" in capsys.readouterr().err
    # an image directory needs --imu; a feature file takes none
    assert main(["run", str(rendered), "--out", str(tmp_path / "x")]) == 2
    assert "--imu" in capsys.readouterr().err
    assert main(["run", str(tracked), "--imu", str(tracked), "--out", str(tmp_path / "y")]) == 2
    assert "feature file" in capsys.readouterr().err
    # a directory without the KITTI layout: one line naming what is missing
    (tmp_path / "empty").mkdir()
    assert main(["track", str(tmp_path / "empty"), "--imu", str(rendered / "data.npz"), "--out", str(tmp_path / "z.npz")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "image_0" in err
    assert not (tmp_path / "z.npz").exists()
    # `vislam track --set` takes only the front end's options, named tracker.KEY
    refused = [("noise.pixel_sigma=1", "[tracker]"), ("target_tracks=100", "'tracker.target_tracks'"),
               ("tracker.target_trakcs=100", "'tracker.target_trakcs'"), ("tracker.lk_window=14", "'tracker.lk_window'")]
    for item, needle in refused:
        assert main(["track", str(rendered), "--imu", str(rendered / "data.npz"), "--out", str(tmp_path / "s.npz"),
                     "--set", item]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and needle in err, (item, err)
        assert not (tmp_path / "s.npz").exists()


def test_draw_writes_one_png_per_frame(rendered, tmp_path):
    draw = tmp_path / "draw"
    out = tmp_path / "t.npz"
    assert main(["track", str(rendered), "--imu", str(rendered / "data.npz"), "--out", str(out), "--quiet",
                 "--draw", str(draw), "--set", "tracker.target_tracks=100"]) == 0
    names = sorted(p.name for p in draw.iterdir())
    assert names == [f"{i:06d}.png" for i in range(80)]
    import cv2

    from vislam.frontend.draw import CAPTION_HEIGHT

    image = cv2.imread(str(draw / names[5]))
    assert image.shape == (CAPTION_HEIGHT + 2 * 376, 1241, 3)  # the caption, left above right
    band = image[:CAPTION_HEIGHT]
    text = band.max(axis=2) > 200  # white letters on a dark band, whatever the sky below
    assert np.median(band) < 60 and 0.01 < text.mean() < 0.5
    left = cv2.imread(str(rendered / "image_0" / names[5]), cv2.IMREAD_GRAYSCALE)
    assert np.mean(image[CAPTION_HEIGHT:CAPTION_HEIGHT + 376, :, 0] == left) > 0.8  # the left image, marks aside


def _copy_frames(src: Path, dst: Path, n: int, black=(), size=None, extra_stamps: int = 0) -> Path:
    """The first ``n`` pairs of the KITTI-layout ``src`` in ``dst`` (resized to ``size``; the frames in
    ``black`` all zeros), its calib.txt and the first ``n + extra_stamps`` lines of its times.txt."""
    for folder in ("image_0", "image_1"):
        (dst / folder).mkdir(parents=True)
        for k in range(n):
            image = cv2.imread(str(src / folder / f"{k:06d}.png"), cv2.IMREAD_GRAYSCALE)
            if size is not None:
                image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
            if k in black:
                image[:] = 0
            assert cv2.imwrite(str(dst / folder / f"{k:06d}.png"), image)
    shutil.copy(src / "calib.txt", dst / "calib.txt")
    stamps = (src / "times.txt").read_text().splitlines()
    assert len(stamps) >= n + extra_stamps
    (dst / "times.txt").write_text("\n".join(stamps[: n + extra_stamps]) + "\n")
    return dst


def _no_tracking(monkeypatch):
    """Make any tracking fail loudly: a refusal must come before the first frame is tracked."""
    def step(self, left, right):
        raise AssertionError("tracking started on input that must be refused first")

    monkeypatch.setattr(StereoTracker, "step", step)


@pytest.mark.parametrize("black", [(0,), (3,), tuple(range(6))], ids=["first", "middle", "all"])
def test_featureless_frames_do_not_stop_track_or_run(rendered, tmp_path, capsys, black):
    """All-black frames give no observations; `vislam track` and `vislam run IMAGES` go on (exit 0)."""
    images = _copy_frames(rendered, tmp_path / "images", 6, black)
    data = tmp_path / "tracks.npz"
    assert main(["track", str(images), "--imu", str(rendered / "data.npz"), "--out", str(data), "--quiet"]) == 0
    seq = load_sequence(data)
    assert seq.num_steps == 6
    for k in range(6):
        ids, pixels = seq.observations(k)
        if k in black:
            assert ids.shape == (0,) and pixels.shape == (0, 4), k
        else:
            assert ids.size >= 50, (k, ids.size)
    out = tmp_path / "run"
    assert main(["run", str(images), "--imu", str(rendered / "data.npz"), "--out", str(out), "--quiet"]) == 0
    assert json.loads((out / "summary.json").read_text())["steps"] == 6
    assert len(np.loadtxt(out / "trajectory.txt", ndmin=2)) == 6
    assert "Traceback" not in capsys.readouterr().err


@pytest.mark.parametrize("size", [(8, 8), (20, 15)], ids=["8x8", "20x15"])
def test_images_too_small_to_track_are_refused_in_one_line(rendered, tmp_path, capsys, monkeypatch, size):
    images = _copy_frames(rendered, tmp_path / "images", 3, size=size)
    _no_tracking(monkeypatch)
    data = tmp_path / "tracks.npz"
    out = tmp_path / "run"
    for argv in (["track", str(images), "--imu", str(rendered / "data.npz"), "--out", str(data), "--quiet"],
                 ["run", str(images), "--imu", str(rendered / "data.npz"), "--out", str(out), "--quiet"]):
        assert main(argv) == 2, argv[0]
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and str(images) in err and f"{size[0]}x{size[1]}" in err and "too small" in err, err
    assert not data.exists()
    assert not (out / "trajectory.txt").exists()


def test_times_txt_may_hold_more_stamps_than_frames(rendered, tmp_path, capsys):
    images = _copy_frames(rendered, tmp_path / "images", 4, extra_stamps=20)
    data = tmp_path / "tracks.npz"
    assert main(["track", str(images), "--imu", str(rendered / "data.npz"), "--out", str(data), "--quiet"]) == 0
    assert load_sequence(data).num_steps == 4
    # fewer stamps than frames stays an error naming times.txt
    (images / "times.txt").write_text("".join((rendered / "times.txt").read_text().splitlines(keepends=True)[:3]))
    assert main(["track", str(images), "--imu", str(rendered / "data.npz"), "--out", str(data), "--force"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "times.txt" in err and "3 time stamps for 4 frames" in err


def test_draw_into_a_regular_file_is_refused_before_any_work(rendered, tmp_path, capsys, monkeypatch):
    images = _copy_frames(rendered, tmp_path / "images", 3)
    drawing = tmp_path / "pictures.png"
    drawing.write_bytes(b"a file, not a directory")
    _no_tracking(monkeypatch)
    data = tmp_path / "tracks.npz"
    out = tmp_path / "run"
    for argv in (["track", str(images), "--imu", str(rendered / "data.npz"), "--out", str(data), "--quiet"],
                 ["run", str(images), "--imu", str(rendered / "data.npz"), "--out", str(out), "--quiet"]):
        for target in (drawing, drawing / "frames"):
            assert main([*argv, "--draw", str(target)]) == 2, (argv[0], target)
            err = capsys.readouterr().err.strip()
            assert err.count("\n") == 0 and str(target) in err and "not a directory" in err, err
    assert drawing.read_bytes() == b"a file, not a directory"
    assert not data.exists()
    assert not (out / "trajectory.txt").exists()


@pytest.mark.parametrize("stamps, needle", [
    (lambda t: np.where(np.arange(t.size) >= 40, t + 3600.0, t), "a gap of 3600"),
    (lambda t: t * 1e9, "not seconds"),
    (lambda t: t[::-1].copy(), "not strictly increasing"),
], ids=["hour-gap", "nanoseconds", "backwards"])
def test_an_image_run_refuses_bad_imu_stamps_before_tracking(rendered, tmp_path, capsys, monkeypatch, stamps, needle):
    """One-pass image runs and track check the frames' stamps (here the IMU CSV's t column) before
    the first frame is tracked, naming the file (and its column or line), not a '<stream>'."""
    from vislam.backend.data.npz import load_sequence

    seq = load_sequence(rendered / "data.npz")
    csv = tmp_path / "imu.csv"
    rows = np.column_stack([stamps(seq.time_stamps.copy()), seq.linear_velocity, seq.angular_velocity])
    np.savetxt(csv, rows, delimiter=",", header="t,vx,vy,vz,wx,wy,wz", comments="", fmt="%.9f")
    extrinsic = tmp_path / "T.txt"
    np.savetxt(extrinsic, seq.imu_T_cam)
    _no_tracking(monkeypatch)
    for argv in (["run", str(rendered), "--out", str(tmp_path / "o")], ["track", str(rendered), "--out",
                                                                         str(tmp_path / "t.npz")]):
        assert main([*argv, "--imu", str(csv), "--imu-T-cam", str(extrinsic), "--quiet"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and err.startswith(f"vislam: error: {csv}: ") and needle in err, err
    assert not (tmp_path / "o").exists() and not (tmp_path / "t.npz").exists()
