"""`vislam batch`: inputs x configurations on a process pool or Ray, one table; the same numbers as single runs."""

from __future__ import annotations

import csv
import json
import shutil

import pytest

from vislam.backend.config import Config
from vislam.backend.data.npz import load_sequence
from vislam.backend.data.tum import read_tum
from vislam.backend.evaluation.metrics import trajectory_errors
from vislam.backend.run.runner import run_sequence
from vislam.tools.cli import main


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """Two synthetic feature files s0.npz, s1.npz with ground truth s0_gt.txt, s1_gt.txt."""
    root = tmp_path_factory.mktemp("batch_inputs")
    for seed in (0, 1):
        scene = root / f"scene{seed}"
        assert main(["synth", "--steps", "60", "--seed", str(seed), "--out", str(scene)]) == 0
        shutil.copy(scene / "data.npz", root / f"s{seed}.npz")
        shutil.copy(scene / "gt_tum.txt", root / f"s{seed}_gt.txt")
    return root


def _rows(out):
    with open(out / "batch.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_batch_on_a_process_pool_matches_single_runs(inputs, tmp_path, capsys):
    out = tmp_path / "b"
    argv = ["batch", str(inputs / "s0.npz"), str(inputs / "s1.npz"), "--vary", "noise.pixel_sigma=0.5,1.0",
            "--gt", str(inputs / "{stem}_gt.txt"), "--out", str(out), "--workers", "2", "--no-progress"]
    assert main(argv) == 0
    rows = _rows(out)
    assert [(r["input"].endswith("s0.npz"), r["configuration"]) for r in rows] == [
        (True, "noise.pixel_sigma=0.5"), (True, "noise.pixel_sigma=1.0"),
        (False, "noise.pixel_sigma=0.5"), (False, "noise.pixel_sigma=1.0")]
    # the same number as a single run of that input and configuration
    result = run_sequence(load_sequence(inputs / "s1.npz"), Config().with_assignments(["noise.pixel_sigma=1.0"]))
    gt_t, gt = read_tum(inputs / "s1_gt.txt")
    expected = trajectory_errors(result.time_stamps, result.world_T_imu, gt_t, gt).ate_rmse
    assert float(rows[3]["ate_m"]) == pytest.approx(expected, rel=1e-3)  # the CSV keeps 4 significant digits
    data = json.loads((out / "batch.json").read_text())
    assert data["rows"][3]["ate_m"] == pytest.approx(expected, rel=1e-12)
    assert (out / "batch.png").stat().st_size > 1000
    assert "s1.npz" in capsys.readouterr().out


def test_batch_on_a_local_ray_instance_gives_the_pool_numbers(inputs, tmp_path):
    pytest.importorskip("ray", reason="the cluster extra (ray) is not installed")
    argv = ["batch", str(inputs / "s0.npz"), "--vary", "noise.pixel_sigma=0.5,1.0",
            "--gt", str(inputs / "{stem}_gt.txt"), "--quiet"]
    assert main([*argv, "--out", str(tmp_path / "pool"), "--workers", "1"]) == 0
    assert main([*argv, "--out", str(tmp_path / "ray"), "--ray", "local", "--workers", "1"]) == 0
    pool = json.loads((tmp_path / "pool" / "batch.json").read_text())["rows"]
    ray = json.loads((tmp_path / "ray" / "batch.json").read_text())["rows"]
    assert [r["ate_m"] for r in ray] == [r["ate_m"] for r in pool]


def test_batch_refuses_and_reports(inputs, tmp_path, capsys):
    out = tmp_path / "x"
    assert main(["batch", str(inputs / "s0.npz"), "--vary", "noise.pixel_sigma", "--out", str(out)]) == 2
    assert "--vary" in capsys.readouterr().err
    assert main(["batch", str(inputs / "s0.npz"), "--vary", "noise.pixel_sigmaa=1", "--out", str(out)]) == 2
    assert "pixel_sigmaa" in capsys.readouterr().err
    assert main(["batch", str(tmp_path / "missing.npz"), "--out", str(out)]) == 2
    assert "missing.npz" in capsys.readouterr().err
    assert not out.exists()
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    assert main(["batch", str(bad), str(inputs / "s0.npz"), "--out", str(out), "--quiet", "--workers", "1"]) == 1
    rows = _rows(out)
    assert rows[0]["error"] and "bad.npz" in rows[0]["error"] and not rows[1]["error"]


def test_mc_on_a_local_ray_instance_gives_the_pool_numbers(tmp_path):
    pytest.importorskip("ray", reason="the cluster extra (ray) is not installed")
    argv = ["mc", "--runs", "2", "--steps", "40", "--quiet"]
    assert main([*argv, "--out", str(tmp_path / "pool"), "--workers", "2"]) == 0
    assert main([*argv, "--out", str(tmp_path / "ray"), "--ray", "local", "--workers", "2"]) == 0
    pool = json.loads((tmp_path / "pool" / "consistency.json").read_text())
    ray = json.loads((tmp_path / "ray" / "consistency.json").read_text())
    for key in ("landmark_nees", "nis"):
        assert ray[key] == pool[key]


def test_inputs_of_the_same_name_keep_apart_and_a_key_varied_twice_is_refused(inputs, tmp_path, capsys):
    """Two inputs named s0.npz in two folders: two rows, two bars, told apart by their folder; a
    --vary key given twice would label rows with values they never ran with, so it is refused."""
    import matplotlib.image

    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    shutil.copy(inputs / "s0.npz", tmp_path / "a" / "s0.npz")
    shutil.copy(inputs / "s1.npz", tmp_path / "b" / "s0.npz")
    out = tmp_path / "out"
    assert main(["batch", str(tmp_path / "a" / "s0.npz"), str(tmp_path / "b" / "s0.npz"), "--vary",
                 "noise.pixel_sigma=0.5,1.0", "--out", str(out), "--workers", "1", "--no-progress"]) == 0
    captured = capsys.readouterr()
    assert "2 configuration(s) (noise.pixel_sigma=0.5,1.0); every run: configuration: the defaults" in captured.err
    table = captured.out
    assert "| a/s0.npz | noise.pixel_sigma=0.5 |" in table and "| b/s0.npz | noise.pixel_sigma=1.0 |" in table
    rows = json.loads((out / "batch.json").read_text())["rows"]
    assert [r["label"] for r in rows] == ["a/s0.npz", "a/s0.npz", "b/s0.npz", "b/s0.npz"]
    assert rows[0]["mean_nis"] != rows[2]["mean_nis"]  # two different drives, not one counted twice
    assert matplotlib.image.imread(out / "batch.png").shape[0] > 100
    assert main(["batch", str(inputs / "s0.npz"), "--vary", "noise.pixel_sigma=1,2", "--vary", "noise.pixel_sigma=3",
                 "--out", str(tmp_path / "twice")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "noise.pixel_sigma" in err and "more than once" in err
    assert not (tmp_path / "twice").exists()


def test_input_labels_are_the_shortest_distinct_suffixes():
    from vislam.tools.report import path_labels as input_labels

    assert input_labels(["x/a.npz", "y/b.npz"]) == {"x/a.npz": "a.npz", "y/b.npz": "b.npz"}
    assert input_labels(["r/x/a.npz", "r/y/a.npz", "r/y/b.npz"]) == {
        "r/x/a.npz": "x/a.npz", "r/y/a.npz": "y/a.npz", "r/y/b.npz": "y/b.npz"}
    assert input_labels(["d/a.npz", "d/a.npz"]) == {"d/a.npz": "a.npz"}


def test_inputs_without_ground_truth_are_named_on_screen(inputs, tmp_path, capsys):
    out = tmp_path / "b"
    assert main(["batch", str(inputs / "s0.npz"), str(inputs / "s1.npz"), "--gt", str(inputs / "{stem}_truth.txt"),
                 "--out", str(out), "--workers", "1", "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "no ground truth for 2 of 2 input(s)" in err and str(inputs / "s0_truth.txt") in err, err
    assert all(r["ate_m"] == "" for r in _rows(out))


def test_every_run_keeps_its_trajectory_and_covariance_and_eval_compares_them(inputs, tmp_path, capsys):
    """runs/INPUT/CONFIGURATION/ holds what a single run of it writes; `vislam eval` reads them all
    (with each one's covariance) and gives the ATE the table gave."""
    from vislam.backend.data.covariance import read_pose_covariance

    out = tmp_path / "b"
    assert main(["batch", str(inputs / "s0.npz"), "--vary", "noise.pixel_sigma=0.5,1.0", "--gt",
                 str(inputs / "{stem}_gt.txt"), "--out", str(out), "--workers", "1", "--quiet"]) == 0
    rows = json.loads((out / "batch.json").read_text())["rows"]
    assert [r["run_folder"] for r in rows] == ["runs/s0/noise.pixel_sigma=0.5", "runs/s0/noise.pixel_sigma=1.0"]
    result = run_sequence(load_sequence(inputs / "s0.npz"), Config().with_assignments(["noise.pixel_sigma=1.0"]))
    t, poses = read_tum(out / rows[1]["run_folder"] / "trajectory.txt")
    assert abs(t - result.time_stamps).max() < 1e-6 and abs(poses - result.world_T_imu).max() < 1e-8
    cov_t, cov = read_pose_covariance(out / rows[1]["run_folder"] / "pose_covariance.npz")
    assert abs(cov - result.pose_covariance).max() == 0.0 and (cov_t == result.time_stamps).all()
    capsys.readouterr()
    assert main(["eval", *(str(out / r["run_folder"] / "trajectory.txt") for r in rows), str(inputs / "s0_gt.txt"),
                 "--json", str(tmp_path / "e.json")]) == 0
    evaluated = json.loads((tmp_path / "e.json").read_text())["estimates"]
    for row, e in zip(rows, evaluated):
        assert e["ate_rmse"] == pytest.approx(row["ate_m"], rel=1e-6)  # TUM text rounds the poses
        assert e["nees"]["position"]["steps"] > 0


def test_health_warnings_are_listed_on_stderr_naming_the_run(inputs, tmp_path, capsys):
    """A pixel sigma 20x too large makes the NIS far too small: each run's messages, a line each."""
    out = tmp_path / "b"
    assert main(["batch", str(inputs / "s1.npz"), "--set", "noise.pixel_sigma=20", "--set", "health.nis_window=10",
                 "--out", str(out), "--workers", "1", "--quiet"]) == 0
    row = json.loads((out / "batch.json").read_text())["rows"][0]
    err = capsys.readouterr().err.splitlines()
    assert row["health_warnings"] >= 1
    assert len(err) == row["health_warnings"]
    assert all(line.startswith("warning: s1.npz, defaults: step ") for line in err)


@pytest.mark.parametrize("warmed", [False, True])
def test_a_pool_command_compiles_the_kernels_before_its_workers_start(inputs, tmp_path, monkeypatch, warmed):
    """On the first run after an install, ``batch`` and ``mc`` warm the kernels up in the command's own
    process (with its compile helper) before a local pool starts, so the workers load them; once a
    whole warm-up wrote the caches they leave it to the workers (loading only)."""
    from vislam.backend import compiled

    calls = []
    monkeypatch.setattr(compiled, "warmed_before", lambda: warmed)
    monkeypatch.setattr(compiled, "warm_up",
                        lambda notice=None, inertial=False, window=False: calls.append((inertial, window)) or 0.0)
    assert main(["batch", str(inputs / "s0.npz"), "--out", str(tmp_path / "b"), "--workers", "2", "--no-progress",
                 "--quiet"]) == 0
    assert main(["mc", "--runs", "2", "--steps", "30", "--workers", "2", "--quiet", "--out", str(tmp_path / "m")]) == 0
    assert calls == ([] if warmed else [(False, False), (False, False)])
