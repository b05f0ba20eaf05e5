"""The `vislam` command line: outputs, refusals, exit codes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from backend.sequence import load_sequence, save_sequence
from tools.cli import main

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
    assert {"trajectory.txt", "dead_reckoning.txt", "map.npz", "map.ply", "trajectory.ply",
            "trajectory.png", "ate_over_time.png", "summary.json", "config.toml"} <= names
    assert not [n for n in names if ".tmp" in n]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 150
    assert summary["conventions"]["velocity_index"] == "next"
    # the summary's error is what `vislam eval` computes from the files written
    assert main(["eval", str(out / "trajectory.txt"), str(gt), "--json", str(tmp_path / "eval.json")]) == 0
    evaluated = json.loads((tmp_path / "eval.json").read_text())
    assert evaluated["ate_rmse"] == pytest.approx(summary["errors"]["estimate"]["ate_rmse"], rel=1e-6)
    assert evaluated["num_matched"] == 150
    # with --out: the JSON and both plots; an existing non-empty directory is refused
    assert main(["eval", str(out / "trajectory.txt"), str(gt), "--out", str(tmp_path / "ev")]) == 0
    assert {p.name for p in (tmp_path / "ev").iterdir()} == {"eval.json", "trajectories.png", "ate_over_time.png"}
    assert json.loads((tmp_path / "ev" / "eval.json").read_text()) == evaluated
    assert main(["eval", str(out / "trajectory.txt"), str(gt), "--out", str(tmp_path / "ev")]) == 2
    timing = summary["timing"]
    assert timing["setup_seconds"] > 0  # loading and the convention test count, though run decides them first
    assert timing["real_time_factor"] == pytest.approx(
        timing["sequence_seconds"] / (timing["filter_seconds"] + timing["setup_seconds"]), rel=1e-9)
    assert "kernel_seconds" in timing  # compiling or loading the kernels, once per process, reported apart
    # evo reads the trajectory
    from evo.tools import file_interface

    traj = file_interface.read_tum_trajectory_file(str(out / "trajectory.txt"))
    assert traj.num_poses == 150
    with np.load(out / "map.npz") as m:
        assert m["positions"].shape == (m["ids"].size, 3)
        assert m["covariances"].shape == (m["ids"].size, 3, 3)
    # the config written is loadable and reproduces the run's settings
    assert main(["run", str(short_0027), "--out", str(tmp_path / "again"), "--quiet",
                 "--config", str(out / "config.toml")]) == 0


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


@needs_data
def test_check_prints_both_convention_numbers(capsys):
    assert main(["check", str(DATA / "ece276a_03.npz")]) == 0
    out = capsys.readouterr().out
    assert "flip=yes,velocity=next" in out and "flip=no,velocity=this" in out
    assert "IMU y,z flipped" in out
    assert "track drift: landmark random walk" in out and "(auto: tracks from another tracker" in out
