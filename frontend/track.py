"""Track a KITTI-layout image directory (odometry layout or a raw drive,
:func:`~vislam.frontend.raw_drive.open_images`) into the course sequence layout (what `vislam track` does).

:func:`track_directory` runs :class:`~vislam.frontend.tracker.StereoTracker` over every frame and
returns a :class:`~vislam.backend.data.sequence.Sequence`: time stamps, velocities and the camera
mount from the IMU source (:mod:`~vislam.frontend.imu_input`; frame i = IMU row/step i), K and
baseline from ``calib.txt``, observations per frame, ``num_features`` = number of ids issued.
:func:`iter_tracks` is the online form: it yields each frame's tracks as soon as they exist, and
:func:`image_steps` pairs them with the IMU sample of their frame, the steps
``backend.run.runner.run_stream`` takes (``vislam run IMAGES`` in one pass).
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np

from ..backend.errors import InputError
from ..backend.data.sequence import VISLAM_TRACKER, Sequence, check_baseline, check_camera_matrix, check_time_stamps
from .config import TrackerConfig
from .draw import TrackDrawer, check_draw_dir
from .images import StereoDirectory, open_stereo_directory  # noqa: F401 (imported from here by benchmarks/)
from .imu_input import ImuVelocities, read_imu
from .raw_drive import open_images
from .tracker import StereoTracker

__all__ = ["track_directory", "iter_tracks", "image_steps", "check_imu", "check_image_size", "tracks_to_sequence",
           "opencv_threads"]


@contextmanager
def opencv_threads(n: int):
    """Run the block with ``cv2.setNumThreads(n)`` (0: leave OpenCV's default), then restore."""
    before = cv2.getNumThreads()
    if n:
        cv2.setNumThreads(int(n))
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def _stereo(images_dir) -> StereoDirectory:
    return images_dir if isinstance(images_dir, StereoDirectory) else open_images(images_dir)[0]


def check_image_size(stereo: StereoDirectory, config: TrackerConfig) -> None:
    """InputError naming the directory and the size when its images are smaller than the
    tracker can work in (:attr:`~frontend.config.TrackerConfig.min_image_side`)."""
    w, h = stereo.image_size
    need = config.min_image_side
    if min(w, h) < need:
        raise InputError(
            f"{stereo.root}: images {w}x{h} px are too small to track: each side needs at least {need} px "
            f"(tracker.lk_window {config.lk_window}, tracker.affine_window {config.affine_window}, "
            f"tracker.border_px {config.border_px}, tracker.subpix_window {config.subpix_window})"
        )


def iter_tracks(images_dir, config: TrackerConfig | None = None, draw_dir=None,
                tracker: StereoTracker | None = None, on_frame: Callable | None = None) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """Yield ``(frame index, ids (n,) int64 increasing, pixels (n,4) uL vL uR vR)`` per frame of a
    KITTI-layout directory (path or :class:`~frontend.images.StereoDirectory`), frame by frame; a
    frame without trackable texture yields ids (0,) and pixels (0,4).
    ``draw_dir``: write a debug picture per frame there (:class:`~frontend.draw.TrackDrawer`);
    ``tracker``: a tracker to use (its ``num_ids`` tells how many ids were issued).
    The image size (:func:`check_image_size`) and ``draw_dir`` are checked on the call, before
    the first frame is read; InputError if either is unusable."""
    stereo = _stereo(images_dir)
    config = config if config is not None else TrackerConfig()
    check_image_size(stereo, config)
    tracker = tracker if tracker is not None else StereoTracker(config, stereo.K, stereo.baseline)
    drawer = TrackDrawer(draw_dir) if draw_dir is not None else None
    return _tracked_frames(stereo.frames(), config, tracker, drawer, on_frame)


def _tracked_frames(frames: Iterator, config: TrackerConfig, tracker: StereoTracker,
                    drawer: TrackDrawer | None, on_frame: Callable | None = None) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """The frame loop of :func:`iter_tracks` and :func:`track_euroc` over (index, left, right) ``frames``
    (its inputs already checked)."""
    with opencv_threads(config.threads):
        for index, left, right in frames:
            ids, pixels = tracker.step(left, right)
            if drawer is not None:
                drawer.draw(index, left, right, ids, pixels)
            if on_frame is not None:  # e.g. a viewer recording: the decoded images, not read again
                on_frame(index, left, right, ids, pixels)
            yield index, ids, pixels


def image_steps(stereo: StereoDirectory, imu: ImuVelocities, config: TrackerConfig | None = None,
                draw_dir=None, on_frame: Callable | None = None) -> Iterator[tuple]:
    """Yield ``(t, linear velocity (3,), angular velocity (3,), ids (n,), pixels (n,4))`` per frame:
    the IMU sample of the frame (:func:`check_imu`) and its tracks, as soon as they exist. The
    image size and ``draw_dir`` are checked on the call (:func:`iter_tracks`); ``on_frame(index,
    left, right, ids, pixels)`` is called with each tracked frame."""
    frames = iter_tracks(stereo, config, draw_dir, on_frame=on_frame)
    return ((imu.time_stamps[index], imu.linear_velocity[index], imu.angular_velocity[index], ids, pixels)
            for index, ids, pixels in frames)


def check_imu(imu, stereo: StereoDirectory, imu_T_cam_path=None) -> ImuVelocities:
    """The IMU samples of ``stereo``'s frames (path or :class:`~frontend.imu_input.ImuVelocities`):
    one row per frame and a camera extrinsic, else InputError."""
    n = len(stereo)
    if not isinstance(imu, ImuVelocities):
        imu = read_imu(imu, n, imu_T_cam_path)
    if len(imu) != n:
        raise InputError(f"{imu.source or 'IMU'}: {len(imu)} IMU samples for {n} image frames of {stereo.root}")
    if imu.imu_T_cam is None:
        raise InputError(f"{imu.source or 'IMU'}: no camera extrinsic imu_T_cam (give --imu-T-cam FILE)")
    return imu


def tracks_to_sequence(stereo: StereoDirectory, imu: ImuVelocities, ids: list, pixels: list, num_ids: int) -> Sequence:
    """The course-layout sequence of the first ``len(ids)`` frames: per-frame ids and pixels, the IMU
    rows of those frames, K and baseline from ``calib.txt``; validated."""
    n = len(ids)
    return Sequence.from_steps(imu.time_stamps[:n], imu.linear_velocity[:n], imu.angular_velocity[:n], ids, pixels,
                               stereo.K, stereo.baseline, imu.imu_T_cam, num_features=num_ids,
                               source=str(Path(stereo.root)), layout=imu.layout, tracker=VISLAM_TRACKER)


def track_directory(
    images_dir,
    imu,
    config: TrackerConfig | None = None,
    imu_T_cam_path=None,
    progress: Callable[[int, int], None] | None = None,
    draw_dir=None,
) -> Sequence:
    """Track every frame of ``images_dir`` and return the sequence in the course layout.

    ``imu``: an :class:`~frontend.imu_input.ImuVelocities` with one row per frame, or the path of
    an IMU CSV / course .npz; ``imu_T_cam_path`` (``--imu-T-cam``): a 4x4 text extrinsic, needed
    with a CSV, overriding an .npz's. ``progress``:
    optional callable(frame_index, n_frames). ``draw_dir``: write a debug picture per frame there
    (:class:`~frontend.draw.TrackDrawer`). Raises InputError on unusable input (images too small to
    track, a ``draw_dir`` that cannot be a directory, the IMU) before the first frame is tracked.
    """
    stereo = _stereo(images_dir)
    config = config if config is not None else TrackerConfig()
    check_image_size(stereo, config)
    if draw_dir is not None:
        check_draw_dir(draw_dir)
    imu = check_imu(imu, stereo, imu_T_cam_path)
    tracker = StereoTracker(config, stereo.K, stereo.baseline)
    all_ids, all_pixels = [], []
    for index, ids, pixels in iter_tracks(stereo, config, draw_dir, tracker):
        all_ids.append(ids)
        all_pixels.append(pixels)
        if progress is not None:
            progress(index, len(stereo))
    return tracks_to_sequence(stereo, imu, all_ids, all_pixels, tracker.num_ids)


def open_tracking_input(images, imu=None, imu_T_cam_path=None, config: TrackerConfig | None = None, draw_dir=None):
    """(stereo directory, IMU samples per frame, the KITTI raw drive or None) of an image input,
    every check done before the first frame is tracked: an odometry-layout directory needs ``imu``
    (a path or :class:`~frontend.imu_input.ImuVelocities`), a raw drive carries its own; the image
    size against ``config``; ``draw_dir``. InputError (one line) otherwise."""
    from .raw_drive import drive_imu, is_raw_drive, open_images

    if not imu and not is_raw_drive(images):
        raise InputError(f"{images}: an odometry-layout image directory needs the IMU velocities: --imu FILE "
                         "(.csv or course .npz); a KITTI raw drive (image_00/, oxts/) carries its own")
    stereo, drive = open_images(images)
    check_image_size(stereo, config if config is not None else TrackerConfig())
    if draw_dir is not None:
        check_draw_dir(draw_dir)
    velocities = drive_imu(drive, imu, imu_T_cam_path) if drive is not None else check_imu(imu, stereo, imu_T_cam_path)
    _check_stream(stereo, velocities, drive is not None)
    return stereo, velocities, drive


def _check_stream(stereo: StereoDirectory, imu: ImuVelocities, raw: bool) -> None:
    """What the sequence of the tracks would refuse (``backend.data.sequence``), checked before the
    first frame is tracked, naming the file it comes from: the frames' time stamps (seconds,
    strictly increasing, no gap dead reckoning cannot bridge) and the rectified camera."""
    stamps = (str(Path(stereo.root) / "image_00" / "timestamps.txt"), "stamps") if raw else (imu.source or "IMU", "t")
    check_time_stamps(*stamps, np.asarray(imu.time_stamps, dtype=float))
    calibration = str(Path(stereo.root).parent / "calib_cam_to_cam.txt") if raw else str(Path(stereo.root) / "calib.txt")
    check_camera_matrix(calibration, "K", np.asarray(stereo.K, dtype=float))
    check_baseline(calibration, "baseline", float(stereo.baseline))



def track_euroc(data, config: TrackerConfig | None = None, progress: Callable[[int, int], None] | None = None,
                draw_dir=None) -> Sequence:
    """Track every stereo pair of an EuRoC ASL folder (path or :class:`~frontend.euroc.EurocDataset`)
    or a ROS bag (:class:`~frontend.bag.BagDataset`), rectified (``frontend.euroc.StereoRectification``),
    into an inertial sequence: the pairs' tracks, the rectified left camera's K, baseline and
    ``imu_T_cam``, and the IMU's samples (``Sequence.imu``) with their noise densities (``imu0/sensor.yaml``,
    Kalibr's ``imu.yaml``). ``progress(index, n)`` after each pair."""
    from .euroc import RectifiedRig, read_euroc

    data = data if isinstance(data, RectifiedRig) else read_euroc(data)
    config = config if config is not None else TrackerConfig()
    w, h = data.rectification.size
    if min(w, h) < config.min_image_side:
        raise InputError(f"{data.root}: images of {w}x{h} px are smaller than tracker.min_image_side = "
                         f"{config.min_image_side}")
    return _inertial_sequence(data.pairs(), data.frames.times, data.K, data.baseline, data.imu_T_cam,
                              data.imu.samples, str(data.root), config, progress, draw_dir)


def track_raw_inertial(drive, config: TrackerConfig | None = None, progress: Callable[[int, int], None] | None = None,
                       draw_dir=None) -> Sequence:
    """Track every frame of a KITTI raw drive (:class:`~frontend.raw_drive.RawDrive`) into an
    inertial sequence: the OXTS accelerations and rates as the IMU's samples
    (``RawDrive.inertial_samples``), the calibrated K, baseline and ``imu_T_cam``. Checks (image
    size, ``draw_dir``, the samples) before the first frame."""
    config = config if config is not None else TrackerConfig()
    stereo = drive.stereo
    check_image_size(stereo, config)
    if draw_dir is not None:
        check_draw_dir(draw_dir)
    samples = drive.inertial_samples()
    return _inertial_sequence(stereo.frames(), drive.imu.time_stamps, stereo.K, stereo.baseline, drive.imu.imu_T_cam,
                              samples, str(stereo.root), config, progress, draw_dir)


def _inertial_sequence(frames: Iterator, times: np.ndarray, K: np.ndarray, baseline: float, imu_T_cam: np.ndarray,
                       samples, source: str, config: TrackerConfig, progress, draw_dir) -> Sequence:
    """The inertial sequence of the tracked (index, left, right) ``frames`` at ``times`` with the IMU's ``samples``."""
    tracker = StereoTracker(config, K, baseline)
    drawer = TrackDrawer(draw_dir) if draw_dir is not None else None
    n = len(times)
    ids, pixels = [], []
    for k, i, z in _tracked_frames(frames, config, tracker, drawer):
        ids.append(i)
        pixels.append(z)
        if progress is not None:
            progress(k, n)
    return Sequence.from_steps(times, None, None, ids, pixels, K, baseline, imu_T_cam, num_features=tracker.num_ids,
                               source=source, tracker=VISLAM_TRACKER, imu=samples)
