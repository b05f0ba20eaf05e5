"""NEES of one run against ground truth (E4): the formulas on planted truth, the association and the
relative frames, the run's pose_covariance.npz and summary.json, and `vislam eval --covariance`."""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import warnings

import numpy as np
import pytest
from matplotlib.colors import to_rgba
from scipy.spatial.transform import Rotation

from vislam.backend.data.covariance import read_pose_covariance, write_pose_covariance
from vislam.backend.data.npz import load_sequence
from vislam.backend.data.tum import read_tum, write_tum
from vislam.backend.evaluation.consistency import (
    NeesSummary,
    TrajectoryNees,
    chi2_quantile,
    position_nees,
    pose_nees,
    trajectory_nees,
)
from vislam.backend.evaluation.metrics import associate, associate_indices
from vislam.backend.geometry import se3
from vislam.backend.run.runner import run_sequence
from vislam.synth.scene import SceneConfig, make_scene, write_scene
from vislam.tools import plots
from vislam.tools.cli import main
from vislam.tools.report import nees_text

# ---------------------------------------------------------------------------------------- planted truth


def rigid(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = rng.uniform(-100.0, 100.0, 3)
    return T


def planted(n: int = 3000, seed: int = 0):
    """A drive of ``n`` steps (0.1 s) starting at the identity, random covariances P_k (translation sigma
    0.05-1 m, rotation 0.002-0.03 rad, correlated) and true poses mu_k exp(xi_k^), xi_k ~ N(0, P_k); the
    first pose is the world frame (covariance 1e-12 I, no error). Returns (t, mu, P, truth)."""
    rng = np.random.default_rng(seed)
    t = 1.3e9 + 0.1 * np.arange(n)
    twists = rng.normal(0.0, [1.0, 0.2, 0.05, 0.01, 0.01, 0.05], (n, 6))
    mu = np.empty((n, 4, 4))
    mu[0] = np.eye(4)
    for k in range(1, n):
        mu[k] = mu[k - 1] @ se3.exp_se3(twists[k])
    scale = np.concatenate([rng.uniform(0.05, 1.0, (n, 3)), rng.uniform(0.002, 0.03, (n, 3))], axis=1)
    A = rng.standard_normal((n, 6, 6))
    corr = A @ np.swapaxes(A, 1, 2) / 6 + 0.2 * np.eye(6)
    d = 1.0 / np.sqrt(np.diagonal(corr, axis1=1, axis2=2))
    P = corr * (d * scale)[:, :, None] * (d * scale)[:, None, :]
    P[0] = 1e-12 * np.eye(6)
    xi = np.einsum("nij,nj->ni", np.linalg.cholesky(P), rng.standard_normal((n, 6)))
    xi[0] = 0.0
    truth = mu @ se3.exp_se3_batch(xi)
    return t, mu, P, truth


# The mean of n chi2(k) values has the standard deviation sqrt(2k / n): 0.045 (k = 3) and 0.063 (k = 6)
# for n = 2999; the share inside the 95 % ellipsoid sqrt(0.95 * 0.05 / n) = 0.004. The tolerances are
# 5 of those (the position NEES adds a bias of order |phi|^2 |rho|, below 0.01 at these sigmas).
N_PLANTED = 3000
MEAN_TOL = {3: 5 * np.sqrt(6 / (N_PLANTED - 1)), 6: 5 * np.sqrt(12 / (N_PLANTED - 1))}
SHARE_TOL = 5 * np.sqrt(0.95 * 0.05 / (N_PLANTED - 1))


def test_chi2_quantiles():
    assert chi2_quantile(3) == pytest.approx(7.8147, abs=1e-4)
    assert chi2_quantile(6) == pytest.approx(12.5916, abs=1e-4)


def test_planted_truth_gives_chi2_nees():
    t, mu, P, truth = planted(N_PLANTED)
    gt_t = t + np.random.default_rng(1).uniform(-5e-7, 5e-7, t.size)  # a TUM file's rounding
    nees = trajectory_nees(t, mu, P, gt_t, truth)
    assert isinstance(nees, TrajectoryNees) and isinstance(nees.position, NeesSummary)
    assert nees.skipped == 1 and nees.position.steps == nees.pose.steps == N_PLANTED - 1
    assert np.array_equal(nees.time_stamps, t) and np.array_equal(nees.estimate_index, np.arange(N_PLANTED))
    assert np.isnan(nees.position_nees[0]) and np.isnan(nees.pose_nees[0])
    for summary, dof in ((nees.position, 3), (nees.pose, 6)):
        assert summary.dof == dof and summary.expected == dof and summary.infinite == 0
        assert abs(summary.mean - dof) <= MEAN_TOL[dof], summary
        assert abs(summary.share_inside_95 - 0.95) <= SHARE_TOL, summary
        assert summary.quantile_95 == pytest.approx(chi2_quantile(dof))
        assert summary.median == pytest.approx(np.median(nees.position_nees[1:] if dof == 3 else nees.pose_nees[1:]))
    # the per-step values are the one-pose functions of the (here already relative) poses
    for k in (1, 17, N_PLANTED - 1):
        assert nees.position_nees[k] == pytest.approx(position_nees(mu[k], P[k], truth[k]), rel=1e-9)
        assert nees.pose_nees[k] == pytest.approx(pose_nees(mu[k], P[k], truth[k]), rel=1e-9)
    d = nees.as_dict()
    assert d["matched_steps"] == N_PLANTED and d["skipped_steps"] == 1
    assert set(d["position"]) == {"dof", "expected", "mean", "median", "share_inside_95", "quantile_95", "steps",
                                  "skipped_steps", "infinite_steps"}
    assert d["pose"]["mean"] == nees.pose.mean


def test_a_covariance_four_times_too_small_quadruples_the_nees():
    t, mu, P, truth = planted(N_PLANTED)
    right = trajectory_nees(t, mu, P, t, truth)
    small = trajectory_nees(t, mu, P / 4, t, truth)
    np.testing.assert_allclose(small.position_nees[1:], 4 * right.position_nees[1:], rtol=1e-9)
    np.testing.assert_allclose(small.pose_nees[1:], 4 * right.pose_nees[1:], rtol=1e-9)
    assert abs(small.position.mean - 12.0) <= 4 * MEAN_TOL[3]
    assert abs(small.pose.mean - 24.0) <= 4 * MEAN_TOL[6]
    for summary in (small.position, small.pose):  # what the consistency check above refuses
        assert abs(summary.mean - summary.dof) > MEAN_TOL[summary.dof]
        assert summary.share_inside_95 < 0.7


def test_position_nees_is_the_body_frame_error_in_the_translation_block():
    mu = rigid(3)
    P = np.diag([0.04, 0.09, 0.01, 1.0, 1.0, 1.0])
    e_body = np.array([0.2, -0.3, 0.1])
    truth = mu.copy()
    truth[:3, 3] += mu[:3, :3] @ e_body  # the same rotation: the error is e in the body frame
    assert position_nees(mu, P, truth) == pytest.approx(0.2**2 / 0.04 + 0.3**2 / 0.09 + 0.1**2 / 0.01)
    assert pose_nees(mu, P, truth) == pytest.approx(position_nees(mu, P, truth))
    P[0, 0] = 0.0
    assert position_nees(mu, P, truth) == np.inf  # singular translation block


def test_nees_is_relative_to_the_first_pose():
    """A rigid transform of the whole ground truth (another world frame) or of the whole estimate
    changes nothing: both are taken relative to their first matched pose."""
    t, mu, P, truth = planted(400, seed=5)
    base = trajectory_nees(t, mu, P, t, truth)
    for moved_mu, moved_truth in ((mu, rigid(1) @ truth), (rigid(2) @ mu, truth), (rigid(3) @ mu, rigid(4) @ truth)):
        again = trajectory_nees(t, moved_mu, P, t, moved_truth)
        np.testing.assert_allclose(again.position_nees[1:], base.position_nees[1:], rtol=1e-6)
        np.testing.assert_allclose(again.pose_nees[1:], base.pose_nees[1:], rtol=1e-6)
        assert again.position.mean == pytest.approx(base.position.mean, rel=1e-7)
        assert again.pose.mean == pytest.approx(base.pose.mean, rel=1e-7)


def test_association_by_nearest_stamp_within_max_diff():
    """Ground truth from step 40 on, denser than the estimate, with stamps 5e-7 s before the estimate's:
    each step is matched to its nearest stamp (not the next one, which searchsorted alone would give),
    steps without ground truth are left out, and the first matched step is the reference."""
    t, mu, P, truth = planted(300, seed=7)
    truth[40] = mu[40]  # no error at the reference step: the relative NEES is the absolute one
    gt_t = np.sort(np.concatenate([t[40:] - 5e-7, t[40:] + 0.05]))
    gt = np.empty((gt_t.size, 4, 4))
    gt[0::2], gt[1::2] = truth[40:], rigid(9)  # the in-between poses are far off: a wrong match shows
    est_index, gt_index = associate_indices(t, gt_t)
    assert np.array_equal(est_index, np.arange(40, 300)) and np.array_equal(gt_index, np.arange(0, gt_t.size, 2))
    assert np.array_equal(associate(t, mu, gt_t, gt)[2], t[est_index])  # the same pairs as the ATE's
    nees = trajectory_nees(t, mu, P, gt_t, gt)
    assert np.array_equal(nees.estimate_index, np.arange(40, 300)) and np.array_equal(nees.time_stamps, t[40:])
    assert nees.skipped == 1  # the reference step (its error is zero by construction), covariance or not
    # relative to step 40 on both sides: mu_40^-1 mu_k and mu_40^-1 mu_k exp(xi_k^)
    assert nees.pose.steps == 259
    for k in (41, 100, 299):
        assert nees.pose_nees[k - 40] == pytest.approx(pose_nees(mu[k], P[k], truth[k]), rel=1e-6)
        assert nees.position_nees[k - 40] == pytest.approx(position_nees(mu[k], P[k], truth[k]), rel=1e-6)
    with pytest.raises(Exception, match="at least 3"):
        trajectory_nees(t, mu, P, t + 0.02, truth)  # beyond max_diff: nothing matches


def test_zero_covariances_at_the_start_are_skipped_singular_ones_count_as_inf():
    t, mu, P, truth = planted(200, seed=2)
    P = P.copy()
    P[:3] = 1e-12 * np.eye(6)
    truth = truth.copy()
    truth[:3] = mu[:3]
    P[50] = 0.0  # singular later on: inf, counted
    nees = trajectory_nees(t, mu, P, t, truth)
    assert nees.skipped == 3 and nees.position.skipped == nees.pose.skipped == 3
    assert nees.position.steps == nees.pose.steps == 197
    assert nees.position_nees[50] == np.inf and nees.pose_nees[50] == np.inf
    assert nees.position.infinite == nees.pose.infinite == 1
    assert nees.position.mean == np.inf and np.isfinite(nees.position.median)
    line = nees_text(nees.position.as_dict(), "position")
    assert "mean inf" in line and "1 steps with a singular covariance" in line and "3 skipped" in line
    # a run whose poses were held fixed (dead reckoning, mapping): every covariance zero, nothing counted
    held = trajectory_nees(t, mu, np.zeros_like(P), t, truth)
    assert held.position.steps == held.pose.steps == 0 and held.skipped == 200
    assert np.isnan(held.position.mean) and np.all(np.isnan(held.pose_nees))
    assert "no step to count" in nees_text(held.position.as_dict(), "position")


def test_nees_plot_of_skipped_and_infinite_steps(tmp_path):
    t, mu, P, truth = planted(100, seed=4)
    P = P.copy()
    P[30] = 0.0
    fig = plots.plot_nees_over_time(tmp_path / "nees.png", trajectory_nees(t, mu, P, t, truth), title="x")
    assert (tmp_path / "nees.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "1 with a singular covariance" in fig.axes[0].get_title()
    held = trajectory_nees(t, mu, np.zeros_like(P), t, truth)
    fig = plots.plot_nees_over_time(tmp_path / "held.png", held)
    assert "no step" in fig.axes[0].get_title()


# ---------------------------------------------------------------------------------------- runs and `vislam eval`


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """`vislam run` with --gt on a synthetic street of 80 steps: (scene dir, run dir, printed text)."""
    root = tmp_path_factory.mktemp("nees")
    scene_dir = write_scene(make_scene(SceneConfig(steps=80, seed=3)), root / "scene")
    out = root / "run"
    text = io.StringIO()
    with contextlib.redirect_stdout(text), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        assert main(["run", str(scene_dir / "data.npz"), "--out", str(out), "--gt", str(scene_dir / "gt_tum.txt"),
                     "--no-progress"]) == 0
    return scene_dir, out, text.getvalue()


def test_run_writes_the_covariance_the_observer_sees(run_dir):
    scene_dir, out, printed = run_dir
    time_stamps, covariance = read_pose_covariance(out / "pose_covariance.npz")
    with np.load(out / "pose_covariance.npz") as f:
        assert sorted(f.files) == ["covariance", "time_stamps"]
        assert f["time_stamps"].dtype == f["covariance"].dtype == np.float64
    seq = load_sequence(scene_dir / "data.npz")
    assert np.array_equal(time_stamps, seq.time_stamps)
    traj_t, traj = read_tum(out / "trajectory.txt")
    np.testing.assert_allclose(time_stamps, traj_t, rtol=0, atol=1e-6)  # TUM text: 6 decimals
    assert covariance.shape == (seq.num_steps, 6, 6)
    scale = np.abs(covariance).max(axis=(1, 2))[:, None, None]
    assert np.all(np.abs(covariance - np.swapaxes(covariance, 1, 2)) <= 1e-12 * scale)
    assert np.all(np.linalg.eigvalsh(covariance)[:, 0] >= -1e-12 * scale[:, 0, 0])
    # the API with an observer: the pose covariance of every step, equal to the file's
    seen = np.zeros((seq.num_steps, 6, 6))

    def observe(k, ekf, step_stats) -> None:
        seen[k] = ekf.pose_covariance

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        result = run_sequence(seq, observer=observe)
    np.testing.assert_array_equal(result.pose_covariance, seen)
    np.testing.assert_allclose(covariance, seen, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(traj[:, :3, 3], result.world_T_imu[:, :3, 3], atol=1e-8)
    # summary.json: the NEES summary under errors, and the printed position line
    summary = json.loads((out / "summary.json").read_text())
    nees = summary["errors"]["nees"]
    gt_t, gt = read_tum(scene_dir / "gt_tum.txt")
    expected = trajectory_nees(result.time_stamps, result.world_T_imu, seen, gt_t, gt).as_dict()
    assert nees["matched_steps"] == seq.num_steps and nees["skipped_steps"] == 1
    for what in ("position", "pose"):
        for key in ("mean", "median", "share_inside_95", "steps"):
            assert nees[what][key] == pytest.approx(expected[what][key], rel=1e-6), (what, key)
    assert nees_text(nees["position"], "position") in printed
    assert "position NEES (3 dof): mean" in printed and "pose NEES" not in printed


def _eval(args, capsys) -> tuple[int, str, str]:
    code = main(["eval", *map(str, args)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_eval_finds_the_covariance_beside_the_estimate(run_dir, tmp_path, capsys, monkeypatch):
    scene_dir, out, _ = run_dir
    gt = scene_dir / "gt_tum.txt"
    drawn: dict = {}
    save = plots._save

    def keep(fig, path):
        drawn[path.name] = fig
        save(fig, path)

    monkeypatch.setattr(plots, "_save", keep)
    code, printed, _ = _eval([out / "trajectory.txt", gt, "--json", tmp_path / "e.json", "--out", tmp_path / "ev"],
                             capsys)
    assert code == 0
    lines = printed.splitlines()
    position = [ln for ln in lines if ln.startswith("position NEES (3 dof): mean ")]
    pose = [ln for ln in lines if ln.startswith("pose NEES (6 dof): mean ")]
    assert len(position) == len(pose) == 1
    assert "inside the 95 % ellipsoid (<= 7.81); expected 3" in position[0]
    assert "inside the 95 % ellipsoid (<= 12.59); expected 6" in pose[0]
    d = json.loads((tmp_path / "e.json").read_text())
    assert d["nees"]["covariance_file"] == str(out / "pose_covariance.npz")
    summary = json.loads((out / "summary.json").read_text())["errors"]["nees"]
    for what in ("position", "pose"):  # from the files: the same numbers as the run's (TUM rounding aside)
        assert d["nees"][what]["mean"] == pytest.approx(summary[what]["mean"], rel=1e-3)
        assert d["nees"][what]["steps"] == summary[what]["steps"]
        assert d["nees"][what]["dof"] == {"position": 3, "pose": 6}[what]
    assert d["ate_rmse"] > 0  # the rest as before
    assert {p.name for p in (tmp_path / "ev").iterdir()} == {"eval.json", "trajectories.png", "ate_over_time.png",
                                                            "nees_over_time.png", "xyz_over_time.png",
                                                            "rpy_over_time.png", "ape_trajectory.zip",
                                                            "rpe_trajectory.zip"}
    assert json.loads((tmp_path / "ev" / "eval.json").read_text()) == d
    # the plot, read back: both curves, log y, the 95 % quantiles and the expected values, labelled
    ax = drawn["nees_over_time.png"].axes[0]
    assert ax.get_yscale() == "log"
    assert "[s]" in ax.get_xlabel() and "NEES" in ax.get_ylabel()
    by_label = {ln.get_label(): ln for ln in ax.get_lines()}
    assert {"position NEES (3 dof)", "pose NEES (6 dof)"} <= set(by_label)
    for dof, quantile in ((3, 7.8147), (6, 12.5916)):
        (q,) = [ln for label, ln in by_label.items() if label.startswith(f"95 % quantile, {dof} dof")]
        assert np.allclose(q.get_ydata(), quantile, atol=1e-3) and q.get_linestyle() == "--"
        (e,) = [ln for label, ln in by_label.items() if label.startswith(f"expected value, {dof} dof")]
        assert np.allclose(e.get_ydata(), dof)
    assert to_rgba(by_label["pose NEES (6 dof)"].get_color()) == to_rgba(plots.COLORS["estimate"])
    legend = {t.get_text() for t in ax.get_legend().get_texts()}
    assert set(by_label) - {lb for lb in by_label if lb.startswith("_")} <= legend
    curve = by_label["position NEES (3 dof)"].get_ydata()
    assert np.isnan(curve[0]) and np.nanmean(curve) == pytest.approx(d["nees"]["position"]["mean"], rel=1e-9)


def test_eval_covariance_option_none_and_explicit(run_dir, tmp_path, capsys):
    scene_dir, out, _ = run_dir
    gt = scene_dir / "gt_tum.txt"
    code, printed, _ = _eval([out / "trajectory.txt", gt, "--covariance", "none", "--json", tmp_path / "n.json"], capsys)
    assert code == 0 and "NEES" not in printed
    assert "nees" not in json.loads((tmp_path / "n.json").read_text())
    # an estimate elsewhere: no covariance beside it, none used; given explicitly, the same numbers as beside
    alone = tmp_path / "alone"
    alone.mkdir()
    shutil.copy(out / "trajectory.txt", alone / "trajectory.txt")
    code, printed, _ = _eval([alone / "trajectory.txt", gt, "--json", tmp_path / "a.json"], capsys)
    assert code == 0 and "NEES" not in printed and "nees" not in json.loads((tmp_path / "a.json").read_text())
    code, printed, _ = _eval([alone / "trajectory.txt", gt, "--covariance", out / "pose_covariance.npz",
                              "--json", tmp_path / "x.json"], capsys)
    assert code == 0 and "pose NEES (6 dof)" in printed
    _, _, _ = _eval([out / "trajectory.txt", gt, "--json", tmp_path / "b.json"], capsys)
    explicit, beside = (json.loads((tmp_path / f"{n}.json").read_text())["nees"] for n in ("x", "b"))
    assert explicit["position"] == beside["position"] and explicit["pose"] == beside["pose"]


def test_eval_refuses_a_covariance_of_other_stamps(run_dir, tmp_path, capsys):
    scene_dir, out, _ = run_dir
    gt = scene_dir / "gt_tum.txt"
    t, cov = read_pose_covariance(out / "pose_covariance.npz")
    shifted, short = tmp_path / "shifted.npz", tmp_path / "short.npz"
    write_pose_covariance(shifted, t + np.where(np.arange(t.size) == 7, 0.01, 0.0), cov)
    write_pose_covariance(short, t[:-1], cov[:-1])
    for path, needle in ((shifted, "[7] ="), (short, f"{t.size - 1} stamps"),
                         (tmp_path / "missing.npz", "does not exist")):
        code, printed, err = _eval([out / "trajectory.txt", gt, "--covariance", path, "--out", tmp_path / "o"],
                                   capsys)
        assert code == 2 and not printed, printed
        assert len(err.strip().splitlines()) == 1 and str(path) in err and needle in err, err
        if needle != "does not exist":
            assert "key 'time_stamps'" in err and "trajectory.txt" in err
        assert not (tmp_path / "o").exists()  # refused before any work
