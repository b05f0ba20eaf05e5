"""``vislam track``: stereo images (KITTI odometry layout + IMU, or a KITTI raw drive with its OXTS
velocities) -> observations in the course .npz layout; an EuRoC folder, a ROS bag (with its
calibration), or a raw drive with ``--imu-input inertial``, -> the inertial layout (the IMU's samples)."""

from __future__ import annotations

import argparse

from .. import console, options


def add_parser(sub) -> None:
    p = sub.add_parser("track", help="stereo images (KITTI odometry layout + IMU, or a KITTI raw drive) -> "
                                     "observations in the course .npz layout")
    p.add_argument("images", help="directory with image_0/, image_1/, calib.txt, times.txt; a KITTI raw drive "
                                  "DATE/DATE_drive_NNNN_sync/ (image_00/, image_01/, oxts/; calibration in DATE/); or an "
                                  "EuRoC ASL folder mav0/ or a ROS bag (a ROS 1 .bag or a ROS 2 bag folder, with "
                                  "--calib; both written in the inertial layout: the IMU's samples)")
    p.add_argument("--imu", help="IMU velocities: CSV t,vx,vy,vz,wx,wy,wz or a course .npz (frame i = step i); "
                                 "needed with the odometry layout (a raw drive has its oxts/)")
    p.add_argument("--imu-T-cam", dest="imu_T_cam", metavar="FILE", help="4x4 text imu_T_cam (needed with a CSV)")
    p.add_argument("--imu-input", dest="imu_input", choices=["auto", "velocity", "inertial"], default="auto",
                   help="a KITTI raw drive: write its OXTS velocities vf vl vu turned into the IMU frame by the record's "
                        "roll and pitch, with the rates wx wy wz (auto, velocity: the course layout), or its "
                        "accelerations ax ay az with the rates wx wy wz as a real IMU's samples (inertial: the "
                        "inertial layout). Default: auto")
    p.add_argument("-o", "--out", required=True, help="output .npz (refused if it exists, unless --force)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing --out file and write into a --draw directory holding files")
    p.add_argument("--draw", metavar="DIR", help="write each frame's tracks as PNG (left image on top with track "
                                                 "tails, right image below with the stereo matches)")
    options.add_bag_options(p)
    options.add_config_options(p, "its [tracker] table", example="tracker.target_tracks=500")
    console.add_verbosity_options(p)
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from ...backend.data.files import check_output_file
    from ...frontend.track import open_tracking_input, track_directory

    out = check_output_file(args.out, overwrite=args.force)  # refused before any work
    if args.draw:
        from ...frontend.draw import check_draw_dir

        check_draw_dir(args.draw, replace_files=args.force)
    config = options.tracker_config(args, only=True)
    from ...frontend.euroc import is_euroc

    if options.check_bag_options(args, "images"):
        return _track_bag(args, config, out)
    if is_euroc(args.images):
        return _track_euroc(args, config, out)
    if args.imu_input == "inertial":
        return _track_raw_inertial(args, config, out)
    directory, imu, _ = open_tracking_input(args.images, args.imu, args.imu_T_cam, config, args.draw)
    return _track_and_write(args, config, out, imu.notes, len(directory),
                            lambda progress: track_directory(directory, imu, config, None, progress, args.draw))


def _track_raw_inertial(args: argparse.Namespace, config, out) -> int:
    """A KITTI raw drive -> the inertial layout (its tracks, the OXTS accelerations and rates as the IMU's samples)."""
    from ...frontend.raw_drive import open_inertial_drive
    from ...frontend.track import track_raw_inertial

    drive = open_inertial_drive(args.images, args.imu, args.imu_T_cam)
    return _track_and_write(args, config, out, drive.imu.notes, len(drive.stereo),
                           lambda progress: track_raw_inertial(drive, config, progress, args.draw))


def _track_euroc(args: argparse.Namespace, config, out) -> int:
    """An EuRoC ASL folder -> the inertial layout (rectified pairs' tracks, the IMU's samples)."""
    from ...frontend.euroc import open_euroc_input
    from ...frontend.track import track_euroc

    data = open_euroc_input(args.images, args.imu, args.imu_T_cam, args.imu_input)
    return _track_and_write(args, config, out, data.notes, len(data.frames),
                           lambda progress: track_euroc(data, config, progress, args.draw))


def _track_bag(args: argparse.Namespace, config, out) -> int:
    """A ROS bag -> the inertial layout (rectified pairs' tracks, the IMU topic's samples)."""
    from ...frontend.bag import open_bag
    from ...frontend.track import track_euroc

    data = open_bag(args.images, args.calib, args.imu_calib, args.left_topic, args.right_topic, args.imu_topic)
    return _track_and_write(args, config, out, data.notes, len(data.frames),
                            lambda progress: track_euroc(data, config, progress, args.draw))


def _track_and_write(args: argparse.Namespace, config, out, notes, frames: int, track) -> int:
    """Say the input's notes and the configuration, ``track(progress)`` its ``frames`` into a
    sequence, and write it to ``out`` (the inertial layout when it holds a real IMU's samples)."""
    from ...backend.data.npz import save_sequence

    say = console.sayer(args.quiet)
    for note in notes:
        say(f"note: {note}")
    say(console.configuration_text(args.verbose, config))
    with console.progress_bar(frames, "track", "frame", console.progress_off(args)) as progress:
        seq = track(progress)
    save_sequence(seq, out)
    if not args.quiet:
        counts = (f"{seq.num_steps} frames, {seq.num_features} tracks, {seq.num_observations} stereo observations "
                  f"({seq.num_observations / seq.num_steps:.0f} per frame)")
        print(f"{counts}, {seq.imu.num_samples} IMU samples; wrote {out} (inertial layout)" if seq.inertial
              else f"{counts}; wrote {out}")
    return 0
