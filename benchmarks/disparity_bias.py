"""Disparity error of vislam's stereo matching, per disparity bin: on renders against the true depth,
on the 51 real KITTI 01 frames against depth from the ground-truth motion; and the stereo offset
the run finds on its own (``backend.run.stereo_offset``).

1. Renders, fronto-parallel planes: one plane filling the view at the depth of each disparity
   (1-80 px; true disparity fx b / z everywhere), textured (``synth.textures.blobs``) and weakly
   textured (smooth noise, 5 grey levels), with 1 grey level of image noise; a fresh
   :class:`~vislam.frontend.tracker.StereoTracker` matches its corners (block-matching seed, LK,
   back-check, affine refinement).
2. Renders, the street (``vislam demo``'s scene, 50 frames, the full tracker frame after frame):
   each observation against ``synth.render.render_depth`` at its left pixel (1 / depth is affine
   within a plane, so it is interpolated exactly), split into plane interiors and depth edges
   (a 4 x 4 neighbourhood not on one plane: the patch mixes two depths).
3. Real frames: each track seen in >= 4 frames with >= 3 deg of parallax is triangulated from
   its left pixels and the KITTI camera poses (``poses.txt``), and its disparity in each frame
   compared with fx b / z; before and after removing the offset the run identifies (vision only).
   The KITTI poses carry their own errors (the reprojection residual of these points is ~0.5 px),
   so this column has a spread of about 1 px, and it measures the sum of matcher and rig.

Bias columns: the median error and the mean of the errors within 5 robust standard deviations of
it (what survives an outlier gate); spread: 1.4826 MAD.

Usage: python benchmarks/disparity_bias.py [--shared ../shared] [--frames 50] [--seed 0]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from vislam.backend.data.sequence import Sequence
from vislam.backend.geometry import se3
from vislam.backend.run.stereo_offset import identify_stereo_offset
from vislam.frontend.config import TrackerConfig
from vislam.frontend.tracker import StereoTracker
from vislam.synth import render, textures
from vislam.synth.observe import kitti_calibration
from vislam.synth.render import RENDER_STREAM, build_street_planes, render_depth, render_pair
from vislam.synth.scene import SceneConfig, make_scene

DISPARITIES = [1, 1.5, 2, 3, 5, 8, 12, 20, 30, 45, 60, 80]
BINS = [0.5, 2, 3, 5, 8, 12, 20, 30, 45, 80]
MIN_SAMPLES = 30


def stats(errors: np.ndarray) -> tuple[float, float, float]:
    """(median, mean within 5 robust sigma of the median, robust sigma)."""
    med = float(np.median(errors))
    sigma = 1.4826 * float(np.median(np.abs(errors - med)))
    core = errors[np.abs(errors - med) <= 5 * max(sigma, 1e-3)]
    return med, float(core.mean()), sigma


def row(label: str, errors: np.ndarray) -> str:
    if errors.size < MIN_SAMPLES:
        return f"| {label} | {errors.size} | | | |"
    med, mean, sigma = stats(errors)
    return f"| {label} | {errors.size} | {med:+.3f} | {mean:+.3f} | {sigma:.3f} |"


def planes_table(seed: int) -> None:
    cal = kitti_calibration()
    K, b = np.asarray(cal.K), cal.baseline
    fx, (w, h) = K[0, 0], cal.image_size
    rng = np.random.default_rng(seed)
    rich = textures.blobs(rng, (1024, 1024))
    weak = np.clip(128 + textures._smooth_noise(rng, 1024, 1024, 2.0, 5.0), 0, 255).astype(np.uint8)
    print("\n1. fronto-parallel planes (renders), error = measured - true disparity, px")
    print("| texture, true disparity px | matches | median | mean (core) | spread |")
    print("|---|---:|---:|---:|---:|")
    right_T_left = np.eye(4)
    right_T_left[0, 3] = -b
    for name, tex in (("textured", rich), ("weak", weak)):
        for d in DISPARITIES:
            z = fx * b / d
            half_w, half_h = z * w / fx * 0.8 + b, z * h / fx * 0.8
            corners = np.array([[-half_w, -half_h, z], [half_w, -half_h, z], [half_w, half_h, z], [-half_w, half_h, z]])
            planes = [render.Plane(corners, tex)]
            noise = np.random.default_rng(seed + 1)
            pair = [np.clip(render.render_image(planes, T, K, (w, h)) + noise.normal(0, 1.0, (h, w)), 0, 255).astype(np.uint8)
                    for T in (np.eye(4), right_T_left)]
            _, px = StereoTracker(TrackerConfig(), K, b).step(*pair)
            print(row(f"{name}, {d:g}", px[:, 0] - px[:, 2] - d))


def street_table(frames: int, seed: int) -> None:
    scene = make_scene(SceneConfig(steps=frames, seed=seed))
    cal = scene.config.calibration
    K, b = np.asarray(cal.K, float), float(cal.baseline)
    fb = K[0, 0] * b
    world_T_cam = scene.world_T_imu_true @ np.asarray(cal.imu_T_cam, float)
    planes = build_street_planes(scene.world_T_imu_true, np.random.default_rng([seed, RENDER_STREAM]))
    tracker = StereoTracker(TrackerConfig(), K, b)
    true_d, measured, edge = [], [], []
    for k, T in enumerate(scene.world_T_imu_true):
        _, px = tracker.step(*render_pair(planes, T, cal))
        inv = 1.0 / render_depth(planes, se3.inverse(world_T_cam[k]), K, cal.image_size)
        u0, v0 = np.floor(px[:, 0]).astype(int), np.floor(px[:, 1]).astype(int)
        for i in np.flatnonzero((u0 >= 1) & (v0 >= 1) & (u0 < inv.shape[1] - 2) & (v0 < inv.shape[0] - 2)):
            patch = inv[v0[i] - 1:v0[i] + 3, u0[i] - 1:u0[i] + 3]
            if not np.all(patch > 0):
                continue  # sky in the neighbourhood
            curvature = np.abs(np.diff(patch, 2, axis=0)).max() + np.abs(np.diff(patch, 2, axis=1)).max()
            fu, fv = px[i, 0] - u0[i], px[i, 1] - v0[i]
            q = inv[v0[i]:v0[i] + 2, u0[i]:u0[i] + 2]
            iz = q[0, 0] * (1 - fu) * (1 - fv) + q[0, 1] * fu * (1 - fv) + q[1, 0] * (1 - fu) * fv + q[1, 1] * fu * fv
            true_d.append(fb * iz)
            measured.append(px[i, 0] - px[i, 2])
            edge.append(curvature * fb > 0.01)
    true_d, measured, edge = np.array(true_d), np.array(measured), np.array(edge)
    print(f"\n2. rendered street, seed {seed}, {frames} frames: {true_d.size} observations, {edge.sum()} at depth edges")
    print("| where, true disparity px | observations | median | mean (core) | spread |")
    print("|---|---:|---:|---:|---:|")
    for name, mask in (("plane interior", ~edge), ("depth edge", edge)):
        for lo, hi in zip(BINS[:-1], BINS[1:]):
            m = mask & (true_d >= lo) & (true_d < hi)
            print(row(f"{name}, {lo:g}-{hi:g}", measured[m] - true_d[m]))


def kitti_tables(shared: Path) -> None:
    images = shared / "images" / "kitti_odom01_f000000-000050"
    if not images.is_dir():
        print(f"\n3. skipped: {images} not found")
        return
    calib = {line.split(":")[0]: np.array(line.split(":")[1].split(), float)
             for line in (images / "calib.txt").read_text().splitlines() if ":" in line}
    P0, P1 = calib["P0"].reshape(3, 4), calib["P1"].reshape(3, 4)
    K, b = P0[:, :3], -P1[0, 3] / P1[0, 0]
    fb = K[0, 0] * b
    poses = np.loadtxt(images / "poses.txt").reshape(-1, 3, 4)
    world_T_cam = np.tile(np.eye(4), (len(poses), 1, 1))
    world_T_cam[:, :3, :] = poses
    tracker = StereoTracker(TrackerConfig(), K, b)
    ids_k, pixels_k = [], []
    for f in sorted((images / "image_0").glob("*.png")):
        ids, px = tracker.step(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE),
                               cv2.imread(str(images / "image_1" / f.name), cv2.IMREAD_GRAYSCALE))
        ids_k.append(ids)
        pixels_k.append(px)
    n = len(ids_k)
    seq = Sequence.from_steps(np.arange(n) * 0.1, np.zeros((n, 3)), np.zeros((n, 3)), ids_k, pixels_k, K, b, np.eye(4))
    offset = identify_stereo_offset(seq, np.eye(4))
    print(f"\n3. KITTI 01 frames 0-{n - 1} (real), vislam's tracker: {offset.describe()}")
    tracks: dict[int, list] = {}
    for k, (ids, px) in enumerate(zip(ids_k, pixels_k)):
        for i, p in zip(ids.tolist(), px):
            tracks.setdefault(i, []).append((k, p))
    K_inv = np.linalg.inv(K)
    true_d, measured = [], []
    for obs in tracks.values():
        if len(obs) < 4:
            continue
        ks = np.array([k for k, _ in obs])
        px = np.array([p for _, p in obs])
        C = world_T_cam[ks]
        A, B = np.zeros((3, 3)), np.zeros(3)
        for T, p in zip(C, px):
            ray = T[:3, :3] @ K_inv @ np.array([p[0], p[1], 1.0])
            ray /= np.linalg.norm(ray)
            M = np.eye(3) - np.outer(ray, ray)
            A += M
            B += M @ T[:3, 3]
        x = np.linalg.solve(A, B)
        r0, r1 = x - C[0][:3, 3], x - C[-1][:3, 3]
        if np.degrees(np.arccos(np.clip(r0 @ r1 / np.linalg.norm(r0) / np.linalg.norm(r1), -1, 1))) < 3:
            continue
        q = np.einsum("nij,j->ni", np.linalg.inv(C), np.append(x, 1.0))
        uv = q[:, :3] @ K.T
        if (q[:, 2] <= 0).any() or np.linalg.norm(uv[:, :2] / uv[:, 2:3] - px[:, :2], axis=1).max() > 1.5:
            continue
        true_d.extend(fb / q[:, 2])
        measured.extend(px[:, 0] - px[:, 2])
    true_d, measured = np.array(true_d), np.array(measured)
    print(f"against depth from the KITTI poses: {true_d.size} observations")
    print("| true disparity px | observations | before: median | before: mean (core) | after: median | after: mean (core) | spread |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    beta = offset.offsets(0.0)
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        m = (true_d >= lo) & (true_d < hi)
        if m.sum() < MIN_SAMPLES:
            continue
        before = stats(measured[m] - true_d[m])
        after = stats(measured[m] - beta - true_d[m])
        print(f"| {lo:g}-{hi:g} | {m.sum()} | {before[0]:+.2f} | {before[1]:+.2f} | {after[0]:+.2f} | {after[1]:+.2f} | {before[2]:.2f} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    parser.add_argument("--frames", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    planes_table(args.seed)
    street_table(args.frames, args.seed)
    kitti_tables(args.shared)
    return 0


if __name__ == "__main__":
    sys.exit(main())
