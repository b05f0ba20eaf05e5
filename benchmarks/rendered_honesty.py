"""Honesty of SLAM from rendered images, and the tracks' errors against the renderer's truth.

For each seed a street scene (``synth.scene``, ``--steps`` steps) is rendered (``synth.render``),
tracked by vislam's tracker (``frontend.track.track_directory``, the scene's noisy IMU velocities)
and filtered with the defaults (``run_sequence``). Printed per seed: ATE (SE(3)-aligned) of SLAM and
dead reckoning, the position NEES of the run's own pose covariance (mean, share inside the 95 %
ellipsoid; every step relative to the first pose), the mean NIS per observation and the pixel noise
the run identified; then the tracks' errors against the truth, each track's 3-D point taken from the
rendered depth at its first observation (so errors are measured from the first observation on):

- ``median |e|`` and ``RMS`` (errors within 3 px) per coordinate [uL, vL] at age >= 1;
- ``> 2 px``: the share of tracks that stray more than 2 px from their true point at some frame;
- ``slope u, v``: the least-squares slope of the error on the point's true displacement since the
  track's first frame, with its standard error: a tracker that follows the image motion by a
  factor 1 + s has slope s, the same for every track, an error white noise does not explain and
  averaging over tracks does not reduce (it turns the rotation of every step by about s);
- ``frame-common``: the RMS over frames of the mean error of the frame's observations against the
  RMS its standard error alone would give (errors common to a frame, as a jittering camera makes);
- the same tracks (ids, lives, observations with a true point) with their pixels replaced, filtered
  again: the true pixels plus white noise of the identified sigma (the filter and this evaluation
  alone), and the true pixels plus the tracked errors where all four are within 0.5 px (the
  tracker's errors without their tail).

Usage: python benchmarks/rendered_honesty.py [--seeds 11,12,13] [--steps 150]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from vislam.backend.config import Config  # noqa: E402
from vislam.backend.evaluation.consistency import trajectory_nees  # noqa: E402
from vislam.backend.evaluation.metrics import trajectory_errors  # noqa: E402
from vislam.backend.geometry import se3  # noqa: E402
from vislam.backend.run.runner import run_sequence  # noqa: E402
from vislam.frontend.config import TrackerConfig  # noqa: E402
from vislam.frontend.imu_input import ImuVelocities  # noqa: E402
from vislam.frontend.track import open_stereo_directory, track_directory  # noqa: E402
from vislam.synth.render import RENDER_STREAM, build_street_planes, render_depth, write_kitti_sequence  # noqa: E402
from vislam.synth.scene import SceneConfig, make_scene  # noqa: E402


def observation_errors(seq, depths, world_T_cam, K, baseline) -> dict[str, np.ndarray]:
    """Every observation of ``seq`` against the renderer's truth: its track's 3-D point from the
    rendered depth ``depths[k]`` (H, W) at its first observation (the side of a depth edge whose
    disparity the track has), projected at each later frame. Returns arrays over observations:
    ``track`` (n,), ``frame`` (n,), ``age`` (n,), ``error`` (n, 4) px measured - true, ``moved`` (n, 4)
    px the true pixels moved since the track's first frame; tracks with no depth are left out."""
    fb = K[0, 0] * baseline
    points, first = {}, {}
    rows = {"track": [], "frame": [], "age": [], "error": [], "moved": []}
    for k in range(seq.num_steps):
        ids, pixels = seq.observations(k)
        cam_T_world = se3.inverse(world_T_cam[k])
        for i, z in zip(ids.tolist(), pixels):
            if i not in points:
                u0, v0 = int(z[0]), int(z[1])
                block = depths[k][v0:v0 + 2, u0:u0 + 2]
                inv = np.where(np.isfinite(block), 1.0 / block, 0.0).ravel()
                w = inv[np.argmin(np.abs(fb * inv - (z[0] - z[2])))]
                if w <= 0:
                    points[i] = None
                    continue
                d = 1.0 / w
                p = np.array([(z[0] - K[0, 2]) * d / K[0, 0], (z[1] - K[1, 2]) * d / K[1, 1], d])
                points[i] = world_T_cam[k][:3, :3] @ p + world_T_cam[k][:3, 3]
                first[i] = None
            if points[i] is None:
                continue
            p = cam_T_world[:3, :3] @ points[i] + cam_T_world[:3, 3]
            uL, v = K[0, 0] * p[0] / p[2] + K[0, 2], K[1, 1] * p[1] / p[2] + K[1, 2]
            true = np.array([uL, v, uL - fb / p[2], v])
            if first[i] is None:
                first[i] = (k, true)
            rows["track"].append(i)
            rows["frame"].append(k)
            rows["age"].append(k - first[i][0])
            rows["error"].append(z - true)
            rows["moved"].append(true - first[i][1])
    return {key: np.array(value) for key, value in rows.items()}


def stray_share(errors: dict[str, np.ndarray], px: float = 2.0) -> float:
    """Share of tracks whose left or right pixel is more than ``px`` from its true point at some frame."""
    e = errors["error"]
    worst = np.maximum(np.hypot(e[:, 0], e[:, 1]), np.hypot(e[:, 2], e[:, 3]))
    tracks, index = np.unique(errors["track"], return_inverse=True)
    per_track = np.zeros(tracks.size)
    np.maximum.at(per_track, index, worst)
    return float(np.mean(per_track > px)) if tracks.size else float("nan")


def displacement_slope(errors: dict[str, np.ndarray], coordinate: int, trim_px: float = 1.0) -> tuple[float, float]:
    """Slope (and its standard error) of the error on the true displacement since the first frame,
    coordinate 0 = uL, 1 = vL, over observations of age >= 1 with every error within ``trim_px``."""
    keep = (errors["age"] >= 1) & np.all(np.abs(errors["error"]) < trim_px, axis=1)
    x, y = errors["moved"][keep, coordinate], errors["error"][keep, coordinate]
    A = np.column_stack([np.ones_like(x), x])
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    r = y - A @ coef
    return float(coef[1]), float(np.sqrt(np.linalg.inv(A.T @ A)[1, 1] * r.var()))


def frame_common(errors: dict[str, np.ndarray], trim_px: float = 1.0) -> tuple[float, float]:
    """(RMS over frames of the frames' mean uL error, RMS of its standard error) over age >= 1."""
    keep = (errors["age"] >= 1) & np.all(np.abs(errors["error"]) < trim_px, axis=1)
    frames, e = errors["frame"][keep], errors["error"][keep, 0]
    means, ses = [], []
    for k in np.unique(frames):
        ek = e[frames == k]
        if ek.size >= 10:
            means.append(ek.mean())
            ses.append(ek.std() / np.sqrt(ek.size))
    return float(np.sqrt(np.mean(np.square(means)))), float(np.sqrt(np.mean(np.square(ses))))


def with_pixels(seq, errors: dict[str, np.ndarray], replace_error) -> object:
    """``seq`` with its observations that have a true point only, their pixels = true + replace_error(error)
    ((n, 4) -> (n, 4) px)."""
    steps = np.repeat(np.arange(seq.num_steps), np.diff(seq.obs_ptr))
    row = {(int(i), int(k)): r for r, (i, k) in enumerate(zip(seq.obs_ids, steps))}
    rows = np.array([row[(int(i), int(k))] for i, k in zip(errors["track"], errors["frame"])], dtype=np.int64)
    keep = np.zeros(seq.obs_ids.size, dtype=bool)
    keep[rows] = True
    pixels = seq.obs_pixels.copy()
    pixels[rows] = seq.obs_pixels[rows] - errors["error"] + replace_error(errors["error"])
    ptr = np.r_[0, np.cumsum(np.bincount(steps[keep], minlength=seq.num_steps))]
    return dataclasses.replace(seq, obs_ptr=ptr, obs_ids=seq.obs_ids[keep], obs_pixels=pixels[keep])


def filtered(seq, gt) -> tuple:
    """(run result, ATE m, position NEES) of the defaults on ``seq``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = run_sequence(seq, Config())
    return (r, trajectory_errors(r.time_stamps, r.world_T_imu, *gt).ate_rmse,
            trajectory_nees(r.time_stamps, r.world_T_imu, r.pose_covariance, *gt).position)


def one_seed(seed: int, steps: int, tmp: Path) -> str:
    scene = make_scene(SceneConfig(steps=steps, seed=seed))
    street = tmp / f"street{seed}"
    write_kitti_sequence(street, scene)
    cal = scene.config.calibration
    K, baseline = np.asarray(cal.K, float), float(cal.baseline)
    world_T_cam = scene.world_T_imu_true @ np.asarray(cal.imu_T_cam, float)
    planes = build_street_planes(scene.world_T_imu_true, np.random.default_rng([seed, RENDER_STREAM]))
    depths = [render_depth(planes, se3.inverse(T), K, cal.image_size) for T in world_T_cam]
    truth = scene.sequence
    imu = ImuVelocities(truth.time_stamps, truth.linear_velocity, truth.angular_velocity, truth.imu_T_cam)
    tracks = track_directory(open_stereo_directory(street), imu, TrackerConfig())
    gt = (truth.time_stamps, scene.world_T_imu_true)
    r, ate, nees = filtered(tracks, gt)
    dr = trajectory_errors(r.time_stamps, r.dead_reckoning, *gt).ate_rmse
    errors = observation_errors(tracks, depths, world_T_cam, K, baseline)
    rng = np.random.default_rng(seed)
    sigma = r.decisions.pixels.sigma
    _, _, white = filtered(with_pixels(tracks, errors, lambda e: rng.normal(0.0, sigma, e.shape)), gt)
    _, _, core_only = filtered(with_pixels(tracks, errors, lambda e: np.where(np.all(np.abs(e) < 0.5, axis=1)[:, None],
                                                                           e, 0.0)), gt)
    aged = (errors["age"] >= 1)
    e = errors["error"][aged][:, :2]
    core = np.where(np.abs(e) < 3.0, e, np.nan)
    (su, su_se), (sv, sv_se) = displacement_slope(errors, 0), displacement_slope(errors, 1)
    common, expected = frame_common(errors)
    return (f"| {seed} | {ate:.4f} | {dr:.3f} | {nees.mean:.1f} / {100 * nees.share_inside_95:.0f} % "
            f"| {r.stats.mean_nis:.2f} | {r.decisions.pixels.sigma:.3f} "
            f"| {np.median(np.abs(e[:, 0])):.3f}, {np.median(np.abs(e[:, 1])):.3f} "
            f"| {np.sqrt(np.nanmean(core[:, 0] ** 2)):.3f}, {np.sqrt(np.nanmean(core[:, 1] ** 2)):.3f} "
            f"| {100 * stray_share(errors):.1f} % | {1e3 * su:.2f} +- {1e3 * su_se:.2f}, {1e3 * sv:.2f} +- {1e3 * sv_se:.2f} "
            f"| {common:.3f} ({expected:.3f}) | {white.mean:.1f} / {100 * white.share_inside_95:.0f} % "
            f"| {core_only.mean:.1f} / {100 * core_only.share_inside_95:.0f} % |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="11,12,13")
    parser.add_argument("--steps", type=int, default=150)
    args = parser.parse_args()
    print(f"street scenes of {args.steps} steps, rendered, tracked by vislam's tracker, filtered with the defaults")
    print("| seed | ATE m | dead reckoning m | position NEES mean / inside | NIS | pixel sigma px "
          "| median abs error uL, vL px | RMS (< 3 px) uL, vL px | tracks > 2 px | slope on displacement u, v (x 1e-3) "
          "| frame-common uL px (its noise alone) | NEES: true pixels + white noise | NEES: true pixels + the "
          "tracked errors within 0.5 px |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for seed in (int(s) for s in args.seeds.split(",")):
            print(one_seed(seed, args.steps, Path(tmp)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
