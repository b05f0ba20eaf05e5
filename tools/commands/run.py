"""``vislam run``: the estimator on a feature file, or on stereo images in one pass; every output."""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

from ...backend.config import Config
from ...backend.errors import InputError
from .. import console, options


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


#: Free space the outputs of a run need at most (trajectories, map, PLY, plots, summary: a few MB)
OUTPUT_SPACE = 32 * 2**20


def main(args: argparse.Namespace) -> int:
    from ...backend.data.files import output_directory
    from ...backend.data.tum import read_tum
    from ..report import format_summary, write_run_outputs

    images = Path(args.data).is_dir()
    if not images:
        for flag, value in (("--imu", args.imu), ("--imu-T-cam", args.imu_T_cam), ("--draw", args.draw)):
            if value:
                raise InputError(f"{args.data}: {flag} is for an image directory; a feature file carries "
                                 f"its velocities, extrinsic and tracks")
    config = options.filter_config(args)
    tracker = options.tracker_config(args)  # checked with a feature file too: a typo is refused either way
    tracker = tracker if images else None
    gt = (args.gt, *read_tum(args.gt)) if args.gt else None
    say = console.sayer(args.quiet)
    out = Path(args.out)
    with output_directory(args.out, args.force, OUTPUT_SPACE) as staging:  # checked before any work
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # health messages: listed in the summary
            result, notes = (_run_images(args, config, tracker, gt, say) if images
                             else _run_file(args, config, gt, say))
        summary = write_run_outputs(result, staging, str(args.data), gt[1:] if gt else None, tracker, notes)
    print(format_summary(summary, out))
    return 0


def _check_ground_truth(gt, time_stamps) -> None:
    """Refuse, before the run, ground truth whose stamps do not match the data's (naming its file)."""
    if gt is None:
        return
    from ...backend.evaluation.metrics import require_matches

    require_matches(time_stamps, gt[1], gt[0])


def _run_file(args: argparse.Namespace, config: Config, gt, say):
    from ...backend.data.npz import load_sequence
    from ...backend.run.runner import run_sequence

    t0 = time.perf_counter()
    seq = load_sequence(args.data, image_size=config.input.image_size)  # bad input is refused before any waiting
    load_seconds = time.perf_counter() - t0
    _check_ground_truth(gt, seq.time_stamps)
    say(f"vislam run {args.data}: {seq.num_steps} steps, {seq.num_observations} observations of "
        f"{seq.num_features} features" + (f"; dropped {seq.dropped}" if any(seq.dropped.values()) else ""))
    for note in seq.notes:
        say(f"note: {note}")
    say("configuration:\n" + config.describe())
    with console.progress_bar(seq.num_steps, "filter", "step", args.quiet) as progress:
        return run_sequence(seq, config, load_seconds=load_seconds, progress=progress, say=say), list(seq.notes)


def _run_images(args: argparse.Namespace, config: Config, tracker, gt, say):
    """Tracking and the filter in one pass: each frame goes to the filter as soon as it is tracked;
    the conventions are decided from the first frames (``backend.run.runner.decide_online``)."""
    from ...backend.data.sequence import VISLAM_TRACKER
    from ...backend.geometry.camera import StereoCamera
    from ...backend.run.runner import run_stream
    from ...frontend.images import open_stereo_directory
    from ...frontend.draw import check_draw_dir
    from ...frontend.track import check_image_size, check_imu, image_steps

    if not args.imu:
        raise InputError(f"{args.data}: an image directory needs the IMU velocities: --imu FILE (.csv or course .npz)")
    stereo = open_stereo_directory(args.data)  # refuse a bad input before any work
    check_image_size(stereo, tracker)
    if args.draw is not None:
        check_draw_dir(args.draw)
    imu = check_imu(args.imu, stereo, args.imu_T_cam)
    _check_ground_truth(gt, imu.time_stamps)
    notes = list(imu.notes)
    for note in notes:
        say(f"note: {note}")
    say("configuration:\n" + config.describe() + "\n" + tracker.describe())
    steps = image_steps(stereo, imu, tracker, args.draw)
    with console.progress_bar(len(stereo), "track+filter", "frame", args.quiet) as progress:
        return run_stream(steps, StereoCamera(stereo.K, stereo.baseline), imu.imu_T_cam, config,
                          imu_velocities=(imu.linear_velocity, imu.angular_velocity), num_steps=len(stereo),
                          tracker=VISLAM_TRACKER, progress=progress, say=say), notes
