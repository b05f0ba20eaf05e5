"""Landmark points placed along a trajectory where its camera will see them.

* street: a "street frame" along the path (arc length s, horizontal heading, road level
  ``imu z - imu_height``), extended straight ahead past the end so the last steps see a street
  too. Points on two facades (blocks of random length and setback, |y| 6-12 m from the path,
  up to 12 m high), on the road and pavement (|y| < 5.5 m, up to 0.2 m high) and far points
  (|y| 14-40 m, up to 25 m high). Densities are per metre of path.
* aerial: points uniform in the union of balls around the path (a volume around it), none
  closer than ``clearance`` to the path.
"""

from __future__ import annotations

import numpy as np

from ..backend.errors import ConfigError
from ._random import generator

__all__ = ["path_frames", "street_landmarks", "aerial_landmarks", "LANDMARKS", "MAX_POINTS"]

#: The most landmark points a scene may have (24 bytes each, and ~40 observations each in a
#: 300-step street): checked on the expected count before any point is drawn
MAX_POINTS = 2_000_000


def _check_point_budget(expected: float, density: float) -> None:
    """ConfigError, before allocating, when a scene would have more than MAX_POINTS points."""
    if expected > MAX_POINTS:
        raise ConfigError(
            f"synthetic scene: landmark_density {density:g} gives about {expected:.3g} landmark points "
            f"({expected * 24 / 2**30:.1f} GiB before projecting them, ~40 observations each); a scene may "
            f"have at most {MAX_POINTS:,}: lower landmark_density or steps")


def path_frames(world_T_imu: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(arc length s (N,), positions (N,3), unwrapped heading yaw (N,)) of the IMU path."""
    poses = np.asarray(world_T_imu, dtype=float)
    positions = poses[:, :3, 3]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])
    yaw = np.unwrap(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
    return s, positions, yaw


def _along(s_query: np.ndarray, s: np.ndarray, positions: np.ndarray, yaw: np.ndarray):
    """Position and heading at arc lengths ``s_query``; beyond the end, straight on at the last heading."""
    if s[-1] <= 0.0:  # standing still: everything at the start
        return np.repeat(positions[:1], s_query.shape[0], axis=0), np.full(s_query.shape, yaw[0])
    _, unique = np.unique(s, return_index=True)  # drop zero-length steps for interp
    s_u, pos_u, yaw_u = s[unique], positions[unique], yaw[unique]
    inside = np.clip(s_query, 0.0, s_u[-1])
    pos = np.stack([np.interp(inside, s_u, pos_u[:, i]) for i in range(3)], axis=1)
    heading = np.interp(inside, s_u, yaw_u)
    beyond = np.maximum(s_query - s_u[-1], 0.0)
    pos[:, 0] += beyond * np.cos(yaw_u[-1])
    pos[:, 1] += beyond * np.sin(yaw_u[-1])
    return pos, heading


def _place(s_query, lateral, height, s, positions, yaw, imu_height):
    """World points at arc length, lateral offset (left +) and height above the road."""
    base, heading = _along(s_query, s, positions, yaw)
    left = np.stack([-np.sin(heading), np.cos(heading), np.zeros_like(heading)], axis=1)
    out = base + lateral[:, None] * left
    out[:, 2] += height - imu_height
    return out


def _count(rng: np.random.Generator, per_metre: float, length: float) -> int:
    return int(rng.poisson(per_metre * length)) if per_metre * length > 0 else 0


def street_landmarks(
    world_T_imu: np.ndarray,
    seed=0,
    *,
    density: float = 1.0,
    imu_height: float = 0.93,
    ahead: float = 70.0,
    facade_setback=(6.3, 11.7),
    facade_jitter: float = 0.3,
    facade_height: float = 12.0,
    block_length=(10.0, 40.0),
    road_halfwidth: float = 5.5,
    far_lateral=(14.0, 40.0),
    far_height: float = 25.0,
    per_metre=(0.75, 0.35, 0.15),
) -> np.ndarray:
    """Points (P,3) of a street along the path. ``per_metre`` = (each facade, road, far) times
    ``density``; facade |y| = setback +- jitter (6-12 m by default)."""
    rng = generator(seed)
    s, positions, yaw = path_frames(world_T_imu)
    length = s[-1] + ahead
    facade_rate, road_rate, far_rate = (density * r for r in per_metre)
    _check_point_budget((2 * facade_rate + road_rate + far_rate) * length, density)
    parts = []
    for side in (1.0, -1.0):
        ends = [0.0]
        while ends[-1] < length:
            ends.append(ends[-1] + rng.uniform(*block_length))
        setbacks = rng.uniform(*facade_setback, size=len(ends))
        n = _count(rng, facade_rate, length)
        along = rng.uniform(0.0, length, n)
        block = np.searchsorted(np.asarray(ends), along)
        lateral = side * (setbacks[block] + rng.uniform(-facade_jitter, facade_jitter, n))
        parts.append(_place(along, lateral, rng.uniform(0.0, facade_height, n), s, positions, yaw, imu_height))
    n = _count(rng, road_rate, length)
    parts.append(
        _place(
            rng.uniform(0.0, length, n),
            rng.uniform(-road_halfwidth, road_halfwidth, n),
            rng.uniform(0.0, 0.2, n),
            s, positions, yaw, imu_height,
        )
    )
    n = _count(rng, far_rate, length)
    parts.append(
        _place(
            rng.uniform(0.0, length, n),
            rng.choice([-1.0, 1.0], n) * rng.uniform(*far_lateral, n),
            rng.uniform(0.0, far_height, n),
            s, positions, yaw, imu_height,
        )
    )
    return np.concatenate(parts, axis=0)


def aerial_landmarks(
    world_T_imu: np.ndarray,
    seed=0,
    *,
    density: float = 1.0,
    radius: float = 35.0,
    clearance: float = 3.0,
    spacing: float = 5.0,
    ahead: float = 40.0,
    per_cubic_metre: float = 0.0016,
) -> np.ndarray:
    """Points (P,3) uniform (``per_cubic_metre * density``) in the union of balls of ``radius``
    around the path (centres every ``spacing`` m, the path extended ``ahead`` m straight on),
    none closer than ``clearance`` to a pose. Uniform over the union: each ball keeps only the
    points whose nearest centre is its own (its Voronoi cell)."""
    from scipy.spatial import cKDTree

    rng = generator(seed)
    s, positions, yaw = path_frames(world_T_imu)
    stations = np.arange(0.0, s[-1] + ahead + 0.5 * spacing, spacing)
    centres, _ = _along(stations, s, positions, yaw)
    per_ball = density * per_cubic_metre * 4.0 / 3.0 * np.pi * radius**3
    _check_point_budget(per_ball * centres.shape[0], density)  # an upper bound (Voronoi cells cut it)
    counts = rng.poisson(per_ball, centres.shape[0])
    owner = np.repeat(np.arange(centres.shape[0]), counts)
    direction = rng.standard_normal((owner.shape[0], 3))
    direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-12)
    r = radius * np.cbrt(rng.random(owner.shape[0]))
    points = centres[owner] + r[:, None] * direction
    _, nearest = cKDTree(centres).query(points)
    points = points[nearest == owner]
    distance, _ = cKDTree(positions).query(points)
    return points[distance >= clearance]


LANDMARKS = {"street": street_landmarks, "aerial": aerial_landmarks}
