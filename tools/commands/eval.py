"""``vislam eval``: ATE and RPE of a TUM trajectory against ground truth (evo), with plots."""

from __future__ import annotations

import argparse
import contextlib
import math
from pathlib import Path

from ...backend.errors import ConfigError
from .. import outputs


def add_parser(sub) -> None:
    p = sub.add_parser("eval", help="ATE and RPE of a TUM trajectory against ground truth (evo)")
    p.add_argument("estimate")
    p.add_argument("ground_truth")
    p.add_argument("--sim3", action="store_true", help="Sim(3) alignment (default SE(3))")
    p.add_argument("--delta", type=float, default=100.0, help="RPE distance in metres (default 100)")
    p.add_argument("--json", help="write the numbers as JSON (with alignment_scale: 1 for SE(3))")
    p.add_argument("--out", help="directory for eval.json, trajectories.png (aligned, ground truth over the "
                   "estimate's time span) and ate_over_time.png")
    p.add_argument("--force", action="store_true", help="write into a non-empty --out directory")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from ...backend.data.tum import read_tum
    from ...backend.data.files import check_output_file, output_directory
    from ...backend.evaluation.metrics import require_matches

    if not (math.isfinite(args.delta) and args.delta > 0):
        raise ConfigError(f"--delta must be a positive number of metres, got {args.delta!r}")
    if args.json is not None:
        check_output_file(args.json)  # before any work
    est_t, est = read_tum(args.estimate)
    gt_t, gt = read_tum(args.ground_truth)
    require_matches(est_t, gt_t, args.ground_truth)
    with output_directory(args.out, args.force) if args.out is not None else contextlib.nullcontext() as staging:
        _evaluate(args, est_t, est, gt_t, gt, staging)
    if args.out is not None:
        print(f"outputs in {args.out}/ (eval.json, trajectories.png, ate_over_time.png)")
    return 0


def _evaluate(args: argparse.Namespace, est_t, est, gt_t, gt, out: Path | None) -> None:
    from ...backend.evaluation.metrics import alignment_scale, trajectory_errors
    from ..plots import plot_trajectories_topdown
    from ..report import write_error_plot

    errors = trajectory_errors(est_t, est, gt_t, gt, sim3=args.sim3, rpe_delta=args.delta)
    d = errors.as_dict()
    d["alignment_scale"] = alignment_scale(est_t, est, gt_t, gt) if args.sim3 else 1.0
    print(f"ATE RMSE ({'Sim(3)' if args.sim3 else 'SE(3)'}-aligned) {d['ate_rmse']:.3f} m (mean {d['ate_mean']:.3f}, "
          f"max {d['ate_max']:.3f}) over {d['path_length']:.1f} m, {d['num_matched']} poses; "
          f"RPE per {d['rpe_delta']:g} {d['rpe_unit']}: {d['rpe_trans_rmse']:.3f} m, {d['rpe_rot_rmse_deg']:.3f} deg")
    if args.sim3:
        print(f"Sim(3) scale {d['alignment_scale']:.12g} (applied to the estimate; < 1: its path is longer "
              "than the ground truth's)")
    if args.json is not None:
        outputs.write_json(args.json, d)
    if out is not None:
        plot_trajectories_topdown(out / "trajectories.png", {"estimate": (est_t, est)}, (gt_t, gt), sim3=args.sim3,
                                  title=f"{Path(args.estimate).name} vs {Path(args.ground_truth).name}")
        write_error_plot(out / "ate_over_time.png", {"estimate": est}, est_t, gt_t, gt, sim3=args.sim3)
        outputs.write_json(out / "eval.json", d)
