"""Tests of the output files: vislam.backend.data.files (atomic_write), vislam.backend.data.tum (TUM
trajectories), vislam.tools.outputs (output directory, map and trajectory PLY/NPZ, JSON) and
vislam.tools.plots."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vislam.backend.data.covariance import read_pose_covariance, write_pose_covariance
from vislam.backend.data.files import atomic_write
from vislam.backend.data.tum import read_tum, write_tum
from vislam.backend.errors import InputError
from vislam.tools.outputs import (
    uncertainty_colors,
    write_json,
    write_map_npz,
    write_map_ply,
    write_trajectory_ply,
)


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.random(n, random_state=rng.integers(1 << 31)).as_matrix()
    poses[:, :3, 3] = rng.uniform(-50.0, 50.0, size=(n, 3))
    return poses


def rotation_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (rad) of a_i^T b_i, robust for tiny angles."""
    return Rotation.from_matrix(np.swapaxes(a, 1, 2) @ b).magnitude()


def listing(path) -> list[str]:
    return sorted(os.listdir(path))


# ---------------------------------------------------------------- atomic_write


def test_atomic_write_success_replaces_target(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with atomic_write(target) as tmp:
        assert tmp.parent == tmp_path
        assert tmp.name.startswith(".out.tmp-") and tmp.suffix == ".txt"
        tmp.write_text("new")
        assert target.read_text() == "old"  # not replaced before success
    assert target.read_text() == "new"
    assert listing(tmp_path) == ["out.txt"]


@pytest.mark.parametrize("exc_type", [RuntimeError, KeyboardInterrupt])
def test_atomic_write_failure_leaves_no_files(tmp_path, exc_type):
    target = tmp_path / "map.ply"
    with pytest.raises(exc_type):
        with atomic_write(target) as tmp:
            assert tmp.suffix == ".ply"
            tmp.write_bytes(b"half")
            raise exc_type("interrupted")
    assert listing(tmp_path) == []


def test_atomic_write_failure_keeps_existing_target(tmp_path):
    target = tmp_path / "traj.txt"
    target.write_text("previous")
    with pytest.raises(KeyboardInterrupt):
        with atomic_write(target) as tmp:
            tmp.write_text("partial")
            raise KeyboardInterrupt
    assert target.read_text() == "previous"
    assert listing(tmp_path) == ["traj.txt"]


# ---------------------------------------------------------------- TUM


def test_tum_round_trip(tmp_path):
    poses = random_poses(50)
    t = 1403636579.763555 + 0.05 * np.arange(50)
    path = tmp_path / "traj.txt"
    write_tum(path, t, poses, header="vislam estimate\nworld_T_imu")
    text = path.read_text().splitlines()
    assert text[0] == "# vislam estimate" and text[1] == "# world_T_imu"
    t2, poses2 = read_tum(path)
    assert t2.shape == (50,) and poses2.shape == (50, 4, 4)
    np.testing.assert_allclose(t2, t, atol=1e-6, rtol=0)
    np.testing.assert_allclose(poses2[:, :3, 3], poses[:, :3, 3], atol=1e-6, rtol=0)
    assert rotation_angle(poses2[:, :3, :3], poses[:, :3, :3]).max() < 1e-8
    np.testing.assert_array_equal(poses2[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (50, 1)))
    assert listing(tmp_path) == ["traj.txt"]
    # time with 6 decimals, translation and quaternion with 9 (qw >= 0)
    first = text[2].split()
    assert [len(v.split(".")[1]) for v in first] == [6] + [9] * 7
    assert float(first[7]) >= 0.0
    np.testing.assert_allclose(poses2[:, :3, 3], poses[:, :3, 3], atol=1e-9, rtol=0)


def test_evo_reads_what_write_tum_wrote(tmp_path):
    from evo.tools.file_interface import read_tum_trajectory_file

    poses = random_poses(20, seed=3)
    t = np.arange(20) * 0.1
    path = tmp_path / "traj.tum"
    write_tum(path, t, poses, header="comment")
    traj = read_tum_trajectory_file(str(path))
    np.testing.assert_allclose(traj.positions_xyz, poses[:, :3, 3], atol=1e-6, rtol=0)
    np.testing.assert_allclose(traj.timestamps, t, atol=1e-6, rtol=0)
    assert rotation_angle(np.array(traj.poses_se3)[:, :3, :3], poses[:, :3, :3]).max() < 1e-8


GOOD = "1.0 0 0 0 0 0 0 1"


def test_read_tum_normalizes_a_quaternion_typed_to_few_decimals(tmp_path):
    path = tmp_path / "typed.txt"
    path.write_text("0 1 2 3 0.7071 0 0 0.7071\n1 1 2 3 0 0 0 1\n")  # norm 0.99999
    _, poses = read_tum(path)
    np.testing.assert_allclose(poses[0, :3, :3], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)


@pytest.mark.parametrize(
    "bad_line, lineno, fragment",
    [
        ("2.0 0 0 0 0 0 1", 4, "expected 8 columns"),
        ("2.0 0 0 0 0 0 0 1 5", 4, "expected 8 columns"),
        ("2.0 0 abc 0 0 0 0 1", 4, "not a number"),
        ("2.0 0 nan 0 0 0 0 1", 4, "non-finite"),
        ("2.0 0 0 0 0 0 0 0", 4, "zero norm"),
        ("1.0 0 0 0 0 0 0 1", 4, "not greater than the previous"),
    ],
)
def test_read_tum_errors_name_file_and_line(tmp_path, bad_line, lineno, fragment):
    path = tmp_path / "bad.txt"
    path.write_text(f"# header\n{GOOD}\n\n{bad_line}\n")
    with pytest.raises(InputError) as info:
        read_tum(path)
    message = str(info.value)
    assert f"{path}:{lineno}:" in message
    assert fragment in message
    assert "\n" not in message


def test_read_tum_empty_and_missing(tmp_path):
    path = tmp_path / "empty.txt"
    path.write_text("# only a comment\n\n")
    with pytest.raises(InputError, match="empty.txt"):
        read_tum(path)
    with pytest.raises(InputError, match="missing.txt"):
        read_tum(tmp_path / "missing.txt")


def test_read_tum_normalises_quaternion(tmp_path):
    path = tmp_path / "t.txt"
    path.write_text("0 1 2 3 0 0 0 2\n1 1 2 3 0 0 2 2\n")
    _, poses = read_tum(path)
    expected = np.eye(4)
    expected[:3, 3] = [1.0, 2.0, 3.0]
    np.testing.assert_allclose(poses[0], expected, atol=1e-12)
    # (0, 0, 2, 2) normalised: 90 degrees about z
    np.testing.assert_allclose(poses[1, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    # components beyond 1e154 (their squares overflow) and below 1e-154 (underflow) alike
    path.write_text("0 1 2 3 1e200 0 0 1\n1 1 2 3 0 0 1e-200 1e-200\n")
    _, poses = read_tum(path)
    np.testing.assert_allclose(poses[0, :3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    np.testing.assert_allclose(poses[1, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)


# ---------------------------------------------------------------- map


def make_map(k: int = 40, seed: int = 1):
    rng = np.random.default_rng(seed)
    positions = rng.normal(scale=10.0, size=(k, 3))
    sigmas = np.geomspace(0.01, 2.0, k)  # increasing uncertainty with the index
    axes = Rotation.random(k, random_state=seed).as_matrix()
    scales = np.stack([sigmas, 0.5 * sigmas, 0.2 * sigmas], axis=1) ** 2
    covariances = axes @ (scales[:, :, None] * np.swapaxes(axes, 1, 2))
    return np.arange(100, 100 + k), positions, covariances, sigmas


def test_map_npz(tmp_path):
    ids, pos, cov, _ = make_map()
    path = tmp_path / "map.npz"
    write_map_npz(path, ids, pos, cov)
    with np.load(path) as data:
        assert sorted(data.files) == ["covariances", "ids", "positions"]
        assert data["ids"].shape == (40,) and data["positions"].shape == (40, 3)
        assert data["covariances"].shape == (40, 3, 3)
        np.testing.assert_array_equal(data["ids"], ids)
        np.testing.assert_array_equal(data["positions"], pos)
        np.testing.assert_array_equal(data["covariances"], cov)
    assert listing(tmp_path) == ["map.npz"]


def test_pose_covariance_npz_round_trip(tmp_path):
    """write_pose_covariance: exactly the two arrays, float64, read back unchanged; the exact name (no
    ".npz" appended), an existing file replaced, nothing left on a refusal."""
    rng = np.random.default_rng(4)
    t = 1.3e9 + 0.1 * np.arange(30)
    A = rng.standard_normal((30, 6, 6))
    cov = A @ np.swapaxes(A, 1, 2)
    path = tmp_path / "pose_covariance.npz"
    path.write_text("old")
    write_pose_covariance(path, t, cov.astype(np.float32).astype(np.float64))
    write_pose_covariance(path, t, cov)
    with np.load(path) as data:
        assert sorted(data.files) == ["covariance", "time_stamps"]
        assert data["time_stamps"].dtype == data["covariance"].dtype == np.float64
    t_read, cov_read = read_pose_covariance(path)
    np.testing.assert_array_equal(t_read, t)
    np.testing.assert_array_equal(cov_read, cov)
    write_pose_covariance(tmp_path / "cov.bin", t, cov)  # the exact name
    np.testing.assert_array_equal(read_pose_covariance(tmp_path / "cov.bin")[1], cov)
    bad = cov.copy()
    bad[3, 0, 0] = np.nan
    for stamps, matrices, match in ((t, cov[:, :, :5], "shape"), (t[:-1], cov, "shape"), (t, bad, "index 3")):
        with pytest.raises(ValueError, match=match):
            write_pose_covariance(tmp_path / "refused.npz", stamps, matrices)
    assert listing(tmp_path) == ["cov.bin", "pose_covariance.npz"]


def test_uncertainty_colors_monotonic():
    _, _, cov, sigmas = make_map()
    rgb, sigma, u = uncertainty_colors(cov)
    np.testing.assert_allclose(sigma, sigmas, rtol=1e-9)  # sqrt of the largest eigenvalue
    assert np.all(np.diff(u) >= 0) and u[0] == 0.0 and u[-1] == 1.0
    assert np.all(np.diff(rgb[:, 1]) >= 0)  # viridis green channel grows with uncertainty
    assert rgb[-1, 1] - rgb[0, 1] > 0.5


def test_map_ply(tmp_path):
    import open3d as o3d

    _, pos, cov, _ = make_map()
    path = tmp_path / "map.ply"
    write_map_ply(path, pos, cov)
    assert listing(tmp_path) == ["map.ply"]
    cloud = o3d.io.read_point_cloud(str(path))
    points = np.asarray(cloud.points)
    colors = np.asarray(cloud.colors)
    assert points.shape == (40, 3)
    np.testing.assert_allclose(points, pos, atol=1e-9)
    assert colors.shape == (40, 3) and colors.min() >= 0.0 and colors.max() <= 1.0
    expected, _, _ = uncertainty_colors(cov)
    np.testing.assert_allclose(colors, expected, atol=1.0 / 255.0)
    assert np.abs(colors[-1] - colors[0]).max() > 0.3  # uncertain != certain
    assert colors[-1, 1] > colors[20, 1] > colors[0, 1]


def test_empty_map_ply_is_not_written(tmp_path):
    """A PLY cloud needs a point: an empty map writes nothing and says so (False)."""
    path = tmp_path / "map.ply"
    assert write_map_ply(path, np.zeros((0, 3)), np.zeros((0, 3, 3))) is False
    assert listing(tmp_path) == []
    _, pos, cov, _ = make_map()
    assert write_map_ply(path, pos, cov) is True


def test_trajectory_ply(tmp_path):
    import open3d as o3d

    poses = random_poses(30, seed=5)
    path = tmp_path / "trajectory.ply"
    write_trajectory_ply(path, poses)
    lines = o3d.io.read_line_set(str(path))
    np.testing.assert_allclose(np.asarray(lines.points), poses[:, :3, 3], atol=1e-9)
    edges = np.asarray(lines.lines)
    np.testing.assert_array_equal(edges, np.column_stack([np.arange(29), np.arange(1, 30)]))
    colors = np.asarray(lines.colors)
    assert colors.shape == (29, 3) and np.abs(colors[0] - colors[-1]).max() > 0.3
    assert listing(tmp_path) == ["trajectory.ply"]
    write_trajectory_ply(tmp_path / "one.ply", poses[:1])  # open3d refuses 0 lines: one vertex
    one = o3d.io.read_point_cloud(str(tmp_path / "one.ply"))
    np.testing.assert_allclose(np.asarray(one.points), poses[:1, :3, 3], atol=1e-9)
    with pytest.raises(ValueError, match="no poses"):
        write_trajectory_ply(tmp_path / "none.ply", poses[:0])


# ---------------------------------------------------------------- JSON


def test_write_json(tmp_path):
    path = tmp_path / "r.json"
    obj = {
        "a": np.float32(1.5),
        "b": np.arange(3),
        "c": [np.nan, np.inf, 2.0],
        "d": {"e": np.int64(7), "f": np.bool_(True)},
        "g": (1, 2),
        "h": tmp_path,
    }
    write_json(path, obj)
    text = path.read_text()
    assert text.startswith('{\n  "a": 1.5')
    data = json.loads(text)
    assert data == {
        "a": 1.5, "b": [0, 1, 2], "c": [None, None, 2.0], "d": {"e": 7, "f": True},
        "g": [1, 2], "h": str(tmp_path),
    }


# ---------------------------------------------------------------- plots


def test_plots(tmp_path):
    from vislam.tools.plots import plot_errors_over_time, plot_trajectories_topdown

    poses = random_poses(100, seed=2)
    path = tmp_path / "topdown.png"
    t = np.arange(100) * 0.1
    plot = plot_trajectories_topdown(
        path,
        {"estimate": (t, poses[:, :3, 3] + 0.1), "other": (t, poses[:, :3, 3] * 2)},
        (t, poses),
        landmarks=np.random.default_rng(0).normal(size=(25000, 3)),
        title="test",
    )
    assert plot.landmarks_total == 25000 and plot.landmarks_drawn == 20000  # a random subset of those in view
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    errors_path = tmp_path / "ate.png"
    plot_errors_over_time(errors_path, {"error": (np.arange(100) * 0.1, np.abs(np.sin(np.arange(100))))}, "ATE")
    assert errors_path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert listing(tmp_path) == ["ate.png", "topdown.png"]
    two = tmp_path / "two.png"  # several series, with different stamps; an empty one is skipped
    plot_errors_over_time(two, {"estimate": (np.arange(50) * 0.1, np.linspace(0.0, 1.0, 50)),
                                "dead reckoning": (5.0 + np.arange(30) * 0.2, np.full(30, np.nan)),
                                "none": (np.zeros(0), np.zeros(0))}, "ATE", ylabel="m")
    assert two.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="same shape"):
        plot_errors_over_time(tmp_path / "bad.png", {"e": (np.arange(3), np.arange(4))}, "ATE")
    assert listing(tmp_path) == ["ate.png", "topdown.png", "two.png"]


def test_plot_consistency(tmp_path):
    from types import SimpleNamespace

    from vislam.tools.plots import plot_consistency

    rng = np.random.default_rng(0)
    steps = 60
    nees = rng.chisquare(6, steps)
    nees[0] = 0.0  # not positive: left out of the log-scale panel
    result = SimpleNamespace(steps=steps, runs=5, skip=10, pose_nees_mean=nees, pose_nees_band=(3.5, 9.4),
                             pose_nees_in_band=0.9, nis_per_step=rng.chisquare(4, steps), nis_band=(3.8, 4.2),
                             nis_mean=4.01, nis_expected=4.0, per_run_nis=np.array([3.9, 4.05, 4.0, 4.1, 3.95]))
    path = tmp_path / "consistency.png"
    fig = plot_consistency(path, result)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert listing(tmp_path) == ["consistency.png"]
    nees_ax, nis_ax = fig.axes
    labels = [ln.get_label() for ln in nees_ax.get_lines()]
    assert any(label.startswith("step 10: counted from here") for label in labels), labels  # the dotted line
    fig.canvas.draw()
    ticks = [t.get_text() for t in nees_ax.get_yticklabels() if t.get_text()]
    assert ticks and all("times" not in t and "^" not in t for t in ticks), ticks  # 2, 5, 10, not 6x10^0
    (mean_line,) = [ln for ln in nis_ax.get_lines() if ln.get_label().startswith("mean 4.010")]
    lo = 4.0 - 2.776 * np.std([3.9, 4.05, 4.0, 4.1, 3.95], ddof=1) / np.sqrt(5)  # t(0.975, 4) = 2.776
    assert f"95 % interval of the runs' mean [{lo:.3f}," in mean_line.get_label(), mean_line.get_label()


_IMPORT_OPEN3D = r"""
import json, sys
from pathlib import Path
import numpy as np
from vislam.tools.outputs import import_open3d, write_map_ply
o3d = import_open3d()
light = [name for name in ("dash", "plotly", "plotly.graph_objects") if name in sys.modules]
write_map_ply(Path(sys.argv[1]), np.eye(3), np.stack([np.eye(3)] * 3))
points = np.asarray(o3d.io.read_point_cloud(sys.argv[1]).points).tolist()
import dash  # the real package is still importable afterwards
print(json.dumps({"light": light, "points": points, "real_dash": isinstance(dash.Dash, type)}))
"""


def test_open3d_is_imported_without_its_web_viewer(tmp_path):
    """In a fresh process (other tests import open3d the usual way): no dash/plotly while writing
    PLY files, and the real dash importable afterwards."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", _IMPORT_OPEN3D, str(tmp_path / "m.ply")], cwd=root, check=True,
                         capture_output=True, text=True)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["light"] == []
    assert result["points"] == np.eye(3).tolist()
    assert result["real_dash"]


def _small_run():
    from vislam.backend.run.runner import run_sequence
    from vislam.synth.scene import SceneConfig, make_scene

    scene = make_scene(SceneConfig(steps=40, seed=2))
    return run_sequence(scene.sequence), (scene.sequence.time_stamps, scene.world_T_imu_true)


def test_the_output_helper_writes_what_the_run_would(tmp_path):
    """``tools.output_process``: with the helper process writing the PNG and PLY files, a run's outputs
    are the same files, byte for byte, as written in the run's own process."""
    from vislam.tools.output_process import output_process
    from vislam.tools.report import write_run_outputs

    result, gt = _small_run()
    here, there = tmp_path / "here", tmp_path / "there"
    here.mkdir()
    there.mkdir()
    write_run_outputs(result, here, "scene.npz", gt)
    with output_process() as helper:
        assert helper is not None
        write_run_outputs(result, there, "scene.npz", gt, helper=helper)
    assert listing(here) == listing(there) and "map.ply" in listing(here) and "ate_over_time.png" in listing(here)
    for name in ("map.ply", "trajectory.ply", "trajectory.png", "ate_over_time.png", "trajectory.txt"):
        assert (here / name).read_bytes() == (there / name).read_bytes(), name


def test_with_a_helper_the_run_imports_neither_matplotlib_nor_open3d(tmp_path):
    """The point of the helper: the run's own process never pays for matplotlib's and open3d's
    imports (checked in a fresh interpreter: this one has them from other tests)."""
    import subprocess
    import sys
    from pathlib import Path

    script = f"""
import sys
from pathlib import Path
sys.path.insert(0, {str(Path(__file__).parent)!r})
from test_outputs import _small_run
from vislam.tools.output_process import output_process
from vislam.tools.report import write_run_outputs
result, gt = _small_run()
with output_process() as helper:
    write_run_outputs(result, Path({str(tmp_path)!r}), "scene.npz", gt, helper=helper)
print(sorted(m for m in ("matplotlib", "open3d") if m in sys.modules))
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "[]"
    assert {"map.ply", "trajectory.ply", "trajectory.png", "ate_over_time.png"} <= set(listing(tmp_path))


def test_a_helper_that_is_gone_leaves_its_outputs_to_the_run(tmp_path):
    """A helper that died (or failed) writes nothing: the run writes those files itself; and the helper
    is ended with its block, by a stop too (no process left)."""
    import multiprocessing

    from vislam.tools.output_process import output_process
    from vislam.tools.report import write_run_outputs

    result, gt = _small_run()
    with output_process() as helper:
        helper._process.kill()
        helper._process.join()
        write_run_outputs(result, tmp_path, "scene.npz", gt, helper=helper)
    assert {"map.ply", "trajectory.ply", "trajectory.png", "ate_over_time.png"} <= set(listing(tmp_path))
    with pytest.raises(KeyboardInterrupt):
        with output_process() as helper:
            helper.submit(write_map_ply, tmp_path / "other.ply", *make_map()[1:3])
            raise KeyboardInterrupt
    assert multiprocessing.active_children() == []
