"""Figures of vislam runs, evaluations and Monte Carlo consistency (PNG, 150 dpi), written atomically.

``vislam run``, ``vislam eval`` and ``vislam mc`` draw through this module only, so a curve kind
has one look everywhere (:data:`COLORS`): estimate blue, dead reckoning orange, ground truth black
dashed, landmarks light grey dots, start (o) and end (x) markers in their curve's colour (grey keys
in the legend);
NEES of the pose blue (as the estimate's), of the position brown (:data:`NEES_COLORS`).

Only matplotlib's object-oriented API is used (``matplotlib.figure.Figure`` rendered by the
Agg canvas); pyplot is never imported, so no display or GUI backend is needed, no global
figure state is kept and importing this module does not change the caller's backend.
"""

from __future__ import annotations

import os
import textwrap
from dataclasses import dataclass, field
from typing import Any, Mapping, Optional

import numpy as np

from ..backend.data.files import atomic_write
from ..backend.evaluation.metrics import Alignment, alignment, ate_per_pose

__all__ = [
    "COLORS",
    "TrajectoryPlot",
    "trajectory_figure",
    "plot_trajectories_topdown",
    "plot_errors_over_time",
    "write_error_plot",
    "plot_xyz_over_time",
    "within_span",
    "plot_rpy_over_time",
    "plot_consistency",
    "plot_nees_over_time",
]

DPI = 150
#: characters a title's note line holds at the consistency figure's 9 inches (medium font); longer ones wrap
NOTE_WIDTH = 110
MAX_LANDMARKS_PLOTTED = 20000
#: Ground truth is drawn from this many seconds before the first estimated stamp to as many after the last.
GT_CROP_TOLERANCE = 0.05
#: Margin around the trajectories' extent, as a share of its larger side.
MARGIN = 0.05
#: Height / width of the data area is kept within these bounds (the shorter side is widened).
ASPECT_BOUNDS = (0.5, 1.25)

#: One colour per curve kind, in every figure of every command.
COLORS = {
    "estimate": "tab:blue",
    "dead reckoning": "tab:orange",
    "ground truth": "black",
    "landmarks": "0.7",
    "start/end": "tab:gray",
}
_LINES = {
    "estimate": dict(linestyle="-", linewidth=1.5, zorder=4),
    "dead reckoning": dict(linestyle="-", linewidth=1.0, zorder=3),
    "ground truth": dict(linestyle=(0, (4, 3)), linewidth=1.0, zorder=5),  # on top: the others show through
}
#: NEES curves: pose NEES as in :func:`plot_consistency`, position NEES in a colour no other curve has
NEES_COLORS = {"pose": COLORS["estimate"], "position": "tab:brown"}
_OTHER_COLORS = ("tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan", "tab:red")


def _color(kind: str, others: dict) -> str:
    """The fixed colour of ``kind``, else the next unused one of ``_OTHER_COLORS`` (kept in ``others``)."""
    if kind in COLORS:
        return COLORS[kind]
    if kind not in others:
        others[kind] = _OTHER_COLORS[len(others) % len(_OTHER_COLORS)]
    return others[kind]


def _new_figure(figsize: tuple[float, float]):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: str | os.PathLike) -> None:
    with atomic_write(path) as tmp:
        fig.savefig(tmp, dpi=DPI, format="png")


# ---------------------------------------------------------------------------------------- poses


def within_span(stamps: Any, curves_stamps) -> np.ndarray:
    """(M,) bool: which of the ground truth's ``stamps`` (M,) lie within the span of the curves'
    stamps (each (N_i,), increasing), widened by ``GT_CROP_TOLERANCE`` on both sides: the ground
    truth every figure draws."""
    first = min(t[0] for t in curves_stamps) - GT_CROP_TOLERANCE
    last = max(t[-1] for t in curves_stamps) + GT_CROP_TOLERANCE
    stamps = np.asarray(stamps, dtype=float)
    return (stamps >= first) & (stamps <= last)


def _as_poses(traj: Any, name: str) -> np.ndarray:
    """(N, 4, 4) poses from (N, 4, 4) poses or (N, 3) / (N, 2) positions (identity rotations)."""
    arr = np.asarray(traj, dtype=float)
    if arr.ndim == 3 and arr.shape[1:] == (4, 4):
        return arr
    if arr.ndim == 2 and arr.shape[1] in (2, 3):
        poses = np.tile(np.eye(4), (arr.shape[0], 1, 1))
        poses[:, : arr.shape[1], 3] = arr
        return poses
    raise ValueError(f"trajectory {name!r} must have shape (N, 4, 4), (N, 3) or (N, 2), got {arr.shape}")


# ---------------------------------------------------------------------------------------- trajectories


@dataclass
class TrajectoryPlot:
    """A drawn top-down figure and what it shows."""

    figure: Any  # matplotlib.figure.Figure (Agg canvas)
    xlim: tuple[float, float]  # m
    ylim: tuple[float, float]  # m
    alignments: dict[str, Alignment] = field(default_factory=dict)  # curve -> alignment (with ground truth)
    ground_truth_span: Optional[tuple[float, float]] = None  # first and last stamp (s) of the ground truth drawn
    landmarks_total: int = 0  # finite landmarks given
    landmarks_outside: int = 0  # of those, beyond the axes (not shown)
    landmarks_drawn: int = 0


def _metres(value: float) -> str:
    return f"{value:.0f} m" if abs(value) >= 1000 else f"{value:.3g} m"


def _alignment_lines(alignments: Mapping[str, Alignment]) -> list[str]:
    if not alignments:
        return []
    first = next(iter(alignments.values()))
    if len(alignments) == 1:
        what = f"Sim(3), scale {first.scale:.5f}" if first.kind == "sim3" else first.name
        return [f"aligned ({what}); ATE RMSE {_metres(first.ate_rmse)}"]
    if first.kind == "sim3":
        per_curve = "; ".join(f"{name}: scale {a.scale:.5f}, ATE RMSE {_metres(a.ate_rmse)}"
                              for name, a in alignments.items())
    else:
        per_curve = "ATE RMSE " + ", ".join(f"{name} {_metres(a.ate_rmse)}" for name, a in alignments.items())
    return [f"each curve aligned ({first.name}) to the ground truth", per_curve]


def _limits(xy: np.ndarray) -> tuple[tuple[float, float], tuple[float, float]]:
    """Axes limits around the (P, 2) points: a margin, then the shorter side widened to ASPECT_BOUNDS."""
    if len(xy) == 0:
        return (-1.0, 1.0), (-1.0, 1.0)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    size = hi - lo
    margin = MARGIN * float(size.max()) if size.max() > 0 else 1.0
    lo, hi = lo - margin, hi + margin
    width, height = hi - lo
    low, high = ASPECT_BOUNDS
    if height < low * width:
        grow = 0.5 * (low * width - height)
        lo[1], hi[1] = lo[1] - grow, hi[1] + grow
    elif height > high * width:
        grow = 0.5 * (height / high - width)
        lo[0], hi[0] = lo[0] - grow, hi[0] + grow
    return (float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1]))


def trajectory_figure(
    curves: Mapping[str, tuple[Any, Any]],
    ground_truth: Optional[tuple[Any, Any]] = None,
    landmarks: Any = None,
    *,
    sim3: bool = False,
    title: str = "",
    landmarks_of: str = "estimate",
    max_diff: float = 0.01,
    origin: bool = False,
) -> TrajectoryPlot:
    """Top-down (x-y, equal aspect) figure of trajectories, the ground truth and the landmarks.

    With ground truth each curve is aligned to it (as for its ATE) and the title says how, with
    each ATE RMSE; the ground truth is cut to the curves' time span (``GT_CROP_TOLERANCE``). The
    axes limits come from the drawn curves (with a margin); landmarks beyond them are not
    shown, and the title says how many.

    Parameters
    ----------
    curves : mapping of str to (stamps (N,), poses (N, 4, 4) or positions (N, 3))
        Keyed by kind (``"estimate"``, ``"dead reckoning"``; other names get other colours).
    ground_truth : (stamps (M,), poses (M, 4, 4)), optional
    landmarks : (K, 3) array, optional
        In the frame of ``curves[landmarks_of]`` (else of the first curve); moved with its alignment.
    sim3 : bool
        Sim(3) instead of SE(3) alignment.
    title : str
        First title line.
    landmarks_of : str
    max_diff : float
        Largest stamp difference (s) of a matched pair for the alignment.
    origin : bool
        Align the first matched poses instead (evo's ``align_origin``).

    Returns
    -------
    TrajectoryPlot
    """
    parsed = {}
    for name, (stamps, poses) in curves.items():
        P = _as_poses(poses, name)
        t = np.asarray(stamps, dtype=float)
        if t.shape != (P.shape[0],):
            raise ValueError(f"trajectory {name!r}: stamps must have shape ({P.shape[0]},), got {t.shape}")
        if len(t):
            parsed[name] = (t, P)
    alignments: dict[str, Alignment] = {}
    xy = {}
    for name, (t, P) in parsed.items():
        positions = P[:, :3, 3]
        if ground_truth is not None:
            alignments[name] = alignment(t, P, *ground_truth, sim3=sim3, origin=origin, max_diff=max_diff)
            positions = alignments[name].apply(positions)
        xy[name] = positions[:, :2]
    gt_span = None
    if ground_truth is not None:
        gt_t = np.asarray(ground_truth[0], dtype=float)
        gt_xy = _as_poses(ground_truth[1], "ground truth")[:, :2, 3]
        if parsed:
            keep = within_span(gt_t, [t for t, _ in parsed.values()])
            gt_t, gt_xy = gt_t[keep], gt_xy[keep]
        if len(gt_t):
            xy["ground truth"] = gt_xy
            gt_span = (float(gt_t.min()), float(gt_t.max()))
    points = np.concatenate([p for p in xy.values()]) if xy else np.zeros((0, 2))
    xlim, ylim = _limits(points[np.all(np.isfinite(points), axis=1)])

    lm = np.zeros((0, 2))
    total = outside = 0
    if landmarks is not None:
        lm3 = np.asarray(landmarks, dtype=float)
        if lm3.ndim != 2 or lm3.shape[1] != 3:
            raise ValueError(f"landmarks must have shape (K, 3), got {lm3.shape}")
        lm3 = lm3[np.all(np.isfinite(lm3), axis=1)]
        frame = alignments.get(landmarks_of, next(iter(alignments.values()), None))
        lm = (frame.apply(lm3) if frame is not None else lm3)[:, :2]
        total = len(lm)
        inside = (lm[:, 0] >= xlim[0]) & (lm[:, 0] <= xlim[1]) & (lm[:, 1] >= ylim[0]) & (lm[:, 1] <= ylim[1])
        outside = int(total - inside.sum())
        lm = lm[inside]
        if len(lm) > MAX_LANDMARKS_PLOTTED:
            keep = np.random.default_rng(0).choice(len(lm), MAX_LANDMARKS_PLOTTED, replace=False)
            lm = lm[np.sort(keep)]

    width, height = xlim[1] - xlim[0], ylim[1] - ylim[0]
    fig = _new_figure((8.0, 7.0 * height / width + 1.6))
    ax = fig.add_subplot(1, 1, 1)
    if total:
        ax.scatter(lm[:, 0], lm[:, 1], s=1.5, c=COLORS["landmarks"], linewidths=0, label="landmarks",
                   zorder=1, rasterized=True)
    others: dict = {}
    colors = {}
    for name, points in xy.items():
        style = dict(_LINES.get(name, dict(linestyle="-", linewidth=1.2, zorder=3)))
        colors[name] = _color(name, others)
        ax.plot(points[:, 0], points[:, 1], color=colors[name], label=name, **style)
    for name, points in xy.items():  # each curve's start and end in its colour; the legend keys in grey
        ax.plot(points[0, 0], points[0, 1], marker="o", markersize=7, markeredgewidth=1.5, color=colors[name],
                markerfacecolor="none", linestyle="none", zorder=6)
        ax.plot(points[-1, 0], points[-1, 1], marker="x", markersize=7, markeredgewidth=1.5, color=colors[name],
                linestyle="none", zorder=6)
    key = COLORS["start/end"]
    ax.plot([], [], marker="o", markersize=7, markeredgewidth=1.5, color=key, markerfacecolor="none",
            linestyle="none", label="start")
    ax.plot([], [], marker="x", markersize=7, markeredgewidth=1.5, color=key, linestyle="none", label="end")
    ax.set_xlim(*xlim)
    ax.set_ylim(*ylim)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, linewidth=0.3)
    lines = [title] if title else []
    lines += _alignment_lines(alignments) if ground_truth is not None else ["not aligned (no ground truth)"]
    if outside:
        lines.append(f"{outside} of {total} landmarks beyond the axes not shown")
    if len(lm) < total - outside:
        lines.append(f"a random {len(lm)} of the {total - outside} landmarks in view drawn")
    ax.set_title("\n".join(lines), fontsize="medium")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize="small", markerscale=1.0)
    fig.tight_layout()
    return TrajectoryPlot(fig, xlim, ylim, alignments, gt_span, total, outside, len(lm))


def plot_trajectories_topdown(
    path: str | os.PathLike,
    curves: Mapping[str, tuple[Any, Any]],
    ground_truth: Optional[tuple[Any, Any]] = None,
    landmarks: Any = None,
    **kwargs: Any,
) -> TrajectoryPlot:
    """:func:`trajectory_figure` written to ``path`` (PNG); same parameters, returns its result."""
    plot = trajectory_figure(curves, ground_truth, landmarks, **kwargs)
    _save(plot.figure, path)
    return plot


# ---------------------------------------------------------------------------------------- errors, consistency


def plot_errors_over_time(
    path: str | os.PathLike,
    series: Mapping[str, tuple[Any, Any]],
    title: str,
    ylabel: str = "error [m]",
    xlabel: str = "time [s]",
):
    """Errors over time since the earliest stamp, each with its RMSE as a dashed line.

    Parameters
    ----------
    path : path of the PNG
    series : mapping of str to (time_stamps (N,), errors (N,))
        Keyed by curve kind (colours of :data:`COLORS`).
    title, ylabel, xlabel : str

    Returns
    -------
    matplotlib.figure.Figure
    """
    checked = {}
    for name, (time_stamps, errors) in series.items():
        t = np.asarray(time_stamps, dtype=float)
        e = np.asarray(errors, dtype=float)
        if t.ndim != 1 or e.shape != t.shape:
            raise ValueError(f"time_stamps and errors must have the same shape (N,), got {t.shape} and {e.shape}")
        checked[name] = (t, e)
    starts = [t[0] for t, _ in checked.values() if len(t)]
    t0 = min(starts) if starts else 0.0
    fig = _new_figure((9.0, 4.0))
    ax = fig.add_subplot(1, 1, 1)
    others: dict = {}
    for name, (t, e) in checked.items():
        if not len(t):
            continue
        color = _color(name, others)
        finite = e[np.isfinite(e)]
        rmse = float(np.sqrt(np.mean(finite**2))) if len(finite) else float("nan")
        ax.plot(t - t0, e, color=color, linewidth=1.0, label=f"{name} (RMSE {rmse:.3g} m)")
        if len(finite):
            ax.axhline(rmse, color=color, linestyle="--", linewidth=0.8)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize="small")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, linewidth=0.3)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    _save(fig, path)
    return fig


def write_error_plot(path: str | os.PathLike, estimates: dict, gt_t: np.ndarray, gt_poses: np.ndarray,
                     sim3: bool = False, max_diff: float = 0.01, origin: bool = False,
                     xlabel: str = "time [s]") -> None:
    """Position error over time of each named estimate (``{name: (stamps (N,), poses (N,4,4))}``), each
    aligned to the ground truth (poses matched within ``max_diff`` s; ``origin``: first poses on each other)."""
    series = {name: ate_per_pose(t, poses, gt_t, gt_poses, sim3=sim3, max_diff=max_diff, origin=origin,
                                 return_stamps=True)
              for name, (t, poses) in estimates.items()}
    how = "first-pose" if origin else "Sim(3)" if sim3 else "SE(3)"
    title = f"position error after {how} alignment"
    plot_errors_over_time(path, series, title + (" (each curve on its own)" if len(series) > 1 else ""),
                          xlabel=xlabel)


def _three_panels(path, curves: Mapping[str, tuple[Any, Any]], values, axis_labels: tuple[str, str, str],
                  title: str, xlabel: str = "time [s]"):
    """Three stacked panels over time since the earliest stamp, a curve each per name (evo_traj's
    ``xyz`` and ``rpy`` views); ``values(poses (N,4,4)) -> (N, 3)``."""
    checked = {}
    for name, (stamps, poses) in curves.items():
        t = np.asarray(stamps, dtype=float)
        P = _as_poses(poses, name)
        if t.shape != (P.shape[0],):
            raise ValueError(f"trajectory {name!r}: stamps must have shape ({P.shape[0]},), got {t.shape}")
        if len(t):
            checked[name] = (t, values(P))
    t0 = min((t[0] for t, _ in checked.values()), default=0.0)
    fig = _new_figure((9.0, 7.0))
    axes = fig.subplots(3, 1, sharex=True)
    others: dict = {}
    for name, (t, v) in checked.items():
        color = _color(name, others)
        style = dict(_LINES.get(name, dict(linestyle="-", linewidth=1.2, zorder=3)))
        for k, ax in enumerate(axes):
            ax.plot(t - t0, v[:, k], color=color, label=name if k == 0 else None, **style)
    for ax, label in zip(axes, axis_labels):
        ax.set_ylabel(label)
        ax.grid(True, linewidth=0.3)
    axes[-1].set_xlabel(xlabel)
    if axes[0].get_legend_handles_labels()[0]:
        axes[0].legend(loc="best", fontsize="small")
    if title:
        axes[0].set_title(title, fontsize="medium")
    fig.tight_layout()
    _save(fig, path)
    return fig


def plot_xyz_over_time(path: str | os.PathLike, curves: Mapping[str, tuple[Any, Any]], title: str = "",
                       xlabel: str = "time [s]"):
    """Position x, y, z over time of each curve (evo_traj's ``xyz`` view).

    Parameters
    ----------
    path : path of the PNG
    curves : mapping of str to (stamps (N,), poses (N, 4, 4))
        Already in one frame (aligned); keyed by kind (colours of :data:`COLORS`).
    title : str
    xlabel : str
        The time axis ("frame" for poses matched by index).

    Returns
    -------
    matplotlib.figure.Figure
    """
    return _three_panels(path, curves, lambda P: P[:, :3, 3], ("x [m]", "y [m]", "z [m]"), title, xlabel)


def plot_rpy_over_time(path: str | os.PathLike, curves: Mapping[str, tuple[Any, Any]], title: str = "",
                       xlabel: str = "time [s]"):
    """Roll, pitch, yaw over time of each curve (evo_traj's ``rpy`` view): the fixed-axis x-y-z
    angles of the rotation (``scipy`` ``as_euler("xyz")``, evo's ``sxyz``), unwrapped, in degrees.

    Parameters
    ----------
    path : path of the PNG
    curves : mapping of str to (stamps (N,), poses (N, 4, 4))
    title : str
    xlabel : str
        The time axis ("frame" for poses matched by index).

    Returns
    -------
    matplotlib.figure.Figure
    """
    from scipy.spatial.transform import Rotation

    def rpy(P: np.ndarray) -> np.ndarray:
        return np.degrees(np.unwrap(Rotation.from_matrix(P[:, :3, :3]).as_euler("xyz"), axis=0))

    return _three_panels(path, curves, rpy, ("roll [deg]", "pitch [deg]", "yaw [deg]"), title, xlabel)


def _plain_log_ticks(ax) -> None:
    """A log y axis labelled with plain numbers (2, 5, 10, 20) rather than 6x10^0."""
    from matplotlib.ticker import FuncFormatter, LogLocator

    plain = FuncFormatter(lambda v, _: f"{v:g}")
    ax.yaxis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
    ax.yaxis.set_major_formatter(plain)
    ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, _: ""))


def plot_consistency(path: str | os.PathLike, result, notes: tuple[str, ...] = ()):
    """Run-averaged pose NEES with its 95 % band (log y) and NIS per observation over the steps.

    Parameters
    ----------
    path : path of the PNG
    result : ``backend.evaluation.consistency.ConsistencyResult``
    notes : lines added under the first panel's title (e.g. the landmark NEES check), each wrapped at
        ``NOTE_WIDTH`` characters

    Returns
    -------
    matplotlib.figure.Figure
    """
    steps = np.arange(result.steps)
    notes = [line for note in notes for line in textwrap.wrap(note, NOTE_WIDTH)]  # the figure's width
    fig = _new_figure((9.0, 6.5 + 0.2 * len(notes)))
    ax = fig.add_subplot(2, 1, 1)
    lo, hi = result.pose_nees_band
    nees = np.asarray(result.pose_nees_mean, dtype=float)
    positive = nees > 0
    ax.plot(steps[positive], nees[positive], color=COLORS["estimate"], linewidth=1.0,
            label=f"pose NEES, average of {result.runs} runs")
    ax.axhspan(lo, hi, color="tab:green", alpha=0.2, label=f"95 % band [{lo:.2f}, {hi:.2f}]")
    ax.axhline(6.0, color="tab:green", linewidth=0.8, linestyle="--", label="expectation 6")
    ax.axvline(result.skip, color="0.5", linewidth=0.6, linestyle=":",
               label=f"step {result.skip}: counted from here (before, the prior dominates)")
    ax.set_yscale("log")
    _plain_log_ticks(ax)
    ax.set_ylabel("pose NEES (6 dof)")
    ax.set_title("\n".join([f"{100 * result.pose_nees_in_band:.0f} % of steps {result.skip}..{result.steps - 1} "
                            "in the band", *notes]), fontsize="medium")
    ax.grid(True, which="both", linewidth=0.3)
    ax.legend(loc="best", fontsize="small")

    ax = fig.add_subplot(2, 1, 2, sharex=ax)
    nis = np.asarray(result.nis_per_step, dtype=float)
    ax.plot(steps, nis, color="tab:purple", linewidth=0.8, label="NIS per observation (all runs)")
    expected = result.nis_expected
    ax.axhline(expected, color="tab:green", linewidth=0.8, linestyle="--", label=f"expectation {expected:.3g}")
    from ..backend.evaluation.consistency import run_mean_interval

    nlo, nhi = run_mean_interval(result.per_run_nis)
    interval = f"95 % interval of the runs' mean [{nlo:.3f}, {nhi:.3f}]" if np.isfinite(nlo) else "one run"
    ax.axhline(result.nis_mean, color="tab:red", linewidth=0.8, label=f"mean {result.nis_mean:.3f} ({interval})")
    ax.set_xlabel("step")
    ax.set_ylabel("NIS / observation (4 dof)")
    ax.grid(True, linewidth=0.3)
    ax.legend(loc="best", fontsize="small")
    fig.tight_layout()
    _save(fig, path)
    return fig


def plot_nees_over_time(path: str | os.PathLike, nees, title: str = ""):
    """Position (3 dof) and pose (6 dof) NEES of one run over time (log y), each with its 95 % quantile
    (dashed) and its expected value (dotted), in the curve's colour (:data:`NEES_COLORS`).

    Parameters
    ----------
    path : path of the PNG
    nees : ``backend.evaluation.consistency.TrajectoryNees``
        Skipped steps (nan), zeros and inf are not drawn (log scale); the title counts the inf.
    title : str
        First title line.

    Returns
    -------
    matplotlib.figure.Figure
    """
    t = np.asarray(nees.time_stamps, dtype=float)
    fig = _new_figure((9.0, 4.5))
    ax = fig.add_subplot(1, 1, 1)
    t0 = t[0] if len(t) else 0.0
    for what, values, summary in (("position", nees.position_nees, nees.position),
                                  ("pose", nees.pose_nees, nees.pose)):
        v = np.asarray(values, dtype=float)
        drawn = np.where(np.isfinite(v) & (v > 0), v, np.nan)
        color = NEES_COLORS[what]
        ax.plot(t - t0, drawn, color=color, linewidth=1.0, label=f"{what} NEES ({summary.dof} dof)")
        ax.axhline(summary.quantile_95, color=color, linestyle="--", linewidth=0.9,
                   label=f"95 % quantile, {summary.dof} dof ({summary.quantile_95:.2f})")
        ax.axhline(summary.expected, color=color, linestyle=":", linewidth=0.9,
                   label=f"expected value, {summary.dof} dof ({summary.expected:g})")
    ax.set_yscale("log")
    _plain_log_ticks(ax)
    ax.set_xlabel("time since the first matched pose [s]")
    ax.set_ylabel("NEES [dimensionless]")
    ax.grid(True, which="both", linewidth=0.3)

    def stats(s) -> str:
        if not s.steps:
            return f"{s.dof} dof: no step (zero covariance)"
        return f"{s.dof} dof: mean {s.mean:.2f}, {100 * s.share_inside_95:.0f} % inside the 95 % ellipsoid"

    lines = [title] if title else []
    lines.append(f"position {stats(nees.position)}; pose {stats(nees.pose)}")
    extra = (f"{nees.position.steps} steps ({nees.position.skipped} skipped at the start: the reference pose, "
             "zero covariances)")
    infinite = max(nees.position.infinite, nees.pose.infinite)
    if infinite:
        extra += f"; {infinite} with a singular covariance (NEES inf, not drawn)"
    lines.append(extra)
    ax.set_title("\n".join(lines), fontsize="medium")
    ax.legend(loc="best", fontsize="small", ncol=2)
    fig.tight_layout()
    _save(fig, path)
    return fig


def plot_batch(path: str | os.PathLike, rows: list[dict]) -> None:
    """``vislam batch``: ATE RMSE (m, SE(3)-aligned) per input, one bar per configuration; an input
    without ground truth, or a run that failed, has no bar."""
    def name_of(r):
        return r.get("label") or os.path.basename(r["input"])

    names = list(dict.fromkeys(name_of(r) for r in rows))
    labels = list(dict.fromkeys(r["configuration"] for r in rows))
    fig = _new_figure((max(6.0, 0.8 * len(names) * max(len(labels), 1)), 4.0))
    ax = fig.add_subplot(1, 1, 1)
    width = 0.8 / max(len(labels), 1)
    for j, label in enumerate(labels):
        heights = []
        for name in names:
            value = next((r.get("ate_m") for r in rows
                          if name_of(r) == name and r["configuration"] == label), None)
            heights.append(value if isinstance(value, float) and np.isfinite(value) else 0.0)
        ax.bar(np.arange(len(names)) + (j - (len(labels) - 1) / 2) * width, heights, width, label=label,
               color=_OTHER_COLORS[j % len(_OTHER_COLORS)] if j else COLORS["estimate"])
    ax.set_xticks(np.arange(len(names)), names)
    ax.set_ylabel("ATE RMSE (m), aligned (SE(3))")
    ax.set_title("vislam batch: ATE per input and configuration (no bar: no ground truth, or the run failed)",
                 fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    _save(fig, path)
