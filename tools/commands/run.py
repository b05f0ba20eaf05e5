"""``vislam run``: the estimator on a feature file, or on stereo images (an odometry-layout directory
or a KITTI raw drive) in one pass; every output."""

from __future__ import annotations

import argparse
import contextlib
import os
import time
import warnings
from pathlib import Path

from ...backend.config import Config
from ...backend.errors import ConfigError, HealthWarning, InputError
from .. import console, options


def add_parser(sub) -> None:
    p = sub.add_parser("run", help="the filter on a feature file (.npz) or stereo images: trajectory, map, summary")
    p.add_argument("data", help="feature + IMU file in the course .npz layout (IMU velocities or a real IMU's samples), "
                               "a stereo image directory (with --imu), a KITTI raw drive (..._sync/: IMU and ground "
                               "truth from its oxts/) or an EuRoC ASL folder (mav0/: raw stereo pairs, rectified, the "
                               "IMU's samples, ground truth from state_groundtruth_estimate0/) or a ROS bag (a ROS 1 "
                               ".bag or a ROS 2 bag folder, with --calib: its stereo images and IMU topics)")
    p.add_argument("--imu", help="with an odometry-layout image directory: IMU velocities (CSV t,vx,vy,vz,wx,wy,wz "
                                 "or a course .npz)")
    p.add_argument("--imu-T-cam", dest="imu_T_cam", metavar="FILE", help="with an image directory: 4x4 text imu_T_cam")
    p.add_argument("--imu-input", dest="imu_input", choices=["auto", "velocity", "inertial"], default="auto",
                   help="which IMU input to use: a feature file with both (velocities and a real IMU's samples) needs "
                        "one; a KITTI raw drive runs on its OXTS velocities vf vl vu in the IMU frame (by the record's "
                        "roll and pitch) with the rates wx wy wz (auto, velocity) or on its accelerations ax ay az "
                        "with the rates wx wy wz as a real IMU (inertial). Default: auto, the one input the data has")
    p.add_argument("--draw", metavar="DIR", help="with an image directory: write each frame's tracks as PNG "
                                                 "(left image on top with track tails, right image below with the stereo matches)")
    p.add_argument("-o", "--out", required=True, help="output directory (refused if non-empty, unless --force)")
    p.add_argument("--gt", help="ground truth TUM file (world_T_imu, the data's stamps) for ATE/RPE "
                                "(a KITTI raw drive's default: its OXTS poses)")
    p.add_argument("--force", action="store_true",
                   help="write into a non-empty output directory, replace an existing --rerun file and write into "
                        "a --draw directory holding files")
    p.add_argument("--format", choices=["tum", "kitti"], default="tum",
                   help="kitti: also write trajectory_kitti.txt and dead_reckoning_kitti.txt (the left camera's "
                        "pose in its first frame, 12 numbers a line, KITTI odometry poses format)")
    p.add_argument("--rerun", metavar="FILE.rrd", help="also record the run for the Rerun viewer (rerun FILE.rrd): "
                   "pose, trajectory, landmarks with their uncertainty; from images each frame and its tracks "
                   "(pip install 'vislam[viewer]')")
    p.add_argument("--rerun-live", dest="rerun_live", action="store_true",
                   help="stream the same to a Rerun viewer while the run goes (one is started if none is running)")
    console.add_verbosity_options(p)
    options.add_bag_options(p)
    p.add_argument("--gt-topic", dest="gt_topic", metavar="TOPIC",
                   help="a ROS bag's ground truth: a geometry_msgs/PoseStamped, PoseWithCovarianceStamped, "
                        "TransformStamped or nav_msgs/Odometry topic (its frame's poses taken as the IMU's; or --gt, "
                        "a TUM file); written as ground_truth.txt")
    options.add_config_options(p)
    options.add_filter_flags(p)
    p.set_defaults(func=main)


#: The OXTS poses of a KITTI raw drive, written next to the outputs (TUM)
GROUND_TRUTH = "ground_truth.txt"

#: Free space the outputs of a run need at most (trajectories, map, PLY, plots, summary: a few MB)
OUTPUT_SPACE = 32 * 2**20


def _is_euroc(path) -> bool:
    """``frontend.euroc.is_euroc``, imported only for a directory (a feature file's run need not)."""
    from ...frontend.euroc import is_euroc

    return is_euroc(path)


def main(args: argparse.Namespace) -> int:
    from ...backend.data.files import output_directory
    from ...backend.data.tum import read_tum, write_tum
    from ..output_process import output_process
    from ..report import format_summary, print_health, write_run_outputs

    bag = options.check_bag_options(args, "data")
    images = Path(args.data).is_dir() or bag
    if not images:
        for flag, value in (("--imu", args.imu), ("--imu-T-cam", args.imu_T_cam), ("--draw", args.draw)):
            if value:
                raise InputError(f"{args.data}: {flag} is for an image directory; a feature file carries "
                                 f"its velocities, extrinsic and tracks")
    config = options.filter_config(args)
    tracker = options.tracker_config(args)  # checked with a feature file too: a typo is refused either way
    tracker = tracker if images else None
    gt = (args.gt, *read_tum(args.gt)) if args.gt else None
    _check_extra_outputs(args)
    say = console.sayer(args.quiet)
    out = Path(args.out)
    # the recording is moved into place after the outputs, and written whole before them (finish_writing)
    # the helper that writes the figures and point clouds ends before the staging directory is removed
    with _recorder(args) as recorder, output_directory(args.out, args.force, OUTPUT_SPACE) as staging, \
            output_process() as helper:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", HealthWarning)  # listed in the summary, shown by print_health
            drive = euroc_truth = None
            if bag:
                (result, notes), gt, euroc_truth = _run_bag(args, config, tracker, gt, say, recorder)
            elif images and _is_euroc(args.data):
                (result, notes), gt, euroc_truth = _run_euroc(args, config, tracker, gt, say, recorder)
            elif images and args.imu_input == "inertial":
                (result, notes), gt, drive = _run_raw_inertial(args, config, tracker, gt, say, recorder)
            elif images:
                (result, notes), gt, drive = _run_images(args, config, tracker, gt, say, recorder)
            else:
                result, notes = _run_file(args, config, gt, say, recorder)
        if recorder is not None:
            recorder.log_result(result, gt[2] if gt else None)
        if euroc_truth is not None:
            write_tum(staging / GROUND_TRUTH, euroc_truth.times, euroc_truth.world_T_imu,
                      header=f"world_T_imu from {euroc_truth.source}" + ("" if bag else " (EuRoC ground truth of the "
                                                                                       "body = IMU frame)"))
        if drive is not None and result.inertial:
            write_tum(staging / GROUND_TRUTH, *drive.level_ground_truth[1:],
                      header=f"world_T_imu from the OXTS records of {drive.stereo.root} (KITTI devkit "
                             "convertOxtsToPose; world = the first frame's position, z up, x along its heading)")
        elif drive is not None:
            write_tum(staging / GROUND_TRUTH, drive.imu.time_stamps, drive.world_T_imu,
                      header=f"world_T_imu from the OXTS records of {drive.stereo.root} (KITTI devkit "
                             "convertOxtsToPose; world = the IMU frame at the first frame)")
        summary = write_run_outputs(result, staging, str(args.data), gt[1:] if gt else None, tracker, notes, helper)
        if args.format == "kitti":
            from ...backend.data.tum import write_kitti_poses

            for name, poses in (("trajectory", result.world_T_imu), ("dead_reckoning", result.dead_reckoning)):
                write_kitti_poses(staging / f"{name}_kitti.txt", poses, result.decisions.imu_T_cam)
        if recorder is not None:
            recorder.finish_writing()
    if not args.quiet:
        print(format_summary(summary, out))
    print_health(summary)  # with --quiet too: nothing but errors and the warnings that say the result is not what was asked for
    return 0


def _drive_truth(truth, notes: list[str], what: str):
    """A drive's own ground truth (source, stamps, poses), or None with a note when it has too few
    poses to evaluate a trajectory against (the run goes on: nobody asked for the evaluation)."""
    from ...backend.evaluation.metrics import MIN_MATCHES

    if len(truth[1]) < MIN_MATCHES:
        notes.append(f"ground truth: not evaluated ({truth[0]} holds {len(truth[1])} poses; an evaluation needs "
                     f"{MIN_MATCHES})")
        return None
    notes.append(f"ground truth: {what}")
    return truth


def _check_ground_truth(gt, time_stamps) -> None:
    """Refuse, before the run, ground truth whose stamps do not match the data's (naming its file)."""
    if gt is None:
        return
    from ...backend.evaluation.metrics import require_matches

    require_matches(time_stamps, gt[1], gt[0])


def _check_extra_outputs(args: argparse.Namespace) -> None:
    """Before any work: ``--rerun`` and ``--draw`` are not ``--out``, not an input, and replace an
    existing file (or write into a folder holding files) only with ``--force``."""
    from ...backend.data.files import check_output_file
    from ...frontend.draw import check_draw_dir

    out = os.path.realpath(args.out)
    for flag, value in (("--rerun", args.rerun), ("--draw", args.draw)):
        if value and os.path.realpath(value) == out:
            raise ConfigError(f"{value}: {flag} names the output directory --out; give it a path of its own")
    if args.rerun:
        check_output_file(args.rerun, overwrite=args.force)
    if args.draw:
        check_draw_dir(args.draw, replace_files=args.force)


def _recorder(args: argparse.Namespace):
    """The --rerun recorder (tools.viewer), or an empty context."""
    if not (args.rerun or args.rerun_live):
        return contextlib.nullcontext()
    from ..viewer import RerunRecorder

    return RerunRecorder(args.rerun, spawn=args.rerun_live)


def _run_file(args: argparse.Namespace, config: Config, gt, say, recorder=None):
    from ...backend.data.npz import load_sequence

    t0 = time.perf_counter()
    seq = load_sequence(args.data, image_size=config.input.image_size, imu=args.imu_input)  # refused before any waiting
    load_seconds = time.perf_counter() - t0
    _check_ground_truth(gt, seq.time_stamps)
    say(f"vislam run {args.data}: {seq.num_steps} steps, {seq.num_observations} observations of "
        f"{seq.num_features} features" + (f"; {seq.dropped_text()}" if seq.dropped_text() else ""))
    for note in seq.notes:
        say(f"note: {note}")
    say(console.configuration_text(args.verbose, config))
    return _filter(args, seq, config, load_seconds, say, recorder), list(seq.notes)


def _run_euroc(args: argparse.Namespace, config: Config, tracker, gt, say, recorder=None):
    """An EuRoC ASL folder: every pair rectified and tracked (``frontend.track.track_euroc``), then the
    filter with the inertial state over the sequence. Returns ((result, notes), ground truth, the
    folder's ground truth or None): without ``--gt`` its state_groundtruth_estimate0 is the ground truth."""
    from ...frontend.euroc import open_euroc_input

    t0 = time.perf_counter()
    data = open_euroc_input(args.data, args.imu, args.imu_T_cam, args.imu_input)
    return _run_rig(args, data, "EuRoC", config, tracker, gt, say, recorder, t0)


def _run_bag(args: argparse.Namespace, config: Config, tracker, gt, say, recorder=None):
    """A ROS bag with its calibration (``frontend.bag.open_bag``): as an EuRoC folder, the pairs
    rectified and tracked, then the inertial filter; ground truth from ``--gt`` or ``--gt-topic``."""
    from ...frontend.bag import open_bag

    t0 = time.perf_counter()
    if gt is not None and args.gt_topic is not None:
        raise ConfigError(f"--gt {args.gt} and --gt-topic {args.gt_topic}: give one ground truth")
    data = open_bag(args.data, args.calib, args.imu_calib, args.left_topic, args.right_topic, args.imu_topic,
                    args.gt_topic)
    kind = f"ROS bag (topics {data.topics.left}, {data.topics.right}, {data.topics.imu})"
    return _run_rig(args, data, kind, config, tracker, gt, say, recorder, t0)


def _run_rig(args: argparse.Namespace, data, kind: str, config: Config, tracker, gt, say, recorder, t0: float):
    """A rectified stereo pair on a real IMU (``frontend.euroc.RectifiedRig``: an EuRoC folder or a
    bag) tracked and filtered; ((result, notes), ground truth, the input's own ground truth or None)."""
    from ...frontend.track import track_euroc

    truth = data.ground_truth if gt is None else None
    if truth is not None:
        gt = (truth.source, truth.times, truth.world_T_imu)
    notes = list(data.notes)
    say(f"vislam run {args.data}: {kind}, {len(data.frames)} stereo pairs ({data.rectification.size[0]}x"
        f"{data.rectification.size[1]}, rectified: fx {data.K[0, 0]:.1f} px, baseline {data.baseline:.4f} m), "
        f"{data.imu.samples.num_samples} IMU samples at {data.imu.samples.rate_hz:.0f} Hz"
        + (f"; ground truth {truth.source}" if truth is not None else ""))
    _check_ground_truth(gt, data.frames.times)  # before the tracking, as every input
    for note in notes:
        say(f"note: {note}")
    say(console.configuration_text(args.verbose, config))
    with console.progress_bar(len(data.frames), "track", "frame", console.progress_off(args)) as progress:
        seq = track_euroc(data, tracker, progress, args.draw)
    return (_filter(args, seq, config, time.perf_counter() - t0, say, recorder), notes), gt, truth


def _filter(args: argparse.Namespace, seq, config: Config, load_seconds: float, say, recorder=None):
    """The filter over a whole sequence (a feature file, or tracked from an EuRoC folder or a raw drive's
    inertial input), with its progress bar and the recorder's time stamps."""
    from ...backend.run.runner import run_sequence

    if recorder is not None:
        recorder.time_stamps = seq.time_stamps
    with console.progress_bar(seq.num_steps, "filter", "step", console.progress_off(args)) as progress:
        return run_sequence(seq, config, load_seconds=load_seconds, progress=progress, say=say,
                            observer=None if recorder is None else recorder.observer)


def _run_raw_inertial(args: argparse.Namespace, config: Config, tracker, gt, say, recorder=None):
    """A KITTI raw drive with ``--imu-input inertial``: every frame tracked
    (``frontend.track.track_raw_inertial``), then the filter with the inertial state, the OXTS
    accelerations and rates as the IMU's samples. Returns ((result, notes), ground truth, the drive):
    without ``--gt`` its OXTS poses in a gravity-aligned world."""
    from ...frontend.raw_drive import open_inertial_drive
    from ...frontend.track import track_raw_inertial

    t0 = time.perf_counter()
    drive = open_inertial_drive(args.data, args.imu, args.imu_T_cam)
    notes = list(drive.imu.notes)
    if gt is None:
        gt = _drive_truth(drive.level_ground_truth, notes, f"the OXTS poses of {drive.ground_truth_source} in a "
                                                           f"gravity-aligned world ({GROUND_TRUTH})")
    _check_ground_truth(gt, drive.imu.time_stamps)
    say(f"vislam run {args.data}: KITTI raw drive, {len(drive.stereo)} stereo pairs, the OXTS accelerations "
        "ax ay az and rates wx wy wz as the IMU's samples (one a frame)")
    for note in notes:
        say(f"note: {note}")
    say(console.configuration_text(args.verbose, config, tracker))
    with console.progress_bar(len(drive.stereo), "track", "frame", console.progress_off(args)) as progress:
        seq = track_raw_inertial(drive, tracker, progress, args.draw)
    return (_filter(args, seq, config, time.perf_counter() - t0, say, recorder), notes), gt, drive


def _run_images(args: argparse.Namespace, config: Config, tracker, gt, say, recorder=None):
    """Tracking and the filter in one pass: each frame goes to the filter as soon as it is tracked;
    the conventions are decided from the first frames (``backend.run.runner.decide_online``).
    Returns ((result, notes), ground truth, the raw drive or None): a KITTI raw drive brings its IMU
    velocities and, without ``--gt``, its OXTS poses as the ground truth."""
    from ...backend.data.sequence import VISLAM_TRACKER
    from ...backend.geometry.camera import StereoCamera
    from ...backend.run.runner import run_stream
    from ...frontend.track import image_steps, open_tracking_input

    stereo, imu, drive = open_tracking_input(args.data, args.imu, args.imu_T_cam, tracker, args.draw)
    notes = list(imu.notes)
    if gt is None and drive is not None:
        gt = _drive_truth(drive.ground_truth, notes, f"the OXTS poses of {drive.ground_truth_source} ({GROUND_TRUTH})")
    _check_ground_truth(gt, imu.time_stamps)
    w, h = stereo.image_size
    kind = "KITTI raw drive" if drive is not None else "image directory"
    velocities = (f"the OXTS velocities of {drive.ground_truth_source}" if drive is not None
                  else f"IMU velocities of {imu.source}")
    say(f"vislam run {args.data}: {kind}, {len(stereo)} stereo pairs of {w}x{h} px over "
        f"{imu.time_stamps[-1] - imu.time_stamps[0]:.1f} s, {velocities}; tracked and filtered in one pass")
    for note in notes:
        say(f"note: {note}")
    say(console.configuration_text(args.verbose, config, tracker))
    if recorder is not None:
        recorder.time_stamps = imu.time_stamps
    steps = image_steps(stereo, imu, tracker, args.draw, on_frame=None if recorder is None else recorder.log_frame)
    with console.progress_bar(len(stereo), "track+filter", "frame", console.progress_off(args)) as progress:
        result = run_stream(steps, StereoCamera(stereo.K, stereo.baseline), imu.imu_T_cam, config,
                            imu_velocities=(imu.linear_velocity, imu.angular_velocity), num_steps=len(stereo),
                            tracker=VISLAM_TRACKER, source=str(args.data), progress=progress, say=say,
                            observer=None if recorder is None else recorder.observer)
    return (result, notes), gt, drive
