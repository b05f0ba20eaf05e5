"""Synthetic feature scenes with ground truth: configuration, assembly and writing.

``make_scene(SceneConfig(...))`` is a pure function of the configuration: the trajectory, the
landmarks, the pixel noise, the track cuts, the outliers, each track error
(``SceneConfig.track_errors``, :mod:`~vislam.synth.track_errors`) and the IMU noise each come
from their own random stream of ``seed``, so e.g. changing the IMU noise leaves the map and the
pixels as they are.
"""

from __future__ import annotations

import json
from dataclasses import InitVar, dataclass, field, fields, replace
from pathlib import Path
from typing import Optional

import numpy as np

from ..backend.config import Config
from ..backend.errors import ConfigError
from ..backend.data.sequence import SYNTHETIC_TRACKER, Sequence, validate_sequence
from ..backend.data.files import atomic_write
from ..backend.data.npz import save_sequence
from ..backend.data.tum import write_tum
from ._random import generator
from .imu import DEFAULT_ANGULAR_SIGMA, DEFAULT_GYRO_BIAS, DEFAULT_LINEAR_SIGMA, measure_velocities
from .landmarks import LANDMARKS
from .observe import Calibration, check_observation_count, kitti_calibration, observe
from .track_errors import DRIFTING_TRACKER, FAST, JUMP, TrackErrors, TrackErrorTruth
from .trajectories import TRAJECTORIES

__all__ = ["SceneConfig", "SceneFactory", "Scene", "check_scene_size", "make_scene", "write_scene", "scene_facts"]


#: The most steps a synthetic scene has: its trajectory alone is 128 bytes a step, and a day at 10 Hz
#: is more than any test of a filter needs
MAX_STEPS = 864_000


@dataclass(frozen=True)
class SceneConfig:
    """Everything a synthetic scene depends on (same config -> identical arrays).

    The observations' errors are ``track_errors``; the keywords ``pixel_sigma`` and
    ``outlier_share``, when given, replace its values of the same name, and both read back as
    attributes (``config.pixel_sigma`` is ``config.track_errors.pixel_sigma``). So
    ``dataclasses.replace(config, pixel_sigma=0.3)`` changes the white noise, while
    ``dataclasses.replace(config, track_errors=e)`` keeps the config's white noise and outliers
    (replace passes them on as keywords): :meth:`with_track_errors` takes all of ``e``.
    """

    scenario: str = "street"  # "street" | "aerial"
    steps: int = 500
    dt: float = 0.1  # s
    seed: int = 0
    # IMU: white noise per axis (a number or 3 values), gyro bias (constant unless gyro_bias_walk > 0)
    linear_sigma: float | tuple = DEFAULT_LINEAR_SIGMA  # m/s
    angular_sigma: float | tuple = DEFAULT_ANGULAR_SIGMA  # rad/s
    gyro_bias: tuple = DEFAULT_GYRO_BIAS  # rad/s at step 0
    gyro_bias_walk: float | tuple = 0.0  # rad/s per sqrt(s)
    velocity_index: str = "this"  # "this" | "next"
    # camera
    pixel_sigma: InitVar[Optional[float]] = None  # px, each of uL vL uR vR (track_errors.pixel_sigma)
    outlier_share: InitVar[Optional[float]] = None  # track_errors.outlier_share
    mean_track_length: float | None = 20.0  # steps (geometric); None: whole visible runs
    min_depth: float = 2.0  # m
    max_depth: float = 60.0  # m
    landmark_density: float = 1.0  # multiplies the scenario's landmark density
    calibration: Calibration = field(default_factory=kitti_calibration, compare=False)
    track_errors: TrackErrors = field(default_factory=TrackErrors)  # every error of the pixels

    def __post_init__(self, pixel_sigma: Optional[float], outlier_share: Optional[float]) -> None:
        def bad(key, what):
            return ConfigError(f"synthetic scene: {key} {what}")

        if self.scenario not in TRAJECTORIES:
            raise bad("scenario", f"must be one of {sorted(TRAJECTORIES)}, got {self.scenario!r}")
        if int(self.steps) != self.steps or not 2 <= self.steps <= MAX_STEPS:
            raise bad("steps", f"must be an integer from 2 to {MAX_STEPS} (a day at 10 Hz), got {self.steps!r}")
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise bad("dt", f"must be > 0 seconds, got {self.dt!r}")
        if int(self.seed) != self.seed or self.seed < 0:
            raise bad("seed", f"must be a non-negative integer, got {self.seed!r}")
        if self.velocity_index not in ("this", "next"):
            raise bad("velocity_index", f"must be 'this' or 'next', got {self.velocity_index!r}")
        for key in ("linear_sigma", "angular_sigma", "gyro_bias_walk"):
            a = np.asarray(getattr(self, key), dtype=float)
            if a.shape not in ((), (3,)) or not (np.all(np.isfinite(a)) and np.all(a >= 0)):
                raise bad(key, f"must be >= 0 (a number or 3 values), got {getattr(self, key)!r}")
        b = np.asarray(self.gyro_bias, dtype=float)
        if b.shape not in ((), (3,)) or not np.all(np.isfinite(b)):
            raise bad("gyro_bias", f"must be finite (a number or 3 values), got {self.gyro_bias!r}")
        if not isinstance(self.track_errors, TrackErrors):
            raise bad("track_errors", f"must be a TrackErrors, got {type(self.track_errors).__name__}")
        given = {k: v for k, v in (("pixel_sigma", pixel_sigma), ("outlier_share", outlier_share)) if v is not None}
        if given:
            object.__setattr__(self, "track_errors", replace(self.track_errors, **given))
        if self.mean_track_length is not None and not self.mean_track_length >= 1:
            raise bad("mean_track_length", f"must be >= 1 step (or None), got {self.mean_track_length!r}")
        if not 0 < self.min_depth < self.max_depth:
            raise bad("min_depth/max_depth", f"need 0 < min_depth < max_depth, got {self.min_depth}, {self.max_depth}")
        if not (np.isfinite(self.landmark_density) and self.landmark_density >= 0):
            raise bad("landmark_density", f"must be >= 0, got {self.landmark_density!r}")

    @property
    def source(self) -> str:
        return f"synthetic:{self.scenario}:seed{self.seed}"

    def filter_config(self) -> Config:
        """The filter told this scene's own noise (pixel and velocity sigmas, the largest axis): the
        filter on its own model (``vislam mc --true-noise``); by default a run identifies them."""
        return Config.from_values({
            "noise.pixel_sigma": self.pixel_sigma,
            "noise.linear_velocity_sigma": float(np.max(self.linear_sigma)),
            "noise.angular_velocity_sigma": float(np.max(self.angular_sigma)),
        })

    def with_track_errors(self, errors: TrackErrors) -> "SceneConfig":
        """This configuration with every track error of ``errors`` (white noise and outliers included)."""
        return replace(self, track_errors=errors, pixel_sigma=None, outlier_share=None)

    def as_dict(self) -> dict:
        """The configuration's fields (the calibration left out), ``track_errors`` as a dict and
        its ``pixel_sigma`` and ``outlier_share`` also at the top."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("calibration", "track_errors")}
        out.update(pixel_sigma=self.pixel_sigma, outlier_share=self.outlier_share,
                   track_errors=self.track_errors.as_dict())
        return out


# the keywords of SceneConfig that live in its track_errors
SceneConfig.pixel_sigma = property(lambda self: self.track_errors.pixel_sigma,
                                   doc="px: white noise of each of uL vL uR vR (track_errors.pixel_sigma)")
SceneConfig.outlier_share = property(lambda self: self.track_errors.outlier_share,
                                     doc="outliers' share (track_errors.outlier_share)")


@dataclass(frozen=True)
class SceneFactory:
    """The scene of ``config`` with the noise of a noise seed and, optionally, another constant gyro
    bias: what a Monte Carlo run needs (``backend.evaluation.consistency``); picklable, so runs can
    go to worker processes. ``factory(s)`` equals ``make_scene(config, noise_seed=s)``."""

    config: SceneConfig

    def __call__(self, noise_seed: int, gyro_bias=None) -> "Scene":
        config = self.config if gyro_bias is None else replace(self.config, gyro_bias=tuple(float(b) for b in gyro_bias))
        return make_scene(config, noise_seed=noise_seed)

    def as_dict(self) -> dict:
        return self.config.as_dict()


@dataclass(eq=False)
class Scene:
    """A synthetic sequence and its ground truth (landmarks by track id)."""

    config: SceneConfig
    sequence: Sequence  # layout "2022", noisy velocities, noisy pixels
    world_T_imu_true: np.ndarray  # (N,4,4)
    twists_true: np.ndarray  # (N,6) [v, w]; row k drives step k -> k+1 (last row copies N-2)
    landmark_ids: np.ndarray  # (K,) int64 = arange(K), every track id of the sequence
    landmark_positions: np.ndarray  # (K,3) true world position of each id
    landmark_point_index: np.ndarray  # (K,) int64 id -> row of ``points``
    points: np.ndarray  # (P,3) every scene point (one point may carry several ids)
    gyro_bias_true: np.ndarray  # (N,3) rad/s, bias contained in each angular velocity sample
    outlier: np.ndarray  # (L,) bool, per observation of ``sequence`` (CSR order)
    track_errors: TrackErrorTruth  # the drawn track errors (content poses, jitter, drift and bad tracks by id)

    @property
    def image_size(self) -> tuple[int, int]:
        return self.config.calibration.image_size


def check_scene_size(config: SceneConfig) -> int:
    """The scene's number of observations, estimated from its trajectory, its points and a sample
    of them, without drawing any; ConfigError naming the memory needed when the points or the
    observations exceed their bounds (``synth.landmarks.MAX_POINTS``, ``synth.observe.MAX_OBSERVATIONS``).
    What ``vislam synth`` and ``vislam mc`` check before any work."""
    seed = int(config.seed)
    traj = TRAJECTORIES[config.scenario](int(config.steps), config.dt, generator(seed, "trajectory"))
    points = LANDMARKS[config.scenario](traj.world_T_imu, generator(seed, "landmarks"), density=config.landmark_density)
    return check_observation_count(traj.world_T_imu, points, config.calibration, config.min_depth, config.max_depth)


def make_scene(config: SceneConfig | None = None, noise_seed: int | None = None) -> Scene:
    """Build the scene described by ``config`` (default: the 500-step street, seed 0).

    Trajectory and landmark points come from ``config.seed``; pixel noise, track cuts, outliers,
    the track errors and IMU noise from ``noise_seed`` (default: ``config.seed``), each from its
    own random stream, so Monte Carlo runs can share the geometry and differ only in the noise.
    The sequence's ``tracker`` is ``"synthetic"``, or ``"synthetic-drifting"`` when its tracks
    drift (``TrackErrors.drifts``).
    """
    cfg = SceneConfig() if config is None else config
    seed = int(cfg.seed)
    noise = seed if noise_seed is None else int(noise_seed)
    traj = TRAJECTORIES[cfg.scenario](int(cfg.steps), cfg.dt, generator(seed, "trajectory"))
    points = LANDMARKS[cfg.scenario](traj.world_T_imu, generator(seed, "landmarks"), density=cfg.landmark_density)
    obs = observe(
        traj.world_T_imu,
        points,
        cfg.calibration,
        mean_track_length=cfg.mean_track_length,
        min_depth=cfg.min_depth,
        max_depth=cfg.max_depth,
        seed=noise,
        track_errors=cfg.track_errors,
    )
    imu = measure_velocities(
        traj.twists,
        traj.time_stamps,
        generator(noise, "imu"),
        linear_sigma=cfg.linear_sigma,
        angular_sigma=cfg.angular_sigma,
        gyro_bias=cfg.gyro_bias,
        gyro_bias_walk=cfg.gyro_bias_walk,
        velocity_index=cfg.velocity_index,
    )
    calib = cfg.calibration
    num_tracks = obs.point_index.shape[0]
    sequence = Sequence(
        time_stamps=traj.time_stamps.copy(),
        linear_velocity=np.ascontiguousarray(imu.linear_velocity),
        angular_velocity=np.ascontiguousarray(imu.angular_velocity),
        K=np.array(calib.K),
        baseline=float(calib.baseline),
        imu_T_cam=np.array(calib.imu_T_cam),
        obs_ptr=obs.obs_ptr,
        obs_ids=obs.obs_ids,
        obs_pixels=obs.obs_pixels,
        num_features=num_tracks,
        source=cfg.source if noise == seed else f"{cfg.source}:noise{noise}",
        layout="2022",
        dropped={"nonpositive_disparity": 0, "outside_image": 0},
        tracker=DRIFTING_TRACKER if cfg.track_errors.drifts else SYNTHETIC_TRACKER,
    )
    validate_sequence(sequence)
    return Scene(
        config=cfg,
        sequence=sequence,
        world_T_imu_true=traj.world_T_imu,
        twists_true=traj.twists,
        landmark_ids=np.arange(num_tracks, dtype=np.int64),
        landmark_positions=points[obs.point_index],
        landmark_point_index=obs.point_index,
        points=points,
        gyro_bias_true=imu.gyro_bias,
        outlier=obs.outlier,
        track_errors=obs.truth,
    )


def write_with_truth(out_dir, seq: Sequence, world_T_imu_true: np.ndarray, frame: str, landmark_ids: np.ndarray,
                     landmark_positions: np.ndarray) -> Path:
    """What every synthetic scene writes into ``out_dir`` (created if missing): ``data.npz`` (``seq``),
    ``gt_tum.txt`` (``world_T_imu_true`` (N,4,4) at its stamps; ``frame`` names the poses in the
    header) and ``landmarks.npz`` (``ids`` (K,), ``positions`` (K,3)); returns the directory."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    save_sequence(seq, out / "data.npz")
    write_tum(out / "gt_tum.txt", seq.time_stamps, world_T_imu_true,
              header=f"{seq.source} ground truth {frame}: t tx ty tz qx qy qz qw")
    with atomic_write(out / "landmarks.npz") as tmp, open(tmp, "wb") as fh:
        np.savez(fh, ids=landmark_ids, positions=landmark_positions)
    return out


def write_scene(scene: Scene, out_dir) -> Path:
    """Write ``data.npz`` (course 2022 layout), ``gt_tum.txt`` (world_T_imu) and ``landmarks.npz``
    (``ids``, ``positions``) into ``out_dir`` (created if missing); returns the directory. A scene
    with track errors beyond white noise and outliers also gets ``scene.json`` (its configuration
    and a summary of the drawn errors, :func:`scene_facts`) and ``track_errors.npz`` (the
    :class:`~vislam.synth.track_errors.TrackErrorTruth` arrays, tracks by id)."""
    out = write_with_truth(out_dir, scene.sequence, scene.world_T_imu_true, "world_T_imu", scene.landmark_ids,
                           scene.landmark_positions)
    if scene.config.track_errors.effects():
        with atomic_write(out / "track_errors.npz") as tmp, open(tmp, "wb") as fh:
            np.savez(fh, ids=scene.landmark_ids, **scene.track_errors._asdict())
        with atomic_write(out / "scene.json") as tmp:
            tmp.write_text(json.dumps(scene_facts(scene), indent=2) + "\n", encoding="utf-8")
    return out


def scene_facts(scene: Scene) -> dict:
    """The scene's configuration and what its track errors drew: repeated steps, drifting and bad
    tracks, quantiles of the drift speed (px/step), the jitter's rms (plain JSON values)."""
    truth, cfg = scene.track_errors, scene.config
    speed = np.linalg.norm(truth.drift_velocity, axis=1)
    drifting = speed[(truth.bad == 0) & (speed > 0)]
    quantiles = {f"p{q}": float(np.percentile(drifting, q)) for q in (50, 90, 99)} if drifting.size else {}
    config = {k: (list(v) if isinstance(v, tuple) else v) for k, v in cfg.as_dict().items()}
    return {
        "source": cfg.source,
        "tracker": scene.sequence.tracker,
        "config": config,
        "track_errors": {
            "repeated_steps": np.flatnonzero(truth.repeated).tolist(),
            "tracks": int(truth.bad.size),
            "drifting_tracks": int(drifting.size),
            "drift_speed_px_per_step": quantiles,
            "bad_tracks": {"jump": int(np.sum(truth.bad == JUMP)), "fast": int(np.sum(truth.bad == FAST)),
                           "jumps_seen": int(np.sum(truth.jump_step >= 0))},
            "disparity_offset_px": cfg.track_errors.disparity_offset,
            "jitter_rms": {"translation_m": float(np.sqrt(np.mean(truth.jitter[:, :3] ** 2))),
                           "rotation_rad": float(np.sqrt(np.mean(truth.jitter[:, 3:] ** 2)))},
        },
    }
