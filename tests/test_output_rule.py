"""No output ever replaces an input (``backend.data.files.inputs_of_the_run``), with or without
--force, and an existing file at an explicit output path (--json, --rerun, --draw's folder) is
replaced only with --force. Each case: the command is refused in one line naming the path, and the
input is byte for byte what it was."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from vislam.backend.data import files
from vislam.backend.data.tum import write_tum
from vislam.backend.errors import OutputError
from vislam.tools.cli import EXIT_USAGE, main


@pytest.fixture(scope="module")
def rendered(tmp_path_factory) -> Path:
    """A rendered synthetic street of 20 frames: image_0/, image_1/, calib.txt, times.txt, data.npz."""
    out = tmp_path_factory.mktemp("render") / "street"
    assert main(["synth", "--scenario", "street", "--steps", "20", "--seed", "3", "--out", str(out), "--render",
                 "--quiet"]) == 0
    return out


@pytest.fixture
def drive(rendered, tmp_path) -> Path:
    """A copy of the rendered drive the test may damage."""
    return Path(shutil.copytree(rendered, tmp_path / "drive"))


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def refused(capsys, argv: list[str], *needles: str) -> str:
    assert main(argv) == EXIT_USAGE
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("vislam: error: "), err
    for needle in needles:
        assert needle in err, err
    return err


def test_draw_into_the_image_folder_is_refused_even_with_force(drive, tmp_path, capsys):
    before = snapshot(drive)
    for extra in ([], ["--force"]):
        refused(capsys, ["track", str(drive), "--imu", str(drive / "data.npz"), "--out", str(tmp_path / "t.npz"),
                         "--draw", str(drive / "image_0"), "--quiet", *extra], "image_0")
    assert snapshot(drive) == before and not (tmp_path / "t.npz").exists()


def test_draw_into_a_folder_holding_files_needs_force(drive, tmp_path, capsys):
    pictures = tmp_path / "pictures"
    pictures.mkdir()
    (pictures / "000000.png").write_bytes(b"mine")
    argv = ["track", str(drive), "--imu", str(drive / "data.npz"), "--out", str(tmp_path / "t.npz"), "--draw",
            str(pictures), "--quiet"]
    refused(capsys, argv, str(pictures), "--force")
    assert (pictures / "000000.png").read_bytes() == b"mine"
    assert main(argv + ["--force"]) == 0
    assert len(list(pictures.glob("*.png"))) == 20 and (pictures / "000000.png").read_bytes() != b"mine"


def test_track_out_onto_its_own_inputs_is_refused_even_with_force(drive, capsys):
    before = snapshot(drive)
    for target in ("data.npz", "calib.txt", "times.txt"):
        refused(capsys, ["track", str(drive), "--imu", str(drive / "data.npz"), "--out", str(drive / target),
                         "--force", "--quiet"], target, "input")
    assert snapshot(drive) == before


def test_run_out_inside_an_image_folder_is_refused_and_leaves_nothing_there(drive, capsys):
    before = snapshot(drive)
    refused(capsys, ["run", str(drive), "--imu", str(drive / "data.npz"), "--out", str(drive / "image_1" / "run"),
                     "--quiet"], "image_1", "reads")
    assert snapshot(drive) == before
    assert sorted(p.name for p in (drive / "image_1").iterdir()) == sorted(
        p.name for p in (drive / "image_0").iterdir())  # no staging folder left among the frames


def test_run_rerun_onto_the_input_or_the_output_folder_is_refused(drive, tmp_path, capsys):
    data = drive / "data.npz"
    before = data.read_bytes()
    refused(capsys, ["run", str(data), "--out", str(tmp_path / "o"), "--rerun", str(data), "--quiet"], "input")
    refused(capsys, ["run", str(data), "--out", str(tmp_path / "o"), "--rerun", str(tmp_path / "o"), "--quiet"],
            "--rerun", "--out")
    assert data.read_bytes() == before and not (tmp_path / "o").exists()


def test_run_rerun_onto_an_image_folder_of_an_image_run_is_refused(drive, tmp_path, capsys):
    """The image folders become inputs only once the reader lists them, after the recording
    started: the recording is refused when it would be moved into place, and nothing is written."""
    before = snapshot(drive)
    refused(capsys, ["run", str(drive), "--imu", str(drive / "data.npz"), "--out", str(tmp_path / "o"), "--rerun",
                     str(drive / "image_0" / "x.rrd"), "--quiet"], "image_0")
    assert snapshot(drive) == before and not (tmp_path / "o").exists()


def test_an_existing_rerun_file_is_replaced_only_with_force(drive, tmp_path, capsys):
    recording = tmp_path / "x.rrd"
    recording.write_bytes(b"mine")
    argv = ["run", str(drive / "data.npz"), "--out", str(tmp_path / "o"), "--rerun", str(recording), "--quiet"]
    refused(capsys, argv, str(recording), "--force")
    assert recording.read_bytes() == b"mine" and not (tmp_path / "o").exists()


def test_run_force_into_the_folder_holding_its_input_keeps_the_input(drive, tmp_path, capsys):
    folder = tmp_path / "m"
    folder.mkdir()
    data = folder / "map.npz"  # the name of one of run's outputs
    shutil.copy(drive / "data.npz", data)
    before = data.read_bytes()
    refused(capsys, ["run", str(data), "--out", str(folder), "--force", "--quiet"], "map.npz", "input")
    assert data.read_bytes() == before and [p.name for p in folder.iterdir()] == ["map.npz"]


def test_eval_json_onto_an_input_is_refused_and_an_existing_file_needs_force(rendered, tmp_path, capsys):
    est, gt = tmp_path / "est.txt", tmp_path / "gt.txt"
    shutil.copy(rendered / "gt_tum.txt", gt)
    shutil.copy(rendered / "gt_tum.txt", est)
    before = gt.read_bytes()
    for target in (gt, est):
        refused(capsys, ["eval", str(est), str(gt), "--json", str(target), "--force"], str(target), "input")
    assert gt.read_bytes() == before and est.read_bytes() == before
    other = tmp_path / "e.json"
    other.write_text("mine")
    refused(capsys, ["eval", str(est), str(gt), "--json", str(other)], "--force")
    assert other.read_text() == "mine"
    assert main(["eval", str(est), str(gt), "--json", str(other), "--force"]) == 0 and other.read_text() != "mine"


def test_eval_json_onto_the_covariance_beside_the_estimate_is_refused(tmp_path, capsys):
    """pose_covariance.npz beside a run's trajectory.txt is read by default: an input like the trajectories."""
    import numpy as np

    from vislam.backend.data.covariance import POSE_COVARIANCE_FILE, write_pose_covariance

    t = np.arange(5.0)
    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[:, 0, 3] = t
    write_tum(tmp_path / "trajectory.txt", t, poses)
    write_tum(tmp_path / "gt.txt", t, poses)
    covariance = tmp_path / POSE_COVARIANCE_FILE
    write_pose_covariance(covariance, t, np.tile(np.eye(6), (5, 1, 1)))
    before = covariance.read_bytes()
    refused(capsys, ["eval", str(tmp_path / "trajectory.txt"), str(tmp_path / "gt.txt"), "--json", str(covariance),
                     "--force"], POSE_COVARIANCE_FILE, "input")
    assert covariance.read_bytes() == before


def test_a_symlink_to_an_input_is_seen_through(drive, tmp_path):
    """The rule compares resolved paths: a link to an input, or a path through a linked folder, is the input."""
    link = tmp_path / "link"
    link.symlink_to(drive)
    with files.inputs_of_the_run([drive / "data.npz", drive]):
        for path in (link / "data.npz", link, tmp_path / "link" / ".." / "link" / "data.npz"):
            with pytest.raises(OutputError, match="input"):
                files.check_not_an_input(path)
        files.check_not_an_input(link / "new.npz")  # a new name beside the inputs is fine
        files.note_input(drive / "image_0", contents=True)
        with pytest.raises(OutputError, match="reads"):
            files.check_not_an_input(link / "image_0" / "deep" / "new.png")
    files.check_not_an_input(drive / "data.npz")  # outside a run: the library used directly checks nothing


def test_readers_record_inputs_only_inside_a_run(drive):
    """Reading a file outside a command (the library, the tests) records nothing that could refuse a
    later write."""
    from vislam.backend.data.textio import read_lines

    read_lines(drive / "times.txt")
    assert not files._inputs
    with files.inputs_of_the_run([]):
        read_lines(drive / "times.txt")
        with pytest.raises(OutputError, match="times.txt"):
            files.check_output_file(drive / "times.txt")
    assert not files._inputs
    files.check_output_file(drive / "times.txt")
