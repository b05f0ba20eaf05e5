"""The filter over the first steps of a sequence, to compare choices: its own innovation
likelihood (L2) and its scale against the IMU's (H4 of ``backend.estimator.health``, for D5 of
``backend.run.stereo_offset``).

For a candidate (a noise level, a correction), the filter runs over the first steps with the rest
of the decisions fixed and sums, observation by observation, the log-likelihood of its prior
innovations (L1 of ``backend.estimator.ekf``: each observation's 3x3 block of S and the off row,
the NIS capped at the gate so an outlier costs every candidate the same). The prediction-error
decomposition makes this the likelihood of the data under the candidate's model; the mean per
observation compares candidates on the same observations.                                         (L2)
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..config import Config
from ..data.sequence import Sequence
from ..estimator.health import ScaleCheck
from ..geometry.camera import StereoCamera

__all__ = ["log_likelihood", "first_steps_scale", "LIKELIHOOD_STEPS"]

#: Steps of a sequence the comparison runs over.
LIKELIHOOD_STEPS = 300


def _first_steps(seq: Sequence, decisions, config: Config, steps: int, likelihood: bool = False):
    """An ``OnlineRun`` (health silent: a trial of the decisions, not the user's run) over the first
    ``steps`` steps of ``seq``: (the run, the summed log-likelihood, the observations it tested), the
    last two 0 unless ``likelihood``. The caller closes ``run.ekf``."""
    from .online import OnlineRun  # the run layer above: imported when a comparison runs

    run = OnlineRun(StereoCamera(seq.K, seq.baseline), decisions, config)
    run.ekf.track_likelihood = likelihood
    run.ekf.health.silent = True
    total, count = 0.0, 0
    try:
        for k, step in enumerate(seq.steps()):
            if k >= steps:
                break
            stats = run.step(*step)
            if likelihood and stats is not None:
                total += stats.log_likelihood
                count += stats.tested
    except BaseException:
        run.ekf.close()
        raise
    return run, total, count


def log_likelihood(seq: Sequence, decisions, config: Config, steps: int = LIKELIHOOD_STEPS) -> tuple[float, int]:
    """(L2) (mean log-likelihood per observation, observations) of the first ``steps`` steps of ``seq``
    under ``decisions`` (a ``backend.run.decisions.Decisions``); (-inf, 0) when none was tested."""
    run, total, count = _first_steps(seq, decisions, config, steps, likelihood=True)
    run.ekf.close()
    return (total / count, count) if count else (-np.inf, 0)


def first_steps_scale(seq: Sequence, decisions, config: Config, steps: int = LIKELIHOOD_STEPS) -> ScaleCheck:
    """(H4) the filter's scale against the IMU's over the first ``steps`` steps of ``seq`` under
    ``decisions``."""
    run, _, _ = _first_steps(seq, decisions, config, steps)
    try:
        return run.scale_check()
    finally:
        run.ekf.close()


def with_imu(decisions, linear_sigma: np.ndarray | None = None, angular_sigma: np.ndarray | None = None):
    """``decisions`` with other IMU noise sigmas (a candidate of L2)."""
    imu = decisions.imu
    imu = dataclasses.replace(imu, linear_sigma=imu.linear_sigma if linear_sigma is None else linear_sigma,
                              angular_sigma=imu.angular_sigma if angular_sigma is None else angular_sigma)
    return dataclasses.replace(decisions, imu=imu)
