"""Repeated frames: steps whose pixels repeat the previous step's exactly.

Real feature files hold an image when no new one arrived, so some steps repeat the previous
step's pixels exactly while the IMU moves on. Measured on the course drives against ground truth:
across such a repeat the features of steps k-1 and k+1 move by one step of true motion, not two,
and the features after it move with the true motion of their own step, with no lag building up.
That is a content that froze for one step: as if the world had moved with the camera while the
IMU went on. The policies (``conventions.repeated_frames``):

- ``freeze`` (default): the step's pose comes from the IMU fused with a constant-velocity
  prediction (:class:`MotionPrior`), and every landmark in the state keeps its body-frame point
  through the step (I8 of ``backend.estimator.invariant``), so the tracks go on consistently;
- ``use``: the repeated pixels are a new frame (they say the camera did not move);
- ``skip``: a repeated step's observations are not used (the next frame then contradicts the
  landmarks by one step of motion);
- ``cut``: a repeated step ends every track (its landmarks go to the map) and the IMU alone bridges
  the step.

The motion prior. The posterior body velocity of the last step, u_k-1 = log(T_k-2^-1 T_k-1) /
tau, predicts a frozen step's twist as tau u_k-1 (a vehicle's velocity changes little from one step
to the next). Its error is measured on the run itself, against the IMU's sample of each ordinary
step, whose white noise sigma_imu is known: per axis over the recent steps,

    s^2 = mean (u_imu,k - u_k-1)^2 - sigma_imu^2 + SE,                                            (T2)

which holds both the true change of the velocity and the posterior's own error (a spread of
posterior velocities alone misses the latter); one standard error keeps it on the safe side. Where
s is not below sigma_imu the prior adds nothing and the IMU bridges the step alone. The prior is
fused with the IMU's twist (``VisualInertialEKF.predict_frozen``).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from ..compiled import jit, warms_up
from ..data.sequence import Sequence
from ..geometry import se3


def repeats_previous(ids: np.ndarray, pixels: np.ndarray, prev_ids: np.ndarray, prev_pixels: np.ndarray) -> bool:
    """True when every feature seen in both frames has identical pixels (and one at least is shared)."""
    found = _repeats_sorted(np.ascontiguousarray(ids, dtype=np.int64), np.ascontiguousarray(pixels, dtype=np.float64),
                            np.ascontiguousarray(prev_ids, dtype=np.int64),
                            np.ascontiguousarray(prev_pixels, dtype=np.float64))
    if found >= 0:
        return bool(found)
    _, i_now, i_prev = np.intersect1d(ids, prev_ids, assume_unique=True, return_indices=True)  # ids not sorted
    return bool(i_now.size) and np.array_equal(pixels[i_now], prev_pixels[i_prev])


@jit
def _repeats_sorted(ids, pixels, prev_ids, prev_pixels):
    """:func:`repeats_previous` by one merge of two increasing id lists (the sequence's order): 1 or 0,
    or -1 when either list is not increasing (the caller falls back to a set intersection)."""
    for a in (ids, prev_ids):
        for i in range(1, a.size):
            if a[i] <= a[i - 1]:
                return -1
    i = j = shared = 0
    while i < ids.size and j < prev_ids.size:
        if ids[i] < prev_ids[j]:
            i += 1
        elif ids[i] > prev_ids[j]:
            j += 1
        else:
            for c in range(4):
                if pixels[i, c] != prev_pixels[j, c]:
                    return 0
            shared += 1
            i += 1
            j += 1
    return 1 if shared else 0


class MotionPrior:
    """(T2) the constant-velocity prediction of a frozen step's twist and its measured error."""

    #: steps of history the error is measured over, and the fewest it needs
    WINDOW = 200
    MIN_STEPS = 30

    def __init__(self, imu_sigma: np.ndarray) -> None:
        self._imu_var = np.asarray(imu_sigma, dtype=float) ** 2  # (6,) the IMU's white noise, (m/s)^2, (rad/s)^2
        self._squares: deque[np.ndarray] = deque(maxlen=self.WINDOW)  # (u_imu,k - u_k-1)^2 of recent ordinary steps
        self._last: np.ndarray | None = None  # the last step's posterior velocity, None after a frozen step

    def add(self, previous_pose: np.ndarray, pose: np.ndarray, dt: float, imu_velocity: np.ndarray,
            frozen: bool) -> None:
        """The posterior poses before and after a step of ``dt`` s and the IMU's velocity (6,) that drove
        it; a frozen step's posterior is the prediction's own, so it is not a measurement."""
        if frozen:
            self._last = None
            return
        if self._last is not None:
            self._squares.append((np.asarray(imu_velocity) - self._last) ** 2)
        self._last = se3.log_se3(se3.inverse(previous_pose) @ pose) / dt

    def predict(self, dt: float) -> tuple[np.ndarray, np.ndarray] | None:
        """(twist tau u (6,), its sigmas (6,)) for a frozen step of ``dt`` s, or None without enough
        history or where the prior is no better than the IMU. Per axis, the prior's error variance is
        what the squared differences to the IMU hold beyond the IMU's own, and at least the standard
        error of their mean: where the IMU's noise takes up all of them, the data cannot tell the
        prior's error from zero, and the prior is not taken as exact."""
        if self._last is None or len(self._squares) < self.MIN_STEPS:
            return None
        sq = np.array(self._squares)
        var = np.maximum(sq.mean(axis=0) - self._imu_var, 0.0) + sq.std(axis=0) / np.sqrt(sq.shape[0])
        if np.any(var >= self._imu_var):
            return None
        return dt * self._last, dt * np.sqrt(var)


def repeated_steps(seq: Sequence) -> np.ndarray:
    """(N,) bool: step k > 0 repeats the last step before it that was not a repeat (:func:`repeats_previous`)."""
    repeated = np.zeros(seq.num_steps, dtype=bool)
    prev_ids, prev_px = seq.observations(0)
    for k in range(1, seq.num_steps):
        ids, px = seq.observations(k)
        if repeats_previous(ids, px, prev_ids, prev_px):
            repeated[k] = True
        else:
            prev_ids, prev_px = ids, px
    return repeated


@warms_up(only="velocity")
def _warm_up() -> None:
    ids = np.arange(2, dtype=np.int64)
    pixels = np.ones((2, 4))
    _repeats_sorted(ids, pixels, ids, pixels)
