"""Synthetic scenes with a real IMU: a continuous-time flight or drive (:mod:`~vislam.synth.inertial`),
the IMU's samples at their own rate, landmarks, and stereo tracks at the camera rate, as an
inertial :class:`~vislam.backend.data.sequence.Sequence` with its ground truth.

* ``room``: a MAV in an 8 x 8 x 3 m room (as EuRoC's Vicon room) with points on its walls, floor
  and ceiling, seen by a VI-Sensor-like rectified pair (752 x 480, fx 436 px, 0.11 m baseline)
  looking along the IMU's x axis.
* ``street``: a car with the street points of :func:`~vislam.synth.landmarks.street_landmarks`,
  seen by the KITTI-like rig.

Both start at rest (``start_at_rest`` seconds, 2 by default) so that the filter can initialize
from the IMU alone. :func:`write_inertial_scene` writes ``data.npz`` in the inertial layout
(``backend.data.npz``), ``gt_tum.txt``, ``gt_states.npz`` (velocity and biases at the frames) and
``landmarks.npz``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..backend.data.files import atomic_write
from ..backend.data.inertial import ADIS16448, ImuNoiseDensities
from ..backend.data.sequence import SYNTHETIC_TRACKER, Sequence, validate_sequence
from ..backend.errors import ConfigError
from ._random import generator
from .inertial import GRAVITY, ROOM_BOX, frame_times, frame_truth, measure_imu, room, street
from .landmarks import street_landmarks
from .observe import Calibration, kitti_calibration, observe
from .scene import write_with_truth

__all__ = ["InertialSceneConfig", "InertialScene", "InertialSceneFactory", "make_inertial_scene", "write_inertial_scene",
           "room_points", "vi_sensor_calibration", "INERTIAL_SCENARIOS"]

INERTIAL_SCENARIOS = ("room", "street")


def vi_sensor_calibration() -> Calibration:
    """A rectified VI-Sensor-like pair (752 x 480, fx = fy = 436 px, 0.11 m baseline) looking along the
    IMU's x axis (camera z = IMU x, camera x = -IMU y, camera y = -IMU z), 5 cm ahead of it."""
    K = np.array([[436.0, 0.0, 364.0], [0.0, 436.0, 257.0], [0.0, 0.0, 1.0]])
    imu_T_cam = np.array([[0.0, 0.0, 1.0, 0.05], [-1.0, 0.0, 0.0, -0.05], [0.0, -1.0, 0.0, 0.02], [0.0, 0.0, 0.0, 1.0]])
    return Calibration(K=K, baseline=0.11, width=752, height=480, imu_T_cam=imu_T_cam)


def room_points(seed, count: int = 600) -> np.ndarray:
    """``count`` points (count,3) uniform on the six faces of ``ROOM_BOX`` (a face chosen per point
    in proportion to nothing but chance: each face equally likely)."""
    rng = generator(seed, "landmarks")
    lo, hi = np.asarray(ROOM_BOX[0], dtype=float), np.asarray(ROOM_BOX[1], dtype=float)
    points = rng.uniform(lo, hi, size=(count, 3))
    face = rng.integers(0, 6, count)
    axis, side = face // 2, face % 2
    points[np.arange(count), axis] = np.where(side == 0, lo[axis], hi[axis])
    return points


@dataclass(frozen=True)
class InertialSceneConfig:
    """What :func:`make_inertial_scene` builds (:func:`check_inertial_scene`: the bounds a command
    allows)."""

    scenario: str = "room"
    duration: float = 60.0  # s
    seed: int = 0
    imu_rate: float = 200.0  # Hz
    frame_rate: float = 20.0  # Hz
    noise: ImuNoiseDensities = ADIS16448
    start_at_rest: float | None = 2.0  # s at rest before the motion; None: moving from the first sample
    pixel_sigma: float = 0.5  # px
    outlier_share: float = 0.02
    points: int = 600  # room: points on its faces; street: the density factor is points / 600
    mean_track_length: float = 20.0  # frames
    calibration: Calibration | None = None  # default: the VI-Sensor-like pair (room), the KITTI-like rig (street)
    accel_bias0: tuple | None = None  # (3,) m/s^2 at the start; None: drawn by synth.inertial.measure_imu
    gyro_bias0: tuple | None = None  # (3,) rad/s at the start; None: drawn likewise

    def __post_init__(self) -> None:
        if self.scenario not in INERTIAL_SCENARIOS:
            raise ValueError(f"scenario must be one of {INERTIAL_SCENARIOS}, got {self.scenario!r}")
        if not (self.duration > (self.start_at_rest or 0.0) + 1.0 and self.imu_rate > self.frame_rate > 0):
            raise ValueError("need duration > start_at_rest + 1 s and imu_rate > frame_rate > 0")


#: The shortest and the longest inertial scene a command makes (s): 2 s at rest, then the motion;
#: 200 Hz samples and 20 Hz tracks of an hour are about 1 GB
MIN_SECONDS, MAX_SECONDS = 4.0, 3600.0


def check_inertial_scene(scenario: str, duration: float) -> None:
    """ConfigError naming the option for a scenario without a real IMU (``aerial``) or a duration
    outside [:data:`MIN_SECONDS`, :data:`MAX_SECONDS`]; what ``vislam synth`` and ``vislam mc``
    check before any work."""
    if scenario not in INERTIAL_SCENARIOS:
        raise ConfigError(f"--scenario {scenario} with --imu inertial: scenarios {' and '.join(INERTIAL_SCENARIOS)} "
                          "(aerial has body velocities only)")
    if not MIN_SECONDS <= duration <= MAX_SECONDS:
        raise ConfigError(f"--duration {duration:g}: an inertial scene lasts {MIN_SECONDS:g} to {MAX_SECONDS:g} s "
                          "(2 s at rest, then the motion)")


@dataclass
class InertialScene:
    """An inertial sequence and its truth at the frames (poses, velocities, biases) and samples."""

    config: InertialSceneConfig
    sequence: Sequence  # inertial: ``sequence.imu`` holds the noisy samples
    world_T_imu_true: np.ndarray  # (N,4,4) at the frames
    velocity_true: np.ndarray  # (N,3) world frame
    gyro_bias_true: np.ndarray  # (N,3) at the frames
    accel_bias_true: np.ndarray  # (N,3) at the frames
    landmark_positions: np.ndarray  # (K,3) by track id
    gravity: np.ndarray  # (3,)


def make_inertial_scene(config: InertialSceneConfig | None = None, noise_seed: int | None = None) -> InertialScene:
    """Build the scene of ``config``: trajectory and points from ``config.seed``, the IMU's noise and
    biases, the pixel noise, track cuts and outliers from ``noise_seed`` (default ``config.seed``)."""
    cfg = InertialSceneConfig() if config is None else config
    seed = int(cfg.seed)
    noise_seed = seed if noise_seed is None else int(noise_seed)
    make = room if cfg.scenario == "room" else street
    traj = make(cfg.duration, seed=seed, start_at_rest=cfg.start_at_rest)
    samples, truth = measure_imu(traj, cfg.imu_rate, noise=cfg.noise, seed=noise_seed, bias0_gyro=cfg.gyro_bias0,
                                 bias0_accel=cfg.accel_bias0)
    times = frame_times(samples, cfg.frame_rate)
    frames = frame_truth(traj, times)
    calib = cfg.calibration or (vi_sensor_calibration() if cfg.scenario == "room" else kitti_calibration())
    if cfg.scenario == "room":  # the walls from 0.5 m (a camera nearer than that sees a blur)
        points, min_depth, max_depth = room_points(seed, cfg.points), 0.5, 12.0
    else:
        points = street_landmarks(frames.world_T_imu, generator(seed, "landmarks"), density=cfg.points / 600.0)
        min_depth, max_depth = 2.0, 60.0
    obs = observe(frames.world_T_imu, points, calib, pixel_sigma=cfg.pixel_sigma, outlier_share=cfg.outlier_share,
                  mean_track_length=cfg.mean_track_length, min_depth=min_depth, max_depth=max_depth, seed=noise_seed)
    idx = np.clip(np.searchsorted(truth.time_stamps, times), 0, truth.time_stamps.size - 1)
    sequence = Sequence(
        time_stamps=np.asarray(times, dtype=float), linear_velocity=None, angular_velocity=None,
        K=np.array(calib.K), baseline=float(calib.baseline), imu_T_cam=np.array(calib.imu_T_cam),
        obs_ptr=obs.obs_ptr, obs_ids=obs.obs_ids, obs_pixels=obs.obs_pixels, num_features=obs.point_index.shape[0],
        source=f"synthetic-inertial:{cfg.scenario}:seed{seed}" + ("" if noise_seed == seed else f":noise{noise_seed}"),
        layout="2022", dropped={"nonpositive_disparity": 0, "outside_image": 0}, tracker=SYNTHETIC_TRACKER,
        imu=samples)
    validate_sequence(sequence)
    return InertialScene(cfg, sequence, frames.world_T_imu, frames.velocity, truth.gyro_bias[idx],
                         truth.accel_bias[idx], points[obs.point_index], np.asarray(GRAVITY, dtype=float))


@dataclass(frozen=True)
class InertialSceneFactory:
    """The scene of ``config`` with the noise of a noise seed and, optionally, another starting
    accelerometer bias (drawn from the filter's prior by a Monte Carlo run, ``backend.evaluation.
    consistency``); picklable, so runs can go to worker processes."""

    config: InertialSceneConfig
    #: the bias a Monte Carlo run replaces: the accelerometer's (the tilt it fakes at the start)
    sampled_bias = "accelerometer"

    def __call__(self, noise_seed: int, bias=None) -> InertialScene:
        config = self.config if bias is None else dataclasses.replace(self.config, accel_bias0=tuple(float(b) for b in bias))
        return make_inertial_scene(config, noise_seed=noise_seed)

    def as_dict(self) -> dict:
        c = self.config
        return {"imu": "inertial", "scenario": c.scenario, "duration": c.duration, "seed": c.seed,
                "imu_rate": c.imu_rate, "frame_rate": c.frame_rate, "noise": c.noise.as_dict(),
                "start_at_rest": c.start_at_rest, "pixel_sigma": c.pixel_sigma, "outlier_share": c.outlier_share,
                "points": c.points}


def write_inertial_scene(scene: InertialScene, out_dir) -> Path:
    """``data.npz`` (inertial layout), ``gt_tum.txt``, ``gt_states.npz`` (``time_stamps``, ``velocity``,
    ``gyro_bias``, ``accel_bias`` at the frames) and ``landmarks.npz`` into ``out_dir``."""
    seq = scene.sequence
    out = write_with_truth(out_dir, seq, scene.world_T_imu_true, "world_T_imu (gravity-aligned world, z up)",
                           np.arange(scene.landmark_positions.shape[0]), scene.landmark_positions)
    with atomic_write(out / "gt_states.npz") as tmp, open(tmp, "wb") as fh:
        np.savez(fh, time_stamps=seq.time_stamps, velocity=scene.velocity_true, gyro_bias=scene.gyro_bias_true,
                 accel_bias=scene.accel_bias_true)
    return out
