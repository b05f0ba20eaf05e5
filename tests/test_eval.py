"""``vislam eval`` as evo's users expect it: several estimates in one table and overlaid plots, EuRoC
csv, ``--align-origin``, and result files that evo itself reads back."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vislam.backend.data.covariance import POSE_COVARIANCE_FILE, write_pose_covariance
from vislam.backend.data.tum import read_euroc_csv, read_trajectory, write_tum
from vislam.backend.evaluation.metrics import aligned_poses, alignment, trajectory_errors
from vislam.tools.cli import main
from vislam.tools.plots import plot_rpy_over_time, plot_xyz_over_time

EUROC = Path(__file__).resolve().parents[1].parent / "shared" / "euroc"


def drive(t: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses of a winding drive at 10 m/s (never on one line), yaw following the road."""
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    poses[:, 0, 3] = 10.0 * t
    poses[:, 1, 3] = 20.0 * np.sin(t / 4.0)
    poses[:, 2, 3] = 0.5 * np.cos(t / 3.0)
    poses[:, :3, :3] = Rotation.from_euler("zyx", np.c_[np.cos(t / 4.0) / 2.0, 0.1 * np.sin(t), 0.05 * t]).as_matrix()
    return poses


def disturbed(poses: np.ndarray, seed: int, sigma: float, yaw: float = 0.7) -> np.ndarray:
    """``poses`` in another frame (rotated about z by ``yaw``, shifted) with noisy positions."""
    R = Rotation.from_euler("z", yaw).as_matrix()
    out = poses.copy()
    out[:, :3, 3] = poses[:, :3, 3] @ R.T + [30.0, -12.0, 1.0]
    out[:, :3, 3] += np.random.default_rng(seed).normal(0.0, sigma, (len(poses), 3))
    out[:, :3, :3] = R @ poses[:, :3, :3]
    return out


@pytest.fixture
def three(tmp_path):
    """A ground truth and three estimates of it (two runs' trajectory.txt, one with a covariance,
    and a renamed file), 60 s at 10 Hz."""
    t = np.round(np.arange(0.0, 60.0, 0.1), 6)
    gt = drive(t)
    write_tum(tmp_path / "gt.txt", t, gt)
    paths = []
    for k, (folder, name, sigma) in enumerate((("a", "trajectory.txt", 0.2), ("b", "trajectory.txt", 0.6),
                                               ("b", "other.txt", 1.5))):
        (tmp_path / folder).mkdir(exist_ok=True)
        write_tum(tmp_path / folder / name, t, disturbed(gt, k, sigma))
        paths.append(tmp_path / folder / name)
    write_pose_covariance(tmp_path / "a" / POSE_COVARIANCE_FILE, t, np.tile(0.04 * np.eye(6), (len(t), 1, 1)))
    return tmp_path, paths


def test_several_estimates_one_table_json_and_overlaid_plots(three, capsys):
    root, paths = three
    out = root / "E"
    assert main(["eval", *map(str, paths), str(root / "gt.txt"), "--out", str(out), "--json", str(root / "e.json")]) == 0
    printed = capsys.readouterr().out.splitlines()
    gt = read_trajectory(root / "gt.txt")
    read = {p: read_trajectory(p) for p in paths}
    expected = {p: trajectory_errors(read[p].time_stamps, read[p].poses, gt.time_stamps, gt.poses) for p in paths}
    rows = [ln for ln in printed if ln.startswith("| ") and not ln.startswith("| estimate")]
    assert [r.split(" | ")[0] for r in rows] == ["| a/trajectory.txt", "| b/trajectory.txt", "| b/other.txt"]
    for row, p in zip(rows, paths):
        assert row.split(" | ")[1] == f"{expected[p].ate_rmse:.3f}"
    # the covariance beside a/trajectory.txt is its own; b has none and other.txt is no run's trajectory.txt
    assert rows[0].endswith("%|") or rows[0].rstrip().endswith("% |")
    assert rows[1].rstrip().endswith("|  |  |") and rows[2].rstrip().endswith("|  |  |")
    document = json.loads((root / "e.json").read_text())
    assert document == json.loads((out / "eval.json").read_text())
    assert document["ground_truth"] == str(root / "gt.txt")
    assert [e["file"] for e in document["estimates"]] == list(map(str, paths))
    for e, p in zip(document["estimates"], paths):
        assert e["ate_rmse"] == pytest.approx(expected[p].ate_rmse, rel=1e-12)
    assert "nees" in document["estimates"][0] and "nees" not in document["estimates"][1]
    names = {p.name for p in out.iterdir()}
    assert {"trajectories.png", "xyz_over_time.png", "rpy_over_time.png", "ate_over_time.png",
            "nees_over_time_a_trajectory.png", "ape_a_trajectory.zip", "rpe_b_trajectory.zip",
            "ape_b_other.zip"} <= names
    assert not any(n.startswith("nees_over_time_b") or n.startswith("nees_over_time_b_other") for n in names)


def test_the_result_files_are_evos_and_evo_res_reads_them(three, capsys):
    from evo.tools.file_interface import load_res_file

    root, paths = three
    out = root / "E"
    assert main(["eval", *map(str, paths[:2]), str(root / "gt.txt"), "--out", str(out), "--json",
                 str(root / "e.json")]) == 0
    document = json.loads((root / "e.json").read_text())
    for kind, key in (("ape", "ate_rmse"), ("rpe", "rpe_trans_rmse")):
        for stem, numbers in zip(("a_trajectory", "b_trajectory"), document["estimates"]):
            result = load_res_file(out / f"{kind}_{stem}.zip", load_trajectories=True)
            assert result.stats["rmse"] == pytest.approx(numbers[key], rel=1e-12)
            assert result.info["est_name"] == stem and result.info["ref_name"] == "gt.txt"
    evo_res = Path(sys.executable).parent / "evo_res"
    done = subprocess.run([str(evo_res), *map(str, sorted(out.glob("ape_*.zip"))), "--no_warnings"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    table = [ln.split() for ln in done.stdout.splitlines() if ln.split()[:1] in (["a_trajectory"], ["b_trajectory"])]
    assert [float(r[1]) for r in table[:2]] == pytest.approx([e["ate_rmse"] for e in document["estimates"]], rel=1e-5)


def test_align_origin_puts_the_first_poses_on_each_other_as_evo(three, capsys):
    from evo.core.metrics import PoseRelation
    from evo.core.trajectory import PoseTrajectory3D
    from evo.main_ape import ape

    root, paths = three
    est = read_trajectory(paths[1])
    gt = read_trajectory(root / "gt.txt")
    found = alignment(est.time_stamps, est.poses, gt.time_stamps, gt.poses, origin=True)
    moved = found.apply_poses(est.poses)
    np.testing.assert_allclose(moved[0], gt.poses[0], atol=1e-9)
    assert found.kind == "origin" and found.scale == 1.0
    t, aligned, _ = aligned_poses(est.time_stamps, est.poses, gt.time_stamps, gt.poses, origin=True)
    np.testing.assert_allclose(aligned, moved, atol=1e-9)
    reference = ape(PoseTrajectory3D(poses_se3=list(gt.poses), timestamps=gt.time_stamps),
                    PoseTrajectory3D(poses_se3=list(est.poses), timestamps=est.time_stamps),
                    PoseRelation.translation_part, align_origin=True)
    assert main(["eval", str(paths[1]), str(root / "gt.txt"), "--align-origin", "--json", str(root / "o.json")]) == 0
    assert capsys.readouterr().out.startswith("ATE RMSE (first-pose-aligned) ")
    numbers = json.loads((root / "o.json").read_text())
    assert numbers["ate_rmse"] == pytest.approx(reference.stats["rmse"], rel=1e-12)
    assert numbers["alignment"] == "origin"
    # the Umeyama alignment fits better than the first pose alone
    assert numbers["ate_rmse"] > trajectory_errors(est.time_stamps, est.poses, gt.time_stamps, gt.poses).ate_rmse
    with pytest.raises(SystemExit) as e:
        main(["eval", str(paths[1]), str(root / "gt.txt"), "--align-origin", "--sim3"])
    assert e.value.code == 2
    assert "not allowed with argument" in capsys.readouterr().err


def test_xyz_and_rpy_plots_draw_the_poses_they_are_given():
    t = np.round(np.arange(0.0, 20.0, 0.1), 6)
    poses = drive(t)
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        fig = plot_xyz_over_time(Path(d) / "xyz.png", {"estimate": (t + 5.0, poses)}, title="x")
        for k, ax in enumerate(fig.axes[:3]):
            drawn = ax.get_lines()[0]
            np.testing.assert_allclose(drawn.get_ydata(), poses[:, k, 3])
            np.testing.assert_allclose(drawn.get_xdata(), t)  # seconds since the earliest stamp
        fig = plot_rpy_over_time(Path(d) / "rpy.png", {"estimate": (t, poses)})
        expected = np.degrees(np.unwrap(Rotation.from_matrix(poses[:, :3, :3]).as_euler("xyz"), axis=0))
        for k, ax in enumerate(fig.axes[:3]):
            np.testing.assert_allclose(ax.get_lines()[0].get_ydata(), expected[:, k], atol=1e-9)
        assert [ax.get_ylabel() for ax in fig.axes[:3]] == ["roll [deg]", "pitch [deg]", "yaw [deg]"]
        assert fig.axes[2].get_xlabel() == "time [s]"
        fig = plot_xyz_over_time(Path(d) / "frames.png", {"estimate": (np.arange(len(t), dtype=float), poses)},
                                 xlabel="frame")
        assert fig.axes[2].get_xlabel() == "frame"
        assert (Path(d) / "xyz.png").stat().st_size > 0


def test_a_tum_estimate_against_euroc_csv_ground_truth(tmp_path, capsys):
    """evo's ``euroc`` mode: the ground truth as EuRoC csv (ns stamps, w-first quaternion), the
    estimate TUM; the same numbers as with the ground truth written as TUM."""
    t = 1403715273.262142976 + np.round(np.arange(0.0, 30.0, 0.05), 6)
    gt = drive(t - t[0])
    q = Rotation.from_matrix(gt[:, :3, :3]).as_quat()
    ns = [round(x * 1e9) for x in t]
    rows = ["#time(ns),px,py,pz,qw,qx,qy,qz,vx,vy,vz,bwx,bwy,bwz,bax,bay,baz"]
    rows += [",".join([str(n)] + [repr(float(v)) for v in (*p[:3, 3], qi[3], qi[0], qi[1], qi[2])] + ["0"] * 9)
             for n, p, qi in zip(ns, gt, q)]
    (tmp_path / "data.csv").write_text("\n".join(rows) + "\n")
    write_tum(tmp_path / "gt.txt", t, gt)
    write_tum(tmp_path / "est.txt", t, disturbed(gt, 3, 0.3))
    for truth in ("data.csv", "gt.txt"):
        assert main(["eval", str(tmp_path / "est.txt"), str(tmp_path / truth), "--json",
                     str(tmp_path / f"{truth}.json")]) == 0
    a, b = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("data.csv", "gt.txt"))
    assert a["num_matched"] == b["num_matched"] == len(t)
    assert a["ate_rmse"] == pytest.approx(b["ate_rmse"], rel=1e-6)


@pytest.mark.skipif(not EUROC.is_dir(), reason=f"EuRoC data not found at {EUROC} (../shared/euroc)")
def test_euroc_csv_reads_as_the_folder_reader_and_evo_read_it():
    from evo.tools.file_interface import read_euroc_csv_trajectory

    from vislam.frontend.euroc import read_ground_truth

    (path,) = EUROC.glob("*/mav0/state_groundtruth_estimate0/data.csv")
    t, poses = read_euroc_csv(path)
    truth = read_ground_truth(path.parents[1])
    np.testing.assert_array_equal(t, truth.times)
    np.testing.assert_allclose(poses, truth.world_T_imu, atol=1e-12)
    theirs = read_euroc_csv_trajectory(str(path))
    np.testing.assert_allclose(t, theirs.timestamps, rtol=0, atol=1e-6)
    np.testing.assert_allclose(poses, np.array(theirs.poses_se3), atol=1e-9)


def test_an_estimate_given_twice_and_one_covariance_for_several_are_refused(three, capsys):
    root, paths = three
    assert main(["eval", str(paths[0]), str(paths[0]), str(root / "gt.txt")]) == 2
    assert "given twice" in capsys.readouterr().err
    assert main(["eval", *map(str, paths[:2]), str(root / "gt.txt"), "--covariance",
                 str(root / "a" / POSE_COVARIANCE_FILE)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "one file for 2 estimates" in err
