"""Measured IMU velocities from the true twists: stamping, white noise and a gyro bias.

``measured = stamped true twist + bias (angular only) + white noise``, where the stamping follows
``velocity_index`` (see :mod:`~vislam.backend.estimator.propagation`): with "this" the sample stamped k holds the twist of
step k -> k+1; with "next" the sample stamped k+1 holds it (and sample 0 repeats twist 0).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ._random import generator

__all__ = [
    "ImuMeasurements",
    "stamp_twists",
    "gyro_bias_series",
    "measure_velocities",
    "DEFAULT_LINEAR_SIGMA",
    "DEFAULT_ANGULAR_SIGMA",
    "DEFAULT_GYRO_BIAS",
]

DEFAULT_LINEAR_SIGMA = 0.2  # m/s per axis
DEFAULT_ANGULAR_SIGMA = 0.01  # rad/s per axis
DEFAULT_GYRO_BIAS = (0.002, -0.002, 0.001)  # rad/s, constant unless a random walk is asked for


class ImuMeasurements(NamedTuple):
    linear_velocity: np.ndarray  # (N,3) m/s
    angular_velocity: np.ndarray  # (N,3) rad/s
    gyro_bias: np.ndarray  # (N,3) rad/s, the bias in each angular sample


def _per_axis(name: str, value) -> np.ndarray:
    a = np.broadcast_to(np.asarray(value, dtype=float), (3,)).copy()
    if not (np.all(np.isfinite(a)) and np.all(a >= 0)):
        raise ValueError(f"{name} must be finite and >= 0 (a number or 3 per-axis values), got {value!r}")
    return a


def stamp_twists(twists: np.ndarray, velocity_index: str = "this") -> np.ndarray:
    """The true sample at each stamp (N,6): "this" -> twists as is; "next" -> [twists[0], twists[:-1]]."""
    twists = np.asarray(twists, dtype=float)
    if velocity_index == "this":
        return twists.copy()
    if velocity_index == "next":
        return np.concatenate([twists[:1], twists[:-1]], axis=0)
    raise ValueError(f"velocity_index must be 'this' or 'next', got {velocity_index!r}")


def gyro_bias_series(time_stamps: np.ndarray, rng, bias0=DEFAULT_GYRO_BIAS, walk_sigma=0.0) -> np.ndarray:
    """Bias per sample (N,3): bias0 at sample 0, then a random walk of ``walk_sigma`` rad/s per sqrt(s)
    (b_{k+1} = b_k + walk_sigma sqrt(t_{k+1} - t_k) n_k); constant when walk_sigma is 0."""
    rng = generator(rng)
    t = np.asarray(time_stamps, dtype=float)
    bias0 = np.broadcast_to(np.asarray(bias0, dtype=float), (3,))
    if not np.all(np.isfinite(bias0)):
        raise ValueError(f"gyro_bias must be finite, got {bias0!r}")
    walk = _per_axis("gyro_bias_walk", walk_sigma)
    steps = rng.standard_normal((t.shape[0] - 1, 3)) * walk * np.sqrt(np.diff(t))[:, None]
    return bias0 + np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)], axis=0)


def measure_velocities(
    twists_true: np.ndarray,
    time_stamps: np.ndarray,
    rng=0,
    *,
    linear_sigma=DEFAULT_LINEAR_SIGMA,
    angular_sigma=DEFAULT_ANGULAR_SIGMA,
    gyro_bias=DEFAULT_GYRO_BIAS,
    gyro_bias_walk=0.0,
    velocity_index: str = "this",
) -> ImuMeasurements:
    """Noisy velocity samples from the true twists (N,6) (row k drives step k -> k+1).

    ``linear_sigma`` (m/s) and ``angular_sigma`` (rad/s) are white-noise standard deviations, a
    number or 3 per-axis values. The random draws do not depend on the settings, so a zero
    sigma gives the stamped truth exactly and changing one sigma leaves the other noise as is.
    """
    rng = generator(rng)
    stamped = stamp_twists(twists_true, velocity_index)
    lin_sigma = _per_axis("linear_sigma", linear_sigma)
    ang_sigma = _per_axis("angular_sigma", angular_sigma)
    white = rng.standard_normal(stamped.shape)
    bias = gyro_bias_series(time_stamps, rng, gyro_bias, gyro_bias_walk)
    linear = stamped[:, :3] + white[:, :3] * lin_sigma
    angular = stamped[:, 3:] + bias + white[:, 3:] * ang_sigma
    return ImuMeasurements(linear, angular, bias)
