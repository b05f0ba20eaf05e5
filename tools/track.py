"""`vislam track IMAGES_DIR --imu IMU --out DATA.npz`: stereo images -> course-layout observations,
and `vislam run IMAGES_DIR --imu IMU`: tracking and the filter in one pass, frame by frame
(thin over frontend/ and backend.pipeline.OnlineRun)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

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


def decisive(errors_px: dict, margin: float = 1.1) -> bool:
    """True when the convention test has nothing to choose (one variant) or its best variant fits at
    least ``margin`` times better than every other."""
    finite = sorted(v for v in errors_px.values() if np.isfinite(v))
    return len(errors_px) <= 1 or (len(finite) >= 2 and finite[1] >= margin * finite[0])


def run_images(args: argparse.Namespace, tracker_set: list[str], config, quiet: bool = False):
    """`vislam run IMAGES --imu IMU` in one pass: each frame is tracked and handed to the filter at once.

    The convention test (extrinsic flip, velocity timing) needs tracks, so the first frames are
    tracked and tested (backend.conventions) from 20 frames on, every 10 frames, until the test
    is :func:`decisive` or ``config.online_convention_steps`` frames are in; those frames then go
    to the filter, and every later frame as soon as it is tracked. The IMU
    noise comes from the whole IMU file. Returns the :class:`backend.pipeline.RunResult`.
    """
    import time

    from backend import kernels
    from backend.camera import StereoCamera
    from backend.conventions import decide_conventions
    from backend.pipeline import OnlineRun, imu_noise
    from backend.sequence import VISLAM_TRACKER
    from frontend.images import open_stereo_directory
    from frontend.track import check_imu, iter_tracks, tracks_to_sequence
    from frontend.tracker import StereoTracker
    from threadpoolctl import threadpool_limits

    images = args.data
    if not args.imu:
        raise InputError(f"{images}: an image directory needs the IMU velocities: --imu FILE (.csv or course .npz)")
    tracker_config_ = tracker_config(args, tracker_set)
    stereo = open_stereo_directory(images)  # refuse a bad layout before any work
    imu = check_imu(args.imu, stereo, getattr(args, "imu_T_cam", None))
    kernels.warm_up()  # before the convention test calls one; reported apart, as imports
    say = (lambda *a: None) if quiet else (lambda *a: print(*a, file=sys.stderr))
    say("tracker configuration:\n" + tracker_config_.describe())
    n = len(stereo)
    bar = None
    if not quiet:
        from tqdm import tqdm

        bar = tqdm(total=n, unit="frame", file=sys.stderr, desc="track+filter")
    tracker = StereoTracker(tracker_config_, stereo.K, stereo.baseline)
    frames = iter_tracks(stereo, tracker_config_, getattr(args, "draw", None), tracker)
    warm_ids, warm_pixels = [], []
    setup = 0.0
    run = None
    try:
        with threadpool_limits(limits=config.blas_threads):
            for index, ids, pixels in frames:
                if run is None:
                    warm_ids.append(ids)
                    warm_pixels.append(pixels)
                    k = len(warm_ids)
                    last = k >= min(config.online_convention_steps, n)
                    if not last and (k < 20 or k % 10):
                        continue
                    t0 = time.perf_counter()
                    warm = tracks_to_sequence(stereo, imu, warm_ids, warm_pixels, tracker.num_ids)
                    conventions = decide_conventions(warm, config.imu_flip, config.velocity_index, config.convention_horizon)
                    setup += time.perf_counter() - t0
                    if not last and not decisive(conventions.errors_px):
                        continue
                    t0 = time.perf_counter()
                    noise = imu_noise(config, imu.linear_velocity, imu.angular_velocity,
                                      warm.num_observations / warm.num_steps)
                    setup += time.perf_counter() - t0
                    say(f"conventions from the first {warm.num_steps} frames: " + conventions.describe())
                    say(noise.describe())
                    run = OnlineRun(StereoCamera(stereo.K, stereo.baseline), conventions, noise, config,
                                    tracker=VISLAM_TRACKER)
                    say(run.stats.track_drift)
                    for k in range(warm.num_steps):
                        run.step(imu.time_stamps[k], imu.linear_velocity[k], imu.angular_velocity[k], *warm.observations(k))
                        if bar is not None:
                            bar.update(1)
                    warm_ids = warm_pixels = None
                    continue
                run.step(imu.time_stamps[index], imu.linear_velocity[index], imu.angular_velocity[index], ids, pixels)
                if bar is not None:
                    bar.update(1)
            if run is None:
                raise InputError(f"{images}: no frames")
            return run.result(setup)
    finally:
        if bar is not None:
            bar.close()


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
