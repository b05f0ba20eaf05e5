"""Data conventions, checked rather than assumed.

Two questions the files do not answer reliably:

1. Extrinsic: is ``imu_T_cam`` right as given, or do the velocities use an IMU frame with the
   y and z axes flipped (``diag(1,-1,-1,1) @ imu_T_cam``)?
2. Velocity timing: does the velocity stamped k ("this", the course formulation) or the one
   stamped k+1 ("next") drive the step from k to k+1?

The test: stereo points triangulated at step k, carried by dead reckoning to step k+h and
reprojected into the left image,

    p_b = cam_T_imu T_{k+h}^-1 T_k imu_T_cam p_a,   e = |pi(p_b) - z_left(k+h)|               (C1)

with the median pixel error e of each variant. The variant with the smaller error fits the data.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from ..compiled import jit, warms_up
from ..geometry import se3
from ..geometry.camera import StereoCamera
from ..estimator.propagation import dead_reckoning
from ..data.sequence import Sequence

IMU_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])


def flipped_extrinsic(imu_T_cam: np.ndarray) -> np.ndarray:
    """The extrinsic with the IMU's y and z axes flipped."""
    return IMU_FLIP @ imu_T_cam


@dataclass
class MatchedPairs:
    """Features seen at step k and at k+horizon: the data of the reprojection test (variant-free)."""

    step: np.ndarray  # (P,) k
    p_cam: np.ndarray  # (P,3) triangulated at k
    z_later: np.ndarray  # (P,2) left pixel at k+horizon
    horizon: int


def matched_pairs(seq: Sequence, horizon: int = 3, min_disparity: float = 1.0) -> MatchedPairs:
    """Stereo points triangulated at k with their left pixels at k+horizon (same id), in the
    sequence's own order (by step, then id): every observation (id, k) is looked up as
    (id, k + horizon) among all observations sorted by (id, step), one search for the whole file."""
    camera = StereoCamera(seq.K, seq.baseline)
    n = seq.num_steps
    step = np.repeat(np.arange(n, dtype=np.int64), np.diff(seq.obs_ptr))
    key = seq.obs_ids * n + step  # unique per observation: ids are unique within a step
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    a = np.flatnonzero(step < n - horizon)
    pos = np.minimum(np.searchsorted(sorted_key, key[a] + horizon), max(key.size - 1, 0))
    found = sorted_key[pos] == key[a] + horizon if key.size else np.zeros(0, dtype=bool)
    a, b = a[found], order[pos[found]]
    z_a = seq.obs_pixels[a]
    keep = (z_a[:, 0] - z_a[:, 2]) >= min_disparity
    a, b, z_a = a[keep], b[keep], z_a[keep]
    return MatchedPairs(step[a], camera.triangulate(z_a).reshape(-1, 3), seq.obs_pixels[b, :2].copy(), horizon)


def reprojection_error(
    seq: Sequence, imu_T_cam: np.ndarray, velocity_index: str, horizon: int = 3,
    min_disparity: float = 1.0, pairs: MatchedPairs | None = None, poses: np.ndarray | None = None,
) -> float:
    """Median left-image error (px) of points triangulated at k and reprojected at k+horizon,
    carried by dead reckoning: p_b = cam_T_imu T_b^-1 T_a imu_T_cam p_a."""
    pairs = pairs if pairs is not None else matched_pairs(seq, horizon, min_disparity)
    if pairs.step.size == 0:
        return float("nan")
    camera = StereoCamera(seq.K, seq.baseline)
    if poses is None:
        poses = dead_reckoning(seq.time_stamps, seq.linear_velocity, seq.angular_velocity, velocity_index)
    b_T_a = se3.inverse(imu_T_cam) @ se3.inverse(poses[pairs.horizon :]) @ poses[: -pairs.horizon] @ imu_T_cam
    err = _left_errors(b_T_a, pairs.step, pairs.p_cam, pairs.z_later, camera.fx, camera.fy, camera.cx, camera.cy)
    err = err[np.isfinite(err)]
    return float(np.median(err)) if err.size else float("nan")


@jit
def _left_errors(b_T_a, step, p_cam, z_later, fx, fy, cx, cy):
    """|pi(b_T_a[step] p) - z| per pair (left image), NaN for points not in front (depth <= 0.1)."""
    out = np.empty(step.size)
    for i in range(step.size):
        T = b_T_a[step[i]]
        x, y, z = p_cam[i, 0], p_cam[i, 1], p_cam[i, 2]
        qx = T[0, 0] * x + T[0, 1] * y + T[0, 2] * z + T[0, 3]
        qy = T[1, 0] * x + T[1, 1] * y + T[1, 2] * z + T[1, 3]
        qz = T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3]
        if qz > 0.1:
            out[i] = np.hypot(fx * qx / qz + cx - z_later[i, 0], fy * qy / qz + cy - z_later[i, 1])
        else:
            out[i] = np.nan
    return out


@dataclass
class ConventionDecision:
    """The extrinsic and velocity timing used, with the test's numbers behind them."""

    imu_flip: bool
    velocity_index: str  # "this" | "next"
    imu_T_cam: np.ndarray  # the extrinsic used (flipped or not)
    errors_px: dict[str, float]  # "flip=no,velocity=this" -> median px, every variant tested
    flip_source: str  # "auto" | "configured"
    velocity_source: str

    @property
    def chosen_error_px(self) -> float | None:
        """The convention test's median error (C1) of the variant used; None when it was not tested."""
        return self.errors_px.get(_key(self.imu_flip, self.velocity_index))

    def as_dict(self) -> dict:
        return {
            "imu_flip": self.imu_flip,
            "imu_flip_decided_by": self.flip_source,
            "velocity_index": self.velocity_index,
            "velocity_index_decided_by": self.velocity_source,
            "reprojection_median_px": self.errors_px,
            "imu_T_cam_used": self.imu_T_cam.tolist(),
        }

    def describe(self) -> str:
        def err(flip: bool, vel: str) -> str:
            value = self.errors_px.get(_key(flip, vel))
            return "n/a" if value is None else f"{value:.2f} px"

        v = self.velocity_index
        f = self.imu_flip
        if self.errors_px and not any(np.isfinite(e) for e in self.errors_px.values()):
            return (
                "extrinsic and velocity timing could not be tested (no feature seen at both k and k+horizon "
                f"with positive disparity): using the extrinsic {'flipped' if f else 'as given'} and the velocity "
                f"stamped {'k+1' if v == 'next' else 'k'}"
            )
        return (
            f"extrinsic: {'IMU y,z flipped' if f else 'as given'} ({self.flip_source}; median reprojection "
            f"as given {err(False, v)}, flipped {err(True, v)})\n"
            f"velocity timing: velocity stamped {'k+1' if v == 'next' else 'k'} drives step k->k+1 "
            f"({self.velocity_source}; stamped k {err(f, 'this')}, stamped k+1 {err(f, 'next')})"
        )


def _key(flip: bool, velocity_index: str) -> str:
    return f"flip={'yes' if flip else 'no'},velocity={velocity_index}"


def decide_conventions(seq: Sequence, imu_flip: str = "auto", velocity_index: str = "auto", horizon: int = 3,
                       pairs: MatchedPairs | None = None) -> ConventionDecision:
    """Test every variant that is not fixed by the caller and take the one that fits best; ``pairs``:
    ``matched_pairs(seq, horizon)`` when the caller has them."""
    flips = [False, True] if imu_flip == "auto" else [imu_flip == "yes"]
    indices = ["this", "next"] if velocity_index == "auto" else [velocity_index]
    errors: dict[str, float] = {}
    if len(flips) * len(indices) > 1:
        pairs = pairs if pairs is not None else matched_pairs(seq, horizon)
        poses = {i: dead_reckoning(seq.time_stamps, seq.linear_velocity, seq.angular_velocity, i) for i in indices}
        for flip, index in itertools.product(flips, indices):
            extrinsic = flipped_extrinsic(seq.imu_T_cam) if flip else seq.imu_T_cam
            errors[_key(flip, index)] = reprojection_error(seq, extrinsic, index, horizon, pairs=pairs, poses=poses[index])
        finite = {k: v for k, v in errors.items() if np.isfinite(v)}
        best = min(finite, key=finite.get) if finite else _key(flips[0], indices[0])
    else:
        best = _key(flips[0], indices[0])
    flip = "flip=yes" in best
    index = best.split("velocity=")[1]
    extrinsic = flipped_extrinsic(seq.imu_T_cam) if flip else seq.imu_T_cam
    return ConventionDecision(
        imu_flip=flip,
        velocity_index=index,
        imu_T_cam=extrinsic,
        errors_px=errors,
        flip_source="auto" if imu_flip == "auto" else "configured",
        velocity_source="auto" if velocity_index == "auto" else "configured",
    )


@warms_up(only="velocity")
def _warm_up() -> None:
    pixels = np.array([[600.0, 180.0]] * 2)
    _left_errors(np.eye(4)[None], np.zeros(2, dtype=np.int64), np.ones((2, 3)) + 5.0, pixels, 700.0, 700.0, 600.0,
                 180.0)
