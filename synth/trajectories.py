"""Smooth synthetic trajectories whose body velocities are exact.

A trajectory is generated as body twists ``u_k = [v_k, w_k]`` (m/s, rad/s; IMU frame x forward,
y left, z up) and integrated in closed form,
``world_T_imu_{k+1} = world_T_imu_k exp(tau_k u_k^)`` with ``tau_k = t_{k+1} - t_k``, the same
arithmetic as :func:`~vislam.backend.estimator.propagation.dead_reckoning`. So ``u_k`` is exactly the velocity stamped k
("this") of the course formulation, and dead reckoning on the noise-free twists gives back the
poses to rounding.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..backend.geometry import se3
from ._random import generator

__all__ = ["Trajectory", "integrate", "street", "aerial", "TRAJECTORIES"]


class Trajectory(NamedTuple):
    """Time, poses and the twists that produced them."""

    time_stamps: np.ndarray  # (N,) seconds, k * dt
    world_T_imu: np.ndarray  # (N,4,4)
    twists: np.ndarray  # (N,6) [v (m/s), w (rad/s)]; row k drives k -> k+1, the last row copies N-2


def integrate(time_stamps: np.ndarray, twists: np.ndarray, world_T_imu0: np.ndarray | None = None) -> np.ndarray:
    """Poses (N,4,4) from T_{k+1} = T_k exp(tau_k twists[k]^), tau = diff(time_stamps)."""
    time_stamps = np.asarray(time_stamps, dtype=float)
    twists = np.asarray(twists, dtype=float)
    n = time_stamps.shape[0]
    tau = np.diff(time_stamps)
    scaled = twists[: n - 1] * tau[:, None]
    poses = np.empty((n, 4, 4))
    poses[0] = np.eye(4) if world_T_imu0 is None else world_T_imu0
    for k in range(n - 1):
        poses[k + 1] = poses[k] @ se3.exp_se3(scaled[k])
    return poses


def _time(steps: int, dt: float) -> np.ndarray:
    steps, dt = int(steps), float(dt)
    if steps < 2:
        raise ValueError(f"a trajectory needs at least 2 steps, got {steps}")
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number of seconds, got {dt}")
    return np.arange(steps) * dt


def _sinusoids(rng: np.random.Generator, t: np.ndarray, terms) -> np.ndarray:
    """Sum of A sin(2 pi t / T + phi) over ``terms`` = [(A, T_min, T_max), ...], random T and phi."""
    out = np.zeros_like(t)
    for amplitude, period_min, period_max in terms:
        period = rng.uniform(period_min, period_max)
        phase = rng.uniform(0.0, 2.0 * np.pi)
        out += amplitude * np.sin(2.0 * np.pi * t / period + phase)
    return out


def _turns(
    rng: np.random.Generator,
    t: np.ndarray,
    max_rate: float,
    angle=(np.pi / 6, np.pi / 2),
    duration=(4.0, 9.0),
    gap=(5.0, 15.0),
) -> np.ndarray:
    """Yaw rate of occasional turns: raised-cosine bumps of peak <= max_rate between straights.

    A turn of angle a lasting D has the rate (a/D)(1 - cos(2 pi s/D)) (peak 2a/D), D lengthened so
    that the peak stays <= max_rate. The direction is random while |heading| < 60 degrees,
    otherwise back towards the start heading (no loops).
    """
    rate = np.zeros_like(t)
    heading = 0.0
    start = rng.uniform(1.0, gap[1])
    while start < t[-1]:
        a = rng.uniform(*angle)
        d = max(rng.uniform(*duration), 2.0 * a / max_rate)
        sign = rng.choice([-1.0, 1.0]) if abs(heading) < np.pi / 3 else -np.sign(heading)
        inside = (t >= start) & (t < start + d)
        rate[inside] += sign * (a / d) * (1.0 - np.cos(2.0 * np.pi * (t[inside] - start) / d))
        heading += sign * a
        start += d + rng.uniform(*gap)
    return rate


def _finish(t: np.ndarray, columns) -> Trajectory:
    twists = np.stack(columns, axis=1)
    twists[-1] = twists[-2]  # the last sample drives no step
    return Trajectory(t, integrate(t, twists), twists)


def street(steps: int, dt: float = 0.1, seed=0) -> Trajectory:
    """Car-like drive: forward speed 5-12 m/s, occasional turns (yaw rate <= ~0.3 rad/s),
    pitch/roll rates ~0.01 rad/s, lateral/vertical velocity a few cm/s. Starts at the identity."""
    t = _time(steps, dt)
    rng = generator(seed)
    speed = 8.5 + _sinusoids(rng, t, [(1.8, 25.0, 60.0), (1.0, 8.0, 20.0), (0.5, 3.0, 8.0)])
    lateral = _sinusoids(rng, t, [(0.03, 3.0, 10.0)])
    vertical = _sinusoids(rng, t, [(0.02, 1.0, 4.0)])
    roll_rate = _sinusoids(rng, t, [(0.006, 5.0, 15.0), (0.004, 1.5, 5.0)])
    pitch_rate = _sinusoids(rng, t, [(0.006, 5.0, 15.0), (0.004, 1.5, 5.0)])
    yaw_rate = _sinusoids(rng, t, [(0.015, 10.0, 30.0)]) + _turns(rng, t, max_rate=0.28)
    return _finish(t, [speed, lateral, vertical, roll_rate, pitch_rate, yaw_rate])


def aerial(steps: int, dt: float = 0.1, seed=0) -> Trajectory:
    """Hand-held / drone-like 6-DoF motion: body speed ~1-2 m/s, rotation rates up to ~0.3 rad/s
    on every axis (bounded attitude oscillations). Starts at the identity."""
    t = _time(steps, dt)
    rng = generator(seed)
    v_x = 1.5 + _sinusoids(rng, t, [(0.3, 8.0, 20.0), (0.15, 3.0, 8.0)])
    v_y = _sinusoids(rng, t, [(0.3, 6.0, 15.0), (0.1, 2.0, 5.0)])
    v_z = _sinusoids(rng, t, [(0.2, 6.0, 15.0), (0.1, 2.0, 5.0)])
    w = [_sinusoids(rng, t, [(0.2, 6.0, 15.0), (0.1, 2.0, 6.0)]) for _ in range(3)]
    return _finish(t, [v_x, v_y, v_z, *w])


TRAJECTORIES = {"street": street, "aerial": aerial}
