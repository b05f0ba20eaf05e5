"""Kalibr's calibration files: ``camchain.yaml`` (the stereo pair and each camera's pose in the IMU
frame) and ``imu.yaml`` (the IMU's noise densities), as Kalibr writes them after a calibration.

``camchain.yaml`` holds ``cam0`` and ``cam1``, each with ``camera_model: pinhole``,
``intrinsics: [fu, fv, cu, cv]``, ``distortion_model: radtan`` with ``distortion_coeffs: [k1, k2,
p1, p2]``, ``resolution: [w, h]``, ``T_cam_imu`` (4x4: maps IMU-frame points into the camera),
optionally ``rostopic`` and ``timeshift_cam_imu`` (s: ``t_imu = t_cam + timeshift``); ``cam1`` may
give ``T_cn_cnm1`` (maps cam0 points into cam1) instead of its own ``T_cam_imu``. The body frame of
the result is the IMU frame. ``imu.yaml`` gives ``accelerometer_noise_density``,
``accelerometer_random_walk``, ``gyroscope_noise_density``, ``gyroscope_random_walk`` and
optionally ``rostopic`` and ``update_rate``, at its top level or under ``imu0`` (Kalibr's output).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..backend.data.inertial import KALIBR_KEYS, ImuNoiseDensities, check_noise_densities
from ..backend.data.sequence import check_camera_matrix, input_error
from ..backend.geometry import se3
from .euroc import CameraCalibration, _number, _read_yaml, _required, _show, pinhole, rigid_matrix

__all__ = ["KalibrCameras", "read_camchain", "read_kalibr_imu"]

#: The largest |timeshift_cam_imu| read (s): a shift of seconds is a wrong file, not a clock offset
MAX_TIMESHIFT = 1.0


@dataclass(frozen=True, eq=False)
class KalibrCameras:
    """The stereo pair of a ``camchain.yaml``.

    Attributes
    ----------
    cam0, cam1 : CameraCalibration
        Left and right camera, ``body_T_cam`` = ``inv(T_cam_imu)`` (the body frame is the IMU's).
    topics : (str or None, str or None)
        Their ``rostopic``, where given.
    timeshift : float
        ``cam0``'s ``timeshift_cam_imu`` (s; 0 when absent): the camera stamps plus this are IMU time.
    source : str
    """

    cam0: CameraCalibration
    cam1: CameraCalibration
    topics: tuple[str | None, str | None]
    timeshift: float
    source: str


def _camera(src: str, data: dict, name: str) -> tuple[dict, str]:
    value = _required(src, data, name, f"the {'left' if name == 'cam0' else 'right'} camera")
    if not isinstance(value, dict):
        raise input_error(src, name, f"expected a mapping of the camera's keys, got {_show(value)}")
    return value, name


def _topic(src: str, cam: dict, key: str) -> str | None:
    topic = cam.get("rostopic")
    if topic is None:
        return None
    if not isinstance(topic, str) or not topic.strip():
        raise input_error(src, key, f"expected a topic name, got {_show(topic)}")
    return topic.strip()


def read_camchain(path) -> KalibrCameras:
    """A Kalibr ``camchain.yaml`` (module docstring): the two cameras in the IMU frame, their topics
    and the camera-IMU time shift. InputError ``<file>: key '<key>': <what>`` for a missing or
    malformed key, a transform that is not rigid, another camera or distortion model, or cam1's
    two transforms (``T_cam_imu`` and ``T_cn_cnm1 T_cam0_imu``) disagreeing.

    Returns
    -------
    KalibrCameras
    """
    path = Path(path)
    src = str(path)
    data = _read_yaml(path, "Kalibr's camchain.yaml: cam0 and cam1 with intrinsics, distortion_coeffs, resolution, "
                            "T_cam_imu")
    cams, notes, poses = [], [], {}
    for name in ("cam0", "cam1"):
        cam, _ = _camera(src, data, name)
        K, distortion, resolution = pinhole(src, cam, f"{name}.", "distortion_coeffs")
        check_camera_matrix(src, f"{name}.intrinsics", K)
        if cam.get("T_cam_imu") is not None:
            T, note = rigid_matrix(src, f"{name}.T_cam_imu", cam["T_cam_imu"])
            notes += [note] if note else []
            poses[name] = T
        elif name == "cam1" and cam.get("T_cn_cnm1") is not None:
            T, note = rigid_matrix(src, "cam1.T_cn_cnm1", cam["T_cn_cnm1"])
            notes += [note] if note else []
            poses[name] = T @ poses["cam0"]
        else:
            raise input_error(src, f"{name}.T_cam_imu", "missing (4x4: maps IMU-frame points into the camera)"
                              + ("; or T_cn_cnm1" if name == "cam1" else ""))
        if name == "cam1" and cam.get("T_cam_imu") is not None and cam.get("T_cn_cnm1") is not None:
            chained = rigid_matrix(src, "cam1.T_cn_cnm1", cam["T_cn_cnm1"])[0] @ poses["cam0"]
            gap = float(np.abs(chained[:3, 3] - poses["cam1"][:3, 3]).max())
            if gap > 1e-3:
                raise input_error(src, "cam1.T_cn_cnm1", f"T_cn_cnm1 T_cam0_imu places cam1 {gap:.3g} m away from "
                                                          "its own T_cam_imu: the file contradicts itself")
        cams.append(CameraCalibration(body_T_cam=se3.inverse(poses[name]), K=K, distortion=distortion,
                                      resolution=resolution, rate_hz=None, source=src))
    cam0 = data["cam0"]
    shift = cam0.get("timeshift_cam_imu", 0.0)
    shift = 0.0 if shift is None else _number(src, "cam0.timeshift_cam_imu", shift)
    if not abs(shift) <= MAX_TIMESHIFT:
        raise input_error(src, "cam0.timeshift_cam_imu", f"{shift:g} s: more than {MAX_TIMESHIFT:g} s is no clock "
                                                         "offset between a camera and its IMU")
    left, right = cams
    if notes:
        left = CameraCalibration(left.body_T_cam, left.K, left.distortion, left.resolution, None, src, tuple(notes))
    return KalibrCameras(left, right, (_topic(src, data["cam0"], "cam0.rostopic"),
                                       _topic(src, data["cam1"], "cam1.rostopic")), shift, src)


def read_kalibr_imu(path) -> tuple[ImuNoiseDensities, str | None]:
    """A Kalibr ``imu.yaml`` (module docstring): (the noise densities, the ``rostopic`` or None).
    InputError naming the file and key for a missing, negative or non-finite density."""
    path = Path(path)
    src = str(path)
    data = _read_yaml(path, "Kalibr's imu.yaml: " + ", ".join(KALIBR_KEYS))
    if isinstance(data.get("imu0"), dict):
        data = data["imu0"]
    values = {k: _number(src, k, data[k]) for k in KALIBR_KEYS if data.get(k) is not None}
    return check_noise_densities(src, values), _topic(src, data, "rostopic")
