"""``vislam run``: the estimator on a feature file, or on stereo images in one pass; every output."""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

from ...backend.config import Config
from ...backend.errors import InputError, VislamError
from .. import console, options, outputs


def add_parser(sub) -> None:
    p = sub.add_parser("run", help="the filter on a feature file (.npz) or stereo images: trajectory, map, summary")
    p.add_argument("data", help="feature + IMU file in the course .npz layout, or a stereo image directory (with --imu)")
    p.add_argument("--imu", help="with an image directory: IMU velocities (CSV t,vx,vy,vz,wx,wy,wz or a course .npz)")
    p.add_argument("--imu-T-cam", dest="imu_T_cam", metavar="FILE", help="with an image directory: 4x4 text imu_T_cam")
    p.add_argument("--draw", metavar="DIR", help="with an image directory: write each frame's tracks as PNG")
    p.add_argument("--out", required=True, help="output directory (refused if non-empty, unless --force)")
    p.add_argument("--gt", help="ground truth TUM file (world_T_imu, the data's stamps) for ATE/RPE")
    p.add_argument("--force", action="store_true", help="write into a non-empty output directory")
    p.add_argument("--quiet", action="store_true", help="no progress bar, no start-up listing")
    options.add_config_options(p)
    options.add_filter_flags(p)
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from ...backend.data.tum import read_tum
    from ..report import format_summary, write_run_outputs

    images = Path(args.data).is_dir()
    if not images and args.imu:
        raise VislamError(f"{args.data}: --imu is for an image directory; a feature file carries its velocities")
    config = options.filter_config(args)
    tracker = options.tracker_config(args) if images else None
    out_dir = outputs.prepare_output_dir(args.out, args.force)
    gt = read_tum(args.gt) if args.gt else None
    say = console.sayer(args.quiet)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # health messages: listed in the summary
        result = _run_images(args, config, tracker, say) if images else _run_file(args, config, say)
    summary = write_run_outputs(result, out_dir, str(args.data), gt, tracker)
    print(format_summary(summary, out_dir))
    return 0


def _run_file(args: argparse.Namespace, config: Config, say):
    from ...backend.data.npz import load_sequence
    from ...backend.run.runner import run_sequence

    t0 = time.perf_counter()
    seq = load_sequence(args.data, image_size=config.input.image_size)  # bad input is refused before any waiting
    load_seconds = time.perf_counter() - t0
    say(f"vislam run {args.data}: {seq.num_steps} steps, {seq.num_observations} observations of "
        f"{seq.num_features} features" + (f"; dropped {seq.dropped}" if any(seq.dropped.values()) else ""))
    say("configuration:\n" + config.describe())
    with console.progress_bar(seq.num_steps, "filter", "step", args.quiet) as progress:
        return run_sequence(seq, config, load_seconds=load_seconds, progress=progress, say=say)


def _run_images(args: argparse.Namespace, config: Config, tracker, say):
    """Tracking and the filter in one pass: each frame goes to the filter as soon as it is tracked;
    the conventions are decided from the first frames (``backend.run.runner.decide_online``)."""
    from ...backend.data.sequence import VISLAM_TRACKER
    from ...backend.geometry.camera import StereoCamera
    from ...backend.run.runner import run_stream
    from ...frontend.images import open_stereo_directory
    from ...frontend.track import check_imu, image_steps

    if not args.imu:
        raise InputError(f"{args.data}: an image directory needs the IMU velocities: --imu FILE (.csv or course .npz)")
    stereo = open_stereo_directory(args.data)  # refuse a bad layout before any work
    imu = check_imu(args.imu, stereo, args.imu_T_cam)
    say("configuration:\n" + config.describe() + "\n" + tracker.describe())
    steps = image_steps(stereo, imu, tracker, args.draw)
    with console.progress_bar(len(stereo), "track+filter", "frame", args.quiet) as progress:
        return run_stream(steps, StereoCamera(stereo.K, stereo.baseline), imu.imu_T_cam, config,
                          imu_velocities=(imu.linear_velocity, imu.angular_velocity), num_steps=len(stereo),
                          tracker=VISLAM_TRACKER, progress=progress, say=say)
