"""The OpenCV stereo front end (vislam.frontend): tracks on rendered images against exact geometry, real
KITTI pairs, the input readers and the course-layout output.

Truth of a track: the 3-D point under its first left pixel, from vislam.synth.render.render_depth with the
true pose (where the pixel's 2x2 block straddles a depth edge, of the block's surfaces the one
whose disparity the track's first stereo match has: the tracker may follow either side of an
edge); at every later frame that point, projected with the true pose, must be where the track is,
in the left and in the right image. Bounds are what the tracker achieves with a margin (measured
values in the comments, 50 frames of the default street, seed 0); where a target is not met
that is said in the test.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from vislam.backend.data.npz import load_sequence, save_sequence
from vislam.backend.data.sequence import validate_sequence
from vislam.backend.errors import ConfigError, InputError
from vislam.backend.geometry import se3
from vislam.backend.options import parse_assignment
from vislam.frontend.config import FundamentalMethod, TrackerConfig
from vislam.frontend.images import open_stereo_directory
from vislam.frontend.draw import TrackDrawer
from vislam.frontend.imu_input import read_imu, read_imu_T_cam
from vislam.frontend.track import check_imu, image_steps, iter_tracks, track_directory
from vislam.frontend.tracker import StereoTracker
from vislam.synth.observe import Calibration
from vislam.synth.render import RENDER_STREAM, Plane, build_street_planes, render_depth, render_pair, write_kitti_sequence
from vislam.synth.scene import SceneConfig, make_scene

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
KITTI = SHARED / "images" / "kitti_odom01_f000000-000050"
FRAMES = 50
#: The configuration that trades track length for clean tracks (see vislam.frontend.config).
STRICT = {"motion_threshold_px": 0.7, "affine_max_residual": 0.5, "affine_max_shift_px": 1.0}


# ---------------------------------------------------------------------------------------------- render_depth


def test_render_depth_is_the_z_of_the_visible_plane():
    cal = Calibration()
    K = np.asarray(cal.K, dtype=float)
    tex = np.random.default_rng(0).integers(0, 255, (64, 64), dtype=np.uint8)
    # in camera coordinates (cam_T_world = identity): a far wall z = 20 and a tilted quad in front of it
    far = Plane(np.array([[-30.0, -10, 20], [30, -10, 20], [30, 10, 20], [-30, 10, 20]]), tex, layer=3)
    tilt = Plane(np.array([[-1.0, -1, 4], [1, -1, 6], [1, 1, 6], [-1, 1, 4]]), tex, layer=3)
    depth = render_depth([far, tilt], np.eye(4), K, cal.image_size)
    assert depth.shape == (cal.height, cal.width)
    # rays through pixel centres meet the tilted plane z = 5 + x (x in [-1, 1]) or the wall
    v, u = np.mgrid[0 : cal.height, 0 : cal.width].astype(float)
    a = (u - K[0, 2]) / K[0, 0]  # x / z along the ray
    z_tilt = 5.0 / (1.0 - a)
    x, y = a * z_tilt, (v - K[1, 2]) / K[1, 1] * z_tilt
    on_tilt = (np.abs(x) < 0.98) & (np.abs(y) < 0.98)
    np.testing.assert_allclose(depth[on_tilt], z_tilt[on_tilt], rtol=1e-9)
    wall_only = (np.abs(x) > 1.05) | (np.abs(y) > 1.05)
    a_wall, b_wall = a * 20.0, (v - K[1, 2]) / K[1, 1] * 20.0
    wall = wall_only & (np.abs(a_wall) < 29) & (np.abs(b_wall) < 9.5)
    np.testing.assert_allclose(depth[wall], 20.0, rtol=1e-12)
    # nothing where no plane is
    assert np.isinf(render_depth([tilt], np.eye(4), K, cal.image_size)[~on_tilt & wall_only]).all()


# ---------------------------------------------------------------------------------------------- synthetic street


def _truth_point(depth: np.ndarray, K: np.ndarray, baseline: float, pixels: np.ndarray) -> np.ndarray | None:
    """Camera-frame 3-D point under the left pixel of ``pixels`` (uL vL uR vR), None on the sky."""
    u, v = pixels[0], pixels[1]
    u0, v0 = int(np.floor(u)), int(np.floor(v))
    block = depth[v0 : v0 + 2, u0 : u0 + 2]
    inv = np.where(np.isfinite(block), 1.0 / block, 0.0)
    if inv.max() - inv.min() <= 0.02 * inv.max() and inv.min() > 0:  # one plane: 1/z is affine
        a, b = u - u0, v - v0
        w = (1 - a) * (1 - b) * inv[0, 0] + a * (1 - b) * inv[0, 1] + (1 - a) * b * inv[1, 0] + a * b * inv[1, 1]
    else:  # a depth edge: the side whose disparity the track has
        w = inv.ravel()[np.argmin(np.abs(K[0, 0] * baseline * inv.ravel() - (pixels[0] - pixels[2])))]
    if w <= 0:
        return None
    z = 1.0 / w
    return np.array([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z])


def _track(pairs, K, baseline, config: TrackerConfig):
    tracker = StereoTracker(config, K, baseline)
    return [tracker.step(left, right) for left, right in pairs], tracker


def _errors(emitted, depths, world_T_cam, K, baseline):
    """Per track: max(|left error|, |right error|) at each frame it is seen (px)."""
    points, errors = {}, {}
    for k, (ids, pixels) in enumerate(emitted):
        cam_T_world = se3.inverse(world_T_cam[k])
        for i, z in zip(ids.tolist(), pixels):
            if i not in points:
                p_in_cam = _truth_point(depths[k], K, baseline, z)
                points[i] = None if p_in_cam is None else world_T_cam[k][:3, :3] @ p_in_cam + world_T_cam[k][:3, 3]
            if points[i] is None:
                continue
            p = cam_T_world[:3, :3] @ points[i] + cam_T_world[:3, 3]
            uL, v = K[0, 0] * p[0] / p[2] + K[0, 2], K[1, 1] * p[1] / p[2] + K[1, 2]
            uR = uL - K[0, 0] * baseline / p[2]
            e = max(np.hypot(uL - z[0], v - z[1]), np.hypot(uR - z[2], v - z[3]))
            errors.setdefault(i, []).append(e)
    return errors


@pytest.fixture(scope="module")
def street():
    """50 rendered frames of the default street scene (seed 0), their depth maps and true poses."""
    scene = make_scene(SceneConfig(steps=FRAMES, seed=0))
    cal = scene.config.calibration
    planes = build_street_planes(scene.world_T_imu_true, np.random.default_rng([0, RENDER_STREAM]))
    world_T_cam = scene.world_T_imu_true @ np.asarray(cal.imu_T_cam, dtype=float)
    K = np.asarray(cal.K, dtype=float)
    pairs = [render_pair(planes, T, cal) for T in scene.world_T_imu_true]
    depths = [render_depth(planes, se3.inverse(T), K, cal.image_size) for T in world_T_cam]
    return pairs, depths, world_T_cam, K, float(cal.baseline)


@pytest.fixture(scope="module")
def tracked(street):
    pairs, depths, world_T_cam, K, b = street
    emitted, tracker = _track(pairs, K, b, TrackerConfig())
    return emitted, tracker, _errors(emitted, depths, world_T_cam, K, b)


def test_tracks_stay_on_their_true_points(tracked):
    """Default configuration (tuned for the estimator: long tracks, few cuts)."""
    _, _, errors = tracked
    assert len(errors) > 1000
    every = np.concatenate([np.array(e) for e in errors.values()])
    worst = np.array([max(e) for e in errors.values()])
    assert np.median(every) <= 0.3  # bound 0.3 px; measured 0.17 px
    assert np.mean(worst > 2.0) <= 0.08  # a 1 % bound is met only by STRICT (next test); measured 6.5 %
    assert np.mean(worst > 10.0) <= 0.02  # gross failures; measured 0.55 %


def test_strict_configuration_meets_the_outlier_bound(street):
    pairs, depths, world_T_cam, K, b = street
    emitted, _ = _track(pairs, K, b, TrackerConfig.from_values(STRICT))
    errors = _errors(emitted, depths, world_T_cam, K, b)
    worst = np.array([max(e) for e in errors.values()])
    every = np.concatenate([np.array(e) for e in errors.values()])
    assert np.mean(worst > 2.0) <= 0.012  # bound 1 %; measured 0.88 %
    assert np.median(every) <= 0.2  # measured 0.11 px


def test_patch_scale_limit_ends_growing_tracks(tracked, street):
    """max_patch_scale = 1.3 ends tracks whose patch grew (approaching surfaces): measured 7032
    tracks with 1.7 % beyond 2 px, against 3644 and 6.5 % at the default 10."""
    pairs, depths, world_T_cam, K, b = street
    emitted, _ = _track(pairs, K, b, TrackerConfig.from_values({"max_patch_scale": 1.3}))
    errors = _errors(emitted, depths, world_T_cam, K, b)
    worst = np.array([max(e) for e in errors.values()])
    default_worst = np.array([max(e) for e in tracked[2].values()])
    assert len(errors) > 1.5 * len(tracked[2])
    assert np.mean(worst > 2.0) < 0.5 * np.mean(default_worst > 2.0)


def test_stereo_disparity_matches_true_depth(tracked, street):
    emitted, tracker, _ = tracked
    _, depths, _, K, b = street
    err = []
    for (ids, pixels), depth in zip(emitted, depths):
        for z in pixels:
            u0, v0 = int(np.floor(z[0])), int(np.floor(z[1]))
            block = depth[v0 : v0 + 2, u0 : u0 + 2]
            inv = 1.0 / block
            if np.all(np.isfinite(block)) and inv.max() - inv.min() <= 0.02 * inv.max():  # inside one plane
                a, c = z[0] - u0, z[1] - v0
                w = (1 - a) * (1 - c) * inv[0, 0] + a * (1 - c) * inv[0, 1] + (1 - a) * c * inv[1, 0] + a * c * inv[1, 1]
                err.append((z[0] - z[2]) - K[0, 0] * b * w)
        assert np.all(np.abs(pixels[:, 1] - pixels[:, 3]) <= tracker.config.stereo_row_tolerance_px + 1e-9)
        assert np.all(pixels[:, 0] - pixels[:, 2] > tracker.config.stereo_min_disparity_px)
    err = np.abs(np.array(err))
    assert err.size > 5000
    assert np.median(err) <= 0.1  # measured 0.047 px
    assert np.mean(err > 1.0) <= 0.03  # measured 1.6 %


def test_ids_never_come_back_and_increase_within_a_frame(tracked):
    emitted, tracker, errors = tracked
    seen_in: dict[int, list[int]] = {}
    for k, (ids, pixels) in enumerate(emitted):
        assert ids.dtype == np.int64 and pixels.dtype == np.float64 and pixels.shape == (ids.size, 4)
        assert np.all(np.diff(ids) > 0)
        for i in ids.tolist():
            seen_in.setdefault(i, []).append(k)
    for frames in seen_in.values():  # consecutive frames only: an id that disappears is gone for good
        assert frames == list(range(frames[0], frames[0] + len(frames)))
    assert sorted(seen_in) == list(range(tracker.num_ids))  # every issued id is used once, none skipped
    per_frame = np.array([ids.size for ids, _ in emitted])
    assert per_frame[1:].mean() >= 200  # measured 275 of the 300 targeted
    lengths = np.array([len(f) for f in seen_in.values()])
    # a median track length of 10 frames is out of reach here: the camera moves 0.8-1.2 m a frame
    # past walls 8-12 m away, and points spread evenly over the visible image stay in view (both
    # images, unoccluded) a median 4-5 frames, 30 % of them 10 or more
    # (benchmarks/street_track_life.py). Measured: median 2, 7 observation-weighted.
    assert np.median(np.repeat(lengths, lengths)) >= 5


def test_frame_statistics_account_for_every_track(street):
    """Every live track either survives a frame or is counted under exactly one reason."""
    pairs, _, _, K, b = street
    tracker = StereoTracker(TrackerConfig(), K, b)
    ended, border = 0, 0
    for left, right in pairs:
        ids, _ = tracker.step(left, right)
        s = tracker.last_stats
        lost = s.lost_border + s.lost_temporal + s.lost_appearance + s.lost_fundamental + s.lost_stereo + s.lost_motion
        assert s.live_in == lost + (s.emitted - s.new_ids)
        assert s.emitted == ids.size and s.new_ids == s.born
        ended, border = ended + lost, border + s.lost_border
    # forward motion: the commonest end is leaving the image (measured 40 %; LK / round trip 30 %)
    assert 0.25 <= border / ended <= 0.6


def test_birth_options_trade_coverage_for_length(street):
    """Two options, off by default (vislam.frontend.config says what each costs): birth_lookahead_frames
    starts only points predicted to stay in view that many frames; min_isotropy skips corners
    whose patch has edges nearly all in one direction, which LK and the affine refinement place
    badly along the edge (measured: a quarter of new tracks with isotropy < 0.1 were off by
    > 0.7 px after one frame, 9 % of those above 0.4)."""
    pairs, depths, world_T_cam, K, b = street

    def measure(**values):
        emitted, _ = _track(pairs, K, b, TrackerConfig.from_values(values))
        errors = _errors(emitted, depths, world_T_cam, K, b)
        lengths = np.array([len(e) for e in errors.values()])
        worst = np.array([max(e) for e in errors.values()])
        every = np.concatenate([np.array(e) for e in errors.values()])
        per_frame = np.mean([ids.size for ids, _ in emitted[1:]])
        return np.median(lengths), np.mean(worst > 2.0), np.median(every), per_frame

    length, stray, median, per_frame = measure(birth_lookahead_frames=5)
    assert length >= 3.5 and per_frame >= 250  # measured 4 (default 2), 277 a frame
    assert stray <= 0.13 and median <= 0.25  # longer tracks stray more: measured 10.4 %, 0.22 px
    length, stray, median, per_frame = measure(min_isotropy=0.2)
    assert length >= 3 and per_frame >= 250  # measured 3, 278 a frame
    assert stray <= 0.06 and median <= 0.17  # better than the default: measured 4.9 %, 0.159 px


# ---------------------------------------------------------------------------------------------- real images


@pytest.mark.skipif(not KITTI.is_dir(), reason=f"real KITTI images not found at {KITTI} (../shared/images)")
def test_real_kitti_frames():
    stereo = open_stereo_directory(KITTI)
    assert len(stereo) == 51 and stereo.image_size == (1241, 376)
    assert stereo.baseline == pytest.approx(386.1448 / 718.856, rel=1e-9)
    config = TrackerConfig()
    counts = []
    for index, ids, pixels in iter_tracks(stereo, config):
        counts.append(ids.size)
        assert np.all(np.abs(pixels[:, 1] - pixels[:, 3]) <= config.stereo_row_tolerance_px + 1e-9)
        assert np.all(pixels[:, 0] - pixels[:, 2] > 0)
    assert len(counts) == 51
    assert np.mean(counts) >= 150  # bound 100; measured 231


# ---------------------------------------------------------------------------------------------- featureless and tiny frames


def _texture(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A smooth random grey texture (cubic upsampling of noise): corners the tracker can follow."""
    small = rng.integers(0, 256, (height // 4 + 2, width // 4 + 2)).astype(np.float32)
    return np.clip(cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC), 0, 255).astype(np.uint8)


def _textured_pairs(n: int, black=(), size=(160, 96), disparity: int = 6, seed: int = 0):
    """``n`` stereo pairs of one textured plane sliding 1 px a frame (right image ``disparity`` px
    to the left); the frames in ``black`` are all zeros."""
    w, h = size
    scene = _texture(np.random.default_rng(seed), h, w + n + disparity + 2)
    pairs = []
    for k in range(n):
        left = np.ascontiguousarray(scene[:, k : k + w])
        right = np.ascontiguousarray(scene[:, k + disparity : k + disparity + w])
        if k in black:
            left, right = np.zeros_like(left), np.zeros_like(right)
        pairs.append((left, right))
    return pairs


def _write_pairs(root: Path, pairs, times=None) -> Path:
    """The KITTI layout of ``pairs`` under ``root`` (K: f = 100 px, centre of the image; baseline 0.5 m)."""
    h, w = pairs[0][0].shape
    for folder, side in (("image_0", 0), ("image_1", 1)):
        (root / folder).mkdir(parents=True)
        for k, pair in enumerate(pairs):
            assert cv2.imwrite(str(root / folder / f"{k:06d}.png"), pair[side])
    (root / "calib.txt").write_text(f"P0: 100 0 {w / 2} 0 0 100 {h / 2} 0 0 0 1 0\n"
                                    f"P1: 100 0 {w / 2} -50 0 100 {h / 2} 0 0 0 1 0\n")
    stamps = times if times is not None else [0.1 * k for k in range(len(pairs))]
    (root / "times.txt").write_text("".join(f"{t:.6e}\n" for t in stamps))
    return root


@pytest.mark.parametrize("black", [(0,), (3,), (2, 3), tuple(range(6))], ids=["first", "middle", "two", "all"])
def test_featureless_frames_give_no_observations_and_tracking_goes_on(tmp_path, black):
    """An all-black frame yields ids (0,) and pixels (0,4); the textured frames around it are tracked."""
    root = _write_pairs(tmp_path / "d", _textured_pairs(6, black))
    frames = list(iter_tracks(root, draw_dir=tmp_path / "draw"))
    assert [k for k, _, _ in frames] == list(range(6))
    for k, ids, pixels in frames:
        assert ids.dtype == np.int64 and pixels.dtype == np.float64
        if k in black:
            assert ids.shape == (0,) and pixels.shape == (0, 4), k
        else:
            assert ids.size >= 10 and pixels.shape == (ids.size, 4), (k, ids.size)
            assert np.all(np.diff(ids) > 0) and np.isfinite(pixels).all()
            assert np.all(pixels[:, 0] - pixels[:, 2] > 0)
    # a track never spans a black frame: ids after it are all new
    seen_before = {int(i) for k, ids, _ in frames if k < max(black) for i in ids}
    assert not seen_before & {int(i) for k, ids, _ in frames if k > max(black) for i in ids}
    assert sorted(p.name for p in (tmp_path / "draw").iterdir()) == [f"{k:06d}.png" for k in range(6)]


@pytest.mark.parametrize("size", [(8, 8), (20, 15), (17, 40), (1, 1)])
def test_images_too_small_to_track_are_refused_before_any_work(tmp_path, size):
    rng = np.random.default_rng(1)
    pairs = [(rng.integers(0, 256, size[::-1], dtype=np.uint8),) * 2 for _ in range(3)]
    root = _write_pairs(tmp_path / "d", pairs)
    label = f"{size[0]}x{size[1]}"
    for call in (lambda: iter_tracks(root, draw_dir=tmp_path / "draw"),
                 lambda: track_directory(root, tmp_path / "no_imu.csv", draw_dir=tmp_path / "draw")):
        with pytest.raises(InputError) as info:
            call()  # raised on the call, before any frame is read
        message = str(info.value)
        assert str(root) in message and label in message and "too small" in message and "\n" not in message
        assert f"{TrackerConfig().min_image_side} px" in message
    assert not (tmp_path / "draw").exists()
    with pytest.raises(ValueError, match="too small"):
        StereoTracker().step(*pairs[0])


def test_min_image_side_is_what_the_options_need():
    assert TrackerConfig().min_image_side == 18  # 2 border_px + 2
    assert TrackerConfig.from_values({"border_px": 0}).min_image_side == 15  # lk_window, affine_window
    assert TrackerConfig.from_values({"border_px": 0, "lk_window": 3, "affine_window": 0}).min_image_side == 9  # subpix
    assert TrackerConfig.from_values({"border_px": 0, "lk_window": 3, "affine_window": 0, "subpix_window": 0,
                                      }).min_image_side == 3
    assert TrackerConfig.from_values({"lk_window": 31}).min_image_side == 31


_TRACKER_OPTIONS = [{}, {"border_px": 0}, {"border_px": 0, "lk_window": 3, "affine_window": 0},
                    {"stereo_seed_scale": 8, "lk_levels": 6, "lk_levels_tracked": 5},
                    {"verify_births": True, "motion_threshold_px": 0.7, "birth_lookahead_frames": 3, "min_isotropy": 0.2,
                     "confirm_frames": 1, "predict_flow": False, "fundamental_method": "ransac"}]


@settings(max_examples=60, deadline=None)
@example(options={}, extra=(0, 6), kinds=["noise"], seed=0)  # shrunk pair too small for the disparity seeds' block matcher
@given(options=st.sampled_from(_TRACKER_OPTIONS), extra=st.tuples(st.integers(-2, 14), st.integers(-2, 14)),
       kinds=st.lists(st.sampled_from(["black", "white", "noise", "texture", "dots"]), min_size=1, max_size=5),
       seed=st.integers(0, 2**16))
def test_any_frames_are_tracked_or_refused_for_their_size(options, extra, kinds, seed):
    """Frames of any content at sizes around ``min_image_side``: refused (ValueError) exactly when a
    side is smaller, else every frame gives ids (n,) and finite pixels (n,4), none for a blank frame."""
    config = TrackerConfig.from_values(options)
    w, h = (max(1, config.min_image_side + e) for e in extra)
    rng = np.random.default_rng(seed)
    tracker = StereoTracker(config, np.array([[100.0, 0, w / 2], [0, 100, h / 2], [0, 0, 1]]), 0.5)
    scene = _texture(rng, h, w + 8)
    for k, kind in enumerate(kinds):
        if kind in ("black", "white"):
            wide = np.full((h, w + 8), 0 if kind == "black" else 255, np.uint8)
        elif kind == "noise":
            wide = rng.integers(0, 256, (h, w + 8), dtype=np.uint8)
        elif kind == "dots":
            wide = np.zeros((h, w + 8), np.uint8)
            wide[rng.integers(0, h, 6), rng.integers(0, w + 8, 6)] = 255
        else:
            wide = scene
        shift = k % 3
        left = np.ascontiguousarray(wide[:, 4 + shift : 4 + shift + w])
        right = np.ascontiguousarray(wide[:, 1 + shift : 1 + shift + w])
        if min(w, h) < config.min_image_side:
            with pytest.raises(ValueError, match="too small"):
                tracker.step(left, right)
            return
        ids, pixels = tracker.step(left, right)
        assert ids.shape == (pixels.shape[0],) and pixels.shape[1:] == (4,) and np.isfinite(pixels).all()
        if kind in ("black", "white"):
            assert ids.size == 0


def test_draw_directory_that_cannot_be_one_is_refused(tmp_path, monkeypatch):
    a_file = tmp_path / "pictures"
    a_file.write_text("not a directory")
    for path in (a_file, a_file / "sub"):
        with pytest.raises(InputError) as info:
            TrackDrawer(path)
        assert str(path) in str(info.value) and "not a directory" in str(info.value) and "\n" not in str(info.value)
    root = _write_pairs(tmp_path / "d", _textured_pairs(2))
    with pytest.raises(InputError, match="pictures"):
        iter_tracks(root, draw_dir=a_file)  # on the call, before any frame
    assert a_file.read_text() == "not a directory"
    drawn = TrackDrawer(tmp_path / "new" / "dir")  # missing parents are made
    assert drawn.out_dir.is_dir()
    import vislam.frontend.draw as draw

    monkeypatch.setattr(draw.os, "access", lambda path, mode: False)  # as a read-only directory answers
    for path in (tmp_path / "new" / "dir", tmp_path / "new" / "other"):
        with pytest.raises(InputError, match="not writable") as info:
            TrackDrawer(path)
        assert str(path) in str(info.value)
    assert not (tmp_path / "new" / "other").exists()


# ---------------------------------------------------------------------------------------------- inputs


def _kitti_dir(root: Path, n: int = 4, size=(64, 48)) -> Path:
    rng = np.random.default_rng(0)
    for folder in ("image_0", "image_1"):
        (root / folder).mkdir(parents=True)
        for i in range(n):
            cv2.imwrite(str(root / folder / f"{i:06d}.png"), rng.integers(0, 255, size[::-1], dtype=np.uint8))
    (root / "calib.txt").write_text(
        "P0: 700 0 32 0 0 700 24 0 0 0 1 0\nP1: 700 0 32 -350 0 700 24 0 0 0 1 0\nTr: 1 0 0 0 0 1 0 0 0 0 1 0\n"
    )
    (root / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(n)))
    return root


def test_directory_reader(tmp_path):
    stereo = open_stereo_directory(_kitti_dir(tmp_path / "ok"))
    assert len(stereo) == 4 and stereo.image_size == (64, 48)
    assert stereo.baseline == pytest.approx(0.5) and stereo.K[0, 0] == 700.0 and stereo.K[1, 2] == 24.0
    np.testing.assert_allclose(stereo.times, [0.0, 0.1, 0.2, 0.3])
    frames = list(stereo.frames())
    assert [i for i, _, _ in frames] == [0, 1, 2, 3] and frames[2][1].shape == (48, 64)


def _break(root: Path, what: str) -> str:
    """Damage a good directory; returns the file name the error must name."""
    if what == "missing image_1":
        shutil.rmtree(root / "image_1")
        return "image_1"
    if what == "bad calib":
        (root / "calib.txt").write_text("P0: 700 0 32 0 0 700 24 0 0 0 1 0\nP1: 1 2 3\n")
        return "calib.txt"
    if what == "K differs":
        (root / "calib.txt").write_text("P0: 700 0 32 0 0 700 24 0 0 0 1 0\nP1: 710 0 32 -350 0 700 24 0 0 0 1 0\n")
        return "calib.txt"
    if what == "negative baseline":
        (root / "calib.txt").write_text("P0: 700 0 32 0 0 700 24 0 0 0 1 0\nP1: 700 0 32 350 0 700 24 0 0 0 1 0\n")
        return "calib.txt"
    if what == "frame count mismatch":
        (root / "image_1" / "000003.png").unlink()
        return "image_1"
    if what == "times count":
        (root / "times.txt").write_text("0\n0.1\n0.2\n")
        return "times.txt"
    if what == "non-increasing times":
        (root / "times.txt").write_text("0\n0.1\n0.1\n0.3\n")
        return "times.txt"
    if what == "empty":
        for folder in ("image_0", "image_1"):
            for p in (root / folder).iterdir():
                p.unlink()
        return "image_0"
    if what == "size mismatch":
        cv2.imwrite(str(root / "image_1" / "000000.png"), np.zeros((40, 64), np.uint8))
        return "000000.png"
    raise AssertionError(what)


@pytest.mark.parametrize("what", ["missing image_1", "bad calib", "K differs", "negative baseline",
                                  "frame count mismatch", "times count", "non-increasing times", "empty",
                                  "size mismatch"])
def test_directory_reader_refuses_in_one_line(tmp_path, what):
    root = _kitti_dir(tmp_path / "d")
    name = _break(root, what)
    with pytest.raises(InputError) as info:
        open_stereo_directory(root)
    assert name in str(info.value) and "\n" not in str(info.value)


def test_longer_times_txt_gives_the_first_stamps(tmp_path):
    root = _kitti_dir(tmp_path / "d", n=4)
    (root / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(9)) + "# stamps of frames past the last image\n")
    np.testing.assert_allclose(open_stereo_directory(root).times, [0.0, 0.1, 0.2, 0.3])
    (root / "times.txt").write_text("0\n0.1\n0.2\n")
    with pytest.raises(InputError, match=r"times\.txt: 3 time stamps for 4 frames"):
        open_stereo_directory(root)


def test_unreadable_or_resized_frame_is_named_when_read(tmp_path):
    root = _kitti_dir(tmp_path / "d")
    (root / "image_0" / "000002.png").write_bytes(b"not a png")
    cv2.imwrite(str(root / "image_1" / "000001.png"), np.zeros((48, 60), np.uint8))
    stereo = open_stereo_directory(root)
    with pytest.raises(InputError, match=r"image_1/000001\.png.*differs"):
        stereo.read(1)
    with pytest.raises(InputError, match=r"image_0/000002\.png.*unreadable"):
        list(stereo.frames(start=2))


def _write_extrinsic(path: Path, T: np.ndarray) -> Path:
    path.write_text("# imu_T_cam\n" + "\n".join(" ".join(repr(float(x)) for x in row) for row in T) + "\n")
    return path


def test_imu_csv(tmp_path):
    T = np.array([[0.0, 0, 1, 1.0], [-1, 0, 0, 0.1], [0, -1, 0, 0.5], [0, 0, 0, 1]])
    ext = _write_extrinsic(tmp_path / "imu_T_cam.txt", T)
    csv = tmp_path / "imu.csv"
    csv.write_text("t,vx,vy,vz,wx,wy,wz\n" + "".join(f"{10 + 0.1 * i},{i},0,0,0,0,0.01\n" for i in range(6)))
    imu = read_imu(csv, 4, ext)
    assert len(imu) == 4
    np.testing.assert_allclose(imu.time_stamps, [10.0, 10.1, 10.2, 10.3])
    np.testing.assert_allclose(imu.linear_velocity[:, 0], [0, 1, 2, 3])
    np.testing.assert_array_equal(imu.imu_T_cam, T)
    headless = tmp_path / "plain.csv"
    headless.write_text("".join(f"{0.1 * i} 1 2 3 4 5 6\n" for i in range(4)))  # no header, spaces
    np.testing.assert_allclose(read_imu(headless, 4, ext).angular_velocity[2], [4, 5, 6])


@pytest.mark.parametrize(
    "text, needle",
    [
        ("".join(f"{0.1 * i},1,nan,0,0,0,0\n" for i in range(5)), "non-finite"),
        ("".join(f"{0.1 * i},1,0,0,0,0,0\n" for i in range(3)), "3 IMU rows for 4"),
        ("0,1,0,0,0,0,0\n0.1,1,0,0,0,0,0\n0.1,1,0,0,0,0,0\n0.3,1,0,0,0,0,0\n", "not strictly increasing"),
        ("t,vx\n0,1,0,0,0,0\n", "expected 7 values"),
    ],
    ids=["nan", "too short", "repeated time", "six columns"],
)
def test_imu_csv_refusals_name_the_file(tmp_path, text, needle):
    ext = _write_extrinsic(tmp_path / "e.txt", np.eye(4))
    csv = tmp_path / "velocities.csv"
    csv.write_text(text)
    with pytest.raises(InputError) as info:
        read_imu(csv, 4, ext)
    assert "velocities.csv" in str(info.value) and needle in str(info.value) and "\n" not in str(info.value)


def test_imu_csv_needs_an_extrinsic_and_a_rigid_one(tmp_path):
    csv = tmp_path / "imu.csv"
    csv.write_text("".join(f"{0.1 * i},1,0,0,0,0,0\n" for i in range(4)))
    with pytest.raises(InputError, match="--imu-T-cam"):
        read_imu(csv, 4)
    scaled = np.eye(4)
    scaled[0, 0] = 2.0
    with pytest.raises(InputError, match="rigid"):
        read_imu_T_cam(_write_extrinsic(tmp_path / "s.txt", scaled))
    mirror = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(InputError, match="reflection"):
        read_imu_T_cam(_write_extrinsic(tmp_path / "m.txt", mirror))
    (tmp_path / "short.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n")
    with pytest.raises(InputError, match="short.txt"):
        read_imu_T_cam(tmp_path / "short.txt")


def test_imu_npz_keeps_its_stamps_and_extrinsic(tmp_path):
    scene = make_scene(SceneConfig(steps=12, seed=2))
    path = tmp_path / "data.npz"
    save_sequence(scene.sequence, path)
    imu = read_imu(path, 10)
    np.testing.assert_array_equal(imu.time_stamps, scene.sequence.time_stamps[:10])
    np.testing.assert_array_equal(imu.angular_velocity, scene.sequence.angular_velocity[:10])
    np.testing.assert_allclose(imu.imu_T_cam, scene.sequence.imu_T_cam)
    with pytest.raises(InputError, match="data.npz"):
        read_imu(path, 13)


# ---------------------------------------------------------------------------------------------- output


def test_track_directory_round_trips_through_the_course_layout(tmp_path):
    scene = make_scene(SceneConfig(steps=8, seed=1))
    images = write_kitti_sequence(tmp_path / "images", scene)
    imu_file = tmp_path / "data.npz"
    save_sequence(scene.sequence, imu_file)
    calls = []
    config = TrackerConfig.from_values({"target_tracks": 150})
    seq = track_directory(images, imu_file, config,
                          progress=lambda k, n: calls.append((k, n)), draw_dir=tmp_path / "draw")
    validate_sequence(seq)
    assert calls == [(k, 8) for k in range(8)]
    assert seq.num_steps == 8 and seq.num_observations >= 8 * 100
    np.testing.assert_array_equal(seq.time_stamps, scene.sequence.time_stamps)  # the IMU file's stamps
    np.testing.assert_array_equal(seq.linear_velocity, scene.sequence.linear_velocity)
    np.testing.assert_allclose(seq.imu_T_cam, scene.sequence.imu_T_cam)
    np.testing.assert_allclose(seq.K, scene.sequence.K, atol=1e-9)
    assert seq.baseline == pytest.approx(scene.sequence.baseline, rel=1e-9)
    assert seq.num_features == seq.obs_ids.max() + 1
    # the online path gives the same tracks
    online = list(iter_tracks(images, config))
    for k, ids, pixels in online:
        got_ids, got_pixels = seq.observations(k)
        np.testing.assert_array_equal(ids, got_ids)
        np.testing.assert_array_equal(pixels, got_pixels)
    # ... and so do the filter's steps of a one-pass run, each with the IMU sample of its frame
    stereo = open_stereo_directory(images)
    steps = list(image_steps(stereo, check_imu(imu_file, stereo), config))
    assert len(steps) == 8
    for k, (t, v, w, ids, pixels) in enumerate(steps):
        assert t == scene.sequence.time_stamps[k]
        np.testing.assert_array_equal(v, scene.sequence.linear_velocity[k])
        np.testing.assert_array_equal(w, scene.sequence.angular_velocity[k])
        got_ids, got_pixels = seq.observations(k)
        np.testing.assert_array_equal(ids, got_ids)
        np.testing.assert_array_equal(pixels, got_pixels)
    # written and read back: the same observations
    out = tmp_path / "tracks.npz"
    save_sequence(seq, out)
    back = load_sequence(out)
    assert back.dropped == {"nonpositive_disparity": 0, "outside_image": 0}
    assert back.num_features == seq.num_features
    np.testing.assert_array_equal(back.obs_ptr, seq.obs_ptr)
    np.testing.assert_array_equal(back.obs_ids, seq.obs_ids)
    np.testing.assert_array_equal(back.obs_pixels, seq.obs_pixels)
    # one debug picture a frame: left above right
    names = sorted(p.name for p in (tmp_path / "draw").iterdir())
    assert names == [f"{k:06d}.png" for k in range(8)]
    from vislam.frontend.draw import CAPTION_HEIGHT

    assert cv2.imread(str(tmp_path / "draw" / names[3])).shape == (CAPTION_HEIGHT + 2 * 376, 1241, 3)


def test_track_directory_refuses_a_short_imu(tmp_path):
    images = _kitti_dir(tmp_path / "d", n=4)
    csv = tmp_path / "imu.csv"
    csv.write_text("".join(f"{0.1 * i},1,0,0,0,0,0\n" for i in range(3)))
    ext = _write_extrinsic(tmp_path / "e.txt", np.eye(4))
    with pytest.raises(InputError, match="imu.csv"):
        track_directory(images, csv, imu_T_cam_path=ext)


# ---------------------------------------------------------------------------------------------- configuration


def test_tracker_config(tmp_path):
    config = TrackerConfig()
    assert config.validate() is config
    listing = config.describe()
    assert "[tracker]" in listing
    for f in dataclasses.fields(config):
        assert f.name in listing
    # strings (the command line's --set tracker.KEY=VALUE, dashes as underscores) are coerced
    changed = TrackerConfig.from_values(
        dict(parse_assignment(a) for a in ["target_tracks=120", "predict-flow=no", "fundamental_method=ransac"]), config)
    assert (changed.target_tracks, changed.predict_flow, changed.fundamental_method) == (120, False, "ransac")
    assert changed.fundamental_method is FundamentalMethod.RANSAC
    assert config.target_tracks == 300  # the original is untouched
    for key, value in [("lk_window", "20"), ("target_tracks", "0"), ("stereo_min_disparity_px", "0"),
                       ("fundamental_method", "lmeds"), ("stereo_max_disparity_px", "0.05"), ("no_such_key", "1"),
                       ("target_tracks", "many"), ("stereo_seed_scale", "3"), ("min_isotropy", "1"),
                       ("min_isotropy", "-0.1"), ("birth_lookahead_frames", "-1"), ("max_patch_scale", "1"),
                       ("max_patch_scale", "inf")]:
        with pytest.raises(ConfigError, match=f"'tracker.{key}'"):
            TrackerConfig.from_values({key: value}, config)
    # the [tracker] table of a TOML file, over a base; its other tables are not read
    path = tmp_path / "config.toml"
    path.write_text('[noise]\npixel_sigma = 2.0\n' + changed.to_toml())
    assert TrackerConfig.load(path) == changed
    path.write_text("[tracker]\ntarget_tracks = 120\n")
    over = TrackerConfig.load(path, TrackerConfig.from_values({"grid_cols": 6}))
    assert (over.target_tracks, over.grid_cols) == (120, 6)
    path.write_text("[tracker]\nlk_window = 20\n")
    with pytest.raises(ConfigError, match="'tracker.lk_window'") as info:
        TrackerConfig.load(path)
    assert str(path) in str(info.value)


def test_command_line_splits_tracker_and_filter_options():
    """One --set list: tracker.KEY goes to the front end, every other table to the filter."""
    from argparse import Namespace

    from vislam.tools.options import filter_config, tracker_config

    args = Namespace(config=None, set=["noise.pixel_sigma=2", "tracker.target_tracks=100", "tracker.lk-window=21"])
    assert filter_config(args).noise.pixel_sigma == 2.0
    tracker = tracker_config(args)
    assert (tracker.target_tracks, tracker.lk_window) == (100, 21)
    with pytest.raises(ConfigError, match="noise.pixel_sigma"):  # `vislam track` reads only [tracker]
        tracker_config(args, only=True)
    with pytest.raises(ConfigError, match="'target_tracks' is now 'tracker.target_tracks'"):
        tracker_config(Namespace(config=None, set=["target_tracks=100"]))
