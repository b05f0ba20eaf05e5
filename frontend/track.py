"""Track a KITTI-layout image directory into the course sequence layout (what `vislam track` does).

:func:`track_directory` runs :class:`~frontend.tracker.StereoTracker` over every frame and
returns a :class:`backend.sequence.Sequence`: time stamps, velocities and the camera mount from
the IMU source (:mod:`frontend.imu_input`; frame i = IMU row/step i), K and baseline from
``calib.txt``, observations per frame, ``num_features`` = number of ids issued.
:func:`iter_tracks` is the online form: it yields each frame's tracks as soon as they exist
(``vislam run IMAGES`` feeds them to the filter frame by frame, tools/track.py).
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np

from backend.errors import InputError
from backend.sequence import VISLAM_TRACKER, Sequence, validate_sequence
from frontend.config import TrackerConfig
from frontend.draw import TrackDrawer
from frontend.images import StereoDirectory, open_stereo_directory
from frontend.imu_input import ImuVelocities, read_imu
from frontend.tracker import StereoTracker

__all__ = ["track_directory", "iter_tracks", "check_imu", "tracks_to_sequence", "opencv_threads"]


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
    return images_dir if isinstance(images_dir, StereoDirectory) else open_stereo_directory(images_dir)


def iter_tracks(images_dir, config: TrackerConfig | None = None, draw_dir=None,
                tracker: StereoTracker | None = None) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """Yield ``(frame index, ids (n,) int64 increasing, pixels (n,4) uL vL uR vR)`` per frame of a
    KITTI-layout directory (path or :class:`~frontend.images.StereoDirectory`), frame by frame.
    ``draw_dir``: write a debug picture per frame there (:class:`~frontend.draw.TrackDrawer`);
    ``tracker``: a tracker to use (its ``num_ids`` tells how many ids were issued)."""
    stereo = _stereo(images_dir)
    config = config if config is not None else TrackerConfig()
    tracker = tracker if tracker is not None else StereoTracker(config, stereo.K, stereo.baseline)
    drawer = TrackDrawer(draw_dir) if draw_dir is not None else None
    with opencv_threads(config.threads):
        for index, left, right in stereo.frames():
            ids, pixels = tracker.step(left, right)
            if drawer is not None:
                drawer.draw(index, left, right, ids, pixels)
            yield index, ids, pixels


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
    ptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum([i.size for i in ids], out=ptr[1:])
    seq = Sequence(
        time_stamps=np.array(imu.time_stamps[:n], dtype=np.float64),
        linear_velocity=np.array(imu.linear_velocity[:n], dtype=np.float64),
        angular_velocity=np.array(imu.angular_velocity[:n], dtype=np.float64),
        K=np.array(stereo.K, dtype=np.float64),
        baseline=float(stereo.baseline),
        imu_T_cam=np.array(imu.imu_T_cam, dtype=np.float64),
        obs_ptr=ptr,
        obs_ids=np.concatenate(ids) if ids else np.zeros(0, np.int64),
        obs_pixels=np.concatenate(pixels) if pixels else np.zeros((0, 4)),
        num_features=int(num_ids),
        source=str(Path(stereo.root)),
        layout=imu.layout,
        tracker=VISLAM_TRACKER,
    )
    validate_sequence(seq)
    return seq


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
    (:class:`~frontend.draw.TrackDrawer`). Raises InputError on unusable input.
    """
    stereo = _stereo(images_dir)
    imu = check_imu(imu, stereo, imu_T_cam_path)
    config = config if config is not None else TrackerConfig()
    tracker = StereoTracker(config, stereo.K, stereo.baseline)
    all_ids, all_pixels = [], []
    for index, ids, pixels in iter_tracks(stereo, config, draw_dir, tracker):
        all_ids.append(ids)
        all_pixels.append(pixels)
        if progress is not None:
            progress(index, len(stereo))
    return tracks_to_sequence(stereo, imu, all_ids, all_pixels, tracker.num_ids)
