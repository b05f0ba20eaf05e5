"""An inertial scene with rendered stereo images, written in EuRoC's ASL layout (what
``frontend.euroc`` reads and ``vislam run MAV0_DIR`` runs):

* ``mav0/cam0/``, ``mav0/cam1/``: ``data.csv`` (``#timestamp [ns],filename``), ``data/<ns>.png``
  (8-bit grey, rectified: no distortion) and ``sensor.yaml`` (``T_BS`` = the camera in the IMU
  frame, the body frame being the IMU's; pinhole ``intrinsics``; radial-tangential coefficients 0);
* ``mav0/imu0/``: ``data.csv`` (``#timestamp [ns],w_RS_S_x,...,a_RS_S_z``: rate first, then
  specific force) and ``sensor.yaml`` (``T_BS`` the identity, the scene's noise densities);
* ``mav0/state_groundtruth_estimate0/data.csv``: position, quaternion (w first), velocity and the
  gyroscope and accelerometer biases at every frame.

Stamps are the scene's seconds as whole nanoseconds; the world is the scene's gravity-aligned one.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..backend.geometry import se3
from .inertial_scene import InertialScene
from .observe import Calibration, kitti_calibration
from .render import render_to_png

__all__ = ["write_euroc_folder"]


def _ns(seconds: np.ndarray) -> np.ndarray:
    return np.round(np.asarray(seconds, dtype=float) * 1e9).astype(np.int64)


def _write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")


def _matrix(T: np.ndarray) -> str:
    return "[" + ", ".join(f"{v:.17g}" for v in np.asarray(T, dtype=float).ravel()) + "]"


def _camera_yaml(name: str, body_T_cam: np.ndarray, calibration: Calibration, rate_hz: float) -> str:
    K = calibration.K
    return (f"%YAML:1.0\nsensor_type: camera\ncomment: vislam synthetic {name} (rendered, rectified)\n"
            f"T_BS:\n  cols: 4\n  rows: 4\n  data: {_matrix(body_T_cam)}\nrate_hz: {rate_hz:g}\n"
            f"resolution: [{calibration.width}, {calibration.height}]\ncamera_model: pinhole\n"
            f"intrinsics: [{K[0, 0]:.17g}, {K[1, 1]:.17g}, {K[0, 2]:.17g}, {K[1, 2]:.17g}]\n"
            "distortion_model: radial-tangential\ndistortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n")


def write_euroc_folder(scene: InertialScene, out_dir, calibration: Calibration | None = None, *,
                       png_compression: int = 1, progress=None) -> Path:
    """Render ``scene`` (a street drive: :func:`synth.render.build_street_planes` along its true
    poses, seed the scene's) with the rig ``calibration`` (default: the KITTI-like one its
    observations came from) and write it with its IMU samples and truth as ``out_dir/mav0`` (module
    docstring); ``progress(k, n)`` after each pair. Returns the ``mav0`` folder."""
    import cv2

    cal = calibration if calibration is not None else (scene.config.calibration or kitti_calibration())
    seq, poses = scene.sequence, np.asarray(scene.world_T_imu_true, dtype=float)
    root = Path(out_dir) / "mav0"
    frame_ns = _ns(seq.time_stamps)
    rate = 1.0 / float(np.median(np.diff(seq.time_stamps)))
    cam0_T_cam1 = np.eye(4)
    cam0_T_cam1[0, 3] = cal.baseline
    body_T_cams = (np.asarray(cal.imu_T_cam, dtype=float), np.asarray(cal.imu_T_cam, dtype=float) @ cam0_T_cam1)
    for name, body_T_cam in zip(("cam0", "cam1"), body_T_cams):
        (root / name / "data").mkdir(parents=True, exist_ok=True)
        _write(root / name / "sensor.yaml", _camera_yaml(name, body_T_cam, cal, rate))
        _write(root / name / "data.csv", "#timestamp [ns],filename\n" + "".join(f"{n},{n}.png\n" for n in frame_ns))
    paths = [(root / "cam0" / "data" / f"{n}.png", root / "cam1" / "data" / f"{n}.png") for n in frame_ns]
    render_to_png(poses, cal, paths, seed=int(scene.config.seed), params=[cv2.IMWRITE_PNG_COMPRESSION,
                                                                           int(png_compression)], progress=progress)
    imu = seq.imu
    noise = imu.noise
    _write(root / "imu0" / "sensor.yaml",
           "%YAML:1.0\nsensor_type: imu\ncomment: vislam synthetic IMU\n"
           f"T_BS:\n  cols: 4\n  rows: 4\n  data: {_matrix(np.eye(4))}\nrate_hz: {imu.rate_hz:g}\n"
           f"gyroscope_noise_density: {noise.gyroscope_noise_density:.17g}\n"
           f"gyroscope_random_walk: {noise.gyroscope_random_walk:.17g}\n"
           f"accelerometer_noise_density: {noise.accelerometer_noise_density:.17g}\n"
           f"accelerometer_random_walk: {noise.accelerometer_random_walk:.17g}\n")
    rows = np.column_stack([imu.angular_velocity, imu.linear_acceleration])
    _write(root / "imu0" / "data.csv",
           "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],a_RS_S_x [m s^-2],"
           "a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n"
           + "".join(f"{n}," + ",".join(f"{v:.17g}" for v in r) + "\n" for n, r in zip(_ns(imu.time_stamps), rows)))
    q = se3.quaternion_from_rotation(poses[:, :3, :3])  # x y z w
    truth = np.column_stack([poses[:, :3, 3], q[:, 3], q[:, :3], scene.velocity_true, scene.gyro_bias_true,
                             scene.accel_bias_true])
    _write(root / "state_groundtruth_estimate0" / "data.csv",
           "#timestamp,p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z [],"
           "v_RS_R_x [m s^-1],v_RS_R_y [m s^-1],v_RS_R_z [m s^-1],b_w_RS_S_x [rad s^-1],b_w_RS_S_y [rad s^-1],"
           "b_w_RS_S_z [rad s^-1],b_a_RS_S_x [m s^-2],b_a_RS_S_y [m s^-2],b_a_RS_S_z [m s^-2]\n"
           + "".join(f"{n}," + ",".join(f"{v:.17g}" for v in r) + "\n" for n, r in zip(frame_ns, truth)))
    return root
