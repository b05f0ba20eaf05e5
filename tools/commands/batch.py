"""``vislam batch``: many inputs x configurations, one table and one plot.

``vislam batch A.npz B.npz --vary noise.pixel_sigma=1.0,1.5 --gt '../shared/data/gt/{stem}_gt_tum.txt'
--out DIR`` runs the filter on every feature file with every configuration (the product of the
``--vary`` lists over ``--config``/``--set``), on a local process pool (``--workers``) or a Ray
cluster (``--ray ADDRESS``; ``--ray local`` starts one here), and writes ``batch.csv`` (input,
configuration, ATE, RPE, mean NIS, gated share, seconds, real-time factor, health warnings),
``batch.json`` and ``batch.png`` (ATE per input and configuration), and per run
``runs/INPUT/CONFIGURATION/`` with its ``trajectory.txt`` and ``pose_covariance.npz`` (so ``vislam
eval`` and evo compare the runs afterwards). ``{stem}`` in ``--gt`` is the input file's name without
``.npz``; an input without ground truth gets no ATE. A run that fails is a row with its one-line
error; the exit code is then 1. Health warnings are counted in the table and listed on stderr.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import csv
import itertools
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from ...backend.errors import ConfigError, HealthWarning, VislamError
from .. import console, options, outputs

COLUMNS = ["input", "configuration", "steps", "ate_m", "rpe_m", "mean_nis", "gated_share", "seconds",
           "real_time_factor", "health_warnings", "run_folder", "error"]
#: The folder of every run's trajectory and pose covariance
RUNS = "runs"


@dataclass
class BatchRun:
    """What a worker sends back: the run's row and, when it ran, its trajectory and pose covariance."""

    row: dict
    health: list = field(default_factory=list)  # the run's health messages
    time_stamps: Optional[np.ndarray] = None  # (N,) seconds
    world_T_imu: Optional[np.ndarray] = None  # (N,4,4)
    pose_covariance: Optional[np.ndarray] = None  # (N,6,6)


def add_parser(sub) -> None:
    p = sub.add_parser("batch", help="run many feature files x configurations; one table and one plot")
    p.add_argument("inputs", nargs="+", help="feature files (.npz)")
    p.add_argument("--vary", action="append", default=[], metavar="TABLE.KEY=V1,V2,...",
                   help="values of one option to try (repeatable: every combination runs)")
    p.add_argument("--gt", metavar="PATTERN", help="ground truth TUM file per input; {stem} is the input's name without .npz")
    p.add_argument("--workers", type=int, default=None, help="local worker processes (default: every core)")
    p.add_argument("--ray", metavar="ADDRESS", help="run on a Ray cluster ('auto', 'ray://host:port', or 'local')")
    p.add_argument("-o", "--out", required=True, help="output directory (refused if non-empty, unless --force)")
    p.add_argument("--force", action="store_true", help="write into a non-empty output directory")
    options.add_config_options(p)
    console.add_verbosity_options(p)
    p.set_defaults(func=main)


def configurations(args: argparse.Namespace) -> list[tuple[str, object]]:
    """(label, Config) of every combination of the ``--vary`` values over ``--config``/``--set``;
    every value is checked before any run."""
    base = options.filter_config(args)
    axes = []
    for item in args.vary:
        key, sep, values = item.partition("=")
        choices = [v.strip() for v in values.split(",") if v.strip()]
        if not sep or not key.strip() or not choices:
            raise ConfigError(f"--vary {item!r}: expected TABLE.KEY=V1,V2,...")
        axes.append([f"{key.strip()}={v}" for v in choices])
    keys = [item.partition("=")[0].strip() for item in args.vary]
    repeated = sorted({k for k in keys if keys.count(k) > 1})
    if repeated:
        raise ConfigError(f"--vary {repeated[0]}: given more than once; list all its values in one --vary "
                          f"{repeated[0]}=V1,V2,...")
    combos = list(itertools.product(*axes)) or [()]
    return [(", ".join(c) or "defaults", base.with_assignments(list(c))) for c in combos]


def run_one(path: str, config, gt_path: str | None) -> BatchRun:
    """One run in a worker: its row and trajectory (module level, so a process pool or Ray can run it)."""
    import warnings

    from ...backend.data.npz import load_sequence
    from ...backend.run.runner import run_sequence

    row = {"input": path}
    run = BatchRun(row)
    try:
        t0 = time.perf_counter()
        seq = load_sequence(path)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", HealthWarning)  # health messages: in the row
            result = run_sequence(seq, config, load_seconds=time.perf_counter() - t0)
        stats = result.stats
        row.update(steps=stats.steps, mean_nis=stats.mean_nis, gated_share=stats.gated_share,
                   seconds=stats.total_seconds, real_time_factor=stats.real_time_factor,
                   health_warnings=len(stats.health_messages))
        run = BatchRun(row, list(stats.health_messages), result.time_stamps, result.world_T_imu,
                       result.pose_covariance)
        if gt_path is not None:
            from ...backend.data.tum import read_tum
            from ...backend.evaluation.metrics import require_matches, trajectory_errors

            gt_t, gt = read_tum(gt_path)
            require_matches(result.time_stamps, gt_t, gt_path)
            errors = trajectory_errors(result.time_stamps, result.world_T_imu, gt_t, gt)
            row.update(ate_m=errors.ate_rmse, rpe_m=errors.rpe_trans_rmse)
    except VislamError as exc:
        row["error"] = str(exc).splitlines()[0]
    return run


def main(args: argparse.Namespace) -> int:
    from ...backend.data.files import output_directory
    from ..pool import compile_for_workers, executor
    from ..report import path_labels, print_warnings

    configs = configurations(args)
    varied = "; ".join(item.strip() for item in args.vary)
    console.sayer(args.quiet)(f"vislam batch: {len(args.inputs)} input(s) x {len(configs)} configuration(s)"
                              + (f" ({varied})" if varied else "") + "; every run: "
                              + console.configuration_text(args.verbose, options.filter_config(args)))
    inputs = [str(Path(p)) for p in args.inputs]
    for p in inputs:
        if not Path(p).is_file():
            raise ConfigError(f"{p}: {'not a file' if Path(p).exists() else 'file does not exist'}")
    gts = {p: _gt_path(args.gt, p) for p in inputs}
    if args.gt:
        missing = [p for p in inputs if gts[p] is None]
        if missing:
            shown = ", ".join(_gt_candidate(args.gt, p) for p in missing[:3]) + (", ..." if len(missing) > 3 else "")
            console.sayer(args.quiet)(f"note: no ground truth for {len(missing)} of {len(inputs)} input(s) (--gt "
                                      f"{args.gt}: no file {shown}); their ATE and RPE stay empty")
    jobs = [(p, label, config) for p in inputs for label, config in configs]
    labels = path_labels(inputs)
    with output_directory(args.out, args.force) as staging:  # checked before any work
        if not args.ray:
            compile_for_workers(console.sayer(args.quiet))  # an inertial input's workers compile its few more
        rows = [None] * len(jobs)
        health: list[list[str]] = [[] for _ in jobs]
        with executor(args.workers, args.ray, len(jobs)) as pool, \
                console.progress_bar(len(jobs), "batch", "run", console.progress_off(args)) as progress:
            futures = {pool.submit(run_one, p, config, gts[p]): i for i, (p, _, config) in enumerate(jobs)}
            for future in concurrent.futures.as_completed(futures):
                i = futures[future]
                run = future.result()
                rows[i] = dict(run.row, label=labels[jobs[i][0]], configuration=jobs[i][1])
                if run.world_T_imu is not None:
                    rows[i]["run_folder"] = _write_run(staging, run, labels[jobs[i][0]], jobs[i][1])
                health[i] = [f"{labels[jobs[i][0]]}, {jobs[i][1]}: {m}" for m in run.health]
                progress(i)
        _write_table(staging / "batch.csv", rows)
        outputs.write_json(staging / "batch.json", {"columns": COLUMNS, "rows": rows})
        _plot(staging / "batch.png", rows)
    if not args.quiet:
        print(format_table(rows))
        print(f"wrote batch.csv, batch.json, batch.png and {RUNS}/ (each run's trajectory.txt and "
              f"pose_covariance.npz) to {args.out}/")
    print_warnings([line for lines in health for line in lines])  # in the table's order; with --quiet too, as vislam run's: they say a result is not what was asked for
    return 1 if any(r.get("error") for r in rows) else 0


def run_folder(label: str, configuration: str) -> str:
    """``runs/INPUT/CONFIGURATION``, relative to the output directory: the input's label without
    ``.npz`` and the configuration (``, `` as ``+``), other characters than letters, digits and
    ``._=+-`` replaced by '_'."""
    from ..report import file_stem

    return f"{RUNS}/{file_stem(label.removesuffix('.npz'))}/{file_stem(configuration.replace(', ', '+'))}"


def _write_run(staging: Path, run: BatchRun, label: str, configuration: str) -> str:
    """The run's trajectory.txt and pose_covariance.npz in its folder; returns the folder (relative)."""
    from ...backend.data.covariance import POSE_COVARIANCE_FILE, TRAJECTORY_FILE, write_pose_covariance
    from ...backend.data.tum import write_tum

    relative = run_folder(label, configuration)
    folder = staging / relative
    folder.mkdir(parents=True, exist_ok=True)
    write_tum(folder / TRAJECTORY_FILE, run.time_stamps, run.world_T_imu,
              header=f"world_T_imu of vislam batch: {label}, {configuration}")
    write_pose_covariance(folder / POSE_COVARIANCE_FILE, run.time_stamps, run.pose_covariance)
    return relative


def _gt_candidate(pattern: str, input_path: str) -> str:
    """The ground truth file ``--gt PATTERN`` names for ``input_path`` ({stem}: its name without .npz)."""
    return pattern.replace("{stem}", Path(input_path).name.removesuffix(".npz"))


def _gt_path(pattern: str | None, input_path: str) -> str | None:
    if not pattern:
        return None
    path = _gt_candidate(pattern, input_path)
    return path if Path(path).is_file() else None


def _value(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return "n/a" if not math.isfinite(v) else f"{v:.4g}"
    return str(v)


def _write_table(path: Path, rows: list[dict]) -> None:
    from ...backend.data.files import atomic_write

    with atomic_write(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(COLUMNS)
        for row in rows:
            writer.writerow([_value(row.get(c)) for c in COLUMNS])


def format_table(rows: list[dict]) -> str:
    """The rows as a Markdown table (what the terminal shows)."""
    shown = ["input", "configuration", "ate_m", "rpe_m", "mean_nis", "seconds", "real_time_factor", "health_warnings",
             "error"]
    lines = ["| " + " | ".join(shown) + " |", "|" + "---|" * len(shown)]
    for row in rows:
        lines.append("| " + " | ".join(_value(row.get(c)) if c != "input"
                                       else row.get("label") or Path(row["input"]).name for c in shown) + " |")
    return "\n".join(lines)


def _plot(path: Path, rows: list[dict]) -> None:
    from ..plots import plot_batch

    plot_batch(path, rows)
