"""Trajectory text files: TUM (``t tx ty tz qx qy qz qw`` a line, what evo and the TUM benchmark
read), KITTI odometry poses (the 12 numbers of a pose's top 3x4 a line, line k = frame k) and EuRoC
ASL pose csv (``timestamp [ns], px, py, pz, qw, qx, qy, qz[, ...]``, evo's ``euroc`` format), and
:func:`read_trajectory`, which tells them apart by their columns."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InputError
from ..geometry import se3
from .files import atomic_write
from .sequence import ORTHO_ACCEPT
from .textio import content_lines, finite_numbers, read_lines

__all__ = ["read_tum", "write_tum", "read_kitti_poses", "write_kitti_poses", "read_euroc_csv", "read_trajectory",
           "Trajectory", "poses_from_quaternions", "ns_to_seconds"]

#: The leading columns of an EuRoC pose csv (``state_groundtruth_estimate0/data.csv`` holds 9 more)
EUROC_POSE_COLUMNS = ("timestamp [ns]", "p_x", "p_y", "p_z", "q_w", "q_x", "q_y", "q_z")



def poses_from_quaternions(positions: Any, quaternions: Any) -> np.ndarray:
    """(N,4,4) poses from positions (N,3) and quaternions (N,4) ``[qx, qy, qz, qw]`` of any non-zero
    norm (each scaled by its largest component first, so no square overflows, then normalized)."""
    quat = np.asarray(quaternions, dtype=float)
    quat = quat / np.abs(quat).max(axis=1, keepdims=True)
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    poses = np.tile(np.eye(4), (len(quat), 1, 1))
    poses[:, :3, :3] = se3.rotation_from_quaternion(quat)
    poses[:, :3, 3] = positions
    return poses


def ns_to_seconds(ns: Any) -> np.ndarray:
    """Integer nanoseconds (int64 array) as float64 seconds: whole seconds plus the fraction, so the
    result is within one float64 step of ``ns / 1e9`` computed exactly."""
    ns = np.asarray(ns, dtype=np.int64)
    return (ns // 1_000_000_000).astype(np.float64) + (ns % 1_000_000_000).astype(np.float64) * 1e-9


def _check_poses(world_T_imu: Any, what: str = "world_T_imu") -> np.ndarray:
    poses = np.asarray(world_T_imu, dtype=float)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"{what} must have shape (N, 4, 4), got {poses.shape}")
    return poses


def write_tum(
    path: str | os.PathLike,
    time_stamps: Any,
    world_T_imu: Any,
    header: str | None = None,
) -> None:
    """Write a trajectory in TUM format: ``t tx ty tz qx qy qz qw`` per line.

    Time is written with ``%.6f``, translation and the unit quaternion (scalar last, sign
    chosen so that ``qw >= 0``) with ``%.9f``. ``header`` (may span several lines) is
    written first as ``#`` comment lines.
    """
    t = np.asarray(time_stamps, dtype=float)
    poses = _check_poses(world_T_imu)
    if t.ndim != 1 or t.shape[0] != poses.shape[0]:
        raise ValueError(
            f"time_stamps must have shape ({poses.shape[0]},) to match the poses, got {t.shape}"
        )
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(poses))):
        bad = np.flatnonzero(~(np.isfinite(t) & np.isfinite(poses).all(axis=(1, 2))))
        raise ValueError(f"non-finite time stamp or pose at index {int(bad[0])}")

    lines: list[str] = []
    if header:
        for line in header.splitlines():
            lines.append(line if line.startswith("#") else f"# {line}")
    if len(poses):
        quat = se3.quaternion_from_rotation(poses[:, :3, :3])  # x, y, z, w with w >= 0
        trans = poses[:, :3, 3]
        for ti, p, q in zip(t, trans, quat):
            lines.append(
                f"{ti:.6f} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} "
                f"{q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}"
            )
    text = "\n".join(lines) + ("\n" if lines else "")
    with atomic_write(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def read_tum(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file; return ``(time_stamps (N,), world_T_imu (N, 4, 4))``.

    Blank lines and lines starting with ``#`` are skipped; quaternions are normalised.
    Raises :class:`InputError` with a one-line ``<file>:<line>: <problem>`` message for a
    line without 8 columns, a non-numeric or non-finite value, a zero-norm quaternion or a
    time stamp not greater than the previous one, and for a file without any pose.
    """
    stamps: list[float] = []
    rows: list[list[float]] = []
    for lineno, line in content_lines(read_lines(path)):
        tokens = line.split()
        if len(tokens) != 8:
            raise InputError(
                f"{path}:{lineno}: expected 8 columns (t tx ty tz qx qy qz qw), "
                f"found {len(tokens)}"
            )
        values = finite_numbers(tokens, f"{path}:{lineno}")
        if not any(values[4:]):  # any other scale is normalized
            raise InputError(f"{path}:{lineno}: quaternion has zero norm")
        if stamps and values[0] <= stamps[-1]:
            raise InputError(
                f"{path}:{lineno}: time stamp {tokens[0]} is not greater than the "
                f"previous one ({stamps[-1]:.9g})"
            )
        stamps.append(values[0])
        rows.append(values)

    if not rows:
        raise InputError(f"{path}: no poses found (empty trajectory file)")
    data = np.asarray(rows, dtype=float)
    return data[:, 0].copy(), poses_from_quaternions(data[:, 1:4], data[:, 4:8])


def write_kitti_poses(path: str | os.PathLike, world_T_imu: Any, imu_T_cam: Any, header: str | None = None) -> None:
    """Write a trajectory in the KITTI odometry pose format: per line the 12 numbers (row-major,
    ``%.9e``) of the top 3x4 of ``cam0_T_cam_k = (world_T_imu_0 imu_T_cam)^-1 world_T_imu_k imu_T_cam``,
    the left camera's pose in its first frame, as KITTI's ``poses/XX.txt`` and evo's ``kitti``
    format hold them (no time stamps: line k is frame k). ``header`` is not written (the format has
    no comments); it is accepted for symmetry with :func:`write_tum` and ignored."""
    poses = _check_poses(world_T_imu)
    T = np.asarray(imu_T_cam, dtype=float).reshape(4, 4)
    if not np.all(np.isfinite(poses)):
        bad = np.flatnonzero(~np.isfinite(poses).all(axis=(1, 2)))
        raise ValueError(f"non-finite pose at index {int(bad[0])}")
    world_T_cam = poses @ T
    cam0_T_cam = se3.inverse(world_T_cam[0]) @ world_T_cam if len(poses) else world_T_cam
    text = "".join(" ".join(f"{v:.9e}" for v in P[:3, :].ravel()) + "\n" for P in cam0_T_cam)
    with atomic_write(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def read_kitti_poses(path: str | os.PathLike) -> np.ndarray:
    """Read a KITTI odometry pose file (``poses/XX.txt``, what ``write_kitti_poses`` and evo's
    ``kitti`` format hold); return the poses (N, 4, 4), line k = frame k (no time stamps).

    Each non-blank line holds the 12 numbers of a pose's top 3x4, row-major. Rotations printed to a
    few decimals are replaced by the nearest rotation (SVD); InputError with a one-line
    ``<file>:<line>: <problem>`` for a line without 12 columns, a non-numeric or non-finite value,
    a rotation off orthonormal by more than ``ORTHO_ACCEPT`` or a reflection, and for a file
    without any pose.
    """
    rows: list[list[float]] = []
    for lineno, line in content_lines(read_lines(path)):
        tokens = line.split()
        if len(tokens) != 12:
            raise InputError(f"{path}:{lineno}: expected 12 columns (a KITTI pose: the top 3x4 of the 4x4, "
                             f"row-major), found {len(tokens)}")
        values = finite_numbers(tokens, f"{path}:{lineno}")
        R = np.asarray(values, dtype=float).reshape(3, 4)[:, :3]
        deviation = float(np.abs(R.T @ R - np.eye(3)).max())
        if not deviation <= ORTHO_ACCEPT or np.linalg.det(R) <= 0:
            what = f"off orthonormal by {deviation:.3g}" if deviation > ORTHO_ACCEPT else "a reflection (det < 0)"
            raise InputError(f"{path}:{lineno}: the rotation is not one: {what} (at most {ORTHO_ACCEPT:g})")
        rows.append(values)
    if not rows:
        raise InputError(f"{path}: no poses found (empty pose file)")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = np.asarray(rows, dtype=float).reshape(-1, 3, 4)
    U, _, Vt = np.linalg.svd(poses[:, :3, :3])
    poses[:, :3, :3] = U @ Vt
    return poses


def _nanoseconds(token: str, where: str) -> int:
    if not token.isdigit():
        raise InputError(f"{where}: time stamp {token!r} is not a whole number of nanoseconds (EuRoC csv)")
    return int(token)


def read_euroc_csv(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read an EuRoC ASL pose csv; return ``(time_stamps (N,) seconds, world_T_body (N, 4, 4))``.

    The first 8 comma-separated columns are :data:`EUROC_POSE_COLUMNS` (the quaternion scalar
    first), as in ``mav0/state_groundtruth_estimate0/data.csv`` (whose velocity and bias columns
    are ignored) and evo's ``euroc`` format; ``#`` lines and a first line of column names are
    skipped, quaternions are normalised. InputError ``<file>:<line>: <problem>`` for a line of fewer
    than 8 columns, a stamp that is not whole nanoseconds or not greater than the previous one, a
    non-numeric or non-finite value, a zero-norm quaternion, and for a file without any pose.
    """
    stamps: list[int] = []
    rows: list[list[float]] = []
    for k, (lineno, line) in enumerate(content_lines(read_lines(path))):
        tokens = [token.strip() for token in line.split(",")]
        if k == 0 and not any(c.isdigit() for c in tokens[0]):
            continue  # a first line of column names (no digit in its first column)
        where = f"{path}:{lineno}"
        if len(tokens) < len(EUROC_POSE_COLUMNS):
            raise InputError(f"{where}: expected at least 8 comma-separated columns ({', '.join(EUROC_POSE_COLUMNS)}), "
                             f"found {len(tokens)}")
        ns = _nanoseconds(tokens[0], where)
        values = finite_numbers(tokens[1:8], where)
        if not any(values[3:]):
            raise InputError(f"{where}: quaternion has zero norm")
        if stamps and ns <= stamps[-1]:
            raise InputError(f"{where}: time stamp {tokens[0]} is not greater than the previous one ({stamps[-1]})")
        stamps.append(ns)
        rows.append(values)
    if not rows:
        raise InputError(f"{path}: no poses found (empty EuRoC pose csv)")
    data = np.asarray(rows, dtype=float)
    return ns_to_seconds(stamps), poses_from_quaternions(data[:, 0:3], data[:, [4, 5, 6, 3]])  # w last


@dataclass(frozen=True)
class Trajectory:
    """Poses read from a trajectory file, with their time stamps (TUM, EuRoC csv) or their frame
    index (KITTI)."""

    time_stamps: np.ndarray  # (N,) seconds (TUM, EuRoC), or the frame index 0..N-1 (KITTI)
    poses: np.ndarray  # (N,4,4)
    format: str  # "tum" | "kitti" | "euroc"

    @property
    def by_index(self) -> bool:
        """Whether the poses carry no time (KITTI): they are matched to others line by line."""
        return self.format == "kitti"


def read_trajectory(path: str | os.PathLike) -> Trajectory:
    """A TUM, KITTI or EuRoC pose file, told apart by its first line that is no ``#`` comment (commas:
    EuRoC csv; else 8 columns: TUM, 12: KITTI); InputError naming the file and line for anything
    else (:func:`read_tum`, :func:`read_kitti_poses`, :func:`read_euroc_csv`)."""
    for lineno, line in content_lines(read_lines(path)):
        if "," in line:
            return Trajectory(*read_euroc_csv(path), "euroc")
        columns = len(line.split())
        if columns == 12:
            poses = read_kitti_poses(path)
            return Trajectory(np.arange(len(poses), dtype=float), poses, "kitti")
        if columns != 8:
            raise InputError(f"{path}:{lineno}: expected 8 columns (TUM: t tx ty tz qx qy qz qw), 12 (a KITTI pose: "
                             f"the top 3x4, row-major) or comma-separated EuRoC csv, found {columns}")
        break
    stamps, poses = read_tum(path)
    return Trajectory(stamps, poses, "tum")
