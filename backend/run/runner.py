"""The run: the filter over a whole input, in one loop for feature files, image streams and the API.

A run decides what the data does not say reliably, then steps the filter once per time stamp:

1. :func:`~vislam.backend.run.decisions.decide` (conventions, repeated frames, stereo offset, IMU
   velocity correction and noise, pixel noise, track drift, gyro bias), one frozen ``Decisions``
   with the numbers behind each: for a file from the whole file, for a stream from its first
   frames (:func:`decide_online`);
2. :class:`~vislam.backend.run.online.OnlineRun` over every step (:func:`run_stream`).

:func:`run_sequence` is that for a loaded :class:`~vislam.backend.data.sequence.Sequence`.
What a run says (its decisions, that kernels are compiling) goes to ``say``; the compiled
kernels are loaded (or compiled, once after an install) before any timing starts.
"""

from __future__ import annotations

import itertools
import time
from typing import Callable, Iterable, Iterator, Optional, Sequence as Seq

import numpy as np
from threadpoolctl import threadpool_limits

from ..compiled import warm_up
from ..config import Config, Mode
from ..data.sequence import Sequence
from ..errors import InputError
from ..estimator.ekf import StepStats, VisualInertialEKF
from ..estimator.window import window_text
from ..geometry.camera import StereoCamera
from .conventions import decide_conventions
from .decisions import Decisions, decide
from .online import OnlineRun, RunResult

__all__ = ["run_sequence", "run_stream", "decide", "decide_online", "decisive", "Step"]

#: One time stamp of a stream: (t, linear velocity (3,), angular velocity (3,), ids (n,), pixels (n,4))
Step = tuple
Observer = Callable[[int, VisualInertialEKF, Optional[StepStats]], None]
COMPILING = "vislam: compiling the filter's kernels (once after an install or an update, about 20 s) ..."


def _quiet(_: str) -> None:
    pass


class _Timed:
    """An iterator over ``steps`` that adds up the seconds spent producing them (for an image
    stream: decoding and tracking each frame)."""

    def __init__(self, steps: Iterable[Step]) -> None:
        self._steps = iter(steps)
        self.seconds = 0.0

    def __iter__(self) -> "_Timed":
        return self

    def __next__(self) -> Step:
        t0 = time.perf_counter()
        try:
            return next(self._steps)
        finally:
            self.seconds += time.perf_counter() - t0


def decisive(errors_px: dict, margin: float = 1.1) -> bool:
    """True when the convention test has nothing to choose (one variant) or its best variant fits at
    least ``margin`` times better than every other."""
    finite = sorted(v for v in errors_px.values() if np.isfinite(v))
    return len(errors_px) <= 1 or (len(finite) >= 2 and finite[1] >= margin * finite[0])


#: The name of a stream of steps whose source was not given, in messages
STREAM = "<stream>"


def decide_online(steps: Iterator[Step], camera: StereoCamera, imu_T_cam: np.ndarray, config: Config,
                  imu_velocities: tuple[np.ndarray, np.ndarray], num_steps: int | None = None, tracker: str = "",
                  source: str = STREAM):
    """:func:`~vislam.backend.run.decisions.decide` from the first steps of a stream, read from ``steps``.

    ``conventions.online_steps`` steps (or the ``num_steps`` of the stream, or all it has) are read,
    fewer when only the convention test is wanted (``conventions.stereo_offset = "off"`` and every
    noise configured): then the test runs from 20 steps on, every 10, until it is :func:`decisive`.
    The white noise (N1) comes from ``imu_velocities``, (linear (N,3), angular (N,3)) of the whole
    stream. Returns (decisions, the steps read, the seconds the decisions took).
    """
    limit = config.conventions.online_steps if num_steps is None else min(config.conventions.online_steps, num_steps)
    noise = config.noise
    read_all = (str(config.conventions.stereo_offset) != "off" or noise.pixel_sigma is None
                or noise.linear_velocity_sigma is None or noise.angular_velocity_sigma is None)
    read: list[Step] = []
    c = config.conventions
    for step in steps:
        read.append(step)
        k = len(read)
        if k >= limit:
            break
        if not read_all and k >= 20 and k % 10 == 0:
            test = decide_conventions(_as_sequence(read, camera, imu_T_cam, tracker, source), c.imu_flip,
                                      c.velocity_index, c.horizon)
            if decisive(test.errors_px):
                break
    if not read:
        raise InputError("no steps: nothing to estimate")
    t0 = time.perf_counter()
    decisions = decide(_as_sequence(read, camera, imu_T_cam, tracker, source), config, imu_velocities)
    return decisions, read, time.perf_counter() - t0


def _as_sequence(steps: Seq[Step], camera: StereoCamera, imu_T_cam: np.ndarray, tracker: str,
                 source: str = STREAM) -> Sequence:
    t, v, w, ids, pixels = zip(*steps)
    return Sequence.from_steps(t, v, w, list(ids), list(pixels), camera.K, camera.baseline, imu_T_cam,
                               source=source, tracker=tracker)


def run_stream(
    steps: Iterable[Step],
    camera: StereoCamera,
    imu_T_cam: np.ndarray,
    config: Config,
    *,
    decisions: Decisions | None = None,
    imu_velocities: tuple[np.ndarray, np.ndarray] | None = None,
    num_steps: int | None = None,
    tracker: str = "",
    source: str = STREAM,
    expected_landmarks: int | None = None,
    setup_seconds: float = 0.0,
    load_seconds: float = 0.0,
    progress: Optional[Callable[[int], None]] = None,
    observer: Optional[Observer] = None,
    say: Callable[[str], None] = _quiet,
) -> RunResult:
    """The filter over every step of ``steps`` (:data:`Step` s) with the ``decisions`` given, or
    decided from the stream's first steps (:func:`decide_online`, which needs ``imu_velocities``).

    ``num_steps``: the stream's length, when known; ``tracker``: what made the tracks (reported);
    ``source``: what the steps come from (the image folder), named in messages;
    the seconds spent producing the steps (an image stream's tracking) are counted as
    ``RunStats.input_seconds``, in the real-time factor;
    ``expected_landmarks``: for the full-state size check; ``setup_seconds`` / ``load_seconds``:
    time spent before (deciding, loading), counted in the real-time factor. ``progress(k)`` and
    ``observer(k, ekf, step_stats)`` are called after each step k (step_stats is None where the
    step's observations were not used); ``say`` receives the run's decisions, a line each.
    """
    config.validate()
    with threadpool_limits(limits=config.execution.blas_threads):
        warm_up(notice=lambda: say(COMPILING))  # before the convention test calls a kernel; reported apart
        steps = timed = _Timed(steps)
        if decisions is None:
            if imu_velocities is None:
                raise ValueError("run_stream: decisions or imu_velocities are needed")
            decisions, read, seconds = decide_online(steps, camera, imu_T_cam, config, imu_velocities, num_steps,
                                                     tracker, source)
            setup_seconds += seconds
            steps = itertools.chain(read, steps)
            say(f"decided from the first {len(read)} steps:")
        say(decisions.describe(decisions.config_for(config)))
        if text := window_text(config, inertial=False):
            say(text)
        run = OnlineRun(camera, decisions, config, expected_landmarks=expected_landmarks, observer=observer)
        for k, step in enumerate(steps):
            run.step(*step)
            if progress is not None:
                progress(k)
        return run.result(setup_seconds, load_seconds, input_seconds=timed.seconds)


def run_sequence(
    seq: Sequence,
    config: Config | None = None,
    *,
    decisions: Decisions | None = None,
    load_seconds: float = 0.0,
    progress: Optional[Callable[[int], None]] = None,
    observer: Optional[Observer] = None,
    say: Callable[[str], None] = _quiet,
) -> RunResult:
    """Run the filter over every step and every observation of ``seq``: :func:`decide` on the whole
    sequence (unless ``decisions`` are given), then :func:`run_stream` over its steps; an inertial
    sequence (a real IMU's samples) goes to :func:`~vislam.backend.run.inertial.run_inertial`."""
    config = (config if config is not None else Config()).validate()
    if seq.num_steps < 2:
        raise InputError(f"{seq.source}: key 'time_stamps': need at least 2 steps, got {seq.num_steps}")
    if seq.inertial:  # a real IMU's samples: the inertial state (backend.run.inertial)
        if decisions is not None:
            raise ValueError("run_sequence: decisions of a velocity run given for an inertial sequence")
        from .inertial import run_inertial

        return run_inertial(seq, config, load_seconds=load_seconds, progress=progress, observer=observer, say=say)
    setup = 0.0
    if decisions is None:
        with threadpool_limits(limits=config.execution.blas_threads):
            warm_up(notice=lambda: say(COMPILING))  # the convention test calls a kernel: load them apart from setup
            t0 = time.perf_counter()
            decisions = decide(seq, config)
            setup = time.perf_counter() - t0
    result = run_stream(seq.steps(), StereoCamera(seq.K, seq.baseline), seq.imu_T_cam, config, decisions=decisions,
                        num_steps=seq.num_steps, tracker=seq.tracker, expected_landmarks=seq.num_features,
                        setup_seconds=setup, load_seconds=load_seconds, progress=progress, observer=observer,
                        say=say)
    result.stats.observations_dropped_input = dict(seq.dropped)
    return result
