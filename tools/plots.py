"""Figures of vislam runs and Monte Carlo consistency (PNG, 150 dpi), written atomically.

Only matplotlib's object-oriented API is used (``matplotlib.figure.Figure`` rendered by the
Agg canvas); pyplot is never imported, so no display or GUI backend is needed, no global
figure state is kept and importing this module does not change the caller's backend.
"""

from __future__ import annotations

import os
from typing import Any, Mapping

import numpy as np

from ..backend.data.files import atomic_write

__all__ = ["plot_trajectories_topdown", "plot_errors_over_time", "plot_consistency"]

DPI = 150
MAX_LANDMARKS_PLOTTED = 20000

# Fixed looks for the trajectory names a run produces; other names cycle through tab10.
_STYLES = {
    "ground truth": dict(color="black", linestyle="--", linewidth=1.2),
    "estimate": dict(color="tab:blue", linestyle="-", linewidth=1.5),
    "dead reckoning": dict(color="tab:orange", linestyle="-", linewidth=1.0),
}


def _new_figure(figsize: tuple[float, float]):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: str | os.PathLike) -> None:
    with atomic_write(path) as tmp:
        fig.savefig(tmp, dpi=DPI, format="png")


def _xy(traj: Any, name: str) -> np.ndarray:
    arr = np.asarray(traj, dtype=float)
    if arr.ndim == 3 and arr.shape[1:] == (4, 4):
        return arr[:, :2, 3]
    if arr.ndim == 2 and arr.shape[1] in (2, 3):
        return arr[:, :2]
    raise ValueError(f"trajectory {name!r} must have shape (N, 4, 4), (N, 3) or (N, 2), got {arr.shape}")


def plot_trajectories_topdown(
    path: str | os.PathLike,
    trajectories: Mapping[str, Any],
    landmarks: np.ndarray | None = None,
    title: str = "",
) -> None:
    """Top-down (x-y, equal axes) plot of named trajectories and optionally the landmarks.

    ``trajectories`` maps a legend name (e.g. ``"dead reckoning"``, ``"estimate"``,
    ``"ground truth"``) to ``(N, 4, 4)`` poses or ``(N, 3)`` positions. Each start is marked
    with a circle, each end with a cross. ``landmarks`` ``(K, 3)`` are drawn as small grey
    dots, a fixed random subset of at most 20000 if there are more.
    """
    fig = _new_figure((8.0, 8.0))
    ax = fig.add_subplot(1, 1, 1)
    if landmarks is not None:
        lm = np.asarray(landmarks, dtype=float)
        if lm.ndim != 2 or lm.shape[1] not in (2, 3):
            raise ValueError(f"landmarks must have shape (K, 3), got {lm.shape}")
        lm = lm[np.all(np.isfinite(lm[:, :2]), axis=1)]
        if len(lm) > MAX_LANDMARKS_PLOTTED:
            keep = np.random.default_rng(0).choice(len(lm), MAX_LANDMARKS_PLOTTED, replace=False)
            lm = lm[np.sort(keep)]
        if len(lm):
            ax.scatter(
                lm[:, 0], lm[:, 1], s=1.0, c="0.6", alpha=0.5, linewidths=0,
                label=f"landmarks ({len(lm)})", zorder=1, rasterized=True,
            )
    others = iter(f"C{i}" for i in range(2, 1000))
    start_labelled = False
    for name, traj in trajectories.items():
        xy = _xy(traj, name)
        if len(xy) == 0:
            continue
        style = dict(_STYLES.get(name, {}))
        style.setdefault("color", next(others))
        style.setdefault("linewidth", 1.2)
        ax.plot(xy[:, 0], xy[:, 1], label=name, zorder=3, **style)
        ax.plot(
            xy[0, 0], xy[0, 1], marker="o", markersize=7, color=style["color"],
            markerfacecolor="none", linestyle="none", zorder=4,
            label=None if start_labelled else "start (o) / end (x)",
        )
        ax.plot(xy[-1, 0], xy[-1, 1], marker="x", markersize=7, color=style["color"],
                linestyle="none", zorder=4)
        start_labelled = True
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, linewidth=0.3)
    if title:
        ax.set_title(title)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize="small", markerscale=1.0)
    fig.tight_layout()
    _save(fig, path)


def plot_errors_over_time(
    path: str | os.PathLike,
    series: Mapping[str, tuple[Any, Any]],
    title: str,
    ylabel: str = "error [m]",
) -> None:
    """One line per named ``(time_stamps (N,), errors (N,))`` over time since the earliest stamp
    (seconds), each with its RMSE as a dashed line of the same colour."""
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
    colors = ["tab:blue", "tab:orange", "tab:green", "tab:purple"]
    for i, (name, (t, e)) in enumerate(checked.items()):
        if not len(t):
            continue
        color = colors[i % len(colors)]
        finite = e[np.isfinite(e)]
        rmse = float(np.sqrt(np.mean(finite**2))) if len(finite) else float("nan")
        ax.plot(t - t0, e, color=color, linewidth=1.0, label=f"{name} (RMSE {rmse:.3g})")
        if len(finite):
            ax.axhline(rmse, color=color, linestyle="--", linewidth=0.8)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize="small")
    ax.set_xlabel("time [s]")
    ax.set_ylabel(ylabel)
    ax.grid(True, linewidth=0.3)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    _save(fig, path)


def plot_consistency(path: str | os.PathLike, result) -> None:
    """Two panels over the steps: the run-averaged pose NEES with its 95 % band (log y), and the
    NIS per observation with its band for one step's observations of all runs."""
    steps = np.arange(result.steps)
    fig = _new_figure((9.0, 6.5))
    ax = fig.add_subplot(2, 1, 1)
    lo, hi = result.pose_nees_band
    nees = np.asarray(result.pose_nees_mean, dtype=float)
    positive = nees > 0
    ax.plot(steps[positive], nees[positive], color="tab:blue", linewidth=1.0,
            label=f"pose NEES, average of {result.runs} runs")
    ax.axhspan(lo, hi, color="tab:green", alpha=0.2, label=f"95 % band [{lo:.2f}, {hi:.2f}]")
    ax.axhline(6.0, color="tab:green", linewidth=0.8, linestyle="--", label="expectation 6")
    ax.axvline(result.skip, color="0.5", linewidth=0.6, linestyle=":")
    ax.set_yscale("log")
    ax.set_ylabel("pose NEES (6 dof)")
    ax.set_title(f"{100 * result.pose_nees_in_band:.0f} % of steps {result.skip}..{result.steps - 1} in the band")
    ax.grid(True, which="both", linewidth=0.3)
    ax.legend(loc="best", fontsize="small")

    ax = fig.add_subplot(2, 1, 2, sharex=ax)
    nis = np.asarray(result.nis_per_step, dtype=float)
    ax.plot(steps, nis, color="tab:purple", linewidth=0.8, label="NIS per observation (all runs)")
    ax.axhline(4.0, color="tab:green", linewidth=0.8, linestyle="--", label="expectation 4")
    nlo, nhi = result.nis_band
    ax.axhline(result.nis_mean, color="tab:red", linewidth=0.8,
               label=f"mean {result.nis_mean:.3f} (band [{nlo:.3f}, {nhi:.3f}])")
    ax.set_xlabel("step")
    ax.set_ylabel("NIS / observation (4 dof)")
    ax.grid(True, linewidth=0.3)
    ax.legend(loc="best", fontsize="small")
    fig.tight_layout()
    _save(fig, path)
