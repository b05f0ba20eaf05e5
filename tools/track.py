"""`vislam track IMAGES_DIR --imu IMU --out DATA.npz`: stereo images -> course-layout observations,
and the image input of `vislam run IMAGES_DIR --imu IMU` (thin over frontend/)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from backend.errors import InputError


def tracker_config(args: argparse.Namespace, assignments: list[str]):
    """TrackerConfig: defaults < [tracker] table of --config < tracker keys of --set."""
    from frontend.config import TrackerConfig, apply_tracker_overrides, load_tracker_config

    config = load_tracker_config(args.config) if getattr(args, "config", None) else TrackerConfig()
    return apply_tracker_overrides(config, assignments)


def track_images(args: argparse.Namespace, assignments: list[str], quiet: bool = False):
    """Track ``args.images`` (or ``args.data``, a directory) with the IMU of ``args.imu``: a Sequence."""
    from frontend.images import open_stereo_directory
    from frontend.track import track_directory

    images = getattr(args, "images", None) or args.data
    if not args.imu:
        raise InputError(f"{images}: an image directory needs the IMU velocities: --imu FILE (.csv or course .npz)")
    config = tracker_config(args, assignments)
    directory = open_stereo_directory(images)  # refuse a bad layout before any work
    say = (lambda *a: None) if quiet else (lambda *a: print(*a, file=sys.stderr))
    say("tracker configuration:\n" + config.describe())
    bar = None
    progress = None
    if not quiet:
        from tqdm import tqdm

        bar = tqdm(unit="frame", file=sys.stderr, desc="track")

        def progress(k: int, n: int) -> None:
            bar.total = n
            bar.update(1)

    try:
        seq = track_directory(directory, args.imu, config, getattr(args, "imu_T_cam", None), progress,
                              getattr(args, "draw", None))
    finally:
        if bar is not None:
            bar.close()
    return seq


def cmd_track(args: argparse.Namespace) -> int:
    from backend.sequence import save_sequence

    out = Path(args.out)
    if out.exists() and not args.force:
        raise InputError(f"{out}: exists; refusing to overwrite it (use --force)")
    if not out.parent.is_dir():
        raise InputError(f"{out.parent}: output directory does not exist")
    seq = track_images(args, list(args.set or []), args.quiet)
    save_sequence(seq, out)
    per_frame = seq.num_observations / seq.num_steps
    print(f"{seq.num_steps} frames, {seq.num_features} tracks, {seq.num_observations} stereo observations "
          f"({per_frame:.0f} per frame); wrote {out}")
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("track", help="stereo images (KITTI odometry layout) + IMU -> observations in the course .npz layout")
    p.add_argument("images", help="directory with image_0/, image_1/, calib.txt, times.txt")
    p.add_argument("--imu", required=True, help="IMU velocities: CSV t,vx,vy,vz,wx,wy,wz or a course .npz (frame i = step i)")
    p.add_argument("--imu-T-cam", dest="imu_T_cam", metavar="FILE", help="4x4 text imu_T_cam (needed with a CSV)")
    p.add_argument("--out", required=True, help="output .npz (refused if it exists, unless --force)")
    p.add_argument("--force", action="store_true")
    p.add_argument("--draw", metavar="DIR", help="write each frame's tracks (left: tails, right: stereo matches) as PNG")
    p.add_argument("--config", metavar="TOML", help="[tracker] table of a configuration file")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override one tracker config key (repeatable)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_track)
