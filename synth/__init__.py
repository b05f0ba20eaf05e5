"""vislam synthetic scenes with ground truth: stereo features, IMU velocities or samples, images.

``make_scene(SceneConfig(scenario="street" | "aerial", steps, seed, ...))`` builds a
:class:`~vislam.backend.data.sequence.Sequence` (noisy stereo features with per-track ids, noisy IMU
velocities) together with the true poses, twists and landmark positions by id;
``write_scene(scene, out_dir)`` writes ``data.npz``, ``gt_tum.txt`` and ``landmarks.npz``. The
observations' errors are ``SceneConfig.track_errors`` (:mod:`~vislam.synth.track_errors`: white
noise, drift, bad tracks, a disparity offset, repeated frames, frame jitter, outliers);
:mod:`~vislam.synth.grid` lists a seeded grid of scenes split into a tuning and a held-out part;
:mod:`~vislam.synth.inertial` makes continuous-time flights and drives with exact derivatives and the
samples of a real IMU (specific force and rate, Kalibr noise, random-walk biases);
:mod:`~vislam.synth.render` renders stereo images of a scene, and :mod:`~vislam.synth.asl` writes an
inertial street drive with its rendered pairs as an EuRoC ASL folder.
Depends on ``backend`` only; the names below load on first use.
"""

from __future__ import annotations

import importlib

_PUBLIC = {
    "Calibration": "observe",
    "kitti_calibration": "observe",
    "Scene": "scene",
    "SceneConfig": "scene",
    "make_scene": "scene",
    "write_scene": "scene",
    "TrackErrors": "track_errors",
    "PRESETS": "track_errors",
    "InertialTrajectory": "inertial",
    "measure_imu": "inertial",
    "frame_truth": "inertial",
    "InertialSceneConfig": "inertial_scene",
    "make_inertial_scene": "inertial_scene",
    "write_inertial_scene": "inertial_scene",
    "write_euroc_folder": "asl",
}

__all__ = list(_PUBLIC)


def __getattr__(name: str):
    if name not in _PUBLIC:
        raise AttributeError(f"module 'vislam.synth' has no attribute {name!r}")
    value = getattr(importlib.import_module("." + _PUBLIC[name], __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
