"""IMU velocities (and the camera mount) for the frames of an image sequence.

Two sources, chosen by :func:`read_imu` from the file name:

* a CSV (``.csv``/``.txt``) with rows ``t,vx,vy,vz,wx,wy,wz`` (seconds, m/s, rad/s, IMU frame;
  an optional header line without any number in it, so a damaged first row is refused rather than
  skipped; ``#`` comments and blank lines skipped). Frame i gets row i: the file needs at least
  as many rows as there are frames and its first ``n_frames`` rows are used, time stamps included. The CSV carries no extrinsic: it comes from ``--imu-T-cam FILE``
  (:func:`read_imu_T_cam`, a 4x4 text matrix mapping camera-frame points into the IMU frame);
* a course ``.npz`` (either layout, read with :func:`~vislam.backend.data.npz.load_sequence`): frame i
  is step i, steps beyond the last frame are ignored; its time stamps, velocities and
  ``imu_T_cam`` are used (so ground truth stamped like that file lines up). An explicit
  ``--imu-T-cam`` overrides the file's extrinsic.

Every problem raises :class:`~backend.errors.InputError` with one line naming the file.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..backend.errors import InputError
from ..backend.data.npz import load_sequence
from ..backend.data.sequence import nearest_rigid
from ..backend.data.textio import content_lines, read_lines, text_float

__all__ = ["ImuVelocities", "read_imu", "read_imu_csv", "read_imu_npz", "read_imu_T_cam", "with_imu_T_cam"]



@dataclass(frozen=True, eq=False)
class ImuVelocities:
    """Per-frame IMU samples: row i belongs to image frame i."""

    time_stamps: np.ndarray  # (n,) seconds, strictly increasing
    linear_velocity: np.ndarray  # (n,3) m/s, IMU frame
    angular_velocity: np.ndarray  # (n,3) rad/s, IMU frame
    imu_T_cam: np.ndarray | None  # (4,4) camera -> IMU, None when the source carries none
    layout: str = "2022"  # course layout to write the tracks in (that of an .npz source)
    source: str = ""
    notes: tuple[str, ...] = ()  # what the readers accepted with a remark (a re-orthonormalized rotation)

    def __len__(self) -> int:
        return int(self.time_stamps.shape[0])


def _numbers(text: str) -> list[float] | None:
    try:
        return [text_float(x) for x in text.replace(",", " ").split()]
    except ValueError:
        return None


def _is_header(text: str) -> bool:
    """A line none of whose fields is a number (``t,vx,vy,vz,wx,wy,wz``)."""
    return all(_numbers(field) is None for field in text.replace(",", " ").split())


def read_imu_csv(path, n_frames: int) -> ImuVelocities:
    """The first ``n_frames`` rows ``t,vx,vy,vz,wx,wy,wz`` of a CSV (see the module docstring)."""
    path = Path(path)
    rows, numbers = [], []
    first = True
    for number, text in content_lines(read_lines(path)):
        values = _numbers(text)
        if values is None and first and _is_header(text):
            first = False
            continue  # the header
        first = False
        if values is None:
            raise InputError(f"{path}: line {number}: not 7 numbers t,vx,vy,vz,wx,wy,wz: {text[:60]!r}")
        if len(values) != 7:
            raise InputError(f"{path}: line {number}: expected 7 values t,vx,vy,vz,wx,wy,wz, got {len(values)}")
        if not np.isfinite(values).all():
            raise InputError(f"{path}: line {number}: non-finite value (NaN or inf) in {text[:60]!r}")
        rows.append(values)
        numbers.append(number)
        if len(rows) == n_frames:
            break
    if len(rows) < n_frames:
        raise InputError(f"{path}: {len(rows)} IMU rows for {n_frames} image frames (need at least one a frame)")
    a = np.array(rows, dtype=np.float64).reshape(-1, 7)
    t = a[:, 0]
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise InputError(f"{path}: line {numbers[i]}: time stamps not strictly increasing ({t[i]:.9g} after {t[i - 1]:.9g})")
    return ImuVelocities(
        time_stamps=t.copy(),
        linear_velocity=np.ascontiguousarray(a[:, 1:4]),
        angular_velocity=np.ascontiguousarray(a[:, 4:7]),
        imu_T_cam=None,
        source=str(path),
    )


def read_imu_npz(path, n_frames: int) -> ImuVelocities:
    """Steps ``0..n_frames-1`` of a course .npz: its time stamps, velocities and extrinsic."""
    seq = load_sequence(path)
    if seq.num_steps < n_frames:
        raise InputError(f"{path}: key 'time_stamps': {seq.num_steps} steps for {n_frames} image frames (need one a frame)")
    return ImuVelocities(
        time_stamps=seq.time_stamps[:n_frames].copy(),
        linear_velocity=seq.linear_velocity[:n_frames].copy(),
        angular_velocity=seq.angular_velocity[:n_frames].copy(),
        imu_T_cam=np.array(seq.imu_T_cam, dtype=np.float64),
        layout=seq.layout,
        source=str(path),
        notes=tuple(seq.notes),
    )


def read_imu_T_cam(path) -> np.ndarray:
    """A rigid 4x4 transform (camera -> IMU) from a text file: 4 rows of 4 numbers (spaces or
    commas; ``#`` comments allowed). A rotation typed to a few decimals (within
    ``ORTHO_ACCEPT`` of orthonormal) is replaced by the nearest rotation
    (:func:`~vislam.backend.data.sequence.nearest_rigid`); :func:`read_imu` keeps the note."""
    return _read_imu_T_cam(path)[0]


def _read_imu_T_cam(path) -> tuple[np.ndarray, str | None]:
    path = Path(path)
    lines = read_lines(path)
    rows = []
    for number, line in enumerate(lines, start=1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        values = _numbers(text)
        if values is None or len(values) != 4:
            raise InputError(f"{path}: line {number}: expected 4 numbers of a 4x4 matrix, got {text[:60]!r}")
        rows.append(values)
    if len(rows) != 4:
        raise InputError(f"{path}: expected a 4x4 matrix (4 rows), got {len(rows)} rows")
    T = np.array(rows, dtype=np.float64)
    return nearest_rigid(str(path), "imu_T_cam", T)


def with_imu_T_cam(imu: ImuVelocities, imu_T_cam_path) -> ImuVelocities:
    """``imu`` with the extrinsic of a 4x4 text file (``--imu-T-cam``, :func:`read_imu_T_cam`)
    in place of its own; a re-orthonormalization note is added to its notes."""
    T, note = _read_imu_T_cam(imu_T_cam_path)
    return ImuVelocities(
        imu.time_stamps, imu.linear_velocity, imu.angular_velocity,
        T, imu.layout, imu.source, imu.notes + ((note,) if note else ()),
    )


def read_imu(path, n_frames: int, imu_T_cam_path=None) -> ImuVelocities:
    """IMU samples for ``n_frames`` frames from a CSV or a course .npz (module docstring); the
    result always carries an extrinsic (from ``imu_T_cam_path`` if given, else the .npz)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {'not a regular file' if path.exists() else 'file does not exist'}")
    if path.suffix.lower() == ".npz" or zipfile.is_zipfile(path):
        imu = read_imu_npz(path, n_frames)
    else:
        imu = read_imu_csv(path, n_frames)
    if imu_T_cam_path is not None:
        return with_imu_T_cam(imu, imu_T_cam_path)
    if imu.imu_T_cam is None:
        raise InputError(f"{path}: a CSV carries no camera extrinsic; give it with --imu-T-cam FILE (4x4 imu_T_cam)")
    return imu
