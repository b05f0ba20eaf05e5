"""Readers of the KITTI raw recording files: calibration, image time stamps, OXTS records, and the
OXTS poses by the KITTI devkit's Mercator conversion.

Files (Geiger et al., "Vision meets Robotics: The KITTI Dataset", IJRR 2013, and its raw data
devkit; ``DATE`` = ``YYYY_MM_DD``):

* ``DATE/calib_cam_to_cam.txt``: ``P_rect_00:`` and ``P_rect_01:`` (3x4 row-major, the rectified
  left and right grey cameras), ``R_rect_00:`` (3x3, camera 0 -> rectified camera 0); other keys
  (``calib_time:``, ``K_00:``, ...) are ignored;
* ``DATE/calib_imu_to_velo.txt`` and ``DATE/calib_velo_to_cam.txt``: ``R:`` (9 numbers, 3x3
  row-major) and ``T:`` (3 numbers, m) of ``velo_T_imu`` and ``cam_T_velo`` (``x_to = R x_from + T``);
* ``DRIVE/image_00/timestamps.txt``: ``YYYY-MM-DD HH:MM:SS.fffffffff``, line k for frame k;
* ``DRIVE/oxts/data/NNNNNNNNNN.txt``: one line of the 30 numbers :data:`OXTS_FIELDS` for frame
  ``NNNNNNNNNN`` (the ``_sync`` data holds one record per image frame).

Every problem raises :class:`~vislam.backend.errors.InputError` with one line naming the file, the
key or line, and what is wrong.
"""

from __future__ import annotations

import datetime
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..backend.data.files import note_input
from ..backend.data.sequence import nearest_rigid
from ..backend.data.textio import content_lines, finite_numbers, read_lines
from ..backend.errors import InputError
from ..backend.geometry import se3
from .images import stereo_intrinsics

__all__ = [
    "OXTS_FIELDS", "EARTH_RADIUS", "RawCalibration", "read_cam_to_cam", "read_rigid_calibration",
    "cam_rect_T_imu", "read_drive_calibration", "frame_numbers", "parse_timestamp", "read_timestamps",
    "read_oxts", "oxts_velocities", "oxts_inertial", "mercator_scale", "oxts_world_T_imu",
]

#: The 30 numbers of an OXTS line, in order (the devkit's dataformat.txt): position (deg, deg, m),
#: attitude (rad), velocities (m/s: north, east, forward, left, up), accelerations (m/s^2:
#: x, y, z, forward, left, up), angular rates (rad/s: x, y, z, forward, left, up), accuracies (m,
#: m/s) and status codes. x, y, z are the IMU's own axes (front, left, top of the vehicle); forward,
#: left and up are those of the level frame (forward and left "parallel to earth-surface", up
#: "perpendicular to earth-surface"), which turns with the heading only.
OXTS_FIELDS = ("lat", "lon", "alt", "roll", "pitch", "yaw", "vn", "ve", "vf", "vl", "vu", "ax", "ay", "az",
               "af", "al", "au", "wx", "wy", "wz", "wf", "wl", "wu", "pos_accuracy", "vel_accuracy",
               "navstat", "numsats", "posmode", "velmode", "orimode")
_ROLL, _PITCH = OXTS_FIELDS.index("roll"), OXTS_FIELDS.index("pitch")
_VF, _AX, _WX = OXTS_FIELDS.index("vf"), OXTS_FIELDS.index("ax"), OXTS_FIELDS.index("wx")

#: Equatorial radius (m) of the devkit's Mercator conversion (WGS84).
EARTH_RADIUS = 6378137.0

CAM_TO_CAM, IMU_TO_VELO, VELO_TO_CAM = "calib_cam_to_cam.txt", "calib_imu_to_velo.txt", "calib_velo_to_cam.txt"

_STAMP = re.compile(r"(\d{4})-(\d{2})-(\d{2})[ T](\d{2}):(\d{2}):(\d{2})(?:\.(\d{1,9}))?")


# ---------------------------------------------------------------------------------------------- calibration


def _keyed_rows(path: Path, sizes: dict[str, int]) -> dict[str, np.ndarray]:
    """The rows ``KEY: n numbers`` of ``path`` for the keys of ``sizes`` (key -> count), each as
    a (count,) float array; other keys are skipped. InputError naming the file, the line and the key
    for a key given twice, a wrong count, a value that is not a finite number, or a missing key."""
    rows: dict[str, np.ndarray] = {}
    for number, line in enumerate(read_lines(path, f"missing (need {', '.join(k + ':' for k in sizes)})"), start=1):
        key, sep, values = line.partition(":")
        key = key.strip()
        if not sep or key not in sizes:
            continue
        where = f"{path}: line {number}: key '{key}'"
        if key in rows:
            raise InputError(f"{where}: given twice")
        numbers = finite_numbers(values.split(), where)
        if len(numbers) != sizes[key]:
            raise InputError(f"{where}: needs {sizes[key]} numbers, got {len(numbers)}")
        rows[key] = np.array(numbers, dtype=np.float64)
    for key, size in sizes.items():
        if key not in rows:
            raise InputError(f"{path}: key '{key}': no '{key}:' line ({size} numbers)")
    return rows


def _rigid(path: Path, key: str, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, str | None]:
    """[R t; 0 1] (4,4), its rotation checked and re-orthonormalized (:func:`nearest_rigid`)."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R.reshape(3, 3), t
    return nearest_rigid(str(path), key, T)


def read_cam_to_cam(path) -> tuple[np.ndarray, float, np.ndarray, str | None]:
    """Intrinsics and rectification of the grey pair from ``calib_cam_to_cam.txt``.

    Returns
    -------
    K : (3, 3) ndarray
        ``P_rect_00[:, :3]`` (shared with ``P_rect_01``).
    baseline : float
        ``-P_rect_01[0, 3] / P_rect_01[0, 0]`` (m), > 0.
    rect_T_cam : (4, 4) ndarray
        ``[R_rect_00 0; 0 1]``: camera 0 -> rectified camera 0.
    note : str or None
        Said when ``R_rect_00`` was re-orthonormalized (printed to a few decimals).
    """
    path = Path(path)
    rows = _keyed_rows(path, {"P_rect_00": 12, "P_rect_01": 12, "R_rect_00": 9})
    K, baseline = stereo_intrinsics(path, rows["P_rect_00"].reshape(3, 4), rows["P_rect_01"].reshape(3, 4),
                                    ("P_rect_00", "P_rect_01"))
    rect_T_cam, note = _rigid(path, "R_rect_00", rows["R_rect_00"], np.zeros(3))
    return K, baseline, rect_T_cam, note


def read_rigid_calibration(path) -> tuple[np.ndarray, str | None]:
    """``to_T_from`` (4,4) = [R T; 0 1] from the ``R:`` (9) and ``T:`` (3) rows of a KITTI
    ``calib_A_to_B.txt`` (B_T_A: ``x_B = R x_A + T``), and a note when R was re-orthonormalized."""
    path = Path(path)
    rows = _keyed_rows(path, {"R": 9, "T": 3})
    return _rigid(path, "R", rows["R"], rows["T"])


def cam_rect_T_imu(rect_T_cam: np.ndarray, cam_T_velo: np.ndarray, velo_T_imu: np.ndarray) -> np.ndarray:
    """The IMU (OXTS) -> rectified left camera transform (4,4).

    ``cam_rect_T_imu = [R_rect_00 0; 0 1] @ cam_T_velo @ velo_T_imu`` (the devkit's
    ``x_rect = R_rect_00 Tr_velo_to_cam Tr_imu_to_velo x_imu``); the filter's extrinsic is its
    inverse ``imu_T_cam = cam_rect_T_imu^-1``.
    """
    return rect_T_cam @ cam_T_velo @ velo_T_imu


@dataclass(frozen=True, eq=False)
class RawCalibration:
    """The rectified grey pair of a KITTI raw recording day."""

    K: np.ndarray  # (3,3)
    baseline: float  # m
    imu_T_cam: np.ndarray  # (4,4) rectified left camera -> IMU
    notes: tuple[str, ...] = ()


def read_drive_calibration(date_dir) -> RawCalibration:
    """K, baseline and ``imu_T_cam`` from the three calibration files of ``date_dir``.

    ``imu_T_cam = (R_rect_00_4x4 @ cam_T_velo @ velo_T_imu)^-1`` (:func:`cam_rect_T_imu`), with
    ``velo_T_imu`` from ``calib_imu_to_velo.txt`` and ``cam_T_velo`` from ``calib_velo_to_cam.txt``.
    """
    date_dir = Path(date_dir)
    K, baseline, rect_T_cam, note = read_cam_to_cam(date_dir / CAM_TO_CAM)
    velo_T_imu, note_imu = read_rigid_calibration(date_dir / IMU_TO_VELO)
    cam_T_velo, note_velo = read_rigid_calibration(date_dir / VELO_TO_CAM)
    imu_T_cam = se3.inverse(cam_rect_T_imu(rect_T_cam, cam_T_velo, velo_T_imu))
    return RawCalibration(K, baseline, imu_T_cam, tuple(n for n in (note, note_imu, note_velo) if n))


# ---------------------------------------------------------------------------------------------- time stamps


def frame_numbers(folder: Path, names: list[str]) -> list[int]:
    """The frame number k of each ``NNNNNNNNNN.png`` (its stem, decimal digits); InputError naming
    the first name that is not one."""
    numbers = []
    for name in names:
        stem = Path(name).stem
        if not (stem.isascii() and stem.isdigit()):
            raise InputError(f"{Path(folder) / name}: not a KITTI raw frame name (decimal digits, e.g. 0000000000.png)")
        numbers.append(int(stem))
    return numbers


def parse_timestamp(text: str, where: str) -> float:
    """Seconds since 1970-01-01 UTC (float64) of ``YYYY-MM-DD HH:MM:SS[.fffffffff]``.

    The KITTI stamps carry no time zone: they are read as UTC (differences are what the filter uses).
    Whole seconds and the fraction are added last, so the result is within half a float64 step
    (2.4e-7 s in 2011) of the stamp. InputError ``<where>: ...`` for any other text.
    """
    match = _STAMP.fullmatch(text.strip())
    if match is None:
        raise InputError(f"{where}: not a time stamp YYYY-MM-DD HH:MM:SS.fffffffff: {text.strip()[:40]!r}")
    fields = [int(x) for x in match.groups()[:6]]
    try:
        whole = datetime.datetime(*fields, tzinfo=datetime.timezone.utc).timestamp()
    except ValueError as e:
        raise InputError(f"{where}: not a valid date and time ({e}): {text.strip()[:40]!r}") from None
    fraction = match.group(7) or "0"
    return whole + int(fraction) / 10.0 ** len(fraction)


def read_timestamps(path, frames: list[int]) -> np.ndarray:
    """(n,) seconds of ``frames`` (frame k = the k-th stamp; blank lines skipped), strictly
    increasing; InputError naming the file and the line otherwise (:func:`parse_timestamp`)."""
    path = Path(path)
    lines = list(content_lines(read_lines(path, "missing (need one time stamp a frame)")))
    t, where = [], []
    for k in frames:
        if k >= len(lines):
            raise InputError(f"{path}: {len(lines)} time stamps; frame {k:010d} needs stamp {k + 1}")
        number, text = lines[k]
        t.append(parse_timestamp(text, f"{path}: line {number}"))
        where.append(number)
    stamps = np.array(t, dtype=np.float64)
    bad = np.flatnonzero(np.diff(stamps) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise InputError(f"{path}: line {where[i]}: time stamps not strictly increasing "
                         f"({stamps[i]:.9f} after {stamps[i - 1]:.9f})")
    return stamps


# ---------------------------------------------------------------------------------------------- OXTS


def _oxts_record(path: Path) -> np.ndarray:
    lines = list(content_lines(read_lines(path, "missing (need one OXTS record a frame)")))
    if len(lines) != 1:
        raise InputError(f"{path}: {len(lines)} lines; an OXTS record is one line of {len(OXTS_FIELDS)} numbers")
    number, text = lines[0]
    where = f"{path}: line {number}"
    values = finite_numbers(text.split(), where)
    if len(values) != len(OXTS_FIELDS):
        raise InputError(f"{where}: {len(values)} numbers; an OXTS record has {len(OXTS_FIELDS)} (lat lon alt ... orimode)")
    if not abs(values[0]) < 90:
        raise InputError(f"{where}: lat {values[0]!r} deg out of (-90, 90)")
    if not abs(values[1]) <= 180:
        raise InputError(f"{where}: lon {values[1]!r} deg out of [-180, 180]")
    return np.array(values, dtype=np.float64)


def read_oxts(folder, stems: list[str]) -> np.ndarray:
    """(n, 30) the OXTS records ``folder/STEM.txt`` of the frames ``stems``, columns
    :data:`OXTS_FIELDS`; InputError naming the file for a missing record (a count first when the
    folder holds fewer records than frames), a line without 30 finite numbers, or lat/lon out of range."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: {'not a directory' if folder.exists() else 'missing directory'} "
                         "(KITTI raw: oxts/data/NNNNNNNNNN.txt, one record a frame)")
    note_input(folder, contents=True)
    count = sum(1 for p in folder.iterdir() if p.suffix == ".txt")
    if count < len(stems):
        raise InputError(f"{folder}: {count} OXTS records for {len(stems)} image frames (need one a frame)")
    return np.array([_oxts_record(folder / f"{stem}.txt") for stem in stems]).reshape(-1, len(OXTS_FIELDS))


def oxts_velocities(oxts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(linear (n,3) m/s, angular (n,3) rad/s) in the IMU frame. The records give no velocity in the
    IMU's axes: ``vf vl vu`` are the level frame's (:data:`OXTS_FIELDS`), turned into the IMU frame by
    the record's roll and pitch,

        v_imu = (Ry(pitch) Rx(roll))^T [vf, vl, vu]                                           (K1)

    (the attitude of :func:`oxts_world_T_imu` is Rz(yaw) Ry(pitch) Rx(roll), the level frame Rz(yaw));
    the rates are ``wx wy wz``, the IMU's own. Held as given, ``vf vl vu`` put the vehicle's pitch
    into its vertical motion: v |sin(pitch)|, 0.4 m/s at 22 m/s and 1 deg."""
    tilt = _rotations(oxts[:, _ROLL], oxts[:, _PITCH], np.zeros(len(oxts)))
    linear = np.einsum("kji,kj->ki", tilt, oxts[:, _VF:_VF + 3])
    return np.ascontiguousarray(linear), np.ascontiguousarray(oxts[:, _WX:_WX + 3])


def oxts_inertial(oxts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(specific force (n,3) m/s^2, angular rate (n,3) rad/s) in the IMU frame: ``ax ay az`` and
    ``wx wy wz``, a real IMU's samples (the accelerometer reads about +9.81 up at rest; the inertial
    run's initialization tests that and refuses otherwise). ``af al au`` and ``wf wl wu`` are the
    level frame's (:data:`OXTS_FIELDS`): gravity stays on ``au`` whatever the tilt."""
    return (np.ascontiguousarray(oxts[:, _AX:_AX + 3]), np.ascontiguousarray(oxts[:, _WX:_WX + 3]))


def mercator_scale(lat0_deg: float) -> float:
    """The devkit's Mercator scale ``cos(lat0 * pi / 180)`` of the first record's latitude."""
    return float(np.cos(np.deg2rad(lat0_deg)))


def _rotations(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(n,3,3) ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    R = np.empty((roll.size, 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    R[:, 1, 0], R[:, 1, 1], R[:, 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    R[:, 2, 0], R[:, 2, 1], R[:, 2, 2] = -sp, cp * sr, cp * cr
    return R


def oxts_world_T_imu(oxts: np.ndarray, level: bool = False) -> np.ndarray:
    """(n,4,4) ``world_T_imu`` of OXTS records (n, >=6: lat lon alt roll pitch yaw first), world =
    the IMU frame at the first record: the devkit's ``convertOxtsToPose``; ``level``: world = the
    first record's position with z up and x along its heading (gravity-aligned, as an inertial
    filter's world: the first pose keeps its roll and pitch).

    With ``s = cos(lat_0 pi/180)`` (:func:`mercator_scale`) and ``er`` = :data:`EARTH_RADIUS`::

        t = [s er lon pi/180,  s er ln(tan((90 + lat) pi/360)),  alt]
        R = Rz(yaw) Ry(pitch) Rx(roll)
        world_T_imu_k = [R_0 t_0; 0 1]^-1 [R_k t_k; 0 1]          (level: Rz(yaw_0) in place of R_0)
    """
    oxts = np.asarray(oxts, dtype=np.float64)
    lat, lon, alt, roll, pitch, yaw = oxts[:, :6].T
    scale = mercator_scale(lat[0])
    t = np.column_stack([scale * EARTH_RADIUS * np.deg2rad(lon),
                         scale * EARTH_RADIUS * np.log(np.tan(np.deg2rad(90.0 + lat) / 2.0)),
                         alt])
    R = _rotations(roll, pitch, yaw)
    zero = np.zeros(1)
    first = _rotations(zero, zero, yaw[:1])[0] if level else R[0]
    poses = np.tile(np.eye(4), (len(oxts), 1, 1))
    poses[:, :3, :3] = first.T @ R
    poses[:, :3, 3] = (t - t[0]) @ first  # first^T (t_k - t_0)
    if not level:
        poses[0] = np.eye(4)  # R_0^T R_0, without its rounding
    return poses
