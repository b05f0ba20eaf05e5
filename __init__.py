"""vislam: stereo visual-inertial SLAM with an Extended Kalman Filter on SE(3).

The public face of the package (the names below load on first use)::

    import vislam

    seq = vislam.load_sequence("ece276a_0027.npz")        # a course .npz (either layout)
    result = vislam.run_sequence(seq, vislam.Config())    # trajectory, covariance, map, statistics, decisions
    result.world_T_imu                                    # (N, 4, 4)

    # the online API: what the data says, decided once, then one call per time stamp
    decisions = vislam.decide(seq, vislam.Config())
    run = vislam.OnlineRun(vislam.StereoCamera(seq.K, seq.baseline), decisions, vislam.Config())
    run.step(t, v, w, ids, pixels)                         # run.ekf.world_T_imu, run.ekf.pose_covariance

    # a real IMU's samples (an inertial sequence: seq.imu), started at rest
    decisions = vislam.decide_inertial(seq, vislam.Config())
    run = vislam.InertialRun(vislam.StereoCamera(seq.K, seq.baseline), decisions, vislam.Config(), seq.imu)
    run.step(t, ids, pixels)                               # run.ekf.velocity, run.ekf.accel_bias too

The packages: ``backend`` (the estimator, file formats, the run, evaluation), ``frontend`` (OpenCV
stereo tracking of images), ``synth`` (synthetic scenes with ground truth) and ``tools`` (the
``vislam`` command line).
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

_PUBLIC = {
    # configuration and errors
    "Config": "backend.config",
    "VislamError": "backend.errors",
    "InputError": "backend.errors",
    "ConfigError": "backend.errors",
    "FilterError": "backend.errors",
    "HealthWarning": "backend.errors",
    # data
    "Sequence": "backend.data.sequence",
    "ImuSamples": "backend.data.inertial",
    "ImuNoiseDensities": "backend.data.inertial",
    "load_sequence": "backend.data.npz",
    "save_sequence": "backend.data.npz",
    "read_tum": "backend.data.tum",
    "write_tum": "backend.data.tum",
    "StereoCamera": "backend.geometry.camera",
    # the filter (online API)
    "VisualInertialEKF": "backend.estimator.ekf",
    "StepStats": "backend.estimator.ekf",
    "ImuNoise": "backend.estimator.propagation",
    # a whole run
    "run_sequence": "backend.run.runner",
    "run_stream": "backend.run.runner",
    "decide": "backend.run.decisions",
    "Decisions": "backend.run.decisions",
    "OnlineRun": "backend.run.online",
    "RunResult": "backend.run.online",
    "decide_inertial": "backend.run.inertial",
    "InertialDecisions": "backend.run.inertial",
    "InertialRun": "backend.run.inertial",
    # evaluation
    "trajectory_errors": "backend.evaluation.metrics",
}

__all__ = ["__version__", *_PUBLIC]


def __getattr__(name: str):
    if name not in _PUBLIC:
        raise AttributeError(f"module 'vislam' has no attribute {name!r}")
    value = getattr(importlib.import_module("." + _PUBLIC[name], __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
