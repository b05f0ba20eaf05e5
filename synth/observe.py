"""Stereo observations of known points along a trajectory, cut into tracks with fresh ids.

A point is visible at step k when, in the camera frame ``cam_T_imu world_T_imu_k^-1 p``, its
depth is in [min_depth, max_depth], its disparity is positive and both its true and its noisy
pixels lie in the image (0 <= u < width, 0 <= v < height, both cameras). A point's maximal run
of consecutive visible steps is cut further at random (every observation after the first starts
a new track with probability 1 / mean_track_length, so track lengths are geometric) to mimic a
tracker losing features. Every track gets a new id; ``point_index[id]`` is its point. Ids are
numbered by first step (then point), so they increase with time as a tracker's would.

The errors of the pixels are :class:`~vislam.synth.track_errors.TrackErrors` (white noise by
default; drift, bad tracks, a disparity offset, repeated frames, frame jitter and outliers on
request): points are projected from the content poses of the frames (the steps that are not
repeats), tracks are runs of consecutive frames, and a repeated step shows its frame again.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np

from ..backend.errors import ConfigError
from ..backend.geometry import se3
from ..backend.geometry.camera import StereoCamera
from ._random import generator
from .track_errors import (
    TrackErrors,
    TrackErrorTruth,
    content_poses,
    jitter_series,
    jittered_poses,
    repeated_steps,
    track_offsets,
)

__all__ = [
    "Calibration",
    "kitti_calibration",
    "KITTI_K",
    "KITTI_BASELINE",
    "KITTI_IMAGE_SIZE",
    "KITTI_IMU_T_CAM",
    "check_observation_count",
    "Observations",
    "camera_from_world",
    "visible_pairs",
    "observe",
]

KITTI_K = np.array([[718.856, 0.0, 607.1928], [0.0, 718.856, 185.2157], [0.0, 0.0, 1.0]])
KITTI_BASELINE = 0.537  # m
KITTI_IMAGE_SIZE = (1241, 376)  # width, height (px)
#: Camera optical frame (z forward, x right, y down) in the IMU frame (x forward, y left, z up),
#: 1.1 m forward, 0.3 m right, 0.75 m up.
KITTI_IMU_T_CAM = np.array(
    [
        [0.0, 0.0, 1.0, 1.1],
        [-1.0, 0.0, 0.0, -0.3],
        [0.0, -1.0, 0.0, 0.75],
        [0.0, 0.0, 0.0, 1.0],
    ]
)

#: Steps projected at a time (bounds the memory of the candidate pairs).
_BLOCK_STEPS = 256
#: The most (step, point) pairs in view a scene may have; each costs ~200 bytes while the
#: observations are drawn, so this bounds that at ~4 GiB
MAX_OBSERVATIONS = 20_000_000
_BYTES_PER_OBSERVATION = 200
_SAMPLE_POINTS = 20_000


def _readonly(a) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Calibration:
    """Stereo rig: left intrinsics, baseline (m), image size (px) and the camera mount imu_T_cam."""

    K: np.ndarray = field(default_factory=lambda: KITTI_K.copy())
    baseline: float = KITTI_BASELINE
    width: int = KITTI_IMAGE_SIZE[0]
    height: int = KITTI_IMAGE_SIZE[1]
    imu_T_cam: np.ndarray = field(default_factory=lambda: KITTI_IMU_T_CAM.copy())

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", _readonly(self.K))
        object.__setattr__(self, "imu_T_cam", _readonly(self.imu_T_cam))
        object.__setattr__(self, "baseline", float(self.baseline))
        StereoCamera(self.K, self.baseline)  # validates K and the baseline
        if not (self.width > 0 and self.height > 0):
            raise ValueError(f"image size must be positive, got {self.width} x {self.height}")
        if not se3.is_rigid(self.imu_T_cam):
            raise ValueError("imu_T_cam must be a rigid 4x4 transform")

    @property
    def camera(self) -> StereoCamera:
        return StereoCamera(self.K, self.baseline)

    @property
    def cam_T_imu(self) -> np.ndarray:
        return se3.inverse(self.imu_T_cam)

    @property
    def image_size(self) -> tuple[int, int]:
        return (self.width, self.height)


def kitti_calibration() -> Calibration:
    """The KITTI-like default rig (K, 0.537 m baseline, 1241 x 376 image, KITTI camera mount)."""
    return Calibration()


class Observations(NamedTuple):
    """CSR observations (sorted by step, ids increasing within a step) and their ground truth."""

    obs_ptr: np.ndarray  # (N+1,) int64
    obs_ids: np.ndarray  # (L,) int64 track ids
    obs_pixels: np.ndarray  # (L,4) uL vL uR vR (noisy; outliers replaced)
    point_index: np.ndarray  # (num_tracks,) int64: id -> index of its point
    outlier: np.ndarray  # (L,) bool: observation replaced by a random pixel
    truth: TrackErrorTruth  # the drawn track errors (synth.track_errors)


def camera_from_world(world_T_imu: np.ndarray, calibration: Calibration) -> np.ndarray:
    """cam_T_world (N,4,4) = cam_T_imu world_T_imu^-1."""
    return calibration.cam_T_imu @ se3.inverse(np.asarray(world_T_imu, dtype=float))


def _inside(pixels: np.ndarray, width: float, height: float) -> np.ndarray:
    u, v = pixels[:, 0::2], pixels[:, 1::2]
    return ((u >= 0) & (u < width) & (v >= 0) & (v < height)).all(axis=1) & (pixels[:, 0] > pixels[:, 2])


def _view_radius(calibration: Calibration, max_depth: float) -> float:
    """Largest distance from the camera centre of a point in the frustum up to max_depth."""
    cam = calibration.camera
    x = max(cam.cx, calibration.width - cam.cx) / cam.fx
    y = max(cam.cy, calibration.height - cam.cy) / cam.fy
    return float(max_depth * np.sqrt(1.0 + x * x + y * y)) * (1.0 + 1e-9) + 1e-9


def visible_pairs(
    world_T_imu: np.ndarray,
    points: np.ndarray,
    calibration: Calibration,
    min_depth: float = 2.0,
    max_depth: float = 60.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(steps, point indices, true pixels (n,4)) of every (step, point) in view, sorted by step then point.

    Candidates come from a k-d tree (points within the frustum's radius of the camera centre);
    the projection is vectorized over all candidates of a block of steps.
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=float).reshape(-1, 3)
    cam_T_world = camera_from_world(world_T_imu, calibration)
    centres = se3.inverse(cam_T_world)[:, :3, 3]
    camera = calibration.camera
    radius = _view_radius(calibration, max_depth)
    out_steps, out_points, out_pixels = [], [], []
    if points.shape[0] == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty.copy(), np.zeros((0, 4))
    if points.shape[0] > _SAMPLE_POINTS:  # estimate the pairs from a sample before drawing them all
        check_observation_count(world_T_imu, points, calibration, min_depth, max_depth)
    tree = cKDTree(points)
    total = 0
    for first in range(0, centres.shape[0], _BLOCK_STEPS):
        block = slice(first, min(first + _BLOCK_STEPS, centres.shape[0]))
        lists = tree.query_ball_point(centres[block], radius, return_sorted=True)
        counts = np.fromiter(map(len, lists), dtype=np.int64, count=len(lists))
        _check_observation_budget(total + int(counts.sum()) // 4, block.stop, centres.shape[0])
        idx = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64, count=int(counts.sum()))
        steps = np.repeat(np.arange(block.start, block.stop, dtype=np.int64), counts)
        T = cam_T_world[steps]
        p_cam = np.einsum("nij,nj->ni", T[:, :3, :3], points[idx]) + T[:, :3, 3]
        depth_ok = (p_cam[:, 2] >= min_depth) & (p_cam[:, 2] <= max_depth)
        steps, idx, p_cam = steps[depth_ok], idx[depth_ok], p_cam[depth_ok]
        pixels = camera.project(p_cam)
        keep = _inside(pixels, calibration.width, calibration.height)
        out_steps.append(steps[keep])
        out_points.append(idx[keep])
        out_pixels.append(pixels[keep])
        total += out_steps[-1].shape[0]
        _check_observation_budget(total, block.stop, centres.shape[0])
    return np.concatenate(out_steps), np.concatenate(out_points), np.concatenate(out_pixels)


def check_observation_count(world_T_imu: np.ndarray, points: np.ndarray, calibration: Calibration,
                            min_depth: float = 2.0, max_depth: float = 60.0) -> int:
    """The number of (step, point) pairs in view, estimated from a sample of at most _SAMPLE_POINTS
    points; ConfigError naming the memory when it exceeds MAX_OBSERVATIONS."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    num_steps = np.asarray(world_T_imu).shape[0]
    if points.shape[0] <= _SAMPLE_POINTS:
        sample, scale = points, 1.0
    else:
        sample = points[np.linspace(0, points.shape[0] - 1, _SAMPLE_POINTS).astype(np.int64)]
        scale = points.shape[0] / _SAMPLE_POINTS
    estimate = int(visible_pairs(world_T_imu, sample, calibration, min_depth, max_depth)[0].shape[0] * scale)
    _check_observation_budget(estimate, num_steps, num_steps, estimated=True)
    return estimate


def _check_observation_budget(pairs: int, steps_done: int, num_steps: int, estimated: bool = False) -> None:
    """ConfigError when the pairs in view (estimated, so far, or a block's candidates) exceed MAX_OBSERVATIONS."""
    if pairs > MAX_OBSERVATIONS:
        expected = pairs * num_steps / max(steps_done, 1)
        so_far = "about" if estimated else f"over {MAX_OBSERVATIONS:,} after {steps_done} of {num_steps} steps,"
        raise ConfigError(
            f"synthetic scene: {so_far} {expected:.3g} observations in all ({expected * _BYTES_PER_OBSERVATION / 2**30:.1f} "
            f"GiB to draw them), more than the {MAX_OBSERVATIONS:,} a scene may have: lower landmark_density or steps")


def _random_pixels(rng: np.random.Generator, n: int, calibration: Calibration, min_depth: float) -> np.ndarray:
    """Uniform pixels in the image (uL >= 1, vR = vL) with a disparity uniform in
    [0.5, min(uL, disparity at min_depth)] px, so 0 <= uR < uL."""
    cam = calibration.camera
    u_left = rng.uniform(1.0, calibration.width, n)
    v = rng.uniform(0.0, calibration.height, n)
    max_disp = np.minimum(u_left, max(cam.fx * cam.baseline / min_depth, 1.0))
    u_right = u_left - rng.uniform(0.5, max_disp)
    return np.stack([u_left, v, u_right, v], axis=1)


def observe(
    world_T_imu: np.ndarray,
    points: np.ndarray,
    calibration: Calibration | None = None,
    *,
    pixel_sigma: float | None = None,
    outlier_share: float | None = None,
    mean_track_length: float | None = 15.0,
    min_depth: float = 2.0,
    max_depth: float = 60.0,
    seed=0,
    rng_pixels=None,
    rng_tracks=None,
    rng_outliers=None,
    track_errors: TrackErrors | None = None,
) -> Observations:
    """Noisy stereo observations of ``points`` (P,3) from the poses (N,4,4), cut into tracks.

    ``track_errors`` (default ``TrackErrors()``: white noise of 0.5 px alone) is the error model
    of :mod:`~vislam.synth.track_errors`; ``pixel_sigma`` (px, each of uL, vL, uR, vR) and
    ``outlier_share``, when given, replace its values. An observation whose noisy pixels leave
    the image (or lose their disparity) counts as not visible; one that track offsets move out
    ends its track. Outliers get a uniform random pixel with positive disparity (same id).
    ``mean_track_length`` None or inf keeps whole visible runs. The random streams default to
    independent streams of ``seed``; the track errors always use streams of ``seed``.
    """
    calibration = kitti_calibration() if calibration is None else calibration
    errors = TrackErrors() if track_errors is None else track_errors
    given = {k: v for k, v in (("pixel_sigma", pixel_sigma), ("outlier_share", outlier_share)) if v is not None}
    if given:
        errors = replace(errors, **given)
    if mean_track_length is not None and not mean_track_length >= 1.0:
        raise ValueError(f"mean_track_length must be >= 1 (or None), got {mean_track_length}")
    if not 0.0 < min_depth < max_depth:
        raise ValueError(f"need 0 < min_depth < max_depth, got {min_depth}, {max_depth}")
    rng_pixels = generator(seed, "pixels") if rng_pixels is None else generator(rng_pixels)
    rng_tracks = generator(seed, "tracks") if rng_tracks is None else generator(rng_tracks)
    rng_outliers = generator(seed, "outliers") if rng_outliers is None else generator(rng_outliers)
    world_T_imu = np.asarray(world_T_imu, dtype=float)
    n_steps = world_T_imu.shape[0]

    # frames: the steps that are not repeats, seen from the content poses (R), jittered (J)
    repeated = repeated_steps(n_steps, errors.repeat_interval, generator(seed, "repeats"))
    frame_step = np.flatnonzero(~repeated)  # (F,) the step each frame is first shown at
    frame_of_step = np.cumsum(~repeated) - 1  # (N,)
    content = content_poses(world_T_imu, repeated) if repeated.any() else world_T_imu.copy()
    xi = np.zeros((n_steps, 6))
    poses = content
    if errors.jitters:
        series = jitter_series(n_steps, errors.jitter_rotation, errors.jitter_translation, errors.jitter_correlation,
                               generator(seed, "jitter"))
        xi = series[frame_step][frame_of_step]
        poses = jittered_poses(content, xi, calibration.imu_T_cam)

    steps, idx, pixels = visible_pairs(poses[frame_step], points, calibration, min_depth, max_depth)  # steps: frames
    if errors.disparity_offset != 0.0:
        pixels[:, 2] -= errors.disparity_offset
    pixels = pixels + errors.pixel_sigma * rng_pixels.standard_normal(pixels.shape)
    keep = _inside(pixels, calibration.width, calibration.height)
    steps, idx, pixels = steps[keep], idx[keep], pixels[keep]

    # tracks: runs of consecutive frames of one point, cut at random
    order = np.lexsort((steps, idx))
    steps, idx, pixels = steps[order], idx[order], pixels[order]
    n = steps.shape[0]
    start = np.ones(n, dtype=bool)
    start[1:] = (idx[1:] != idx[:-1]) | (steps[1:] != steps[:-1] + 1)
    cut_draw = rng_tracks.random(n)
    if mean_track_length is not None and np.isfinite(mean_track_length):
        start |= cut_draw < 1.0 / mean_track_length
    track = np.cumsum(start) - 1
    first = np.flatnonzero(start)
    by_time = np.lexsort((idx[first], steps[first]))  # tracks numbered by first step, then point
    track_id = np.empty(first.shape[0], dtype=np.int64)
    track_id[by_time] = np.arange(first.shape[0])
    ids = track_id[track]
    point_index = np.empty(first.shape[0], dtype=np.int64)
    point_index[track_id] = idx[first]

    num_tracks = first.shape[0]
    velocity, jump = np.zeros((num_tracks, 2)), np.zeros((num_tracks, 2))
    bad, jump_step = np.zeros(num_tracks, dtype=np.int8), np.full(num_tracks, -1, dtype=np.int64)
    if errors.drifts:  # (E); a track ends at its first observation that leaves the image
        age = np.arange(n) - first[track]
        length = np.diff(np.append(first, n))
        drift = track_offsets(track, age, length, errors, generator(seed, "drift"), generator(seed, "bad_tracks"))
        pixels += np.tile(drift.offsets, 2)
        out = ~_inside(pixels, calibration.width, calibration.height)
        end = length.copy()
        np.minimum.at(end, track[out], age[out])
        keep = age < end[track]
        jumped = drift.jump_age < end
        velocity[track_id], bad[track_id], jump[track_id] = drift.drift_velocity, drift.bad, drift.jump
        jump_step[track_id[jumped]] = frame_step[steps[first[jumped]] + drift.jump_age[jumped]]
        steps, ids, pixels = steps[keep], ids[keep], pixels[keep]
        n = steps.shape[0]

    order = np.lexsort((ids, steps))
    steps, ids, pixels = steps[order], ids[order], pixels[order]
    outlier = rng_outliers.random(n) < errors.outlier_share
    if outlier.any():
        pixels[outlier] = _random_pixels(rng_outliers, int(outlier.sum()), calibration, min_depth)

    ptr = np.zeros(frame_step.shape[0] + 1, dtype=np.int64)
    np.cumsum(np.bincount(steps, minlength=frame_step.shape[0]), out=ptr[1:])
    if repeated.any():  # a repeated step shows its frame's observations again
        ptr, gather = _expand(ptr, frame_of_step)
        ids, pixels, outlier = ids[gather], pixels[gather], outlier[gather]
    truth = TrackErrorTruth(repeated, content, xi, velocity, bad, jump, jump_step)
    return Observations(ptr, ids, np.ascontiguousarray(pixels), point_index, outlier, truth)


def _expand(frame_ptr: np.ndarray, frame_of_step: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(step_ptr (N+1,), gather (L,)): the CSR rows of the frames (``frame_ptr``, (F+1,)) shown at
    each step, as indices into the frames' observations."""
    counts = np.diff(frame_ptr)[frame_of_step]
    ptr = np.zeros(frame_of_step.shape[0] + 1, dtype=np.int64)
    np.cumsum(counts, out=ptr[1:])
    gather = np.arange(ptr[-1], dtype=np.int64) + np.repeat(frame_ptr[frame_of_step] - ptr[:-1], counts)
    return ptr, gather
