"""The `vislam` command line: thin over backend/, synth/ and tools/.

Every user error is one line on stderr and exit code 2; Ctrl-C exits 130 and leaves no half file.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings

import numpy as np

from backend.config import FilterConfig, apply_overrides, load_config
from backend.errors import VislamError

EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


def _config_from_args(args: argparse.Namespace, assignments: list[str] | None = None) -> FilterConfig:
    """Defaults < --config TOML < dedicated flags < --set KEY=VALUE (``assignments``, default all of --set)."""
    config = load_config(args.config) if args.config else FilterConfig()
    flags = []
    if getattr(args, "mode", None):
        flags.append(f"mode={args.mode}")
    if getattr(args, "full_state", False):
        flags.append("full_state=true")
    if getattr(args, "imu_flip", None):
        flags.append(f"imu_flip={args.imu_flip}")
    if getattr(args, "velocity_index", None):
        flags.append(f"velocity_index={args.velocity_index}")
    assignments = list(args.set or []) if assignments is None else assignments
    return apply_overrides(config, flags + assignments).validate()


def _add_filter_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="TOML", help="configuration file ([filter] table or flat keys)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override one config key (repeatable)")
    p.add_argument("--mode", choices=["slam", "mapping", "dead-reckoning"], help="default: slam")
    p.add_argument("--full-state", action="store_true", help="keep every landmark in the state (small problems)")
    p.add_argument("--imu-flip", choices=["auto", "yes", "no"], help="flip the IMU's y and z axes (default auto)")
    p.add_argument("--velocity-index", choices=["auto", "this", "next"],
                   help="velocity stamped k (this) or k+1 (next) drives step k->k+1 (default auto)")


def cmd_run(args: argparse.Namespace) -> int:
    from backend import kernels
    from backend.pipeline import decide_track_drift, prepare, run_sequence
    from backend.sequence import load_sequence
    from tools import outputs
    from tools.report import format_summary, write_run_outputs

    from pathlib import Path

    images = Path(args.data).is_dir()
    filter_set, tracker_set = list(args.set or []), []
    if images:
        from frontend.config import split_overrides

        filter_set, tracker_set = split_overrides(filter_set)
    elif args.imu:
        raise VislamError(f"{args.data}: --imu is for an image directory; a feature file carries its velocities")
    config = _config_from_args(args, filter_set)
    out_dir = outputs.prepare_output_dir(args.out, args.force)
    gt = outputs.read_tum(args.gt) if args.gt else None
    say = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr))
    if images:
        from tools.track import run_images

        say("configuration:\n" + config.describe())
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # health messages: listed in the summary
            result = run_images(args, tracker_set, config, args.quiet)
        summary = write_run_outputs(result, out_dir, str(args.data), gt)
        print(format_summary(summary, out_dir))
        return 0
    t_load = time.perf_counter()
    seq = load_sequence(args.data, image_size=config.image_size)  # bad input is refused before any waiting
    load_seconds = time.perf_counter() - t_load
    say(f"vislam run {args.data}: {seq.num_steps} steps, {seq.num_observations} observations of "
        f"{seq.num_features} features" + (f"; dropped {seq.dropped}" if any(seq.dropped.values()) else ""))
    say("configuration:\n" + config.describe())
    kernels.warm_up()  # compiled kernels (reported apart, as imports): before the convention test calls one
    t_prepare = time.perf_counter()
    decisions = prepare(seq, config)
    setup_seconds = load_seconds + time.perf_counter() - t_prepare  # loading and conventions: part of the real-time factor
    say(decisions[0].describe())
    say(decisions[1].describe())
    say(decide_track_drift(config, seq.tracker)[1])
    progress = None
    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(total=seq.num_steps, unit="step", file=sys.stderr, desc="filter")
        progress = lambda k: bar.update(1)  # noqa: E731
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # health messages: listed in the summary
            result = run_sequence(seq, config, progress=progress, decisions=decisions)
    finally:
        if bar is not None:
            bar.close()
    result.stats.setup_seconds += setup_seconds  # run_sequence timed only its own (none: decided here)
    summary = write_run_outputs(result, out_dir, str(args.data), gt)
    print(format_summary(summary, out_dir))
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    from backend.pipeline import decide_track_drift, prepare
    from backend.sequence import load_sequence
    from backend.timing import repeated_steps

    seq = load_sequence(args.data)
    defaults = FilterConfig()
    decision, noise = prepare(seq, defaults)
    per_step = np.diff(seq.obs_ptr)
    print(f"{args.data}: {seq.layout} layout, {seq.num_steps} steps over "
          f"{seq.time_stamps[-1] - seq.time_stamps[0]:.1f} s, {seq.num_features} features, "
          f"{seq.num_observations} observations ({per_step.mean():.1f} per step, max {per_step.max()})")
    print(f"dropped by the loader: {seq.dropped}; steps repeating the previous frame: {int(repeated_steps(seq).sum())}")
    print("reprojection test (median px, triangulated at k, dead reckoning to k+"
          f"{defaults.convention_horizon}):")
    for key, value in decision.errors_px.items():
        print(f"  {key:<28} {value:8.2f}")
    print(decision.describe())
    print(noise.describe())
    print(decide_track_drift(defaults, seq.tracker)[1])
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from backend.metrics import trajectory_errors
    from tools import outputs

    est_t, est = outputs.read_tum(args.estimate)
    gt_t, gt = outputs.read_tum(args.ground_truth)
    errors = trajectory_errors(est_t, est, gt_t, gt, sim3=args.sim3, rpe_delta=args.delta)
    d = errors.as_dict()
    print(f"ATE RMSE ({'Sim(3)' if args.sim3 else 'SE(3)'}-aligned) {d['ate_rmse']:.3f} m (mean {d['ate_mean']:.3f}, "
          f"max {d['ate_max']:.3f}) over {d['path_length']:.1f} m, {d['num_matched']} poses; "
          f"RPE per {d['rpe_delta']:g} {d['rpe_unit']}: {d['rpe_trans_rmse']:.3f} m, {d['rpe_rot_rmse_deg']:.3f} deg")
    if args.json:
        outputs.write_json(args.json, d)
    if args.out:
        from backend.metrics import aligned_poses
        from tools.plots import plot_trajectories_topdown
        from tools.report import write_error_plot

        out = outputs.prepare_output_dir(args.out, args.force)
        _, est_aligned, ref = aligned_poses(est_t, est, gt_t, gt, sim3=args.sim3)
        plot_trajectories_topdown(out / "trajectories.png", {"estimate (aligned)": est_aligned, "ground truth": ref},
                                  title=f"{args.estimate} vs {args.ground_truth}")
        write_error_plot(out / "ate_over_time.png", {"estimate": est}, est_t, gt_t, gt, sim3=args.sim3)
        outputs.write_json(out / "eval.json", d)
        print(f"outputs in {out}/ (eval.json, trajectories.png, ate_over_time.png)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vislam", description="Stereo visual-inertial EKF SLAM on SE(3).")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("run", help="run the filter on a feature file (.npz) and write trajectory, map, summary")
    p.add_argument("data", help="feature + IMU file in the course .npz layout, or a stereo image directory (with --imu)")
    p.add_argument("--imu", help="with an image directory: IMU velocities (CSV t,vx,vy,vz,wx,wy,wz or a course .npz)")
    p.add_argument("--imu-T-cam", dest="imu_T_cam", metavar="FILE", help="with an image directory: 4x4 text imu_T_cam")
    p.add_argument("--draw", metavar="DIR", help="with an image directory: write each frame's tracks as PNG")
    p.add_argument("--out", required=True, help="output directory (refused if non-empty, unless --force)")
    p.add_argument("--gt", help="ground truth TUM file (world_T_imu, the data's stamps) for ATE/RPE")
    p.add_argument("--force", action="store_true", help="write into a non-empty output directory")
    p.add_argument("--quiet", action="store_true", help="no progress bar, no start-up listing")
    _add_filter_options(p)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("check", help="validate a feature file and test its conventions (extrinsic, velocity timing)")
    p.add_argument("data")
    p.set_defaults(func=cmd_check)

    p = sub.add_parser("eval", help="ATE and RPE of a TUM trajectory against ground truth (evo)")
    p.add_argument("estimate")
    p.add_argument("ground_truth")
    p.add_argument("--sim3", action="store_true", help="Sim(3) alignment (default SE(3))")
    p.add_argument("--delta", type=float, default=100.0, help="RPE distance in metres (default 100)")
    p.add_argument("--json", help="write the numbers as JSON")
    p.add_argument("--out", help="directory for eval.json, trajectories.png (aligned) and ate_over_time.png")
    p.add_argument("--force", action="store_true", help="write into a non-empty --out directory")
    p.set_defaults(func=cmd_eval)

    from tools import demo, mc, track

    demo.add_parsers(sub)
    mc.add_parsers(sub)
    track.add_parsers(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "quiet", False):
        from backend import kernels

        kernels.slow_notice = lambda: print("vislam: compiling the filter's kernels (once after an install or an "
                                            "update, ~20 s) ...", file=sys.stderr, flush=True)
    try:
        return args.func(args)
    except VislamError as exc:
        print(f"vislam: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("vislam: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
