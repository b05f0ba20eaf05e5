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
import itertools
from contextlib import contextmanager
from typing import Iterator

import numpy as np

from ..config import Config
from ..data.sequence import Sequence
from ..estimator.health import ScaleCheck
from ..geometry.camera import StereoCamera

__all__ = ["log_likelihood", "first_steps_scale", "LIKELIHOOD_STEPS"]

#: Steps of a sequence the comparison runs over.
LIKELIHOOD_STEPS = 300


@contextmanager
def _trial_run(seq: Sequence, decisions, config: Config, likelihood: bool) -> Iterator:
    """An ``OnlineRun`` of ``decisions`` over ``seq`` (health silent: a trial of the decisions, not the
    user's run; the innovation likelihood tracked where ``likelihood``), closed on leaving. A considered
    lever arm (V2 of ``backend.estimator.lever_arm``) moves neither the estimate nor the innovations:
    the trial runs without it."""
    from .online import OnlineRun  # the run layer above: imported when a comparison runs

    if not config.estimator.estimate_lever_arm:
        config = config.with_values({"noise.lever_arm_sigma": 0.0, "noise.imu_rotation_sigma": 0.0})
    run = OnlineRun(StereoCamera(seq.K, seq.baseline), decisions, config)
    run.ekf.track_likelihood = likelihood
    run.ekf.health.silent = True
    try:
        yield run
    finally:
        run.ekf.close()


def log_likelihood(seq: Sequence, decisions, config: Config, steps: int = LIKELIHOOD_STEPS) -> tuple[float, int]:
    """(L2) (mean log-likelihood per observation, observations) of the first ``steps`` steps of ``seq``
    under ``decisions`` (a ``backend.run.decisions.Decisions``); (-inf, 0) when none was tested."""
    total, count = 0.0, 0
    with _trial_run(seq, decisions, config, likelihood=True) as run:
        for step in itertools.islice(seq.steps(), steps):
            stats = run.step(*step)
            if stats is not None:
                total += stats.log_likelihood
                count += stats.tested
    return (total / count, count) if count else (-np.inf, 0)


def first_steps_scale(seq: Sequence, decisions, config: Config, steps: int = LIKELIHOOD_STEPS) -> ScaleCheck:
    """(H4) the filter's scale against the IMU's over the first ``steps`` steps of ``seq`` under
    ``decisions``."""
    with _trial_run(seq, decisions, config, likelihood=False) as run:
        for step in itertools.islice(seq.steps(), steps):
            run.step(*step)
        return run.scale_check()


def with_imu(decisions, linear_sigma: np.ndarray | None = None, angular_sigma: np.ndarray | None = None):
    """``decisions`` with other IMU noise sigmas (a candidate of L2)."""
    imu = decisions.imu
    imu = dataclasses.replace(imu, linear_sigma=imu.linear_sigma if linear_sigma is None else linear_sigma,
                              angular_sigma=imu.angular_sigma if angular_sigma is None else angular_sigma)
    return dataclasses.replace(decisions, imu=imu)
