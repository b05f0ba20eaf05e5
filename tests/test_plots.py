"""The figures of run, eval and mc (vislam.tools.plots): cropping, axes limits, alignment text, colours;
eval's Sim(3) scale; mc's landmark NEES band check."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vislam.backend.data.tum import read_tum, write_tum
from vislam.backend.evaluation.consistency import RunTrace, average_band, summarize
from vislam.backend.evaluation.metrics import alignment, alignment_scale, trajectory_errors
from vislam.tools import plots
from vislam.tools.cli import main
from vislam.tools.plots import COLORS, MARGIN, plot_trajectories_topdown, trajectory_figure


def drive(t: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses of a winding drive at 10 m/s (x forward, y and z wavy: never on one line)."""
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    poses[:, 0, 3] = 10.0 * t
    poses[:, 1, 3] = 20.0 * np.sin(t / 4.0)
    poses[:, 2, 3] = 0.5 * np.cos(t / 3.0)
    poses[:, :3, :3] = Rotation.from_euler("z", (np.cos(t / 4.0) / 2.0)[:, None]).as_matrix()
    return poses


def moved(poses: np.ndarray, scale: float = 1.0, yaw: float = 0.7, shift=(30.0, -12.0, 1.0)) -> np.ndarray:
    """``poses`` in another frame: p -> scale * R p + shift (what an alignment undoes)."""
    R = Rotation.from_euler("z", yaw).as_matrix()
    out = poses.copy()
    out[:, :3, 3] = scale * poses[:, :3, 3] @ R.T + np.asarray(shift)
    out[:, :3, :3] = R @ poses[:, :3, :3]
    return out


def line(fig, label: str):
    (found,) = [ln for ln in fig.axes[0].get_lines() if ln.get_label() == label]
    return found


def test_ground_truth_is_cut_to_the_estimates_time_span():
    """1 km of ground truth (0..100 s) around a 5 s estimate: only 19.95..25.05 s is drawn."""
    gt_t = np.round(np.arange(0.0, 100.0, 0.1), 6)
    gt = drive(gt_t)
    t = np.round(np.arange(20.0, 25.001, 0.1), 6)
    est = moved(drive(t))
    plot = trajectory_figure({"estimate": (t, est)}, (gt_t, gt))
    assert plot.ground_truth_span == (20.0, 25.0)
    x = line(plot.figure, "ground truth").get_xdata()
    assert len(x) == 51 and x.min() == pytest.approx(200.0) and x.max() == pytest.approx(250.0)
    assert plot.xlim[1] - plot.xlim[0] < 60.0  # not the 1000 m of ground truth
    # the tolerance: ground-truth stamps 0.03 s before the first estimate are drawn, 0.07 s after the last are not
    shifted = gt_t - 0.03
    plot = trajectory_figure({"estimate": (t, est)}, (shifted, gt), max_diff=0.05)
    assert plot.ground_truth_span == pytest.approx((19.97, 24.97))
    assert plots.GT_CROP_TOLERANCE == 0.05


def test_axes_limits_come_from_the_trajectories_not_from_far_landmarks(tmp_path):
    t = np.arange(101) * 0.1
    est = np.zeros((101, 3))
    est[:, 0] = np.linspace(0.0, 100.0, 101)  # 100 m x 60 m: inside the aspect bounds, no widening
    est[:, 1] = np.linspace(0.0, 60.0, 101) ** 2 / 60.0
    dr = est * [1.2, 1.0, 1.0]  # dead reckoning reaches x = 120: every curve counts
    rng = np.random.default_rng(0)
    near = np.column_stack([rng.uniform(10, 90, 100), rng.uniform(10, 50, 100), np.zeros(100)])
    far = np.array([[1000.0, 0.0, 0.0], [0.0, -800.0, 5.0], [300.0, 300.0, 0.0]])
    path = tmp_path / "t.png"
    plot = plot_trajectories_topdown(path, {"estimate": (t, est), "dead reckoning": (t, dr)},
                                     landmarks=np.vstack([near, far, [[np.nan, 0.0, 0.0]]]))
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    ax = plot.figure.axes[0]
    m = MARGIN * 120.0
    np.testing.assert_allclose(ax.get_xlim(), (-m, 120.0 + m), atol=1e-9)  # read back after drawing
    np.testing.assert_allclose(ax.get_ylim(), (-m, 60.0 + m), atol=1e-9)
    assert (plot.landmarks_total, plot.landmarks_outside, plot.landmarks_drawn) == (103, 3, 100)
    (scatter,) = ax.collections
    assert len(scatter.get_offsets()) == 100
    title = ax.get_title()
    assert "3 of 103 landmarks beyond the axes not shown" in title
    assert "not aligned (no ground truth)" in title
    assert ax.get_aspect() == 1.0


def test_a_long_thin_drive_fills_the_frame():
    """1 km east with 20 m of sway: the short side is widened to half the long one, about the path."""
    t = np.arange(1001) * 0.1
    est = np.column_stack([np.linspace(0.0, 1000.0, 1001), 10.0 * np.sin(t), np.zeros(1001)])
    plot = trajectory_figure({"estimate": (t, est)}, landmarks=[[500.0, 2000.0, 0.0]])
    width, height = np.diff(plot.xlim)[0], np.diff(plot.ylim)[0]
    assert width == pytest.approx(1000.0 * (1 + 2 * MARGIN))
    assert height == pytest.approx(plots.ASPECT_BOUNDS[0] * width)
    assert np.mean(plot.ylim) == pytest.approx(0.0, abs=0.1)
    assert plot.landmarks_outside == 1


@pytest.mark.parametrize("sim3", [False, True])
def test_title_names_the_alignment_and_its_ate(sim3):
    gt_t = np.round(np.arange(0.0, 60.0, 0.1), 6)
    gt = drive(gt_t)
    scale = 1.0 / 1.05 if sim3 else 1.0
    est = moved(gt, scale=scale)
    est[:, :3, 3] += np.random.default_rng(1).normal(0.0, 0.3, (len(gt_t), 3))
    landmark = np.array([[150.0, 10.0, 2.0]])  # in the ground truth's frame; in the estimate's:
    lm_est = scale * landmark @ Rotation.from_euler("z", 0.7).as_matrix().T + [30.0, -12.0, 1.0]
    plot = trajectory_figure({"estimate": (gt_t, est)}, (gt_t, gt), lm_est, sim3=sim3, title="run")
    errors = trajectory_errors(gt_t, est, gt_t, gt, sim3=sim3)
    a = plot.alignments["estimate"]
    assert a.ate_rmse == pytest.approx(errors.ate_rmse, abs=1e-9)
    title = plot.figure.axes[0].get_title().splitlines()
    assert title[0] == "run"
    if sim3:
        assert a.scale == pytest.approx(alignment_scale(gt_t, est, gt_t, gt), abs=1e-9)
        assert abs(a.scale - 1.05) < 0.01
        assert title[1] == f"aligned (Sim(3), scale {a.scale:.5f}); ATE RMSE {errors.ate_rmse:.3g} m"
    else:
        assert a.scale == 1.0
        assert title[1] == f"aligned (SE(3)); ATE RMSE {errors.ate_rmse:.3g} m"
    # the aligned estimate lies on the ground truth, and the landmark moved with it
    np.testing.assert_allclose(line(plot.figure, "estimate").get_xdata(), gt[:, 0, 3], atol=2.0)
    np.testing.assert_allclose(plot.figure.axes[0].collections[0].get_offsets()[0], landmark[0, :2], atol=1.0)


def test_alignment_refuses_a_straight_line():
    t = np.arange(10) * 0.1
    poses = np.tile(np.eye(4), (10, 1, 1))
    poses[:, 0, 3] = t
    with pytest.raises(Exception, match="straight line"):
        alignment(t, poses, t, poses)


def _captured(monkeypatch) -> dict:
    """Every trajectory and error figure drawn, by file name (in this process: the output helper of
    ``tools.output_process`` left out, so the figures can be read back)."""
    from contextlib import nullcontext

    from vislam.tools import output_process

    monkeypatch.setattr(output_process, "output_process", lambda: nullcontext(None))
    drawn: dict = {}
    save = plots._save

    def keep(fig, path):
        drawn[str(path).rsplit("/", 1)[-1]] = fig
        save(fig, path)

    monkeypatch.setattr(plots, "_save", keep)
    return drawn


def test_run_and_eval_draw_each_curve_kind_in_one_colour(tmp_path, monkeypatch, capsys):
    from matplotlib.colors import to_rgba

    assert len({to_rgba(c) for c in COLORS.values()}) == len(COLORS)  # markers and landmarks have their own
    drawn = _captured(monkeypatch)
    assert main(["demo", "--out", str(tmp_path / "demo")]) == 0
    summary = json.loads((tmp_path / "demo" / "summary.json").read_text())
    run_plot, run_errors = drawn.pop("trajectory.png"), drawn.pop("ate_over_time.png")
    gt = tmp_path / "demo" / "scene" / "gt_tum.txt"
    assert main(["eval", str(tmp_path / "demo" / "trajectory.txt"), str(gt), "--out", str(tmp_path / "ev")]) == 0
    eval_plot, eval_errors = drawn.pop("trajectories.png"), drawn.pop("ate_over_time.png")
    capsys.readouterr()
    for label in ("estimate", "ground truth", "start", "end"):
        colour = COLORS["start/end" if label in ("start", "end") else label]
        assert to_rgba(line(run_plot, label).get_color()) == to_rgba(line(eval_plot, label).get_color()) \
            == to_rgba(colour), label
    assert to_rgba(line(run_plot, "dead reckoning").get_color()) == to_rgba(COLORS["dead reckoning"])
    assert tuple(run_plot.axes[0].collections[0].get_facecolor()[0]) == to_rgba(COLORS["landmarks"])
    for fig in (run_errors, eval_errors):
        (est,) = [ln for ln in fig.axes[0].get_lines() if ln.get_label().startswith("estimate")]
        assert to_rgba(est.get_color()) == to_rgba(COLORS["estimate"])
        assert re.search(r"\(RMSE [0-9.e+-]+ m\)$", est.get_label()), est.get_label()  # with its unit
    # each curve's start (o) and end (x) are drawn in the curve's colour, at its first and last point
    for name in ("estimate", "dead reckoning"):
        curve = line(run_plot, name)
        xs, ys = curve.get_xdata(), curve.get_ydata()
        for marker, index in (("o", 0), ("x", -1)):
            marks = [ln for ln in run_plot.axes[0].get_lines() if ln.get_marker() == marker and len(ln.get_xdata())
                     and ln.get_xdata()[0] == xs[index] and ln.get_ydata()[0] == ys[index]]
            assert marks and to_rgba(marks[0].get_color()) == to_rgba(curve.get_color()), (name, marker)
    # the run's plot says it is aligned and gives the summary's ATE
    title = run_plot.axes[0].get_title()
    assert "each curve aligned (SE(3)) to the ground truth" in title
    ate = float(re.search(r"ATE RMSE estimate ([0-9.e+-]+) m", title).group(1))
    assert ate == pytest.approx(summary["errors"]["estimate"]["ate_rmse"], rel=1e-2)
    assert "aligned (SE(3)); ATE RMSE" in eval_plot.axes[0].get_title()


def test_eval_sim3_prints_and_writes_the_scale(tmp_path, capsys):
    gt_t = np.round(np.arange(0.0, 40.0, 0.1), 6)
    gt = drive(gt_t)
    est = moved(gt, scale=0.93)
    est[:, :3, 3] += np.random.default_rng(2).normal(0.0, 0.2, (len(gt_t), 3))
    write_tum(tmp_path / "gt.txt", gt_t, gt)
    write_tum(tmp_path / "est.txt", gt_t, est)
    assert main(["eval", str(tmp_path / "est.txt"), str(tmp_path / "gt.txt"), "--sim3",
                 "--json", str(tmp_path / "e.json")]) == 0
    out = capsys.readouterr().out
    printed = float(re.search(r"Sim\(3\) scale ([0-9.eE+-]+)", out).group(1))
    expected = alignment_scale(*read_tum(tmp_path / "est.txt"), *read_tum(tmp_path / "gt.txt"))
    assert abs(printed - expected) <= 1e-9
    assert abs(expected - 1 / 0.93) < 0.01
    assert json.loads((tmp_path / "e.json").read_text())["alignment_scale"] == pytest.approx(expected, abs=1e-12)
    assert main(["eval", str(tmp_path / "est.txt"), str(tmp_path / "gt.txt"), "--json", str(tmp_path / "s.json")]) == 0
    assert "scale" not in capsys.readouterr().out
    assert json.loads((tmp_path / "s.json").read_text())["alignment_scale"] == 1.0


# ---------------------------------------------------------------------------------------- mc


def _traces(runs: int, landmark_factor: float, landmarks: int = 200) -> list[RunTrace]:
    rng = np.random.default_rng(3)
    return [RunTrace(noise_seed=i, pose_nees=rng.chisquare(6, 30), nis_sum=rng.chisquare(4 * 5, 30),
                     nis_count=np.full(30, 5), landmark_nees=landmark_factor * rng.chisquare(3, landmarks),
                     ate_estimate=0.1, ate_dead_reckoning=1.0) for i in range(runs)]


@pytest.mark.parametrize("factor, in_band", [(1.0, True), (2.0, False), (0.4, False)])
def test_mc_flags_a_landmark_nees_outside_its_band(factor, in_band):
    from vislam.tools.commands.mc import landmark_nees_check, summary_lines

    result = summarize(_traces(10, factor))
    check = landmark_nees_check(result)
    lo, hi = average_band(3, 10)  # band of the 10-run average of chi2(3): about [1.68, 4.70]
    assert check["band_of_run_average"] == [lo, hi] and 1.6 < lo < 1.7 and 4.6 < hi < 4.8
    assert check["in_band_of_run_average"] is in_band
    warnings = [ln for ln in summary_lines(result, check) if ln.startswith("warning: landmark NEES")]
    assert len(warnings) == (0 if in_band else 1)
    if not in_band:
        assert ("too small (overconfident)" if factor > 1 else "too large (pessimistic)") in warnings[0]
    none = summarize(_traces(3, 1.0, landmarks=0))
    assert landmark_nees_check(none)["in_band_of_run_average"] is None
    assert not any("landmark NEES mean" in ln for ln in summary_lines(none, landmark_nees_check(none)))


@pytest.mark.parametrize("factor, verdict", [(1.0, "consistent with 6"), (1.6, "overconfident")])
def test_mc_plot_note_says_what_the_screen_says_of_the_pose_nees(tmp_path, factor, verdict):
    """nees.png's first note is the screen's pose verdict (the runs' time averages, E1) with the time
    average, and stands in the figure's title, wrapped to lines the figure's width holds."""
    from vislam.tools.commands.mc import pose_nees_line

    traces = _traces(10, 1.0)
    for t in traces:
        t.pose_nees *= factor
    result = summarize(traces)
    note = pose_nees_line(result)
    assert note.startswith(f"pose NEES time average {result.pose_nees_time_average:.2f}; 95 % interval of the 10 runs'")
    assert verdict in note and result.summary_lines()[0].endswith(note.split("; ", 1)[1])
    fig = plots.plot_consistency(tmp_path / "nees.png", result, notes=(note,))
    lines = fig.axes[0].get_title().split("\n")
    assert " ".join(lines[1:]) == note and max(len(line) for line in lines) <= plots.NOTE_WIDTH
    assert (len(lines) > 2) == (len(note) > plots.NOTE_WIDTH)


def test_mc_with_an_overconfident_filter_warns(tmp_path, capsys):
    """Pixel noise taken as 0.1 px instead of the scene's: the map is overconfident (NEES ~50)."""
    assert main(["mc", "--runs", "2", "--steps", "40", "--workers", "1", "--landmark-density", "0.5",
                 "--set", "noise.pixel_sigma=0.1", "--out", str(tmp_path / "mc")]) == 0
    out = capsys.readouterr().out
    assert re.search(r"^warning: landmark NEES mean [0-9.]+ is outside the 95 % band \[0\.62, 7\.22\] of the "
                     r"2-run average", out, re.M), out
    data = json.loads((tmp_path / "mc" / "consistency.json").read_text())["landmark_nees"]
    assert data["in_band_of_run_average"] is False and data["mean"] > 7.22
    np.testing.assert_allclose(data["band_of_run_average"], average_band(3, 2))
