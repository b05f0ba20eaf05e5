"""The `vislam` command line: outputs, refusals, exit codes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import vislam
from vislam.backend.config import Config
from vislam.backend.data.npz import load_sequence, save_sequence
from vislam.tools.cli import main

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"real data not found at {DATA} (../shared/data)")


@pytest.fixture(scope="module")
def short_0027(tmp_path_factory) -> Path:
    """The first 150 steps of ece276a_0027 as a small feature file."""
    out = tmp_path_factory.mktemp("data") / "short.npz"
    save_sequence(load_sequence(DATA / "ece276a_0027.npz").subset(150), out)
    return out


@needs_data
def test_run_writes_every_output(short_0027, tmp_path, capsys):
    out = tmp_path / "out"
    gt = DATA / "gt" / "ece276a_0027_gt_tum.txt"
    assert main(["run", str(short_0027), "--out", str(out), "--gt", str(gt), "--quiet"]) == 0
    names = {p.name for p in out.iterdir()}
    assert {"trajectory.txt", "dead_reckoning.txt", "pose_covariance.npz", "map.npz", "map.ply", "trajectory.ply",
            "trajectory.png", "ate_over_time.png", "summary.json", "config.toml"} <= names
    assert not [n for n in names if ".tmp" in n]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 150
    assert summary["decisions"]["conventions"]["velocity_index"] == "next"
    # the run's scale against the IMU's (H4): 150 steps are enough to test, and they agree
    scale = summary["scale_against_imu"]
    assert scale["tested"] and scale["steps"] == 140 and not scale["failed"]
    assert abs(scale["imu_over_filter"] - 1.0) < 4 * scale["standard_error"] + 0.01
    # the summary's error is what `vislam eval` computes from the files written
    assert main(["eval", str(out / "trajectory.txt"), str(gt), "--json", str(tmp_path / "eval.json")]) == 0
    evaluated = json.loads((tmp_path / "eval.json").read_text())
    assert evaluated["ate_rmse"] == pytest.approx(summary["errors"]["estimate"]["ate_rmse"], rel=1e-6)
    assert evaluated["num_matched"] == 150
    # ... and so is its NEES, from pose_covariance.npz beside the trajectory (found by default)
    nees = summary["errors"]["nees"]
    assert nees["matched_steps"] == 150 and nees["skipped_steps"] >= 1
    for what, dof in (("position", 3), ("pose", 6)):
        assert nees[what]["dof"] == evaluated["nees"][what]["dof"] == dof
        assert evaluated["nees"][what]["mean"] == pytest.approx(nees[what]["mean"], rel=1e-3)
        assert evaluated["nees"][what]["steps"] == nees[what]["steps"]
    # with --out: the JSON and the plots; an existing non-empty directory is refused
    assert main(["eval", str(out / "trajectory.txt"), str(gt), "--out", str(tmp_path / "ev")]) == 0
    assert {p.name for p in (tmp_path / "ev").iterdir()} == {"eval.json", "trajectories.png", "ate_over_time.png",
                                                            "nees_over_time.png", "xyz_over_time.png",
                                                            "rpy_over_time.png", "ape_trajectory.zip",
                                                            "rpe_trajectory.zip"}
    assert json.loads((tmp_path / "ev" / "eval.json").read_text()) == evaluated
    assert main(["eval", str(out / "trajectory.txt"), str(gt), "--out", str(tmp_path / "ev")]) == 2
    timing = summary["timing"]
    assert timing["setup_seconds"] > 0  # the convention test counts, though run decides it first
    assert timing["load_seconds"] > 0  # reading the feature file counts too, reported apart
    parts = ("filter_seconds", "setup_seconds", "load_seconds", "input_seconds")
    assert timing["real_time_factor"] == pytest.approx(
        timing["sequence_seconds"] / sum(timing[p] for p in parts), rel=1e-9)
    assert timing["run_seconds"] == pytest.approx(sum(timing[p] for p in parts), rel=1e-9)
    assert "kernel_seconds" in timing  # compiling or loading the kernels, once per process, reported apart
    # the time the user waited: called in-process, from the command's start (no process start-up),
    # and it holds every part, the outputs included
    assert timing["startup_seconds"] is None
    assert timing["process_seconds"] >= timing["run_seconds"] + timing["outputs_seconds"] > timing["run_seconds"]
    assert timing["process_real_time_factor"] == pytest.approx(timing["sequence_seconds"] / timing["process_seconds"])
    latency = timing["step_ms"]  # README: the latency of one step
    assert 0 < latency["median"] <= latency["p99"] <= latency["max"] < 1e3 * timing["filter_seconds"]
    # evo reads the trajectory
    from evo.tools import file_interface

    traj = file_interface.read_tum_trajectory_file(str(out / "trajectory.txt"))
    assert traj.num_poses == 150
    with np.load(out / "map.npz") as m:
        assert m["positions"].shape == (m["ids"].size, 3)
        assert m["covariances"].shape == (m["ids"].size, 3, 3)
    # the configuration, nested by table (a feature file: no [tracker])
    assert list(summary["config"]) == list(Config().tables())
    # the defaults, with the decisions taken from the data recorded (the course's tracks drift, the pixel
    # noise identified, the gyro bias estimated or not)
    decided = summary["decisions"]
    assert decided["track_drift"]["drifting"] is True and decided["track_drift"]["decided_by"] == "test"
    assert decided["pixel_noise"]["decided_by"] == "two-view fits" and decided["pixel_noise"]["sigma_px"] > 0
    assert summary["config"] == Config().with_values({
        "drift.track_drift": "yes", "noise.pixel_sigma": decided["pixel_noise"]["sigma_px"],
        "noise.pixel_variance_per_disparity": decided["pixel_noise"]["variance_per_disparity_px2_per_px"],
        "drift.pixel_walk": decided["track_drift"]["pixel_walk_px2_per_step"],
        "drift.pixel_walk_per_disparity": decided["track_drift"]["pixel_walk_px2_per_step_per_px"],
        "estimator.estimate_gyro_bias": decided["gyro_bias"]["estimated"],
        "noise.stereo_offset_sigma": decided["stereo_offset"]["state_prior_sigma_px"]}).as_dict()
    assert summary["config"]["estimator"]["mode"] == "slam"
    # the config written is loadable and reproduces the run's settings
    assert Config.load(out / "config.toml").as_dict() == summary["config"]
    assert main(["run", str(short_0027), "--out", str(tmp_path / "again"), "--quiet",
                 "--config", str(out / "config.toml")]) == 0
    again = json.loads((tmp_path / "again" / "summary.json").read_text())
    assert again["config"] == summary["config"]


@needs_data
def test_run_refuses_non_empty_output(short_0027, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    assert main(["run", str(short_0027), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "not empty" in err and "--force" in err
    assert (out / "keep.txt").read_text() == "mine"


@pytest.mark.parametrize(
    "make, needle",
    [
        (lambda p: p.write_text("not a zip"), "npz"),
        (lambda p: np.savez(p, time_stamps=np.zeros((1, 3))), "key"),
    ],
)
def test_bad_input_is_one_line_exit_2(tmp_path, capsys, make, needle):
    bad = tmp_path / "bad.npz"
    make(bad)
    assert main(["run", str(bad), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "bad.npz" in err and needle in err.lower()


def test_bad_config_key_exit_2(tmp_path, capsys):
    assert main(["run", "x.npz", "--out", str(tmp_path / "o"), "--set", "no_such_key=1"]) == 2
    assert "no_such_key" in capsys.readouterr().err
    assert main(["run", "x.npz", "--out", str(tmp_path / "o"), "--set", "noise.no_such_key=1"]) == 2
    assert "'noise.no_such_key'" in capsys.readouterr().err
    assert main(["run", "x.npz", "--out", str(tmp_path / "o"), "--set", "noise.pixel_sigma=-1"]) == 2
    assert "'noise.pixel_sigma'" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()  # refused before any output


@pytest.mark.parametrize(
    "key, new",
    [("pixel_sigma", "noise.pixel_sigma"), ("landmark_parametrization", "landmarks.parametrization"),
     ("convention_horizon", "conventions.horizon"), ("target_tracks", "tracker.target_tracks")],
)
def test_bare_key_exit_2_naming_its_table(tmp_path, capsys, key, new):
    assert main(["run", "x.npz", "--out", str(tmp_path / "o"), "--set", f"{key}=1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert f"'{key}' is now '{new}'" in err


def test_config_file_with_a_filter_table_exit_2(tmp_path, capsys):
    path = tmp_path / "c.toml"
    path.write_text("[filter]\npixel_sigma = 2.5\n")
    assert main(["run", "x.npz", "--out", str(tmp_path / "o"), "--config", str(path)]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and "'noise.pixel_sigma'" in err


def test_version(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out.strip() == f"vislam {vislam.__version__}"
    script = Path(sys.executable).parent / "vislam"  # the console script of the installed package
    if script.is_file():
        done = subprocess.run([str(script), "--version"], capture_output=True, text=True, timeout=120)
        assert done.returncode == 0 and done.stdout.strip() == f"vislam {vislam.__version__}"


def test_every_command_that_writes_takes_o_for_out():
    """``-o DIR`` is ``--out DIR`` in every command that has it (as in most command lines)."""
    from vislam.tools.cli import build_parser

    parser = build_parser()
    commands = parser._subparsers._group_actions[0].choices
    with_out = [name for name, sub in commands.items() if "--out" in sub._option_string_actions]
    assert {"run", "synth", "track", "mc", "batch", "demo", "eval"} <= set(with_out)
    for name in with_out:
        assert commands[name]._option_string_actions["-o"].dest == "out", name


def test_real_time_factor_keeps_its_decimals_below_ten():
    from vislam.tools.report import real_time_text

    assert [real_time_text(x) for x in (0.42, 0.051, 1.09, 9.94, 35.2, float("nan"))] == [
        "0.42x", "0.05x", "1.1x", "9.9x", "35x", "n/a"]


@needs_data
def test_the_command_counts_from_the_process_start(short_0027, tmp_path):
    """``python -m vislam.tools.cli run`` (the command is the process): the summary's whole time
    counts from the operating system's start of the process, so it holds the start-up (the
    interpreter and the imports before the command) and every part, and the screen leads with it."""
    out = tmp_path / "out"
    done = subprocess.run([sys.executable, "-m", "vislam.tools.cli", "run", str(short_0027), "--out", str(out),
                           "--no-progress"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    t = json.loads((out / "summary.json").read_text())["timing"]
    assert t["startup_seconds"] > 0.05  # an interpreter and numpy take longer than that to start
    assert t["process_seconds"] > t["startup_seconds"] + t["run_seconds"] + t["outputs_seconds"]
    line = next(x for x in done.stdout.splitlines() if "s of data" in x)
    assert line.startswith(f"{t['process_seconds']:.2f} s for {t['sequence_seconds']:.1f} s of data")
    assert f"start-up {t['startup_seconds']:.2f}" in line and f"outputs {t['outputs_seconds']:.2f}" in line


@needs_data
def test_check_prints_both_convention_numbers(capsys):
    assert main(["check", str(DATA / "ece276a_03.npz")]) == 0
    out = capsys.readouterr().out
    assert "flip=yes,velocity=next" in out and "flip=no,velocity=this" in out
    assert "IMU y,z flipped" in out
    drift = [line for line in out.splitlines() if line.startswith("track drift: ")]
    assert len(drift) == 1 and drift[0].startswith("track drift: yes (")  # decided by the test on the tracks (T1)
    assert "two-view residuals" in drift[0] and "ratio" in drift[0] and "random walk" in drift[0]


@needs_data
def test_run_without_landmarks_says_map_ply_is_not_written(short_0027, tmp_path, capsys):
    """Dead reckoning maps nothing: no map.ply (a PLY cloud needs a point), and the run says so."""
    out = tmp_path / "dr"
    assert main(["run", str(short_0027), "--out", str(out), "--mode", "dead-reckoning", "--no-progress"]) == 0
    names = {p.name for p in out.iterdir()}
    assert "map.ply" not in names and {"map.npz", "trajectory.ply", "summary.json"} <= names
    summary = json.loads((out / "summary.json").read_text())
    assert any("map.ply not written" in note for note in summary["notes"])
    assert "note: no landmark was mapped" in capsys.readouterr().out


def test_synth_render_says_its_size_first_and_shows_progress(tmp_path, capsys):
    """`vislam synth --render` announces the images' size before writing them (within 30 %) and
    draws a progress bar; --quiet says neither."""
    import re

    out = tmp_path / "s"
    assert main(["synth", "--steps", "12", "--render", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    announced = float(re.search(r"about (\d+) MB of PNG images", err).group(1))
    written = sum(p.stat().st_size for p in out.glob("image_*/*.png")) / 1e6
    assert abs(announced - written) <= 0.3 * written + 1
    assert "render" in err and "12/12" in err
    assert main(["synth", "--steps", "12", "--render", "--out", str(tmp_path / "q"), "--quiet"]) == 0
    assert capsys.readouterr().err == ""


def test_run_writes_kitti_pose_files(tmp_path):
    """--format kitti: the left camera's pose in its first frame, 12 numbers a line, one line per step,
    the TUM trajectory composed with imu_T_cam."""
    from vislam.backend.data.npz import load_sequence
    from vislam.backend.data.tum import read_tum
    from vislam.backend.geometry import se3

    assert main(["synth", "--steps", "40", "-o", str(tmp_path / "s")]) == 0
    out = tmp_path / "run"
    assert main(["run", str(tmp_path / "s" / "data.npz"), "-o", str(out), "--format", "kitti", "--quiet"]) == 0
    imu_T_cam = json.loads((out / "summary.json").read_text())["decisions"]["conventions"]["imu_T_cam_used"]
    _, world_T_imu = read_tum(out / "trajectory.txt")
    world_T_cam = world_T_imu @ np.array(imu_T_cam)
    expected = (se3.inverse(world_T_cam[0]) @ world_T_cam)[:, :3, :].reshape(-1, 12)
    for name in ("trajectory_kitti.txt", "dead_reckoning_kitti.txt"):
        rows = np.loadtxt(out / name)
        assert rows.shape == (load_sequence(tmp_path / "s" / "data.npz").num_steps, 12)
    np.testing.assert_allclose(np.loadtxt(out / "trajectory_kitti.txt"), expected, atol=1e-6)


def test_run_starts_with_one_screen_and_verbose_and_quiet_do_what_they_say(tmp_path, capsys):
    """Default: the options that differ from the defaults in one line; --verbose: every option;
    --quiet: nothing at all on a successful run."""
    assert main(["synth", "--steps", "30", "--out", str(tmp_path / "s")]) == 0
    data = str(tmp_path / "s" / "data.npz")
    capsys.readouterr()
    assert main(["run", data, "--out", str(tmp_path / "a"), "--set", "noise.pixel_sigma=0.7", "--no-progress"]) == 0
    captured = capsys.readouterr()
    assert "configuration: the defaults but noise.pixel_sigma=0.7" in captured.err
    assert "[noise]" not in captured.err and "outputs in" in captured.out
    assert len((captured.err + captured.out).splitlines()) <= 25  # one screen
    assert main(["run", data, "--out", str(tmp_path / "b"), "--verbose", "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "[noise]" in err and "pixel_sigma" in err and "[tracker]" not in err
    assert main(["run", data, "--out", str(tmp_path / "c"), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == ""
    assert (tmp_path / "c" / "summary.json").is_file()


def test_eval_reads_the_kitti_pose_files_run_writes(tmp_path, capsys):
    """`vislam run --format kitti` writes trajectory_kitti.txt; `vislam eval` reads it against KITTI
    ground truth poses (line by line), with the numbers of the camera poses themselves; a KITTI file
    against TUM text is refused in one line naming both."""
    from vislam.backend.data.tum import read_kitti_poses, read_tum, write_kitti_poses
    from vislam.backend.evaluation.metrics import trajectory_errors

    scene = tmp_path / "scene"
    assert main(["synth", "--steps", "80", "--out", str(scene), "--quiet"]) == 0
    out = tmp_path / "run"
    assert main(["run", str(scene / "data.npz"), "--out", str(out), "--format", "kitti", "--quiet"]) == 0
    seq = load_sequence(scene / "data.npz")
    _, truth = read_tum(scene / "gt_tum.txt")
    write_kitti_poses(tmp_path / "gt_kitti.txt", truth, seq.imu_T_cam)
    capsys.readouterr()
    assert main(["eval", str(out / "trajectory_kitti.txt"), str(tmp_path / "gt_kitti.txt"), "--json",
                 str(tmp_path / "e.json")]) == 0
    assert "matched line by line" in capsys.readouterr().out
    numbers = json.loads((tmp_path / "e.json").read_text())
    est, gt = read_kitti_poses(out / "trajectory_kitti.txt"), read_kitti_poses(tmp_path / "gt_kitti.txt")
    index = np.arange(len(est), dtype=float)
    expected = trajectory_errors(index, est, np.arange(len(gt), dtype=float), gt)
    assert numbers["ate_rmse"] == pytest.approx(expected.ate_rmse, rel=1e-12)
    assert numbers["num_matched"] == 80 and "nees" not in numbers  # the covariance beside is trajectory.txt's
    assert main(["eval", str(out / "trajectory_kitti.txt"), str(scene / "gt_tum.txt")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "trajectory_kitti.txt" in err and "gt_tum.txt" in err and "one format" in err


def test_rpe_says_when_it_counts_frames_and_a_reader_that_leaves_is_no_error(tmp_path, capsys):
    """RPE segments longer than the ground truth's path fall back to 10 frames, and the line says
    why; `vislam eval ... | true` (a reader gone before the first line) ends quietly with 141
    (SIGPIPE's code as a shell reports it), no error line."""
    scene = tmp_path / "scene"
    assert main(["synth", "--steps", "60", "--out", str(scene), "--quiet"]) == 0
    gt = str(scene / "gt_tum.txt")
    capsys.readouterr()
    assert main(["eval", gt, gt, "--delta", "100000"]) == 0
    out = capsys.readouterr().out
    assert "RPE per 10 frames (the ground truth's path" in out and "shorter than the 100000 m segments" in out
    assert main(["eval", gt, gt, "--delta", "5"]) == 0
    assert "RPE per 5 m:" in capsys.readouterr().out
    shell = subprocess.run(f"{sys.executable} -m vislam.tools.cli eval {gt} {gt} --delta 5 | true; "
                           "echo ${PIPESTATUS[0]}", shell=True, capture_output=True, text=True, timeout=120,
                           executable="/bin/bash")
    assert shell.stderr == "" and shell.stdout.strip() == "141", shell


def test_eval_time_offset_and_tolerance_as_evo_names_them(tmp_path, capsys):
    """--t-offset shifts the estimate's stamps before matching, --t-max-diff widens the match: an
    estimate stamped 0.55 s late gives, shifted back, the ATE of the unshifted one (to 1e-6);
    stamps jittered by up to 0.03 s match only with a wider tolerance."""
    from vislam.backend.data.tum import read_tum, write_tum

    scene = tmp_path / "scene"
    assert main(["synth", "--steps", "60", "--out", str(scene), "--quiet"]) == 0
    assert main(["run", str(scene / "data.npz"), "--out", str(tmp_path / "run"), "--quiet"]) == 0
    t, poses = read_tum(tmp_path / "run" / "trajectory.txt")
    gt = str(scene / "gt_tum.txt")
    write_tum(tmp_path / "late.txt", t + 0.55, poses)  # between the 0.1 s steps: nothing matches unshifted
    jitter = np.random.default_rng(0).uniform(-0.03, 0.03, t.size)
    write_tum(tmp_path / "jitter.txt", t + jitter, poses)
    numbers = {}
    for name, extra in (("plain", [str(tmp_path / "run" / "trajectory.txt")]),
                        ("late", [str(tmp_path / "late.txt"), "--t-offset", "-0.55"]),
                        ("jitter", [str(tmp_path / "jitter.txt"), "--t-max-diff", "0.04"])):
        assert main(["eval", *extra[:1], gt, *extra[1:], "--json", str(tmp_path / f"{name}.json")]) == 0
        numbers[name] = json.loads((tmp_path / f"{name}.json").read_text())
    assert numbers["late"]["ate_rmse"] == pytest.approx(numbers["plain"]["ate_rmse"], rel=1e-6)
    assert numbers["jitter"]["num_matched"] == numbers["plain"]["num_matched"] == 60
    assert "shifted by -0.55 s" in numbers["late"]["matched_by"]
    capsys.readouterr()
    assert main(["eval", str(tmp_path / "late.txt"), gt]) == 2  # 0.05 s from the nearest: nothing matches
    assert "within 0.01 s" in capsys.readouterr().err
