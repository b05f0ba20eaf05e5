"""A KITTI raw ``_sync`` drive as one input: its stereo frames, IMU velocities and ground truth.

The OXTS records carry both IMU inputs: the velocities ``vf vl vu`` (the level frame's, turned into
the IMU's axes by the record's roll and pitch, K1 of :mod:`~vislam.frontend.kitti_raw`) with the
rates ``wx wy wz`` (the default, the velocity model), and the specific force ``ax ay az`` with the
same rates, one sample a frame, as a real IMU's samples for the inertial state (``--imu-input
inertial``); the ground truth of an inertial run is the OXTS poses in a gravity-aligned world (z up).

``DATE/DATE_drive_NNNN_sync/`` (the drive) holds ``image_00/data/*.png`` and ``image_01/data/*.png``
(rectified grey, left and right), ``image_00/timestamps.txt`` and ``oxts/data/*.txt``; ``DATE/``
holds the calibration (:mod:`~vislam.frontend.kitti_raw` reads every file). Frame
``NNNNNNNNNN.png`` gets stamp k = ``NNNNNNNNNN`` of ``timestamps.txt`` and the record
``oxts/data/NNNNNNNNNN.txt``, so a drive cut to some of its frames still lines up.

:func:`open_images` opens either layout: a directory with ``image_00/`` and no ``image_0/`` is a
raw drive, anything else an odometry-layout directory (:func:`~vislam.frontend.images.open_stereo_directory`).
"""

from __future__ import annotations

import dataclasses
import os
import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..backend.data.inertial import ImuSamples, check_imu_samples
from ..backend.errors import InputError
from .images import LEFT_DIR, StereoDirectory, open_stereo_directory, paired_frame_names, stereo_directory
from .imu_input import ImuVelocities, with_imu_T_cam
from .kitti_raw import (
    CAM_TO_CAM,
    frame_numbers, oxts_inertial, oxts_velocities, oxts_world_T_imu, read_drive_calibration, read_oxts,
    read_timestamps,
)

__all__ = ["RawDrive", "is_raw_drive", "open_raw_drive", "open_inertial_drive", "open_images", "drive_imu", "RAW_LEFT",
           "RAW_RIGHT"]

RAW_LEFT, RAW_RIGHT = "image_00/data", "image_01/data"
_LAYOUT = f"KITTI raw drive: {RAW_LEFT}/ left and {RAW_RIGHT}/ right .png frames"


@dataclass(frozen=True, eq=False)
class RawDrive:
    """A checked raw drive: frames, OXTS velocities (with the calibrated extrinsic) and poses."""

    stereo: StereoDirectory
    imu: ImuVelocities  # one sample a frame, the frames' time stamps, imu_T_cam from the calibration
    world_T_imu: np.ndarray  # (n,4,4) OXTS poses, world = the IMU frame at the first frame
    oxts: np.ndarray  # (n,30) the records, columns kitti_raw.OXTS_FIELDS

    def inertial_samples(self) -> ImuSamples:
        """``ax ay az`` and ``wx wy wz`` (the IMU's axes) at the frames' stamps as a real IMU's
        samples (no noise densities: the run measures them); InputError when they cannot be (a gap
        over ``MAX_IMU_STEP`` between frames)."""
        specific_force, rate = oxts_inertial(self.oxts)
        return check_imu_samples(self.ground_truth_source, self.imu.time_stamps, specific_force, rate,
                                 keys=("image_00/timestamps.txt", "ax ay az", "wx wy wz"))

    @property
    def ground_truth_source(self) -> str:
        """What the ground truth comes from (named in messages)."""
        return str(self.stereo.root / "oxts")

    @property
    def ground_truth(self) -> tuple[str, np.ndarray, np.ndarray]:
        """(source, time stamps (n,), world_T_imu (n,4,4)): the form ``vislam run --gt`` reads."""
        return self.ground_truth_source, self.imu.time_stamps, self.world_T_imu

    @functools.cached_property
    def level_ground_truth(self) -> tuple[str, np.ndarray, np.ndarray]:
        """:attr:`ground_truth` in a gravity-aligned world (z up, x along the first heading; an
        inertial run's): :func:`~frontend.kitti_raw.oxts_world_T_imu` with ``level``."""
        return self.ground_truth_source, self.imu.time_stamps, oxts_world_T_imu(self.oxts, level=True)


def is_raw_drive(path) -> bool:
    """Whether ``path`` is laid out as a KITTI raw drive (``image_00/``, no odometry ``image_0/``)."""
    root = Path(path)
    return (root / "image_00").is_dir() and not (root / LEFT_DIR).exists()


def open_raw_drive(path) -> RawDrive:
    """Check a raw drive (paired frames, calibration in its parent, time stamps, one OXTS record a
    frame, the first pair) and read everything but the images; InputError naming the file otherwise."""
    root = Path(path)
    if not root.is_dir():
        raise InputError(f"{root}: {'not a directory' if root.exists() else 'missing directory'}")
    names = paired_frame_names(root, RAW_LEFT, RAW_RIGHT, _LAYOUT)
    frames = frame_numbers(root / RAW_LEFT, names)
    date_dir, where = _calibration_folder(root)
    calibration = read_drive_calibration(date_dir)
    if where:
        calibration = dataclasses.replace(calibration, notes=(*calibration.notes, where))
    times = read_timestamps(root / "image_00" / "timestamps.txt", frames)
    oxts = read_oxts(root / "oxts" / "data", [Path(n).stem for n in names])
    stereo = stereo_directory(root, RAW_LEFT, RAW_RIGHT, names, times, calibration.K, calibration.baseline)
    linear, angular = oxts_velocities(oxts)
    imu = ImuVelocities(times, linear, angular, calibration.imu_T_cam, source=str(root / "oxts"),
                        notes=calibration.notes)
    return RawDrive(stereo, imu, oxts_world_T_imu(oxts), oxts)


def _calibration_folder(root: Path) -> tuple[Path, str | None]:
    """The ``DATE/`` folder holding the drive's calibration: the parent of the path as given (a
    drive linked into a ``DATE/`` folder takes that folder's); else, when the drive's folder is a
    symbolic link, the parent of its target, with a note saying so."""
    given = Path(os.path.abspath(root)).parent
    target = root.resolve().parent
    if (given / CAM_TO_CAM).exists() or target == given or not (target / CAM_TO_CAM).exists():
        return given, None
    return target, (f"calibration read from {target} (the folder {root} links to {root.resolve()}; "
                    f"{given} holds no {CAM_TO_CAM})")


def open_images(path) -> tuple[StereoDirectory, RawDrive | None]:
    """The stereo frames of an image directory of either layout, and the drive of a raw one."""
    if is_raw_drive(path):
        drive = open_raw_drive(path)
        return drive.stereo, drive
    return open_stereo_directory(path), None


def drive_imu(drive: RawDrive, imu_path=None, imu_T_cam_path=None) -> ImuVelocities:
    """The drive's OXTS velocities, with the extrinsic of ``imu_T_cam_path`` (``--imu-T-cam``) in
    place of the calibrated one when given; an IMU file (``--imu``) is refused: the drive has its own."""
    if imu_path:
        raise InputError(f"{imu_path}: --imu is for an odometry-layout directory; the KITTI raw drive "
                         f"{drive.stereo.root} carries its IMU velocities in oxts/")
    return with_imu_T_cam(drive.imu, imu_T_cam_path) if imu_T_cam_path is not None else drive.imu


def open_inertial_drive(path, imu_path=None, imu_T_cam_path=None) -> RawDrive:
    """The raw drive ``path`` for ``--imu-input inertial`` (its OXTS accelerations as the IMU), with
    the extrinsic of ``imu_T_cam_path`` when given; InputError (one line) for anything but a raw
    drive (an odometry-layout directory's ``--imu`` gives velocities) or with an IMU file."""
    if not is_raw_drive(path):
        raise InputError(f"{path}: --imu-input inertial needs a real IMU's samples: a KITTI raw drive (its OXTS "
                         "accelerations), an EuRoC folder or an inertial .npz; an odometry-layout directory's --imu "
                         "gives velocities")
    drive = open_raw_drive(path)
    imu = drive_imu(drive, imu_path, imu_T_cam_path)
    return drive if imu is drive.imu else dataclasses.replace(drive, imu=imu)
