"""The run: the filter over a whole input, in one loop for feature files, image streams and the API.

A run decides what the data does not say reliably, then steps the filter once per time stamp:

1. the data conventions (``backend.run.conventions``: the extrinsic's flip, the velocity
   timing; ``backend.run.stereo_offset``: the stereo pair's disparity offset, kept only if dead
   reckoning does not contradict it, :func:`checked_offset`) and the IMU noise
   (``backend.run.noise``), recorded with their numbers; for a file from the whole file
   (:func:`decide`), for a stream from its first frames (:func:`decide_online`);
2. the track drift (``backend.run.drift``), from what made the tracks;
3. :class:`~vislam.backend.run.online.OnlineRun` over every step (:func:`run_stream`).

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
from ..geometry.camera import StereoCamera
from .conventions import ConventionDecision, decide_conventions, reprojection_error
from .noise import NoiseDecision, decide_noise
from .stereo_offset import StereoOffset, identify_stereo_offset
from .online import OnlineRun, RunResult

__all__ = ["run_sequence", "run_stream", "decide", "decide_online", "decisive", "Step"]

#: One time stamp of a stream: (t, linear velocity (3,), angular velocity (3,), ids (n,), pixels (n,4))
Step = tuple
Observer = Callable[[int, VisualInertialEKF, Optional[StepStats]], None]
COMPILING = "vislam: compiling the filter's kernels (once after an install or an update, up to a minute) ..."


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


def decide(seq: Sequence, config: Config) -> tuple[ConventionDecision, NoiseDecision]:
    """The extrinsic, the velocity timing and the IMU noise for a whole sequence."""
    c = config.conventions
    conventions = decide_conventions(seq, c.imu_flip, c.velocity_index, c.horizon)
    offset = identify_stereo_offset(seq, conventions.imu_T_cam, _offset_model(config))
    conventions.stereo_offset = checked_offset(seq, conventions, offset, c.horizon,
                                               without=conventions.chosen_error_px)  # C1 ran on this very sequence
    noise = decide_noise(config, seq.linear_velocity, seq.angular_velocity,
                         seq.num_observations / max(seq.num_steps, 1))
    return conventions, noise


def _offset_model(config: Config) -> str:
    """The stereo offset model to estimate: none for dead reckoning, which uses no vision."""
    return "off" if config.estimator.mode == Mode.DEAD_RECKONING else str(config.conventions.stereo_offset)


def checked_offset(seq: Sequence, conventions: ConventionDecision, offset: StereoOffset, horizon: int,
                   tolerance: float = 1.05, without: float | None = None) -> StereoOffset:
    """``offset``, unless removing it makes the convention test's reprojection (C1: points carried
    by dead reckoning, the IMU alone) worse by more than ``tolerance``: then none, and the estimate
    says why. An independent check: vision found the offset, the IMU must not contradict it.
    ``without``: the error without the offset when already measured on ``seq`` (the convention test's)."""
    if not offset.active:
        return offset
    if without is None:
        without = reprojection_error(seq, conventions.imu_T_cam, conventions.velocity_index, horizon)
    errors = [without, reprojection_error(offset.corrected(seq, conventions.imu_T_cam), conventions.imu_T_cam,
                                          conventions.velocity_index, horizon)]
    offset.estimate["dead_reckoning_reprojection_px"] = {"without": errors[0], "with": errors[1]}
    if np.isfinite(errors[0]) and np.isfinite(errors[1]) and errors[1] > tolerance * errors[0]:
        estimate = dict(offset.estimate, rejected=(
            f"an estimated offset of {offset.estimate['beta_mean_px']:+.2f} px made dead reckoning's reprojection worse "
            f"({errors[0]:.2f} -> {errors[1]:.2f} px), so it is not removed"))
        return StereoOffset(0.0, 0.0, estimate, offset.source)
    return offset


def decisive(errors_px: dict, margin: float = 1.1) -> bool:
    """True when the convention test has nothing to choose (one variant) or its best variant fits at
    least ``margin`` times better than every other."""
    finite = sorted(v for v in errors_px.values() if np.isfinite(v))
    return len(errors_px) <= 1 or (len(finite) >= 2 and finite[1] >= margin * finite[0])


def decide_online(steps: Iterator[Step], camera: StereoCamera, imu_T_cam: np.ndarray, config: Config,
                  imu_velocities: tuple[np.ndarray, np.ndarray], num_steps: int | None = None, tracker: str = ""):
    """The decisions of :func:`decide` from the first steps of a stream, read from ``steps`` as needed.

    The convention test runs from 20 steps on, every 10, until it is :func:`decisive` or
    ``conventions.online_steps`` steps (or the ``num_steps`` of the stream, or all it has) are in;
    the stereo offset (unless ``conventions.stereo_offset = "off"``) is identified from all of those.
    The white noise comes from ``imu_velocities``, (linear (N,3), angular (N,3)) of the whole
    stream. Returns ((conventions, noise), the steps read, the seconds the decisions took).
    """
    limit = config.conventions.online_steps if num_steps is None else min(config.conventions.online_steps, num_steps)
    # the stereo offset wants every step up to the limit; the convention test stops once decisive
    read_all = _offset_model(config) != "off"
    read: list[Step] = []
    seconds = 0.0
    conventions = None
    c = config.conventions
    for step in steps:
        read.append(step)
        k = len(read)
        last = k >= limit
        if conventions is not None and not last:
            continue
        if not last and (k < 20 or k % 10):
            continue
        if conventions is None or not decisive(conventions.errors_px):
            t0 = time.perf_counter()
            conventions = decide_conventions(_as_sequence(read, camera, imu_T_cam, tracker), c.imu_flip,
                                             c.velocity_index, c.horizon)
            seconds += time.perf_counter() - t0
            if not decisive(conventions.errors_px) and not last:
                conventions = None
        if last or (conventions is not None and not read_all):
            break
    if not read:
        raise InputError("no steps: nothing to estimate")
    warm = _as_sequence(read, camera, imu_T_cam, tracker)
    if conventions is None:
        t0 = time.perf_counter()
        conventions = decide_conventions(warm, c.imu_flip, c.velocity_index, c.horizon)
        seconds += time.perf_counter() - t0
    t0 = time.perf_counter()
    offset = identify_stereo_offset(warm, conventions.imu_T_cam, _offset_model(config))
    conventions.stereo_offset = checked_offset(warm, conventions, offset, c.horizon)
    noise = decide_noise(config, *imu_velocities, warm.num_observations / warm.num_steps)
    seconds += time.perf_counter() - t0
    return (conventions, noise), read, seconds


def _as_sequence(steps: Seq[Step], camera: StereoCamera, imu_T_cam: np.ndarray, tracker: str) -> Sequence:
    t, v, w, ids, pixels = zip(*steps)
    return Sequence.from_steps(t, v, w, list(ids), list(pixels), camera.K, camera.baseline, imu_T_cam,
                               source="<stream>", tracker=tracker)


def run_stream(
    steps: Iterable[Step],
    camera: StereoCamera,
    imu_T_cam: np.ndarray,
    config: Config,
    *,
    decisions: tuple[ConventionDecision, NoiseDecision] | None = None,
    imu_velocities: tuple[np.ndarray, np.ndarray] | None = None,
    num_steps: int | None = None,
    tracker: str = "",
    expected_landmarks: int | None = None,
    setup_seconds: float = 0.0,
    load_seconds: float = 0.0,
    progress: Optional[Callable[[int], None]] = None,
    observer: Optional[Observer] = None,
    say: Callable[[str], None] = _quiet,
) -> RunResult:
    """The filter over every step of ``steps`` (:data:`Step` s) with the ``decisions`` given, or
    decided from the stream's first steps (:func:`decide_online`, which needs ``imu_velocities``).

    ``num_steps``: the stream's length, when known; ``tracker``: what made the tracks (``drift``);
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
                                                     tracker)
            setup_seconds += seconds
            steps = itertools.chain(read, steps)
            say(f"conventions from the first {len(read)} steps: " + decisions[0].describe())
        else:
            say(decisions[0].describe())
        say(decisions[0].stereo_offset.describe())
        say(decisions[1].describe())
        run = OnlineRun(camera, *decisions, config, expected_landmarks=expected_landmarks, observer=observer,
                        tracker=tracker)
        say(run.stats.track_drift)
        for k, step in enumerate(steps):
            run.step(*step)
            if progress is not None:
                progress(k)
        return run.result(setup_seconds, load_seconds, input_seconds=timed.seconds)


def run_sequence(
    seq: Sequence,
    config: Config | None = None,
    *,
    decisions: tuple[ConventionDecision, NoiseDecision] | None = None,
    load_seconds: float = 0.0,
    progress: Optional[Callable[[int], None]] = None,
    observer: Optional[Observer] = None,
    say: Callable[[str], None] = _quiet,
) -> RunResult:
    """Run the filter over every step and every observation of ``seq``: :func:`decide` on the whole
    sequence (unless ``decisions`` are given), then :func:`run_stream` over its steps."""
    config = (config if config is not None else Config()).validate()
    if seq.num_steps < 2:
        raise InputError(f"{seq.source}: key 'time_stamps': need at least 2 steps, got {seq.num_steps}")
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
