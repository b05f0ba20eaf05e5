"""A run recorded for the Rerun viewer (https://rerun.io): scrub through the estimate step by step.

:class:`RerunRecorder` writes an ``.rrd`` recording (``rerun FILE.rrd`` opens it) and can stream
to a viewer as well. Its :meth:`~RerunRecorder.observer` is a run observer
(``backend.run.runner.run_stream``), :meth:`~RerunRecorder.log_frame` takes a frame's images and
tracks, :meth:`~RerunRecorder.log_result` what a run ends with. What changes is logged on the time
lines ``step`` (the step index) and, when the time stamps are given, ``time`` (their seconds):

- ``world/imu``: the pose estimate world_T_imu (a transform); ``world/imu/uncertainty``: its
  position's 2-sigma ellipsoid, in the IMU frame;
- ``world/estimate/<piece>``: the estimated trajectory so far, in pieces of :data:`PIECE` steps;
- ``world/landmarks/active``: the landmarks in the filter's state (at most ``max_landmarks``);
  ``world/landmarks/active/uncertainty``: their 2-sigma ellipsoids;
- ``world/landmarks/map``: the final map, at the last step;
- ``world/dead_reckoning``, ``world/ground_truth``: those trajectories (static: at every time);
- ``camera/left``, ``camera/right``: a frame's images (JPEG); ``camera/left/tracks``,
  ``camera/right/tracks``: its tracked points, coloured by track id (``track_id`` beside them).

``rerun`` is an optional dependency (the ``viewer`` extra), imported only when a recorder is made.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..backend.data.files import atomic_write, check_not_an_input
from ..backend.errors import OutputError, VislamError
from ..backend.geometry.se3 import quaternion_from_rotation

__all__ = ["MISSING_EXTRA", "PIECE", "RerunRecorder"]

MISSING_EXTRA = "--rerun needs the optional viewer extra: pip install 'vislam[viewer]'"

#: Steps per logged piece of the estimated trajectory: the strip so far is re-logged each step,
#: so a piece bounds that to PIECE points (a whole strip would grow the recording with N^2).
PIECE = 200

_ESTIMATE, _DEAD_RECKONING, _GROUND_TRUTH = (40, 110, 230), (230, 120, 30), (40, 170, 60)
_ACTIVE, _MAP, _POSE = (240, 200, 30), (150, 150, 150), (200, 40, 200)


def _principal_axes(covariances: np.ndarray, sigmas: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Half sizes (K,3) (``sigmas`` standard deviations along the principal axes) and the rotations
    (K,4) [qx qy qz qw] from those axes to the frame of ``covariances`` (K,3,3)."""
    variances, axes = np.linalg.eigh(covariances)
    axes[np.linalg.det(axes) < 0, :, 2] *= -1.0  # a rotation, not a reflection
    return sigmas * np.sqrt(np.clip(variances, 0.0, None)), quaternion_from_rotation(axes)


def _track_colors(ids: np.ndarray) -> np.ndarray:
    """A colour (n,3) uint8 per track id, the same in every frame (hues spaced by the golden ratio)."""
    hue = (np.asarray(ids, dtype=np.int64) * 0.6180339887) % 1.0
    rgb = np.clip(np.abs((hue[:, None] * 6.0 + np.array([0.0, 4.0, 2.0])) % 6.0 - 3.0) - 1.0, 0.0, 1.0)
    return (55 + 200 * rgb).astype(np.uint8)


class RerunRecorder:
    """Records a run for the Rerun viewer: one ``.rrd`` file, one recording stream of its own.

    Parameters
    ----------
    path : str or Path or None
        The ``.rrd`` file to write. It is written under a temporary name beside ``path`` and
        renamed on :meth:`close`; a recorder left by an exception (:meth:`abort`, or the ``with``
        block raising) leaves no file. None: no file (with ``spawn``).
    spawn : bool
        Also start a Rerun viewer (the ``rerun`` executable) and stream to it as the run goes.
    application_id : str
        The application the viewer files the recording under.
    time_stamps : sequence of float, shape (N,), optional
        The time stamp in seconds of each step: logged on the time line ``time`` beside ``step``
        (the attribute ``time_stamps`` may also be set later, once the input is read).
    max_landmarks : int
        At most this many active landmarks are logged per step (the first in the filter's state).
    jpeg_quality : int
        Quality of the JPEG images :meth:`log_frame` logs (1-100).

    Use as a context manager, or call :meth:`close` (success) or :meth:`abort` (failure) once.
    Raises VislamError (:data:`MISSING_EXTRA`) when ``rerun`` is not installed, OutputError when
    ``path`` cannot be written.
    """

    def __init__(self, path: str | Path | None, spawn: bool = False, application_id: str = "vislam",
                 time_stamps: Sequence[float] | None = None, max_landmarks: int = 300,
                 jpeg_quality: int = 90) -> None:
        try:
            import rerun as rr
        except ImportError:
            raise VislamError(MISSING_EXTRA) from None
        if path is None and not spawn:
            raise ValueError("RerunRecorder: a path, spawn=True, or both")
        self._rr = rr
        self.time_stamps = time_stamps
        self._max_landmarks = int(max_landmarks)
        self._jpeg_quality = int(jpeg_quality)
        self._p_in_world: list[np.ndarray] = []  # the estimate's position at each step so far
        self._last_step: int | None = None
        self._path = path
        self._writing = atomic_write(path) if path is not None else None
        tmp = self._writing.__enter__() if self._writing is not None else None  # checks path first
        self.stream = None
        try:
            self.stream = rr.RecordingStream(application_id)
            if spawn:
                self.stream.spawn(connect=tmp is None)
                if tmp is not None:
                    self.stream.set_sinks(rr.FileSink(str(tmp)), rr.GrpcSink())
            elif tmp is not None:
                self.stream.save(tmp)
            self.stream.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        except BaseException as exc:
            self._finish(exc)
            raise

    # ------------------------------------------------------------------ per step
    def _set_step(self, k: int) -> None:
        """Log what follows at step ``k`` (and its time stamp, when known)."""
        self.stream.set_time("step", sequence=int(k))
        if self.time_stamps is not None and 0 <= k < len(self.time_stamps):
            self.stream.set_time("time", duration=float(self.time_stamps[k]))

    def observer(self, k: int, ekf, step_stats=None) -> None:
        """A run observer (``observer(k, ekf, step_stats)``): log step ``k`` of the filter ``ekf``
        (a :class:`~vislam.backend.estimator.ekf.VisualInertialEKF`): the pose, the trajectory so
        far, the pose's position uncertainty and the active landmarks with theirs."""
        rr = self._rr
        self._set_step(k)
        self._last_step = int(k)
        world_T_imu = np.asarray(ekf.world_T_imu, dtype=float)
        self.stream.log("world/imu", rr.Transform3D(translation=world_T_imu[:3, 3], mat3x3=world_T_imu[:3, :3]))
        # right perturbation world_T_imu = mu exp(xi^), xi = [rho, theta]: the position error is rho in the IMU frame
        half_sizes, quaternions = _principal_axes(np.asarray(ekf.pose_covariance)[None, :3, :3])
        self.stream.log("world/imu/uncertainty", rr.Ellipsoids3D(half_sizes=half_sizes, quaternions=quaternions,
                                                                 colors=[_POSE]))
        self._p_in_world.append(world_T_imu[:3, 3].copy())
        first = (len(self._p_in_world) - 1) // PIECE * PIECE  # pieces share their end points: one line
        piece = np.array(self._p_in_world[max(first - 1, 0):])
        self.stream.log(f"world/estimate/{first // PIECE:05d}", rr.LineStrips3D([piece], colors=[_ESTIMATE]))
        self._log_active_landmarks(ekf)

    def _log_active_landmarks(self, ekf) -> None:
        rr = self._rr
        slots = np.arange(min(ekf.num_active, self._max_landmarks))
        p_in_world, covariances = np.zeros((0, 3)), np.zeros((0, 3, 3))
        if slots.size:
            p_in_world, covariances, finite = ekf.model.world_landmarks(ekf.state, slots)
            p_in_world, covariances = p_in_world[finite], covariances[finite]
        half_sizes, quaternions = _principal_axes(covariances)
        self.stream.log("world/landmarks/active", rr.Points3D(p_in_world, colors=[_ACTIVE]))
        self.stream.log("world/landmarks/active/uncertainty",
                        rr.Ellipsoids3D(centers=p_in_world, half_sizes=half_sizes, quaternions=quaternions,
                                        colors=[_ACTIVE]))

    def log_frame(self, k: int, left: np.ndarray, right: np.ndarray, ids: np.ndarray, pixels: np.ndarray) -> None:
        """Log frame ``k``'s images and tracks (the arguments of the tracker's frame loop).

        Parameters
        ----------
        k : int
            The frame's step.
        left, right : array, shape (H, W), uint8
            The rectified stereo images.
        ids : array, shape (n,)
            Track ids.
        pixels : array, shape (n, 4)
            ``[uL vL uR vR]`` of each track.
        """
        rr = self._rr
        self._set_step(k)
        pixels = np.asarray(pixels, dtype=float).reshape(-1, 4)
        colors = _track_colors(ids)
        for side, image, uv in (("left", left, pixels[:, :2]), ("right", right, pixels[:, 2:])):
            self.stream.log(f"camera/{side}", rr.Image(np.asarray(image)).compress(jpeg_quality=self._jpeg_quality))
            self.stream.log(f"camera/{side}/tracks", rr.Points2D(uv, colors=colors),
                            rr.AnyValues(track_id=np.asarray(ids, dtype=np.int64)))

    # ------------------------------------------------------------------ once
    def log_trajectory(self, name: str, world_T_imu: np.ndarray, color=_GROUND_TRUTH) -> None:
        """Log the trajectory ``world_T_imu`` (N,4,4) as a static line strip ``world/<name>``; it is
        drawn in the estimate's world frame as given (align it first if its world differs)."""
        p_in_world = np.asarray(world_T_imu, dtype=float).reshape(-1, 4, 4)[:, :3, 3]
        self.stream.log(f"world/{name}", self._rr.LineStrips3D([p_in_world], colors=[color]), static=True)

    def log_map(self, p_in_world: np.ndarray) -> None:
        """Log the final map, positions (K,3) in the world frame, at the last step observed (static
        if none was)."""
        if self._last_step is not None:
            self._set_step(self._last_step)
        self.stream.log("world/landmarks/map", self._rr.Points3D(np.asarray(p_in_world, dtype=float).reshape(-1, 3),
                                                                  colors=[_MAP]), static=self._last_step is None)

    def log_result(self, result, ground_truth: np.ndarray | None = None) -> None:
        """Log what a run ends with: the dead reckoning and the map of ``result`` (a
        :class:`~vislam.backend.run.online.RunResult`) and the ``ground_truth`` world_T_imu (M,4,4)."""
        self.log_trajectory("dead_reckoning", result.dead_reckoning, _DEAD_RECKONING)
        if ground_truth is not None:
            self.log_trajectory("ground_truth", ground_truth, _GROUND_TRUTH)
        self.log_map(result.map_positions)

    # ------------------------------------------------------------------ end
    def close(self) -> None:
        """Flush the recording and move it onto ``path``."""
        self._finish(None)

    def abort(self) -> None:
        """Stop recording and remove the partial file (the run failed)."""
        self._finish(RuntimeError("recording aborted"))

    def finish_writing(self) -> None:
        """Flush and close the recording, still under its temporary name (:meth:`close` moves it onto
        ``path``); OutputError when the file could not be written whole (a full disk), the partial
        file then removed. Called before the run's other outputs are moved into place, so that a
        failed recording leaves none of them, and a failed output set no recording."""
        stream, self.stream = self.stream, None
        if stream is None:
            return
        failure = None
        try:
            if self._path is not None:
                check_not_an_input(self._path)  # an input the readers found meanwhile: refused before the outputs move
            stream.flush()
        except OutputError as err:
            failure = err
        except RuntimeError as err:  # rerun's file writer stopped: the file is incomplete
            failure = OutputError(f"{self._path}: cannot write the recording: {' '.join(str(err).split())}")
        try:
            stream.disconnect()  # closes the file
        finally:
            if failure is not None:
                self._finish(failure)
        if failure is not None:
            raise failure from None

    def _finish(self, exc: BaseException | None) -> None:
        """Close the stream; then keep the file (``exc`` None) or remove it."""
        if exc is None:
            self.finish_writing()
        stream, self.stream = self.stream, None
        writing, self._writing = self._writing, None
        try:
            if stream is not None:
                stream.disconnect()  # closes the file
        finally:
            if writing is not None:
                writing.__exit__(*((None, None, None) if exc is None else (type(exc), exc, exc.__traceback__)))

    def __enter__(self) -> RerunRecorder:
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        self._finish(exc)
        return False
