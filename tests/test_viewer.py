"""The Rerun recording of a run (vislam.tools.viewer): what is written is read back from the .rrd file
and compared with the run; a missing extra is one line; an interrupted recording leaves no file."""

from __future__ import annotations

import importlib
import importlib.util
import sys

import numpy as np
import pytest

from vislam.backend.errors import OutputError, VislamError
from vislam.backend.geometry.se3 import rotation_from_quaternion
from vislam.tools import viewer
from vislam.tools.viewer import MISSING_EXTRA, RerunRecorder

HAVE_RERUN = importlib.util.find_spec("rerun") is not None
needs_rerun = pytest.mark.skipif(not HAVE_RERUN, reason="rerun-sdk is not installed (pip install 'vislam[viewer]')")

STEPS = 30
PIECE = 12  # the trajectory in 3 pieces over 30 steps: their joints are checked
MAX_LANDMARKS = 20  # below the scene's active landmarks: the cap is checked
FRAME_STEP = 3
FRAME_IDS = np.array([4, 70_000])  # beyond 16 bits: rerun's class ids would not hold it
FRAME_PIXELS = np.array([[10.0, 20.0, 6.5, 20.25], [30.0, 15.0, 22.0, 15.5]])


def read_recording(path) -> dict[str, list]:
    """The record batches of each entity path of the .rrd file ``path``."""
    chunk = importlib.import_module("rerun.chunk")
    if not hasattr(chunk, "RrdReader"):
        pytest.skip("reading a recording back needs rerun.chunk.RrdReader (a newer rerun-sdk)")
    batches: dict[str, list] = {}
    for c in chunk.RrdReader(str(path)).store().stream():
        batches.setdefault(c.entity_path, []).append(c.to_record_batch())
    return batches


def column(batches: list, name: str, sort_by: str | None = "step") -> list:
    """The values of column ``name`` over the record batches of one entity, in ``sort_by`` order."""
    rows = []
    for b in batches:
        values = b.column(name).to_pylist()
        keys = b.column(sort_by).to_pylist() if sort_by else [0] * len(values)
        rows += zip(keys, values)
    return [v for _, v in sorted(rows, key=lambda r: r[0])]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """The 30-step street run recorded with its dead reckoning, ground truth, map and one frame;
    the read-back recording and what the filter held at each step."""
    from vislam.backend.run.runner import run_sequence
    from vislam.synth.scene import SceneConfig, make_scene

    scene = make_scene(SceneConfig(steps=STEPS, seed=0))
    path = tmp_path_factory.mktemp("viewer") / "run.rrd"
    seen = {"active": [], "pose_covariance": []}
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(viewer, "PIECE", PIECE)
        with RerunRecorder(path, time_stamps=scene.sequence.time_stamps, max_landmarks=MAX_LANDMARKS) as recorder:
            def observer(k, ekf, step_stats):
                seen["active"].append(ekf.num_active)
                seen["pose_covariance"].append(np.array(ekf.pose_covariance))
                recorder.observer(k, ekf, step_stats)

            result = run_sequence(scene.sequence, observer=observer)
            recorder.log_result(result, scene.world_T_imu_true)
            image = np.tile(np.arange(64, dtype=np.uint8), (48, 1))
            recorder.log_frame(FRAME_STEP, image, image[::-1], FRAME_IDS, FRAME_PIXELS)
        assert not [p.name for p in path.parent.iterdir() if p != path]  # no temporary file left
    return scene, result, read_recording(path), seen


@needs_rerun
def test_recording_has_every_entity(recorded):
    entities = set(recorded[2])
    assert {"/world/imu", "/world/imu/uncertainty", "/world/landmarks/active", "/world/landmarks/active/uncertainty",
            "/world/landmarks/map", "/world/dead_reckoning", "/world/ground_truth", "/camera/left", "/camera/right",
            "/camera/left/tracks", "/camera/right/tracks"} <= entities
    assert {e for e in entities if e.startswith("/world/estimate/")} == {f"/world/estimate/{j:05d}" for j in range(3)}


@needs_rerun
def test_one_pose_per_step_on_both_time_lines(recorded):
    scene, result, rec, _ = recorded
    pose = rec["/world/imu"]
    assert column(pose, "step") == list(range(STEPS)) == list(range(result.world_T_imu.shape[0]))
    seconds = [t.total_seconds() for t in column(pose, "time")]
    np.testing.assert_allclose(seconds, scene.sequence.time_stamps, atol=1e-9)


@needs_rerun
def test_logged_poses_are_the_estimate(recorded):
    _, result, rec, _ = recorded
    translation = np.array(column(rec["/world/imu"], "Transform3D:translation")).reshape(STEPS, 3)
    np.testing.assert_allclose(translation[-1], result.world_T_imu[-1][:3, 3], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(translation, result.world_T_imu[:, :3, 3], rtol=1e-6, atol=1e-6)
    # Mat3x3 is stored column by column: a transposed rotation would show the IMU turning the wrong way
    mat = np.array(column(rec["/world/imu"], "Transform3D:mat3x3")).reshape(STEPS, 3, 3).transpose(0, 2, 1)
    np.testing.assert_allclose(mat, result.world_T_imu[:, :3, :3], atol=1e-6)


@needs_rerun
def test_trajectory_pieces_join_into_the_estimate(recorded):
    _, result, rec, _ = recorded
    joined = []
    for j in range(3):
        last_strip = np.array(column(rec[f"/world/estimate/{j:05d}"], "LineStrips3D:strips")[-1][0])
        joined.append(last_strip if j == 0 else last_strip[1:])  # a piece starts at the end of the last one
    np.testing.assert_allclose(np.concatenate(joined), result.world_T_imu[:, :3, 3], rtol=1e-6, atol=1e-6)
    # while the run goes, the last piece ends at the current pose
    strips = column(rec["/world/estimate/00001"], "LineStrips3D:strips")
    assert [len(s[0]) for s in strips] == list(range(2, PIECE + 2))


@needs_rerun
def test_active_landmarks_capped_with_their_ellipsoids(recorded):
    _, _, rec, seen = recorded
    points = column(rec["/world/landmarks/active"], "Points3D:positions")
    assert [len(p) for p in points] == [min(n, MAX_LANDMARKS) for n in seen["active"]]
    assert max(seen["active"]) > MAX_LANDMARKS  # the cap was needed
    ellipsoids = rec["/world/landmarks/active/uncertainty"]
    assert [len(c) for c in column(ellipsoids, "Ellipsoids3D:centers")] == [len(p) for p in points]
    np.testing.assert_allclose(np.array(column(ellipsoids, "Ellipsoids3D:centers")[-1]), np.array(points[-1]))


@needs_rerun
def test_pose_uncertainty_is_two_sigma(recorded):
    _, _, rec, seen = recorded
    half = np.array(column(rec["/world/imu/uncertainty"], "Ellipsoids3D:half_sizes")[-1][0])
    q = np.array(column(rec["/world/imu/uncertainty"], "Ellipsoids3D:quaternions")[-1][0])
    R = rotation_from_quaternion(q)
    cov = seen["pose_covariance"][-1][:3, :3]
    np.testing.assert_allclose(R @ np.diag((half / 2.0) ** 2) @ R.T, cov, rtol=1e-4, atol=1e-12)


@needs_rerun
def test_end_of_run_logs(recorded):
    scene, result, rec, _ = recorded
    (map_points,) = column(rec["/world/landmarks/map"], "Points3D:positions")
    assert len(map_points) == result.map_positions.shape[0] > 0
    np.testing.assert_allclose(np.array(map_points), result.map_positions, rtol=1e-6, atol=1e-5)
    assert column(rec["/world/landmarks/map"], "step") == [STEPS - 1]  # appears at the end, not before
    for entity, poses in (("/world/ground_truth", scene.world_T_imu_true), ("/world/dead_reckoning",
                                                                          result.dead_reckoning)):
        (strips,) = column(rec[entity], "LineStrips3D:strips", sort_by=None)
        np.testing.assert_allclose(np.array(strips[0]), poses[:, :3, 3], rtol=1e-6, atol=1e-5)


@needs_rerun
def test_frame_images_and_tracks(recorded):
    _, _, rec, _ = recorded
    for side in ("left", "right"):
        assert column(rec[f"/camera/{side}"], "step") == [FRAME_STEP]
        assert column(rec[f"/camera/{side}"], "EncodedImage:media_type") == [["image/jpeg"]]
    tracks = {side: rec[f"/camera/{side}/tracks"] for side in ("left", "right")}
    np.testing.assert_allclose(column(tracks["left"], "Points2D:positions")[0], FRAME_PIXELS[:, :2])
    np.testing.assert_allclose(column(tracks["right"], "Points2D:positions")[0], FRAME_PIXELS[:, 2:])
    assert column(tracks["left"], "track_id")[0] == FRAME_IDS.tolist()
    colors = column(tracks["left"], "Points2D:colors")[0]
    assert colors == column(tracks["right"], "Points2D:colors")[0] and len(set(colors)) == 2  # one per track


def test_principal_axes_are_two_sigma():
    R = rotation_from_quaternion(np.array([0.2, -0.4, 0.1, 0.9]))
    sigma = np.array([0.5, 2.0, 0.1])
    cov = R @ np.diag(sigma**2) @ R.T
    half, q = viewer._principal_axes(cov[None])
    np.testing.assert_allclose(np.sort(half[0]), np.sort(2.0 * sigma))
    R_axes = rotation_from_quaternion(q[0])
    np.testing.assert_allclose(R_axes @ np.diag((half[0] / 2.0) ** 2) @ R_axes.T, cov, atol=1e-12)
    assert np.linalg.det(R_axes) == pytest.approx(1.0)


def test_missing_extra_is_one_line(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun raises ImportError
    with pytest.raises(VislamError) as err:
        RerunRecorder(tmp_path / "run.rrd")
    assert str(err.value) == MISSING_EXTRA == "--rerun needs the optional viewer extra: pip install 'vislam[viewer]'"
    assert list(tmp_path.iterdir()) == []


@needs_rerun
@pytest.mark.parametrize("existing", [False, True])
def test_interrupted_recording_leaves_no_file(tmp_path, existing):
    path = tmp_path / "run.rrd"
    if existing:
        path.write_bytes(b"an earlier recording")
    with pytest.raises(KeyboardInterrupt):
        with RerunRecorder(path) as recorder:
            recorder.log_trajectory("ground_truth", np.tile(np.eye(4), (5, 1, 1)))
            assert [p.name for p in tmp_path.iterdir() if p != path]  # being written under a temporary name
            raise KeyboardInterrupt
    assert [p.name for p in tmp_path.iterdir()] == (["run.rrd"] if existing else [])
    if existing:
        assert path.read_bytes() == b"an earlier recording"


@needs_rerun
def test_abort_leaves_no_file(tmp_path):
    recorder = RerunRecorder(tmp_path / "run.rrd")
    recorder.abort()
    recorder.close()  # a second end does nothing
    assert list(tmp_path.iterdir()) == []


@needs_rerun
def test_two_recorders_do_not_mix(tmp_path):
    a, b = RerunRecorder(tmp_path / "a.rrd"), RerunRecorder(tmp_path / "b.rrd")
    a.log_trajectory("ground_truth", np.tile(np.eye(4), (3, 1, 1)))
    b.log_trajectory("dead_reckoning", np.tile(np.eye(4), (4, 1, 1)))
    a.close()
    b.close()
    assert "/world/dead_reckoning" not in read_recording(tmp_path / "a.rrd")
    assert "/world/ground_truth" not in read_recording(tmp_path / "b.rrd")


@needs_rerun
def test_unusable_paths_refused_before_recording(tmp_path):
    with pytest.raises(OutputError, match="is a directory"):
        RerunRecorder(tmp_path)
    with pytest.raises(ValueError, match="a path, spawn=True, or both"):
        RerunRecorder(None)


@needs_rerun
def test_run_with_rerun_records_every_step_and_frame(tmp_path):
    """`vislam run IMAGES --rerun F.rrd` on rendered frames: one pose per step, the frames with their
    tracks, the map at the end; the last pose is the run's."""
    from vislam.backend.data.tum import read_tum
    from vislam.tools.cli import main

    scene = tmp_path / "s"
    assert main(["synth", "--steps", "12", "--render", "--out", str(scene), "--quiet"]) == 0
    rrd = tmp_path / "run.rrd"
    assert main(["run", str(scene), "--imu", str(scene / "data.npz"), "--out", str(tmp_path / "out"),
                 "--gt", str(scene / "gt_tum.txt"), "--rerun", str(rrd), "--quiet"]) == 0
    rec = read_recording(rrd)
    assert {"/world/imu", "/camera/left", "/camera/right", "/world/landmarks/map", "/world/ground_truth"} <= set(rec)
    assert sorted(set(column(rec["/world/imu"], "step", sort_by=None))) == list(range(12))
    assert sorted(set(column(rec["/camera/left"], "step", sort_by=None))) == list(range(12))
    _, poses = read_tum(tmp_path / "out" / "trajectory.txt")
    translation = np.array(column(rec["/world/imu"], "Transform3D:translation")).reshape(12, 3)
    np.testing.assert_allclose(translation, poses[:, :3, 3], atol=1e-5)


@needs_rerun
def test_a_recording_that_cannot_be_written_whole_leaves_no_output(tmp_path, monkeypatch, capsys):
    """rerun's file writer stops on a full disk and its flush fails: the run is one line, exit 2, and
    neither the recording (no truncated file under its name) nor any other output is left; outputs
    that cannot be written leave no recording either."""
    import rerun as rr

    from vislam.tools import outputs
    from vislam.tools.cli import main

    scene = tmp_path / "s"
    assert main(["synth", "--steps", "12", "--out", str(scene), "--quiet"]) == 0
    rrd, out = tmp_path / "run.rrd", tmp_path / "out"
    argv = ["run", str(scene / "data.npz"), "--out", str(out), "--rerun", str(rrd), "--quiet"]

    def full_disk(self, *args, **kwargs):
        raise RuntimeError("File-writer thread shut down prematurely")

    with monkeypatch.context() as m:
        m.setattr(rr.RecordingStream, "flush", full_disk)
        assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.splitlines()[-1] == f"vislam: error: {rrd}: cannot write the recording: File-writer thread shut down " \
                                   "prematurely", err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]

    def no_space(*args, **kwargs):
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr(outputs, "write_json", no_space)
        assert main(argv) == 2
    assert "No space left on device" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]
    assert main(argv) == 0 and rrd.is_file() and (out / "trajectory.txt").is_file()
