"""``vislam eval``: ATE and RPE of one or more trajectories against one ground truth (evo), with
plots and the result files ``evo_res`` compares; with a run's pose covariance
(``pose_covariance.npz``) also the NEES of position and pose.

The files are TUM text or EuRoC csv (poses matched by time stamp), or all KITTI pose files
(``poses/XX.txt``, what ``vislam run --format kitti`` writes: the left camera's poses, matched line
by line); the format is told from the columns (``backend.data.tum.read_trajectory``)."""

from __future__ import annotations

import argparse
import contextlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ...backend.errors import ConfigError, InputError
from .. import outputs

#: Largest difference (s) between a covariance stamp and the estimate's: TUM text holds 6 decimals
#: (5e-7 s), float64 stamps near 1.7e9 s are spaced 2.4e-7 s
COVARIANCE_STAMP_TOLERANCE = 1e-5


def add_parser(sub) -> None:
    p = sub.add_parser("eval", help="ATE and RPE of trajectories (TUM, EuRoC csv or KITTI poses) against ground "
                                    "truth (evo); NEES with the run's pose covariance")
    p.add_argument("estimates", nargs="+", metavar="ESTIMATE",
                   help="one or more estimated trajectories: TUM text (timestamp tx ty tz qx qy qz qw; a run's "
                        "trajectory.txt), EuRoC csv (timestamp [ns], px, py, pz, qw, qx, qy, qz, ...) or KITTI pose "
                        "files (12 numbers a line; trajectory_kitti.txt); several: one table and overlaid plots")
    p.add_argument("ground_truth", help="the ground truth, the last argument: TUM or EuRoC csv (poses matched by time "
                                        "stamp, within --t-max-diff) or, for KITTI estimates, a KITTI pose file "
                                        "(matched line by line)")
    align = p.add_mutually_exclusive_group()
    align.add_argument("--sim3", action="store_true", help="Sim(3) alignment (default SE(3))")
    align.add_argument("--align-origin", dest="align_origin", action="store_true",
                       help="instead of a Umeyama alignment, put each estimate's first matched pose on the ground "
                            "truth's (evo's --align_origin): the error then shows the drift from the start")
    p.add_argument("--delta", type=float, default=100.0,
                   help="RPE segment length in metres along the ground truth (default 100); every pose starts a "
                        "segment: evo_rpe --all_pairs --pairs_from_reference, the segments KITTI's devkit measures "
                        "on the ground truth (evo_rpe's own default pairs consecutive segments along the estimate). "
                        "A ground truth path shorter than that: 10 frames, said on screen")
    p.add_argument("--t-max-diff", dest="t_max_diff", type=float, default=0.01, metavar="S",
                   help="largest difference of two time stamps matched as one pose, seconds (default 0.01, as evo's "
                        "--t_max_diff)")
    p.add_argument("--t-offset", dest="t_offset", type=float, default=0.0, metavar="S",
                   help="seconds added to the estimates' time stamps before matching (default 0, as evo's --t_offset)")
    p.add_argument("--covariance", metavar="FILE",
                   help="the estimate's pose covariance (pose_covariance.npz of vislam run, the estimate's stamps) "
                        "for the position and pose NEES; default: pose_covariance.npz beside an estimate named "
                        "trajectory.txt (a run's), when it exists; 'none': no NEES")
    p.add_argument("--json", help="write the numbers as JSON (one estimate: its numbers, with alignment_scale: 1 "
                                  "unless Sim(3), and nees with a covariance; several: ground_truth and a list "
                                  "estimates of those)")
    p.add_argument("-o", "--out", help="directory for eval.json, trajectories.png (aligned, ground truth over the "
                   "estimates' time span), xyz_over_time.png, rpy_over_time.png, ate_over_time.png, with a "
                   "covariance nees_over_time.png, and per estimate ape_NAME.zip and rpe_NAME.zip (evo's result "
                   "files: evo_res DIR/ape_*.zip compares them)")
    p.add_argument("--force", action="store_true",
                   help="write into a non-empty --out directory and replace an existing --json file")
    p.set_defaults(func=main)


@dataclass
class Estimate:
    """One estimate of the command line: its file, label, poses and pose covariance."""

    path: str
    name: str  # on screen and in the plots: "estimate" when alone, else its label
    label: str  # the shortest path suffix that tells it from the others (``report.path_labels``)
    time_stamps: np.ndarray  # (N,) seconds (shifted by --t-offset), or the frame index (KITTI)
    poses: np.ndarray  # (N,4,4)
    covariance: Optional[tuple[Path, np.ndarray]] = None  # (file, (N,6,6))


def main(args: argparse.Namespace) -> int:
    from ...backend.data.files import check_output_file, note_input, output_directory
    from ...backend.evaluation.metrics import require_matches

    if not (math.isfinite(args.delta) and args.delta > 0):
        raise ConfigError(f"--delta must be a positive number of metres, got {args.delta!r}")
    if not (math.isfinite(args.t_max_diff) and args.t_max_diff > 0):
        raise ConfigError(f"--t-max-diff must be a positive number of seconds, got {args.t_max_diff!r}")
    if not math.isfinite(args.t_offset):
        raise ConfigError(f"--t-offset must be a finite number of seconds, got {args.t_offset!r}")
    twice = sorted({p for p in args.estimates if args.estimates.count(p) > 1})
    if twice:
        raise ConfigError(f"{twice[0]}: given twice as an estimate")
    if len(args.estimates) > 1 and args.covariance not in (None, "none"):
        raise ConfigError(f"--covariance {args.covariance}: one file for {len(args.estimates)} estimates; without "
                          "the option the pose_covariance.npz beside each run's trajectory.txt is read")
    estimates, gt, by_index = _read_all(args)
    for e in estimates:
        beside = None if by_index else covariance_file(e.path, args.covariance)
        if beside is not None:
            note_input(beside)  # read by default: an input like the trajectories
    if args.json is not None:
        check_output_file(args.json, overwrite=args.force)  # before any work
    for e in estimates:
        if not by_index:
            e.covariance = _read_covariance(e.path, args.covariance, e.time_stamps)  # the file's own stamps
            e.time_stamps = e.time_stamps + args.t_offset
        require_matches(e.time_stamps, gt.time_stamps, args.ground_truth, max_diff=args.t_max_diff)
    with output_directory(args.out, args.force) if args.out is not None else contextlib.nullcontext() as staging:
        written = _evaluate(args, estimates, gt, staging, by_index)
    if args.out is not None:
        print(f"outputs in {args.out}/ ({', '.join(written)})")
    return 0


def _read_all(args: argparse.Namespace):
    """(estimates, ground truth, by index): the files of one kind, timed (TUM, EuRoC csv) or KITTI
    pose files (stamped with their line index, matched line by line, without covariance)."""
    from ...backend.data.tum import read_trajectory
    from ..report import path_labels

    gt = read_trajectory(args.ground_truth)
    labels = path_labels(args.estimates)
    estimates = []
    for path in args.estimates:
        est = read_trajectory(path)
        if est.by_index != gt.by_index:
            kitti, timed = (path, args.ground_truth) if est.by_index else (args.ground_truth, path)
            raise InputError(f"{kitti}: a KITTI pose file (camera poses, line k = frame k) and {timed} (poses in "
                             "time) cannot be matched: give all in one format (vislam run writes trajectory.txt, and "
                             "trajectory_kitti.txt with --format kitti)")
        if est.by_index and args.covariance not in (None, "none"):
            raise InputError(f"{args.covariance}: the pose covariance of a run is of trajectory.txt (TUM, the IMU's "
                             f"poses in time), not of the KITTI pose file {path}")
        name = "estimate" if len(args.estimates) == 1 else labels[path]
        estimates.append(Estimate(path, name, labels[path], est.time_stamps, est.poses))
    return estimates, gt, gt.by_index


def covariance_file(estimate: str, option: Optional[str]) -> Optional[Path]:
    """The pose covariance to read: ``option`` (``--covariance``; "none": no file), by default
    ``pose_covariance.npz`` beside a run's ``trajectory.txt`` (whose covariance it is; not beside
    ``dead_reckoning.txt`` or a renamed file) when it exists."""
    from ...backend.data.covariance import POSE_COVARIANCE_FILE, TRAJECTORY_FILE

    if option is None:
        beside = Path(estimate).parent / POSE_COVARIANCE_FILE
        return beside if Path(estimate).name == TRAJECTORY_FILE and beside.exists() else None
    return None if option == "none" else Path(option)


def _read_covariance(estimate: str, option: Optional[str], est_t: np.ndarray) -> Optional[tuple[Path, np.ndarray]]:
    """(file, covariance (N,6,6)) of the estimate's N stamps, or None; InputError naming the file when
    its stamps are not the estimate's."""
    from ...backend.data.covariance import read_pose_covariance

    path = covariance_file(estimate, option)
    if path is None:
        return None
    cov_t, cov = read_pose_covariance(path)
    if cov_t.shape != est_t.shape:
        raise InputError(f"{path}: key 'time_stamps': {cov_t.size} stamps, the estimate {estimate} has "
                         f"{est_t.size}: not the covariance of that trajectory")
    gap = np.abs(cov_t - est_t)
    if gap.max() > COVARIANCE_STAMP_TOLERANCE:
        k = int(np.argmax(gap > COVARIANCE_STAMP_TOLERANCE))
        raise InputError(f"{path}: key 'time_stamps': [{k}] = {cov_t[k]:.6f} differs from the estimate's "
                         f"{est_t[k]:.6f} ({estimate}) by {gap[k]:.3g} s: not the covariance of that trajectory")
    return path, cov


def _alignment_name(args: argparse.Namespace) -> str:
    return "first-pose-aligned" if args.align_origin else "Sim(3)-aligned" if args.sim3 else "SE(3)-aligned"


def _evaluate(args: argparse.Namespace, estimates: list[Estimate], gt, out: Path | None, by_index: bool) -> list[str]:
    """Numbers of every estimate on screen, in --json and, with ``out``, every file of --out; returns
    the names of the files written into ``out``."""
    from ...backend.evaluation.metrics import alignment, trajectory_errors

    how = dict(sim3=args.sim3, origin=args.align_origin, max_diff=args.t_max_diff)
    matched_by = ("line (KITTI pose files: line k = frame k)" if by_index
                  else f"time stamp (within {args.t_max_diff:g} s" + (f", the estimates' shifted by {args.t_offset:+g} s)"
                                                                      if args.t_offset else ")"))
    numbers, nees, alignments = [], [], []
    for e in estimates:
        errors = trajectory_errors(e.time_stamps, e.poses, gt.time_stamps, gt.poses, rpe_delta=args.delta, **how)
        alignments.append(alignment(e.time_stamps, e.poses, gt.time_stamps, gt.poses, **how))
        d = errors.as_dict()
        d["alignment_scale"] = alignments[-1].scale  # 1 unless Sim(3)
        d["t_offset"], d["t_max_diff"], d["matched_by"] = args.t_offset, args.t_max_diff, matched_by
        found = None
        if e.covariance is not None:
            from ...backend.evaluation.consistency import trajectory_nees

            path, cov = e.covariance
            found = trajectory_nees(e.time_stamps, e.poses, cov, gt.time_stamps, gt.poses, max_diff=args.t_max_diff)
            d["nees"] = {"covariance_file": str(path), **found.as_dict()}
        numbers.append(d)
        nees.append(found)
    if by_index:
        print("KITTI pose files: poses matched line by line (line k = frame k; the plots count frames)")
    elif args.t_offset or args.t_max_diff != 0.01:
        print(f"poses matched by {matched_by}")
    if len(estimates) == 1:
        _print_one(args, numbers[0])
        document = numbers[0]
    else:
        print(format_table(args, estimates, numbers))
        document = {"ground_truth": args.ground_truth,
                    "estimates": [{"name": e.name, "file": e.path, **d} for e, d in zip(estimates, numbers)]}
    if args.json is not None:
        outputs.write_json(args.json, document)
    if out is None:
        return []
    written = _write_outputs(args, estimates, gt, numbers, nees, alignments, out, by_index)
    outputs.write_json(out / "eval.json", document)
    return written


def _print_one(args: argparse.Namespace, d: dict) -> None:
    from ..report import nees_text, rpe_label

    print(f"ATE RMSE ({_alignment_name(args)}) {d['ate_rmse']:.3f} m (mean {d['ate_mean']:.3f}, "
          f"max {d['ate_max']:.3f}) over {d['path_length']:.1f} m, {d['num_matched']} poses; "
          f"{rpe_label(d, args.delta)}: {d['rpe_trans_rmse']:.3f} m, {d['rpe_rot_rmse_deg']:.3f} deg")
    if args.sim3:
        print(f"Sim(3) scale {d['alignment_scale']:.12g} (applied to the estimate; < 1: its path is longer "
              "than the ground truth's)")
    if "nees" in d:
        print(nees_text(d["nees"]["position"], "position"))
        print(nees_text(d["nees"]["pose"], "pose"))


def format_table(args: argparse.Namespace, estimates: list[Estimate], numbers: list[dict]) -> str:
    """Several estimates against one ground truth: a heading line and a Markdown table (a row each)."""
    from ..report import rpe_label

    first = numbers[0]
    head = (f"{len(estimates)} estimates against {args.ground_truth}, each {_alignment_name(args)}; "
            f"{rpe_label(first, args.delta)}")
    columns = ["estimate", "ATE RMSE [m]", "ATE max [m]", "RPE [m]", "RPE [deg]", "poses"]
    if args.sim3:
        columns.append("Sim(3) scale")
    with_nees = any("nees" in d for d in numbers)
    if with_nees:
        columns += ["position NEES mean", "inside 95 %"]
    lines = [head, "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for e, d in zip(estimates, numbers):
        rpe = f"{d['rpe_trans_rmse']:.3f}"
        if (d["rpe_delta"], d["rpe_unit"]) != (first["rpe_delta"], first["rpe_unit"]):
            rpe += f" (per {d['rpe_delta']:g} {d['rpe_unit']})"
        cells = [e.name, f"{d['ate_rmse']:.3f}", f"{d['ate_max']:.3f}", rpe, f"{d['rpe_rot_rmse_deg']:.3f}",
                 str(d["num_matched"])]
        if args.sim3:
            cells.append(f"{d['alignment_scale']:.6f}")
        if with_nees:
            position = d.get("nees", {}).get("position")
            if position is None or not position["steps"]:
                cells += ["", ""]
            else:
                mean = position["mean"]
                cells += ["inf" if mean is None else f"{mean:.2f}", f"{100 * position['share_inside_95']:.1f} %"]
        lines.append("| " + " | ".join(cells) + " |")
    if with_nees:
        lines.append("position NEES: expected 3 and 95 % inside; empty: no pose covariance (a run's "
                     "pose_covariance.npz is of its trajectory.txt)")
    return "\n".join(lines)


def result_file_stems(estimates: list[Estimate]) -> list[str]:
    """A file-name stem per estimate for its evo result files: its label without the extension
    (:func:`~vislam.tools.report.file_stem`), made unique."""
    from ..report import file_stem

    stems: list[str] = []
    for e in estimates:
        stem = file_stem(e.label.removesuffix(Path(e.label).suffix))
        unique, k = stem, 2
        while unique in stems:
            unique, k = f"{stem}_{k}", k + 1
        stems.append(unique)
    return stems


def _write_outputs(args: argparse.Namespace, estimates: list[Estimate], gt, numbers: list[dict], nees: list,
                   alignments: list, out: Path, by_index: bool = False) -> list[str]:
    """Every file of --out but eval.json (the caller's); ``alignments``: each estimate's
    (``metrics.Alignment``). Returns the names written."""
    from evo.tools.file_interface import save_res_file

    from ...backend.evaluation.metrics import evo_results
    from ..plots import (plot_nees_over_time, plot_rpy_over_time, plot_trajectories_topdown, plot_xyz_over_time,
                         within_span)
    from ..plots import write_error_plot

    how = dict(sim3=args.sim3, origin=args.align_origin, max_diff=args.t_max_diff)
    gt_name = Path(args.ground_truth).name
    title = (f"{Path(estimates[0].path).name} vs {gt_name}" if len(estimates) == 1
             else f"{len(estimates)} estimates vs {gt_name}")
    curves = {e.name: (e.time_stamps, e.poses) for e in estimates}
    written = ["eval.json", "trajectories.png", "xyz_over_time.png", "rpy_over_time.png", "ate_over_time.png"]
    plot_trajectories_topdown(out / "trajectories.png", curves, (gt.time_stamps, gt.poses), title=title, **how)
    aligned = {e.name: (e.time_stamps, a.apply_poses(e.poses)) for e, a in zip(estimates, alignments)}
    keep = within_span(gt.time_stamps, [e.time_stamps for e in estimates])
    aligned["ground truth"] = (gt.time_stamps[keep], gt.poses[keep])
    aligned_title = f"{title}; each estimate {_alignment_name(args)}"
    xlabel = "frame" if by_index else "time [s]"  # KITTI pose files: the index is the only time
    plot_xyz_over_time(out / "xyz_over_time.png", aligned, title=aligned_title, xlabel=xlabel)
    plot_rpy_over_time(out / "rpy_over_time.png", aligned, title=aligned_title, xlabel=xlabel)
    write_error_plot(out / "ate_over_time.png", curves, gt.time_stamps, gt.poses, **how, xlabel=xlabel)
    stems = result_file_stems(estimates)
    for e, found, stem in zip(estimates, nees, stems):
        if found is not None:
            name = "nees_over_time.png" if len(estimates) == 1 else f"nees_over_time_{stem}.png"
            plot_nees_over_time(out / name, found, title=f"{Path(e.path).name} vs {gt_name}")
            written.append(name)
    for e, d, stem in zip(estimates, numbers, stems):
        ape, rpe = evo_results(e.time_stamps, e.poses, gt.time_stamps, gt.poses, rpe_delta=d["rpe_delta"],
                               rpe_unit=d["rpe_unit"], est_name=stem, ref_name=gt_name, **how)
        for kind, result in (("ape", ape), ("rpe", rpe)):
            _save_result(save_res_file, out / f"{kind}_{stem}.zip", result)
            written.append(f"{kind}_{stem}.zip")
    return written


def _save_result(save_res_file, path: Path, result) -> None:
    """evo's result file, written to a temporary name and renamed (``atomic_write``)."""
    from ...backend.data.files import atomic_write

    with atomic_write(path) as tmp:
        save_res_file(str(tmp), result, confirm_overwrite=False)
