"""``vislam track``: stereo images (KITTI odometry layout) + IMU -> observations in the course .npz layout."""

from __future__ import annotations

import argparse

from .. import console, options


def add_parser(sub) -> None:
    p = sub.add_parser("track", help="stereo images (KITTI odometry layout) + IMU -> observations in the course .npz layout")
    p.add_argument("images", help="directory with image_0/, image_1/, calib.txt, times.txt")
    p.add_argument("--imu", required=True, help="IMU velocities: CSV t,vx,vy,vz,wx,wy,wz or a course .npz (frame i = step i)")
    p.add_argument("--imu-T-cam", dest="imu_T_cam", metavar="FILE", help="4x4 text imu_T_cam (needed with a CSV)")
    p.add_argument("--out", required=True, help="output .npz (refused if it exists, unless --force)")
    p.add_argument("--force", action="store_true")
    p.add_argument("--draw", metavar="DIR", help="write each frame's tracks (left: tails, right: stereo matches) as PNG")
    options.add_config_options(p, "its [tracker] table")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from ...backend.data.files import check_output_file
    from ...backend.data.npz import save_sequence
    from ...frontend.images import open_stereo_directory
    from ...frontend.draw import check_draw_dir
    from ...frontend.track import check_image_size, check_imu, track_directory

    out = check_output_file(args.out, overwrite=args.force)  # refused before any work
    config = options.tracker_config(args, only=True)
    directory = open_stereo_directory(args.images)  # refuse a bad input before any work
    check_image_size(directory, config)
    if args.draw is not None:
        check_draw_dir(args.draw)
    imu = check_imu(args.imu, directory, args.imu_T_cam)
    say = console.sayer(args.quiet)
    for note in imu.notes:
        say(f"note: {note}")
    say("tracker configuration:\n" + config.describe())
    with console.progress_bar(len(directory), "track", "frame", args.quiet) as progress:
        seq = track_directory(directory, imu, config, None, progress, args.draw)
    save_sequence(seq, out)
    per_frame = seq.num_observations / seq.num_steps
    print(f"{seq.num_steps} frames, {seq.num_features} tracks, {seq.num_observations} stereo observations "
          f"({per_frame:.0f} per frame); wrote {out}")
    return 0
