"""ROS bags as input (``frontend.bag``, ``frontend.kalibr``): bags written with rosbags from the
EuRoC slice give what its ASL folder gives; Kalibr files give its rectification; topics, damage
and calibration errors end in one line."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bags import euroc_messages, synthetic_street_bag, truth_messages, write_bag, write_camchain, write_kalibr_imu
from helpers import assert_clean_input_error
from vislam.backend.data.tum import read_tum
from vislam.backend.errors import InputError
from vislam.frontend.bag import is_bag, open_bag
from vislam.frontend.euroc import StereoRectification, read_euroc
from vislam.frontend.kalibr import read_camchain, read_kalibr_imu
from vislam.frontend.track import track_euroc
from vislam.tools.cli import main

pytest.importorskip("rosbags", reason="rosbags (the ros extra) is not installed")

EUROC = Path(__file__).resolve().parents[1].parent / "shared" / "euroc" / "V1_01_easy_first40" / "mav0"
needs_euroc = pytest.mark.skipif(not EUROC.is_dir(), reason=f"EuRoC data not found at {EUROC} (../shared/euroc)")


@pytest.fixture(scope="module")
def euroc():
    return read_euroc(EUROC)


@pytest.fixture(scope="module")
def bags(euroc, tmp_path_factory):
    """ROS 1 (raw), ROS 2 (raw) and ROS 1 (PNG, lossless) bags of the slice, its Kalibr files."""
    root = tmp_path_factory.mktemp("bags")
    out = {"ros1": write_bag(root / "v1.bag", euroc_messages(euroc, True), True),
           "ros2": write_bag(root / "v1_ros2", euroc_messages(euroc, False), False),
           "ros2_mcap": write_bag(root / "v1_mcap", euroc_messages(euroc, False), False, mcap=True),
           "ros1_png": write_bag(root / "v1_png.bag", euroc_messages(euroc, True, "png"), True),
           "ros2_png": write_bag(root / "v1_png_ros2", euroc_messages(euroc, False, "png"), False),
           "ros2_jpeg": write_bag(root / "v1_jpeg_ros2", euroc_messages(euroc, False, "jpeg"), False)}
    out["camchain"] = write_camchain(root / "camchain.yaml", euroc)
    out["imu"] = write_kalibr_imu(root / "imu.yaml", euroc.imu.samples.noise)
    return out


@needs_euroc
@pytest.mark.parametrize("kind", ["ros1", "ros2", "ros2_mcap", "ros1_png", "ros2_png"])
def test_a_bag_with_the_folders_calibration_tracks_as_the_folder(bags, euroc, kind):
    """The same pairs, stamps, IMU samples, rectification and tracks as the ASL folder, exactly."""
    data = open_bag(bags[kind], EUROC)
    assert len(data.frames) == len(euroc.frames) and data.frames.unmatched == 0
    assert np.array_equal(data.frames.times, euroc.frames.times)
    assert (data.topics.left, data.topics.right, data.topics.imu) == ("/cam0/image_raw", "/cam1/image_raw", "/imu0")
    ours, theirs = track_euroc(data), track_euroc(euroc)
    assert np.array_equal(ours.imu.time_stamps, theirs.imu.time_stamps)
    assert np.array_equal(ours.imu.linear_acceleration, theirs.imu.linear_acceleration)
    assert ours.imu.noise == theirs.imu.noise
    assert np.array_equal(ours.K, theirs.K) and np.array_equal(ours.imu_T_cam, theirs.imu_T_cam)
    for k in (0, 17, len(euroc.frames) - 1):
        (ia, za), (ib, zb) = ours.observations(k), theirs.observations(k)
        assert np.array_equal(ia, ib) and np.array_equal(za, zb)


@needs_euroc
def test_jpeg_images_are_decoded(bags, euroc):
    """Lossy JPEG: the same pairs and stamps; the decoded pixels within JPEG's error of the raw ones."""
    import cv2

    data = open_bag(bags["ros2_jpeg"], EUROC)
    assert np.array_equal(data.frames.times, euroc.frames.times)
    k, left, right = next(iter(data.pairs()))
    raw_left, raw_right = euroc.read_pair(0)
    assert k == 0 and left.shape == raw_left.shape and left.dtype == np.uint8
    assert cv2.PSNR(left, raw_left) > 30 and cv2.PSNR(right, raw_right) > 30
    assert track_euroc(data).num_observations > 0.8 * track_euroc(euroc).num_observations


@needs_euroc
def test_vislam_run_on_a_bag_gives_the_folders_trajectory(bags, tmp_path):
    assert main(["run", str(EUROC), "--out", str(tmp_path / "a"), "--quiet"]) == 0
    assert main(["run", str(bags["ros2"]), "--calib", str(EUROC), "--out", str(tmp_path / "b"), "--quiet",
                 "--gt", str(tmp_path / "a" / "ground_truth.txt")]) == 0
    (ta, a), (tb, b) = read_tum(tmp_path / "a" / "trajectory.txt"), read_tum(tmp_path / "b" / "trajectory.txt")
    assert np.array_equal(ta, tb) and np.abs(a - b).max() <= 1e-9
    # with Kalibr's files written from the same numbers: the rectification of their round-off
    assert main(["run", str(bags["ros1"]), "--calib", str(bags["camchain"]), "--imu-calib", str(bags["imu"]),
                 "--out", str(tmp_path / "c"), "--quiet"]) == 0
    _, c = read_tum(tmp_path / "c" / "trajectory.txt")
    assert np.abs(a - c).max() <= 1e-4


@needs_euroc
@pytest.mark.parametrize("ros1", [True, False])
@pytest.mark.parametrize("msgtype", ["geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/TransformStamped",
                                     "nav_msgs/msg/Odometry"])
def test_ground_truth_from_a_topic(euroc, tmp_path, ros1, msgtype):
    messages = euroc_messages(euroc, ros1, frames=3) + truth_messages(euroc, ros1, msgtype, every=7)
    bag = write_bag(tmp_path / ("t.bag" if ros1 else "t2"), sorted(messages, key=lambda m: m[0]), ros1)
    data = open_bag(bag, EUROC, gt_topic="/truth")
    truth = data.ground_truth
    np.testing.assert_array_equal(truth.times, euroc.ground_truth.times[::7])
    np.testing.assert_allclose(truth.world_T_imu, euroc.ground_truth.world_T_imu[::7], atol=1e-9)
    assert msgtype in truth.source
    with pytest.raises(InputError, match="is sensor_msgs/msg/Imu, not one of"):
        open_bag(bag, EUROC, gt_topic="/imu0")


@needs_euroc
def test_vislam_run_evaluates_against_a_ground_truth_topic(euroc, tmp_path):
    """The same ATE as the folder's run, which reads the same poses from its csv."""
    import json

    messages = euroc_messages(euroc, False) + truth_messages(euroc, False, "geometry_msgs/msg/PoseStamped")
    bag = write_bag(tmp_path / "gt_bag", sorted(messages, key=lambda m: m[0]), False)
    assert main(["run", str(EUROC), "--out", str(tmp_path / "a"), "--quiet"]) == 0
    assert main(["run", str(bag), "--calib", str(EUROC), "--gt-topic", "/truth", "--out", str(tmp_path / "b"),
                 "--quiet"]) == 0
    a, b = (json.loads((tmp_path / d / "summary.json").read_text())["errors"] for d in "ab")
    assert b["estimate"]["ate_rmse"] == pytest.approx(a["estimate"]["ate_rmse"], rel=1e-9)
    ta, ga = read_tum(tmp_path / "a" / "ground_truth.txt")
    tb, gb = read_tum(tmp_path / "b" / "ground_truth.txt")
    assert np.array_equal(ta, tb) and np.abs(ga - gb).max() < 1e-8
    assert main(["run", str(bag), "--calib", str(EUROC), "--gt-topic", "/truth", "--gt",
                 str(tmp_path / "a" / "ground_truth.txt"), "--out", str(tmp_path / "c")]) == 2


@needs_euroc
def test_kalibr_files_give_the_folders_rectification(euroc, tmp_path):
    for chain in (False, True):
        cameras = read_camchain(write_camchain(tmp_path / f"c{chain}.yaml", euroc, chain=chain))
        ours = StereoRectification.from_cameras(cameras.cam0, cameras.cam1)
        np.testing.assert_allclose(ours.K, euroc.rectification.K, rtol=1e-9)
        assert ours.baseline == pytest.approx(euroc.rectification.baseline, rel=1e-9)
        np.testing.assert_allclose(ours.map_left_x, euroc.rectification.map_left_x, atol=1e-3)
        np.testing.assert_allclose(ours.body_T_cam0, euroc.cam0.body_T_cam, atol=1e-12)
        assert cameras.topics == ("/cam0/image_raw", "/cam1/image_raw") and cameras.timeshift == 0.0
    noise, topic = read_kalibr_imu(write_kalibr_imu(tmp_path / "imu.yaml", euroc.imu.samples.noise))
    assert topic == "/imu0"
    assert noise.gyroscope_noise_density == euroc.imu.samples.noise.gyroscope_noise_density


@needs_euroc
def test_timeshift_moves_the_frames_into_imu_time(euroc, bags, tmp_path):
    calib = write_camchain(tmp_path / "c.yaml", euroc, timeshift=0.0125)
    data = open_bag(bags["ros1"], calib)
    np.testing.assert_allclose(data.frames.times, euroc.frames.times + 0.0125, atol=1e-9)
    assert any("timeshift_cam_imu +0.012500 s" in n for n in data.notes)


@needs_euroc
def test_topics_are_found_or_named(euroc, tmp_path, capsys):
    """Without rostopic entries two image topics and one IMU topic are found; a third image topic
    makes it ambiguous: one line listing every topic; a named topic of the wrong type is refused."""
    messages = euroc_messages(euroc, True, frames=3)
    calib = write_camchain(tmp_path / "c.yaml", euroc, topics=(None, None))
    bag = write_bag(tmp_path / "two.bag", messages, True)
    data = open_bag(bag, calib)
    assert (data.topics.left, data.topics.right, data.topics.imu) == ("/cam0/image_raw", "/cam1/image_raw", "/imu0")
    extra = [(ns, "/cam2/image_raw", typ, msg) for ns, topic, typ, msg in messages if topic == "/cam0/image_raw"]
    bag3 = write_bag(tmp_path / "three.bag", sorted(messages + extra, key=lambda m: m[0]), True)
    with pytest.raises(InputError) as e:
        open_bag(bag3, calib)
    msg = assert_clean_input_error(e.value, str(bag3))
    assert "--left-topic" in msg and "/cam2/image_raw (sensor_msgs/msg/Image)" in msg and "/imu0" in msg
    data = open_bag(bag3, calib, left_topic="/cam0/image_raw", right_topic="/cam2/image_raw")
    assert data.topics.right == "/cam2/image_raw"
    with pytest.raises(InputError, match="is sensor_msgs/msg/Imu, not"):
        open_bag(bag, calib, left_topic="/imu0")
    with pytest.raises(InputError, match="no topic /nope"):
        open_bag(bag, calib, imu_topic="/nope")
    # the command line: the same line, exit 2, nothing written
    assert main(["track", str(bag3), "--calib", str(calib), "--out", str(tmp_path / "t.npz")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--left-topic" in err and not (tmp_path / "t.npz").exists()


@needs_euroc
def test_unmatched_images_and_shuffled_imu_messages(euroc, tmp_path):
    """A right image 20 ms off has no partner (dropped, counted); IMU messages written out of order
    are put in the order of their stamps."""
    messages = euroc_messages(euroc, True, frames=6)
    rights = [i for i, m in enumerate(messages) if m[1] == "/cam1/image_raw"]
    ns, topic, typ, msg = messages[rights[2]]
    msg.header.stamp.nanosec = (msg.header.stamp.nanosec + 20_000_000) % 10**9
    imus = [i for i, m in enumerate(messages) if m[1] == "/imu0"]
    a, b = imus[100], imus[101]
    messages[a], messages[b] = messages[b], messages[a]
    calib = write_camchain(tmp_path / "c.yaml", euroc)
    data = open_bag(write_bag(tmp_path / "x.bag", messages, True), calib)
    assert len(data.frames) == 5 and data.frames.unmatched == 2
    assert any("2 images" in n and "without a partner" in n for n in data.notes)
    assert np.array_equal(data.imu.samples.time_stamps, euroc.imu.samples.time_stamps)
    pairs = list(data.pairs())
    assert [k for k, _, _ in pairs] == list(range(5))


@needs_euroc
def test_damaged_bags_end_in_one_line(euroc, bags, tmp_path):
    calib = write_camchain(tmp_path / "c.yaml", euroc)
    cut = tmp_path / "cut.bag"
    cut.write_bytes(bags["ros1"].read_bytes()[: 2_000_000])
    folder = tmp_path / "broken_ros2"
    shutil.copytree(bags["ros2"], folder)
    (folder / "metadata.yaml").write_text("rosbag2_bagfile_information: [")
    for path in (cut, folder):
        with pytest.raises(InputError) as e:
            list(open_bag(path, calib).pairs())
        assert_clean_input_error(e.value, str(path))
    no_imu = write_bag(tmp_path / "no_imu.bag", [m for m in euroc_messages(euroc, True, frames=3)
                                                  if m[1] != "/imu0"], True)
    with pytest.raises(InputError) as e:
        open_bag(no_imu, calib)
    assert "--imu-topic" in assert_clean_input_error(e.value, str(no_imu))


def test_bag_options_are_refused_for_other_inputs(tmp_path, capsys):
    (tmp_path / "x.npz").write_bytes(b"")
    assert main(["run", str(tmp_path / "x.npz"), "--calib", "c.yaml", "--out", str(tmp_path / "o")]) == 2
    assert "--calib is for a ROS bag" in capsys.readouterr().err
    assert is_bag(tmp_path / "x.bag") is False
    (tmp_path / "x.bag").write_bytes(b"")
    (tmp_path / "r2").mkdir()
    (tmp_path / "r2" / "metadata.yaml").write_text("")
    assert is_bag(tmp_path / "x.bag") and is_bag(tmp_path / "r2")
    assert main(["run", str(tmp_path / "x.bag"), "--out", str(tmp_path / "o")]) == 2
    assert "--calib camchain.yaml" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------
# Kalibr's files (property-based)

SETTINGS = {"deadline": None, "suppress_health_check": [HealthCheck.too_slow]}


def _camchain_doc(fu, cu, tx, shift):
    def cam(t):
        T = np.eye(4)
        T[0, 3] = t
        return dict(camera_model="pinhole", intrinsics=[fu, fu, cu, 240.0], distortion_model="radtan",
                    distortion_coeffs=[-0.28, 0.07, 0.0, 0.0], resolution=[752, 480], T_cam_imu=T.tolist(),
                    timeshift_cam_imu=shift)

    return {"cam0": cam(tx), "cam1": cam(tx - 0.11)}


@settings(max_examples=60, **SETTINGS)
@given(fu=st.floats(100, 2000), cu=st.floats(1, 751), tx=st.floats(-1, 1), shift=st.floats(-0.5, 0.5))
def test_camchain_valid_files_are_read_property(fu, cu, tx, shift):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "camchain.yaml"
        path.write_text(yaml.safe_dump(_camchain_doc(fu, cu, tx, shift)))
        cameras = read_camchain(path)
    assert cameras.cam0.K[0, 0] == fu and cameras.cam0.K[0, 2] == cu and cameras.timeshift == shift
    assert cameras.cam0.body_T_cam[0, 3] == pytest.approx(-tx, abs=1e-12)
    assert cameras.cam1.body_T_cam[0, 3] - cameras.cam0.body_T_cam[0, 3] == pytest.approx(0.11, abs=1e-9)


@settings(max_examples=120, **SETTINGS)
@given(data=st.data())
def test_camchain_damaged_keys_are_one_line_errors_property(data):
    doc = _camchain_doc(450.0, 370.0, 0.0, 0.0)
    cam = data.draw(st.sampled_from(["cam0", "cam1"]))
    key = data.draw(st.sampled_from(["intrinsics", "resolution", "distortion_coeffs", "T_cam_imu", "camera_model",
                                     "distortion_model", "timeshift_cam_imu", "missing"]))
    bad = data.draw(st.sampled_from(["text", "short", "nan", "negative", "scaled"]))
    if key == "missing":
        del doc[cam]
        named = cam
    elif key in ("camera_model", "distortion_model"):
        doc[cam][key] = "omni" if key == "camera_model" else "equidistant"
        named = f"{cam}.{key}"
    elif key == "timeshift_cam_imu":
        doc["cam0"][key] = "x" if bad == "text" else 5.0
        named = "cam0.timeshift_cam_imu"
    elif key == "T_cam_imu":
        T = np.array(doc[cam][key])
        T = T[:3] if bad == "short" else T * 1.1 if bad == "scaled" else T
        doc[cam][key] = "x" if bad == "text" else T.tolist() if bad != "nan" else [[float("nan")] * 4] * 4
        if bad == "negative":
            doc[cam][key] = (np.diag([1.0, 1.0, -1.0, 1.0])).tolist()
        named = f"{cam}.T_cam_imu"
    else:
        value = list(doc[cam][key])
        value = ("x" if bad == "text" else value[:-1] if bad == "short" else
                 [float("nan")] + value[1:] if bad == "nan" else [-abs(value[0]) - 1] + value[1:]
                 if bad == "negative" else value)
        if bad == "scaled" or (key == "distortion_coeffs" and bad == "negative"):
            value = value[:-1]
        doc[cam][key] = value
        named = f"{cam}.{key}"
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "camchain.yaml"
        path.write_text(yaml.safe_dump(doc))
        with pytest.raises(InputError) as e:
            read_camchain(path)
        msg = assert_clean_input_error(e.value, str(path))
    assert named in msg, msg


@needs_euroc
def test_vislam_track_writes_a_bag_in_the_inertial_layout(bags, euroc, tmp_path, capsys):
    from vislam.backend.data.npz import load_sequence

    out = tmp_path / "t.npz"
    assert main(["track", str(bags["ros1_png"]), "--calib", str(EUROC), "--out", str(out), "--quiet"]) == 0
    seq, expected = load_sequence(out), track_euroc(euroc)
    assert seq.inertial and seq.num_steps == expected.num_steps and seq.num_observations == expected.num_observations
    assert np.array_equal(seq.imu.time_stamps, expected.imu.time_stamps)
    assert main(["track", str(bags["ros1"]), "--calib", str(EUROC), "--imu", "x.csv", "--out", str(out),
                 "--force"]) == 2
    assert "--imu is not for a ROS bag" in capsys.readouterr().err


@pytest.mark.parametrize("ros1, encoding", [(True, "mono8"), (False, "bgr8")])
def test_a_bag_of_a_synthetic_drive_runs_end_to_end(tmp_path, ros1, encoding):
    """Rendered stereo images of the inertial street drive (4 s, 2 of them at rest: about a metre of
    motion), its IMU and its true poses in a bag with Kalibr files: `vislam run` with the defaults
    finds the trajectory to 2 cm, under half of dead reckoning's error, against the bag's own ground
    truth topic."""
    import json

    bag, camchain, imu_yaml, scene = synthetic_street_bag(tmp_path, 4.0, ros1, encoding)
    out = tmp_path / "run"
    assert main(["run", str(bag), "--calib", str(camchain), "--imu-calib", str(imu_yaml), "--gt-topic", "/truth",
                 "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    errors = summary["errors"]
    assert summary["steps"] == scene.sequence.num_steps
    assert errors["estimate"]["ate_rmse"] <= 0.02
    assert errors["estimate"]["ate_rmse"] < errors["dead_reckoning"]["ate_rmse"] / 2
    t, truth = read_tum(out / "ground_truth.txt")
    np.testing.assert_allclose(truth[:, :3, 3], scene.world_T_imu_true[:, :3, 3], atol=1e-6)


def test_image_encodings_that_are_not_read_are_named(tmp_path):
    """A mono16 image: one line naming the bag, the topic, the stamp and the encodings read."""
    from bags import _typestore, image_message

    bag, camchain, imu_yaml, scene = synthetic_street_bag(tmp_path, 4.0)
    data = open_bag(bag, camchain, imu_yaml)
    ts = _typestore(True)
    msg = image_message(ts, True, 0, 0, np.zeros((4, 4), np.uint8))
    msg.encoding = "mono16"

    class Reader:
        @staticmethod
        def deserialize(raw, typ):
            return msg

    class Connection:
        topic, msgtype = "/left", "sensor_msgs/msg/Image"

    with pytest.raises(InputError) as e:
        data._decode(Reader, Connection, b"", 1_500_000_000)
    text = assert_clean_input_error(e.value, str(bag))
    assert "topic /left" in text and "1.500000000" in text and "'mono16'" in text and "mono8" in text
