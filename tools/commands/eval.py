"""``vislam eval``: ATE and RPE of a trajectory against ground truth (evo), with plots; with the
run's pose covariance (``pose_covariance.npz``) also the NEES of position and pose.

Both files are TUM text (poses matched by time stamp) or both KITTI pose files (``poses/XX.txt``,
what ``vislam run --format kitti`` writes: the left camera's poses, matched line by line); the
format is told from the columns (``backend.data.tum.read_trajectory``)."""

from __future__ import annotations

import argparse
import contextlib
import math
from pathlib import Path
from typing import Optional

import numpy as np

from ...backend.errors import ConfigError, InputError
from .. import outputs

#: Largest difference (s) between a covariance stamp and the estimate's: TUM text holds 6 decimals
#: (5e-7 s), float64 stamps near 1.7e9 s are spaced 2.4e-7 s
COVARIANCE_STAMP_TOLERANCE = 1e-5


def add_parser(sub) -> None:
    p = sub.add_parser("eval", help="ATE and RPE of a trajectory (TUM, or KITTI poses) against ground truth "
                                    "(evo); NEES with the run's pose covariance")
    p.add_argument("estimate", help="the estimated trajectory: TUM text (timestamp tx ty tz qx qy qz qw; a run's "
                                    "trajectory.txt) or a KITTI pose file (12 numbers a line; trajectory_kitti.txt)")
    p.add_argument("ground_truth", help="the ground truth in the same format: TUM poses are matched by time stamp "
                                        "(within 0.01 s), KITTI poses line by line")
    p.add_argument("--sim3", action="store_true", help="Sim(3) alignment (default SE(3))")
    p.add_argument("--delta", type=float, default=100.0,
                   help="RPE segment length in metres along the ground truth (default 100); every pose starts a "
                        "segment: evo_rpe --all_pairs --pairs_from_reference, the segments KITTI's devkit measures "
                        "on the ground truth (evo_rpe's own default pairs consecutive segments along the estimate). "
                        "A ground truth path shorter than that: 10 frames, said on screen")
    p.add_argument("--t-max-diff", dest="t_max_diff", type=float, default=0.01, metavar="S",
                   help="largest difference of two time stamps matched as one pose, seconds (default 0.01, as evo's "
                        "--t_max_diff)")
    p.add_argument("--t-offset", dest="t_offset", type=float, default=0.0, metavar="S",
                   help="seconds added to the estimate's time stamps before matching (default 0, as evo's --t_offset)")
    p.add_argument("--covariance", metavar="FILE",
                   help="the estimate's pose covariance (pose_covariance.npz of vislam run, the estimate's stamps) "
                        "for the position and pose NEES; default: pose_covariance.npz beside the estimate when it "
                        "exists; 'none': no NEES")
    p.add_argument("--json", help="write the numbers as JSON (with alignment_scale: 1 for SE(3); with a covariance "
                                  "also nees)")
    p.add_argument("--out", help="directory for eval.json, trajectories.png (aligned, ground truth over the "
                   "estimate's time span), ate_over_time.png and, with a covariance, nees_over_time.png")
    p.add_argument("--force", action="store_true",
                   help="write into a non-empty --out directory and replace an existing --json file")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from ...backend.data.files import check_output_file, note_input, output_directory
    from ...backend.evaluation.metrics import require_matches

    if not (math.isfinite(args.delta) and args.delta > 0):
        raise ConfigError(f"--delta must be a positive number of metres, got {args.delta!r}")
    if not (math.isfinite(args.t_max_diff) and args.t_max_diff > 0):
        raise ConfigError(f"--t-max-diff must be a positive number of seconds, got {args.t_max_diff!r}")
    if not math.isfinite(args.t_offset):
        raise ConfigError(f"--t-offset must be a finite number of seconds, got {args.t_offset!r}")
    est_t, est, gt_t, gt, by_index = _read_pair(args)
    beside = None if by_index else covariance_file(args.estimate, args.covariance)
    if beside is not None:
        note_input(beside)  # read by default: an input like the two trajectories
    if args.json is not None:
        check_output_file(args.json, overwrite=args.force)  # before any work
    covariance = None if by_index else _read_covariance(args, est_t)  # against the file's own stamps
    est_t = est_t + args.t_offset
    require_matches(est_t, gt_t, args.ground_truth, max_diff=args.t_max_diff)
    with output_directory(args.out, args.force) if args.out is not None else contextlib.nullcontext() as staging:
        _evaluate(args, est_t, est, gt_t, gt, covariance, staging, by_index)
    if args.out is not None:
        names = "eval.json, trajectories.png, ate_over_time.png" + (", nees_over_time.png" if covariance else "")
        print(f"outputs in {args.out}/ ({names})")
    return 0


def _read_pair(args: argparse.Namespace) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    """(estimate stamps, poses, ground truth stamps, poses, by index) of two files of one format;
    KITTI pose files are stamped with their line index (matched line by line), without covariance."""
    from ...backend.data.tum import read_trajectory

    est, gt = read_trajectory(args.estimate), read_trajectory(args.ground_truth)
    if est.format != gt.format:
        kitti, tum = (args.estimate, args.ground_truth) if est.by_index else (args.ground_truth, args.estimate)
        raise InputError(f"{kitti}: a KITTI pose file (camera poses, line k = frame k) and {tum} TUM text (IMU "
                         "poses in time) cannot be matched: give both in one format (vislam run writes "
                         "trajectory.txt, and trajectory_kitti.txt with --format kitti)")
    if est.by_index and args.covariance not in (None, "none"):
        raise InputError(f"{args.covariance}: the pose covariance of a run is of trajectory.txt (TUM, the IMU's "
                         f"poses in time), not of the KITTI pose file {args.estimate}")
    return est.time_stamps, est.poses, gt.time_stamps, gt.poses, est.by_index


def covariance_file(estimate: str, option: Optional[str]) -> Optional[Path]:
    """The pose covariance to read: ``option`` (``--covariance``; "none": no file), by default
    ``pose_covariance.npz`` beside the estimate when it exists."""
    from ...backend.data.covariance import POSE_COVARIANCE_FILE

    if option is None:
        beside = Path(estimate).parent / POSE_COVARIANCE_FILE
        return beside if beside.exists() else None
    return None if option == "none" else Path(option)


def _read_covariance(args: argparse.Namespace, est_t: np.ndarray) -> Optional[tuple[Path, np.ndarray]]:
    """(file, covariance (N,6,6)) of the estimate's N stamps, or None; InputError naming the file when
    its stamps are not the estimate's."""
    from ...backend.data.covariance import read_pose_covariance

    path = covariance_file(args.estimate, args.covariance)
    if path is None:
        return None
    cov_t, cov = read_pose_covariance(path)
    if cov_t.shape != est_t.shape:
        raise InputError(f"{path}: key 'time_stamps': {cov_t.size} stamps, the estimate {args.estimate} has "
                         f"{est_t.size}: not the covariance of that trajectory")
    gap = np.abs(cov_t - est_t)
    if gap.max() > COVARIANCE_STAMP_TOLERANCE:
        k = int(np.argmax(gap > COVARIANCE_STAMP_TOLERANCE))
        raise InputError(f"{path}: key 'time_stamps': [{k}] = {cov_t[k]:.6f} differs from the estimate's "
                         f"{est_t[k]:.6f} ({args.estimate}) by {gap[k]:.3g} s: not the covariance of that trajectory")
    return path, cov


def _evaluate(args: argparse.Namespace, est_t, est, gt_t, gt, covariance, out: Path | None,
              by_index: bool = False) -> None:
    from ...backend.evaluation.metrics import alignment_scale, trajectory_errors
    from ..plots import plot_nees_over_time, plot_trajectories_topdown
    from ..report import nees_text, rpe_label, write_error_plot

    max_diff = args.t_max_diff
    errors = trajectory_errors(est_t, est, gt_t, gt, sim3=args.sim3, rpe_delta=args.delta, max_diff=max_diff)
    d = errors.as_dict()
    d["alignment_scale"] = alignment_scale(est_t, est, gt_t, gt, max_diff=max_diff) if args.sim3 else 1.0
    d["t_offset"], d["t_max_diff"] = args.t_offset, max_diff
    d["matched_by"] = ("line (KITTI pose files: line k = frame k)" if by_index
                       else f"time stamp (within {max_diff:g} s" + (f", the estimate's shifted by {args.t_offset:+g} s)"
                                                                     if args.t_offset else ")"))
    if by_index:
        print("KITTI pose files: poses matched line by line (line k = frame k; the times in the plots are frames)")
    elif args.t_offset or max_diff != 0.01:
        print(f"poses matched by {d['matched_by']}")
    print(f"ATE RMSE ({'Sim(3)' if args.sim3 else 'SE(3)'}-aligned) {d['ate_rmse']:.3f} m (mean {d['ate_mean']:.3f}, "
          f"max {d['ate_max']:.3f}) over {d['path_length']:.1f} m, {d['num_matched']} poses; "
          f"{rpe_label(d, args.delta)}: {d['rpe_trans_rmse']:.3f} m, {d['rpe_rot_rmse_deg']:.3f} deg")
    if args.sim3:
        print(f"Sim(3) scale {d['alignment_scale']:.12g} (applied to the estimate; < 1: its path is longer "
              "than the ground truth's)")
    nees = None
    if covariance is not None:
        from ...backend.evaluation.consistency import trajectory_nees

        path, cov = covariance
        nees = trajectory_nees(est_t, est, cov, gt_t, gt, max_diff=max_diff)
        d["nees"] = {"covariance_file": str(path), **nees.as_dict()}
        print(nees_text(d["nees"]["position"], "position"))
        print(nees_text(d["nees"]["pose"], "pose"))
    if args.json is not None:
        outputs.write_json(args.json, d)
    if out is not None:
        title = f"{Path(args.estimate).name} vs {Path(args.ground_truth).name}"
        plot_trajectories_topdown(out / "trajectories.png", {"estimate": (est_t, est)}, (gt_t, gt), sim3=args.sim3,
                                  title=title, max_diff=max_diff)
        write_error_plot(out / "ate_over_time.png", {"estimate": est}, est_t, gt_t, gt, sim3=args.sim3,
                         max_diff=max_diff)
        if nees is not None:
            plot_nees_over_time(out / "nees_over_time.png", nees, title=title)
        outputs.write_json(out / "eval.json", d)
