"""A EuRoC MAV sequence in its ASL folder layout: calibration, IMU samples, stereo frames, ground truth.

Burri et al., "The EuRoC micro aerial vehicle datasets", IJRR 2016. A sequence is a folder ``mav0/``
(:func:`read_euroc` also takes the folder holding it) with

* ``cam0/``, ``cam1/`` (left, right): ``data.csv`` (``#timestamp [ns],filename``), ``data/<ns>.png``
  (raw, distorted grey images) and ``sensor.yaml`` (:func:`read_camera_yaml`: ``T_BS`` =
  ``body_T_cam``, ``intrinsics: [fu, fv, cu, cv]``, ``distortion_model: radial-tangential``,
  ``distortion_coefficients: [k1, k2, p1, p2]``, ``resolution: [w, h]``, ``rate_hz``);
* ``imu0/``: ``data.csv`` (``#timestamp [ns],w_RS_S_x,w_RS_S_y,w_RS_S_z,a_RS_S_x,a_RS_S_y,a_RS_S_z``:
  the angular rate (rad/s) first, then the specific force (m/s^2), both in the IMU frame S) and
  ``sensor.yaml`` (``T_BS`` = ``body_T_imu``; Kalibr's four noise values);
* optionally ``state_groundtruth_estimate0/data.csv`` (``#time(ns),px,py,pz,qw,qx,qy,qz,vx,vy,vz,
  bwx,bwy,bwz,bax,bay,baz``: the body frame's pose in the world, quaternion w first, its world
  velocity and the gyroscope and accelerometer biases).

The ``sensor.yaml`` files start with OpenCV's ``%YAML:1.0``, which PyYAML refuses: that line is
skipped. The CSV files are read by position: lines starting with ``#`` are comments, a first line
without any number in it is a header, spaces around the commas are allowed. Stamps are integer
nanoseconds; they are kept as such (``stamps_ns``) and given in seconds as float64
(:func:`ns_to_seconds`, within one float64 step: 2.4e-7 s in 2014).

The images are raw: :class:`StereoRectification` (OpenCV ``stereoRectify``) rectifies a pair and
gives the rectified left camera's ``K``, the ``baseline`` and ``imu_T_cam``, what a tracker of
rectified pairs and the filter need.

Every problem raises :class:`~vislam.backend.errors.InputError` with one line
``<file>: key '<key>': <what>`` (for a CSV the key is the column, and the line is named).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from ..backend.data.inertial import ImuNoiseDensities, ImuSamples, check_imu_samples, check_noise_densities, KALIBR_KEYS
from ..backend.data.sequence import check_camera_matrix, input_error, nearest_rigid
from ..backend.data.files import note_input
from ..backend.data.textio import read_lines, text_float
from ..backend.data.tum import ns_to_seconds
from ..backend.errors import InputError
from ..backend.geometry import se3
from .images import read_grey

__all__ = [
    "CameraCalibration", "EurocImu", "StereoFrames", "GroundTruth", "StereoRectification", "EurocDataset",
    "read_camera_yaml", "read_imu", "read_frames", "read_ground_truth", "read_euroc", "open_euroc_input", "is_euroc",
    "find_mav0",
    "ns_to_seconds", "IMU_COLUMNS", "GROUND_TRUTH_COLUMNS", "CAMERA_COLUMNS", "QUATERNION_TOL",
]

#: Columns of ``imu0/data.csv`` (by position; the names are those errors give as the key)
IMU_COLUMNS = ("timestamp", "w_RS_S_x", "w_RS_S_y", "w_RS_S_z", "a_RS_S_x", "a_RS_S_y", "a_RS_S_z")
#: Columns of ``state_groundtruth_estimate0/data.csv``
GROUND_TRUTH_COLUMNS = ("timestamp", "p_RS_R_x", "p_RS_R_y", "p_RS_R_z", "q_RS_w", "q_RS_x", "q_RS_y", "q_RS_z",
                        "v_RS_R_x", "v_RS_R_y", "v_RS_R_z", "b_w_RS_S_x", "b_w_RS_S_y", "b_w_RS_S_z",
                        "b_a_RS_S_x", "b_a_RS_S_y", "b_a_RS_S_z")
#: Columns of ``cam0/data.csv`` and ``cam1/data.csv``
CAMERA_COLUMNS = ("timestamp", "filename")
#: A ground-truth quaternion whose norm is off 1 by more than this is refused (others are normalized)
QUATERNION_TOL = 1e-3
#: The distortion models read as radial-tangential (k1, k2, p1, p2: OpenCV's first four coefficients)
RADTAN_NAMES = ("radial-tangential", "radtan")
#: Largest |P_right[1,3]| / |P_right[0,3]| of a horizontal rectified pair
_VERTICAL_TOL = 1e-6

GT_DIR = "state_groundtruth_estimate0"
_LAYOUT = "a EuRoC ASL folder: mav0/ with cam0/, cam1/ and imu0/, each holding data.csv and sensor.yaml"


# ---------------------------------------------------------------------------------------------- dataclasses


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """One camera of a ``sensor.yaml``: a pinhole with radial-tangential distortion.

    Attributes
    ----------
    body_T_cam : (4, 4) ndarray
        ``T_BS``: maps camera-frame points into the body frame (rotation re-orthonormalized when it
        was typed to a few digits, :func:`~vislam.backend.data.sequence.nearest_rigid`).
    K : (3, 3) ndarray
        ``[[fu, 0, cu], [0, fv, cv], [0, 0, 1]]`` of the raw (distorted) images.
    distortion : (4,) ndarray
        ``k1, k2, p1, p2`` (OpenCV's order).
    resolution : (int, int)
        Image width and height (px).
    rate_hz : float or None
        ``rate_hz`` when the file gives it.
    source : str
        The file.
    notes : tuple of str
        What was accepted with a remark (a re-orthonormalized rotation).
    """

    body_T_cam: np.ndarray
    K: np.ndarray
    distortion: np.ndarray
    resolution: tuple[int, int]
    rate_hz: float | None
    source: str
    notes: tuple[str, ...] = ()


@dataclass(frozen=True, eq=False)
class EurocImu:
    """The IMU record and where the IMU sits on the body.

    Attributes
    ----------
    samples : ImuSamples
        Stamps (L,) s, specific force (L, 3) m/s^2 and angular rate (L, 3) rad/s in the IMU frame
        (never rotated into the body frame: the filter's IMU frame is the IMU), with the noise of
        ``imu0/sensor.yaml``.
    body_T_imu : (4, 4) ndarray
        ``T_BS`` of ``imu0/sensor.yaml`` (the identity in EuRoC: the body frame is the IMU frame).
    rate_hz : float or None
        ``rate_hz`` of ``imu0/sensor.yaml`` when given (the measured one is ``samples.rate_hz``).
    notes : tuple of str
    """

    samples: ImuSamples
    body_T_imu: np.ndarray
    rate_hz: float | None = None
    notes: tuple[str, ...] = ()


@dataclass(frozen=True, eq=False)
class StereoFrames:
    """The stereo pairs: rows of ``cam0/data.csv`` and ``cam1/data.csv`` with identical stamps.

    Attributes
    ----------
    times : (N,) ndarray
        Seconds (float64), strictly increasing.
    stamps_ns : (N,) ndarray
        The same stamps, int64 nanoseconds as the files give them.
    left_paths, right_paths : tuple of Path
        ``cam0/data/<filename>`` and ``cam1/data/<filename>`` of each pair (each exists).
    unmatched : int
        Rows of either file without a row of the same stamp in the other, dropped.
    """

    times: np.ndarray
    stamps_ns: np.ndarray
    left_paths: tuple[Path, ...]
    right_paths: tuple[Path, ...]
    unmatched: int = 0

    def __len__(self) -> int:
        return int(self.times.shape[0])


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """``state_groundtruth_estimate0/data.csv``: the IMU's pose, velocity and biases over time.

    Attributes
    ----------
    times : (N,) ndarray
        Seconds, strictly increasing.
    world_T_imu : (N, 4, 4) ndarray
        The file's body pose (quaternion normalized) composed with ``body_T_imu``.
    velocity : (N, 3) ndarray
        World-frame velocity (m/s) of the body frame's origin, as the file gives it (the IMU's when
        ``body_T_imu`` has no translation, as in EuRoC).
    gyro_bias, accel_bias : (N, 3) ndarray
        Gyroscope (rad/s) and accelerometer (m/s^2) biases, as the file gives them.
    source : str
    notes : tuple of str
    """

    times: np.ndarray
    world_T_imu: np.ndarray
    velocity: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray
    source: str = ""
    notes: tuple[str, ...] = ()

    def __len__(self) -> int:
        return int(self.times.shape[0])


@dataclass(frozen=True, eq=False)
class StereoRectification:
    """OpenCV's rectification of a raw pair (``stereoRectify`` with ``CALIB_ZERO_DISPARITY``, ``alpha=0``).

    The rectified left camera frame is the raw left one rotated by ``R_left`` (``x_rect = R_left
    x_cam0``); both rectified cameras share ``K`` and that orientation, the right one displaced by
    ``baseline`` along x.

    Attributes
    ----------
    K : (3, 3) ndarray
        Rectified intrinsics, ``P_left[:, :3]`` (= ``P_right[:, :3]``).
    baseline : float
        ``-P_right[0, 3] / P_right[0, 0]`` (m), > 0.
    R_left, R_right : (3, 3) ndarray
        The rectifying rotations R1, R2 (raw camera -> rectified camera).
    P_left, P_right : (3, 4) ndarray
        The rectified projection matrices P1, P2.
    map_left_x, map_left_y, map_right_x, map_right_y : (h, w) float32 ndarray
        ``initUndistortRectifyMap`` maps: rectified pixel -> raw pixel.
    size : (int, int)
        Image width and height (px), raw and rectified.
    body_T_cam0 : (4, 4) ndarray
        The raw left camera in the body frame.
    cam1_T_cam0 : (4, 4) ndarray
        Maps raw left-camera points into the raw right camera (the R, T given to ``stereoRectify``).
    """

    K: np.ndarray
    baseline: float
    R_left: np.ndarray
    R_right: np.ndarray
    P_left: np.ndarray
    P_right: np.ndarray
    map_left_x: np.ndarray
    map_left_y: np.ndarray
    map_right_x: np.ndarray
    map_right_y: np.ndarray
    size: tuple[int, int]
    body_T_cam0: np.ndarray
    cam1_T_cam0: np.ndarray

    @classmethod
    def from_cameras(cls, left: CameraCalibration, right: CameraCalibration) -> "StereoRectification":
        """The rectification of the pair ``left`` (cam0), ``right`` (cam1).

        ``cam1_T_cam0 = inv(body_T_cam1) @ body_T_cam0``: its R, T map left-camera points into the
        right camera, what ``stereoRectify`` wants for (camera 1, camera 2). InputError naming
        ``right``'s file when the resolutions differ, the cameras are displaced vertically or the
        right camera is not to the right of the left one.
        """
        if left.resolution != right.resolution:
            raise input_error(right.source, "resolution",
                              f"{right.resolution[0]}x{right.resolution[1]} differs from the left camera's "
                              f"{left.resolution[0]}x{left.resolution[1]} ({left.source})")
        size = (int(left.resolution[0]), int(left.resolution[1]))
        cam1_T_cam0 = se3.inverse(right.body_T_cam) @ left.body_T_cam
        R, T = cam1_T_cam0[:3, :3].copy(), cam1_T_cam0[:3, 3].reshape(3, 1).copy()
        if not np.linalg.norm(T) > 0:
            raise input_error(right.source, "T_BS", "the two cameras are at the same place: no stereo baseline")
        R1, R2, P1, P2, _, _, _ = cv2.stereoRectify(
            left.K, left.distortion, right.K, right.distortion, size, R, T,
            flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
        if abs(P2[1, 3]) > _VERTICAL_TOL * abs(P2[0, 3]):
            raise input_error(right.source, "T_BS", "the cameras are displaced more vertically than horizontally "
                                                    f"(cam1 at {_fmt(-R.T @ T.ravel())} m in cam0's frame): "
                                                    "not a left-right stereo pair")
        K = P1[:, :3].copy()
        check_camera_matrix(left.source, "intrinsics", K)
        baseline = float(-P2[0, 3] / P2[0, 0])
        if not baseline > 0:
            raise input_error(right.source, "T_BS", f"the right camera (cam1) is {abs(baseline):.6g} m to the LEFT "
                                                    f"of cam0 (cam1 at {_fmt(-R.T @ T.ravel())} m in cam0's frame): "
                                                    "swap cam0 and cam1")
        maps = [cv2.initUndistortRectifyMap(cam.K, cam.distortion, Rr, P, size, cv2.CV_32FC1)
                for cam, Rr, P in ((left, R1, P1), (right, R2, P2))]
        return cls(K=K, baseline=baseline, R_left=R1, R_right=R2, P_left=P1, P_right=P2,
                   map_left_x=maps[0][0], map_left_y=maps[0][1], map_right_x=maps[1][0], map_right_y=maps[1][1],
                   size=size, body_T_cam0=left.body_T_cam.copy(), cam1_T_cam0=cam1_T_cam0)

    @property
    def cam0_T_rect(self) -> np.ndarray:
        """(4, 4) maps rectified-left-camera points into the raw left camera: ``[R_left^T, 0; 0, 1]``."""
        T = np.eye(4)
        T[:3, :3] = self.R_left.T
        return T

    def imu_T_cam(self, body_T_imu: np.ndarray) -> np.ndarray:
        """(4, 4) the rectified left camera in the IMU frame (maps its points into the IMU frame).

        ``imu_T_cam = inv(body_T_imu) @ body_T_cam0 @ [R_left^T, 0; 0, 1]``.
        """
        return se3.inverse(np.asarray(body_T_imu, dtype=np.float64)) @ self.body_T_cam0 @ self.cam0_T_rect

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The rectified pair ``(left_rect, right_rect)`` of raw images of shape (h, w) (``cv2.remap``,
        bilinear); ValueError for another shape."""
        w, h = self.size
        for name, img in (("left", left), ("right", right)):
            if np.shape(img)[:2] != (h, w):
                raise ValueError(f"{name} image of shape {np.shape(img)}: the calibration's is ({h}, {w})")
        return (cv2.remap(left, self.map_left_x, self.map_left_y, cv2.INTER_LINEAR),
                cv2.remap(right, self.map_right_x, self.map_right_y, cv2.INTER_LINEAR))


class RectifiedRig:
    """What a rectified stereo pair on an IMU gives the tracker (:class:`EurocDataset`,
    ``frontend.bag.BagDataset``): needs ``rectification`` and ``imu`` (an :class:`EurocImu`)."""

    @property
    def K(self) -> np.ndarray:
        """(3, 3) rectified left intrinsics."""
        return self.rectification.K

    @property
    def baseline(self) -> float:
        """Rectified baseline (m)."""
        return self.rectification.baseline

    @property
    def imu_T_cam(self) -> np.ndarray:
        """(4, 4) the rectified left camera in the IMU frame."""
        return self.rectification.imu_T_cam(self.imu.body_T_imu)


@dataclass(frozen=True, eq=False)
class EurocDataset(RectifiedRig):
    """Everything of a EuRoC sequence but the image pixels (read on demand by :meth:`read_pair`).

    Attributes
    ----------
    root : Path
        The ``mav0`` folder.
    cam0, cam1 : CameraCalibration
        Left and right camera.
    imu : EurocImu
    frames : StereoFrames
    rectification : StereoRectification
    ground_truth : GroundTruth or None
        None without ``state_groundtruth_estimate0/data.csv``.
    notes : tuple of str
        Every reader's remarks, and frames outside the IMU record.
    """

    root: Path
    cam0: CameraCalibration
    cam1: CameraCalibration
    imu: EurocImu
    frames: StereoFrames
    rectification: StereoRectification
    ground_truth: GroundTruth | None
    notes: tuple[str, ...] = ()

    def read_pair(self, index: int, rectified: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """(left, right) (h, w) uint8 grey images of pair ``index``, rectified unless ``rectified`` is
        False; InputError naming an image that is unreadable or not of the calibration's size."""
        images = []
        w, h = self.rectification.size
        for path in (self.frames.left_paths[index], self.frames.right_paths[index]):
            img = read_grey(path)
            if img.shape != (h, w):
                raise InputError(f"{path}: size {img.shape[1]}x{img.shape[0]} differs from the calibration's "
                                 f"{w}x{h} (resolution of {self.cam0.source})")
            images.append(img)
        return self.rectification.rectify(*images) if rectified else (images[0], images[1])

    def pairs(self):
        """Yield (index, left, right) of every pair, rectified (as ``StereoDirectory.frames`` does)."""
        for k in range(len(self.frames)):
            yield (k, *self.read_pair(k))


# ---------------------------------------------------------------------------------------------- small helpers


def _fmt(v) -> str:
    return "[" + ", ".join(f"{float(x):.6g}" for x in np.ravel(v)) + "]"


def is_euroc(path) -> bool:
    """``path`` is an EuRoC ASL folder (``mav0`` or its parent, with cam0/, cam1/, imu0/)."""
    try:
        find_mav0(path)
    except InputError:
        return False
    return True


def open_euroc_input(path, imu_path=None, imu_T_cam_path=None, imu_input: str = "auto") -> "EurocDataset":
    """The EuRoC folder ``path`` as a command's input (:func:`read_euroc`); InputError (one line) with
    an IMU file or extrinsic (the folder carries both) or ``imu_input`` "velocity" (it has none)."""
    if imu_path or imu_T_cam_path:
        raise InputError(f"{path}: --imu and --imu-T-cam are for an odometry-layout directory; an EuRoC folder "
                         "carries its IMU and calibration")
    if imu_input == "velocity":
        raise InputError(f"{path}: --imu-input velocity: an EuRoC folder has a real IMU's samples, no velocities")
    return read_euroc(path)


def find_mav0(path) -> Path:
    """The ``mav0`` folder of ``path`` (``path`` itself, or ``path/mav0``); InputError naming what is
    missing unless it holds ``cam0/``, ``cam1/`` and ``imu0/``."""
    p = Path(path)
    if not p.is_dir():
        raise InputError(f"{p}: {'not a directory' if p.exists() else 'missing directory'} (expected {_LAYOUT})")
    root = p / "mav0" if (p / "mav0").is_dir() else p
    missing = [f"{name}/" for name in ("cam0", "cam1", "imu0") if not (root / name).is_dir()]
    if missing:
        where = "" if root != p or p.name == "mav0" else " and no mav0/ in it"
        raise InputError(f"{root}: not {_LAYOUT}: missing {', '.join(missing)}{where}")
    note_input(root, contents=True)  # every file under mav0/ is the sequence's: no output goes there
    return root


# ---------------------------------------------------------------------------------------------- YAML


class _Loader(yaml.SafeLoader):
    """PyYAML's safe loader, also reading OpenCV's ``!!opencv-matrix`` tag as a mapping."""


_Loader.add_constructor("tag:yaml.org,2002:opencv-matrix",
                        lambda loader, node: loader.construct_mapping(node, deep=True))


def _read_yaml(path: Path, what: str) -> dict:
    """The mapping of a ``sensor.yaml`` (a first ``%YAML`` line, OpenCV's, is skipped)."""
    lines = read_lines(path, f"missing ({what})")
    for i, line in enumerate(lines):
        if line.strip():
            if line.lstrip().startswith("%YAML"):
                lines[i] = ""  # keep the line numbers of the errors
            break
    try:
        data = yaml.load("\n".join(lines), Loader=_Loader)  # noqa: S506 (a safe loader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e)
        raise InputError(" ".join(f"{path}: {where}not valid YAML: {problem}".split())) from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: not a YAML mapping of keys (got {type(data).__name__}); expected {what}")
    return data


def _number(src: str, key: str, value) -> float:
    """A finite number of a YAML value (a string such as ``1e-3``, which YAML 1.1 reads as text, too)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise input_error(src, key, f"expected a number, got {_show(value)}")
    try:
        x = text_float(value) if isinstance(value, str) else float(value)
    except (ValueError, OverflowError):
        raise input_error(src, key, f"not a number: {_show(value)}") from None
    if not math.isfinite(x):
        raise input_error(src, key, f"non-finite value {_show(value)}")
    return x


def _show(value) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _numbers(src: str, key: str, value, count: int | None = None) -> np.ndarray:
    """A YAML list of finite numbers as a float64 array, of ``count`` numbers when given."""
    if not isinstance(value, list):
        raise input_error(src, key, f"expected a list [..] of {count or 'some'} numbers, got {_show(value)}")
    if count is not None and len(value) != count:
        raise input_error(src, key, f"{len(value)} numbers, expected {count}")
    return np.array([_number(src, f"{key}[{i}]", v) for i, v in enumerate(value)], dtype=np.float64)


def _required(src: str, data: dict, key: str, what: str, prefix: str = ""):
    if key not in data or data[key] is None:
        raise input_error(src, prefix + key, f"missing ({what})")
    return data[key]


def _rate(src: str, data: dict) -> float | None:
    if data.get("rate_hz") is None:
        return None
    rate = _number(src, "rate_hz", data["rate_hz"])
    if not rate > 0:
        raise input_error(src, "rate_hz", f"must be > 0, got {rate:g}")
    return rate


def _sensor_type(src: str, data: dict, expected: str) -> None:
    kind = data.get("sensor_type")
    if kind is not None and str(kind).strip().lower() != expected:
        raise input_error(src, "sensor_type", f"{_show(kind)}: expected {expected!r} (is this the right sensor.yaml?)")


def _T_BS(src: str, data: dict) -> tuple[np.ndarray, str | None]:
    """``T_BS`` (4,4) as ``{rows: 4, cols: 4, data: [16 numbers]}`` (or a 4x4 nested list), checked
    rigid and re-orthonormalized (:func:`nearest_rigid`); (matrix, note or None)."""
    value = _required(src, data, "T_BS", "body_T_sensor: {cols: 4, rows: 4, data: [16 numbers, row by row]}")
    if isinstance(value, dict):
        for key in ("rows", "cols"):
            n = value.get(key)
            if n is None:
                raise input_error(src, f"T_BS.{key}", "missing (T_BS is {cols: 4, rows: 4, data: [16 numbers]})")
            if isinstance(n, bool) or not isinstance(n, int) or n != 4:
                raise input_error(src, f"T_BS.{key}", f"expected 4, got {_show(n)}")
        if value.get("data") is None:
            raise input_error(src, "T_BS.data", "missing (16 numbers, row by row)")
        entries, key = value["data"], "T_BS.data"
    else:
        entries, key = value, "T_BS"
    return rigid_matrix(src, key, entries, "T_BS")


def rigid_matrix(src: str, key: str, entries, name: str | None = None) -> tuple[np.ndarray, str | None]:
    """A 4x4 rigid transform from YAML: a nested list of 4 rows of 4 numbers (Kalibr's ``T_cam_imu``)
    or 16 numbers row by row, checked rigid and re-orthonormalized (:func:`nearest_rigid`, naming
    ``name`` or ``key``); (matrix, note or None)."""
    if isinstance(entries, list) and len(entries) == 4 and all(isinstance(r, list) for r in entries):
        rows = [_numbers(src, f"{key}[{i}]", r, 4) for i, r in enumerate(entries)]
        T = np.array(rows)
    else:
        T = _numbers(src, key, entries, 16).reshape(4, 4)
    return nearest_rigid(src, name or key, T)


# ---------------------------------------------------------------------------------------------- sensor.yaml


def read_camera_yaml(path) -> CameraCalibration:
    """A camera's ``sensor.yaml``: ``T_BS``, ``intrinsics``, ``distortion_*``, ``resolution``, ``rate_hz``.

    Only ``camera_model: pinhole`` (the default when absent) and ``distortion_model:
    radial-tangential`` (or ``radtan``) with 4 coefficients are read; other models (``equidistant``,
    ``fov``, ``omni``, ...) are refused naming them. InputError ``<file>: key '<key>': <what>`` for a
    missing or malformed key, a rotation that is not one, a focal length <= 0 or a principal point
    outside the image.

    Returns
    -------
    CameraCalibration
    """
    path = Path(path)
    src = str(path)
    data = _read_yaml(path, "a camera's sensor.yaml: T_BS, intrinsics, distortion_model, distortion_coefficients, "
                            "resolution")
    _sensor_type(src, data, "camera")
    K, distortion, resolution = pinhole(src, data)
    body_T_cam, note = _T_BS(src, data)
    return CameraCalibration(body_T_cam=body_T_cam, K=K, distortion=distortion, resolution=resolution,
                             rate_hz=_rate(src, data), source=src, notes=(note,) if note else ())


def pinhole(src: str, data: dict, prefix: str = "",
            distortion_key: str = "distortion_coefficients") -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """(K (3,3), distortion (4,) k1 k2 p1 p2, (width, height)) of a camera's YAML mapping ``data``:
    ``camera_model`` (pinhole, the default), ``distortion_model`` (radial-tangential / radtan),
    ``resolution``, ``intrinsics`` and the coefficients under ``distortion_key`` (EuRoC's
    ``distortion_coefficients``, Kalibr's ``distortion_coeffs``); errors name ``prefix`` + the key."""
    model = data.get("camera_model", "pinhole")
    if model is None or str(model).strip().lower() != "pinhole":
        raise input_error(src, prefix + "camera_model", f"{_show(model)} is not supported (only 'pinhole', with "
                                                        "radial-tangential distortion)")
    dist_model = _required(src, data, "distortion_model", "radial-tangential", prefix)
    if str(dist_model).strip().lower() not in RADTAN_NAMES:
        raise input_error(src, prefix + "distortion_model", f"{_show(dist_model)} is not supported (only "
                                                            "'radial-tangential': k1, k2, p1, p2)")
    resolution = _numbers(src, prefix + "resolution",
                          _required(src, data, "resolution", "[width, height] in pixels", prefix), 2)
    if not (np.all(resolution == np.round(resolution)) and np.all(resolution >= 1)):
        raise input_error(src, prefix + "resolution",
                          f"expected two whole numbers >= 1 (width, height), got {resolution.tolist()}")
    w, h = (int(x) for x in resolution)
    fu, fv, cu, cv = _numbers(src, prefix + "intrinsics",
                              _required(src, data, "intrinsics", "[fu, fv, cu, cv]", prefix), 4)
    if not (fu > 0 and fv > 0):
        raise input_error(src, prefix + "intrinsics", f"focal lengths fu = {fu:g}, fv = {fv:g} must be > 0")
    if not (0 <= cu <= w and 0 <= cv <= h):
        raise input_error(src, prefix + "intrinsics", f"principal point ({cu:g}, {cv:g}) outside the {w}x{h} image")
    distortion = _numbers(src, prefix + distortion_key,
                          _required(src, data, distortion_key, "[k1, k2, p1, p2]", prefix), 4)
    return np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]]), distortion, (w, h)


# ---------------------------------------------------------------------------------------------- CSV


def _is_header(fields: list[str]) -> bool:
    """A line none of whose fields is a number."""
    for f in fields:
        try:
            text_float(f)
            return False
        except ValueError:
            pass
    return True


def _read_csv(path: Path, columns: tuple[str, ...], what: str, numeric: bool = True):
    """Rows of a EuRoC ``data.csv`` by position: (stamps_ns (N,) int64, values, line numbers (N,)).

    ``values`` is an (N, len(columns) - 1) float64 array, or with ``numeric`` False a list of the
    rows' other fields as text. Comments (``#``) and blank lines are skipped, and a first line
    without any number (a header without ``#``). InputError naming the file, the column and the line
    for a line of another length, a stamp that is not a whole number of nanoseconds, a value that is
    not a finite number, or stamps not strictly increasing.
    """
    src = str(path)
    n = len(columns)
    stamps: list[int] = []
    rows: list = []
    numbers: list[int] = []
    first = True
    for number, line in enumerate(read_lines(path, f"missing ({what})"), start=1):
        text = line.strip()
        if not text:
            continue
        if text.startswith("#"):
            first = False
            continue
        fields = [f.strip() for f in text.split(",")]
        if first:
            first = False
            if _is_header(fields):
                continue
        if len(fields) != n:
            if len(fields) < n:
                raise input_error(src, columns[len(fields)],
                                  f"line {number}: missing (the line has {len(fields)} of the {n} values: truncated?)")
            raise input_error(src, columns[-1], f"line {number}: {len(fields)} values, expected {n} "
                                                f"({columns[0]},{columns[1]},...)")
        token = fields[0]
        if not (token.isascii() and token.isdigit()):
            raise input_error(src, columns[0], f"line {number}: not a whole number of nanoseconds: {_show(token)}")
        stamp = int(token)
        if stamp >= 2**63:
            raise input_error(src, columns[0], f"line {number}: stamp {token} ns out of range (>= 2^63)")
        if stamps and stamp <= stamps[-1]:
            raise input_error(src, columns[0], f"line {number}: stamps not strictly increasing: {stamp} ns <= "
                                               f"{stamps[-1]} ns (line {numbers[-1]})")
        if numeric:
            values = []
            for key, f in zip(columns[1:], fields[1:]):
                try:
                    x = text_float(f)
                except ValueError:
                    raise input_error(src, key, f"line {number}: not a number: {_show(f)}") from None
                if not math.isfinite(x):
                    raise input_error(src, key, f"line {number}: non-finite value {_show(f)}")
                values.append(x)
            rows.append(values)
        else:
            rows.append(fields[1:])
        stamps.append(stamp)
        numbers.append(number)
    ns = np.array(stamps, dtype=np.int64)
    if numeric:
        rows = np.array(rows, dtype=np.float64).reshape(len(stamps), n - 1)
    return ns, rows, np.array(numbers, dtype=np.int64)


# ---------------------------------------------------------------------------------------------- IMU


def read_imu(mav0) -> EurocImu:
    """``imu0/data.csv`` and ``imu0/sensor.yaml`` of a sequence (``mav0`` or its parent folder).

    The samples stay in the IMU frame S: ``a_RS_S`` (specific force, m/s^2) and ``w_RS_S`` (angular
    rate, rad/s; the csv gives it first), stamps ``ns / 1e9`` s; the noise is ``sensor.yaml``'s
    (:func:`~vislam.backend.data.inertial.check_noise_densities`), ``body_T_imu`` its ``T_BS``.

    Returns
    -------
    EurocImu
    """
    root = find_mav0(mav0)
    noise, body_T_imu, rate, notes = read_imu_yaml(root / "imu0" / "sensor.yaml")
    csv_path = root / "imu0" / "data.csv"
    ns, rows, _ = _read_csv(csv_path, IMU_COLUMNS, "IMU samples: " + ",".join(IMU_COLUMNS))
    samples = check_imu_samples(str(csv_path), ns_to_seconds(ns), rows[:, 3:6], rows[:, 0:3], noise,
                                keys=("timestamp", "a_RS_S", "w_RS_S"))
    return EurocImu(samples=samples, body_T_imu=body_T_imu, rate_hz=rate, notes=notes)


def read_imu_yaml(path) -> tuple[ImuNoiseDensities, np.ndarray, float | None, tuple[str, ...]]:
    """The IMU's ``sensor.yaml``: (noise densities, ``T_BS`` (4,4), ``rate_hz`` or None, notes)."""
    yaml_path = Path(path)
    ysrc = str(yaml_path)
    data = _read_yaml(yaml_path, "the IMU's sensor.yaml: T_BS and " + ", ".join(KALIBR_KEYS))
    _sensor_type(ysrc, data, "imu")
    body_T_imu, note = _T_BS(ysrc, data)
    values = {k: _number(ysrc, k, data[k]) for k in KALIBR_KEYS if data.get(k) is not None}
    return check_noise_densities(ysrc, values), body_T_imu, _rate(ysrc, data), (note,) if note else ()


# ---------------------------------------------------------------------------------------------- frames


def _camera_rows(root: Path, cam: str) -> tuple[np.ndarray, list[Path]]:
    path = root / cam / "data.csv"
    ns, rows, numbers = _read_csv(path, CAMERA_COLUMNS, "one line timestamp [ns],filename an image", numeric=False)
    paths = []
    for fields, number in zip(rows, numbers):
        name = fields[0]
        if not name or Path(name).name != name or name in (".", ".."):
            raise input_error(str(path), "filename", f"line {number}: not a file name in {cam}/data/: {_show(name)}")
        paths.append(root / cam / "data" / name)
    return ns, paths


def read_frames(mav0) -> StereoFrames:
    """The stereo pairs of a sequence (``mav0`` or its parent): rows of ``cam0/data.csv`` and
    ``cam1/data.csv`` with identical stamps, in time order.

    Rows whose stamp is in one file only are dropped and counted (``unmatched``). InputError naming
    the file for a missing image of a pair, or when fewer than 2 pairs remain.

    Returns
    -------
    StereoFrames
    """
    root = find_mav0(mav0)
    ns_left, left = _camera_rows(root, "cam0")
    ns_right, right = _camera_rows(root, "cam1")
    common, i_left, i_right = np.intersect1d(ns_left, ns_right, assume_unique=True, return_indices=True)
    if common.size < 2:
        raise input_error(str(root / "cam1" / "data.csv"), "timestamp",
                          f"{common.size} stamps in common with {root / 'cam0' / 'data.csv'} "
                          f"({ns_left.size} and {ns_right.size} rows): need at least 2 stereo pairs")
    left_paths = tuple(left[i] for i in i_left)
    right_paths = tuple(right[i] for i in i_right)
    for p in (*left_paths, *right_paths):
        if not p.is_file():
            raise InputError(f"{p}: missing image (listed in {p.parent.parent / 'data.csv'})")
    unmatched = int(ns_left.size + ns_right.size - 2 * common.size)
    return StereoFrames(times=ns_to_seconds(common), stamps_ns=common, left_paths=left_paths,
                        right_paths=right_paths, unmatched=unmatched)


# ---------------------------------------------------------------------------------------------- ground truth


def read_ground_truth(mav0, body_T_imu: np.ndarray | None = None) -> GroundTruth | None:
    """``state_groundtruth_estimate0/data.csv`` of a sequence (``mav0`` or its parent), None without it.

    ``world_T_imu = world_T_body @ body_T_imu`` (``body_T_imu`` defaults to the identity, EuRoC's),
    ``world_T_body`` from ``p`` and the quaternion ``q = (w, x, y, z)``, normalized; a quaternion
    whose norm is off 1 by more than :data:`QUATERNION_TOL` is refused naming its line.

    Returns
    -------
    GroundTruth or None
    """
    root = find_mav0(mav0)
    path = root / GT_DIR / "data.csv"
    if not path.is_file():
        return None
    src = str(path)
    ns, rows, numbers = _read_csv(path, GROUND_TRUTH_COLUMNS, "ground truth: " + ",".join(GROUND_TRUTH_COLUMNS))
    if ns.size < 2:
        raise input_error(src, "timestamp", f"{ns.size} rows: need at least 2")
    q = rows[:, 3:7]  # w x y z
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(~(np.abs(norm - 1.0) <= QUATERNION_TOL))
    if bad.size:
        i = int(bad[0])
        raise input_error(src, "q_RS_w", f"line {numbers[i]} (row {i + 1}): quaternion (w, x, y, z) = {_fmt(q[i])} of "
                                         f"norm {norm[i]:.6g}: not a unit quaternion (| |q| - 1 | > {QUATERNION_TOL:g})")
    q = q / norm[:, None]
    world_T_body = np.zeros((ns.size, 4, 4))
    world_T_body[:, :3, :3] = se3.rotation_from_quaternion(q[:, [1, 2, 3, 0]])
    world_T_body[:, :3, 3] = rows[:, 0:3]
    world_T_body[:, 3, 3] = 1.0
    notes = ()
    if body_T_imu is not None:
        body_T_imu = np.asarray(body_T_imu, dtype=np.float64)
        world_T_imu = world_T_body @ body_T_imu
        if np.any(body_T_imu[:3, 3] != 0):
            notes = (f"{src}: velocity is the body origin's; the IMU sits {_fmt(body_T_imu[:3, 3])} m from it "
                     "(its velocity differs by the rotation rate x that lever arm)",)
    else:
        world_T_imu = world_T_body
    return GroundTruth(times=ns_to_seconds(ns), world_T_imu=world_T_imu, velocity=rows[:, 7:10].copy(),
                       gyro_bias=rows[:, 10:13].copy(), accel_bias=rows[:, 13:16].copy(), source=src, notes=notes)


# ---------------------------------------------------------------------------------------------- everything


def read_euroc(path) -> EurocDataset:
    """A EuRoC sequence in the ASL layout: ``path`` is its ``mav0`` folder or the folder holding it.

    Reads both cameras' ``sensor.yaml``, the IMU, the stereo pairs, the rectification and, when
    present, the ground truth (the images are read on demand: :meth:`EurocDataset.read_pair`).
    InputError naming what is missing when ``path`` is not an ASL folder, and naming the file and
    key of any bad input.

    Returns
    -------
    EurocDataset
    """
    root = find_mav0(path)
    cam0 = read_camera_yaml(root / "cam0" / "sensor.yaml")
    cam1 = read_camera_yaml(root / "cam1" / "sensor.yaml")
    imu = read_imu(root)
    frames = read_frames(root)
    rectification = StereoRectification.from_cameras(cam0, cam1)
    ground_truth = read_ground_truth(root, imu.body_T_imu)
    notes = [*cam0.notes, *cam1.notes, *imu.notes, *(ground_truth.notes if ground_truth else ())]
    t = imu.samples.time_stamps
    outside = int(np.count_nonzero((frames.times < t[0]) | (frames.times > t[-1])))
    if outside:
        notes.append(f"{root / 'imu0' / 'data.csv'}: {outside} of {len(frames)} stereo pairs lie outside the IMU "
                     f"record ({t[0]:.3f} - {t[-1]:.3f} s)")
    if frames.unmatched:
        notes.append(f"{root / 'cam1' / 'data.csv'}: {frames.unmatched} frames without a partner of the same "
                     "stamp in the other camera dropped")
    return EurocDataset(root=root, cam0=cam0, cam1=cam1, imu=imu, frames=frames, rectification=rectification,
                        ground_truth=ground_truth, notes=tuple(notes))
