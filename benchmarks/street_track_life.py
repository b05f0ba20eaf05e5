"""How long can a track live on the default street scene? The geometry's bound, and the tracker.

For points spread evenly over the visible part of the left image (every ``--spacing`` px, sky
excluded) at several start frames, the true 3-D point under each (``synth.render.render_depth``)
is followed with the true poses until it leaves either image (the tracker's ``border_px``), falls
behind the camera or is hidden by a nearer surface (depth test against that frame's depth map,
5 %). Its life is the number of frames it was visible, the start frame included: what a tracker
that spreads its tracks over the image (a grid with a per-cell budget, as vislam's does) could
reach if it never lost a track. The tracker's own numbers on the same frames follow.

Usage: python benchmarks/street_track_life.py [--frames 50] [--seed 0] [--spacing 16]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from vislam.backend.geometry import se3
from vislam.frontend.config import TrackerConfig
from vislam.frontend.tracker import StereoTracker
from vislam.synth.render import RENDER_STREAM, build_street_planes, render_depth, render_pair
from vislam.synth.scene import SceneConfig, make_scene


def visible_life(depths, world_T_cam, K, baseline, start, spacing, border) -> np.ndarray:
    """(n,) frames each evenly spread pixel of frame ``start`` stays visible (see the docstring)."""
    h, w = depths[start].shape
    v, u = np.mgrid[border:h - border:spacing, border:w - border:spacing]
    z = depths[start][v, u]
    seen = np.isfinite(z)
    u, v, z = u[seen].astype(float), v[seen].astype(float), z[seen]
    p_in_cam = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z, np.ones_like(z)])
    p_in_world = world_T_cam[start] @ p_in_cam
    life, alive = np.ones(z.size, np.int64), np.ones(z.size, bool)
    for k in range(start + 1, len(depths)):
        q = se3.inverse(world_T_cam[k]) @ p_in_world
        zk = q[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uL, vL = K[0, 0] * q[0] / zk + K[0, 2], K[1, 1] * q[1] / zk + K[1, 2]
            uR = uL - K[0, 0] * baseline / zk
        inside = (zk > 0) & (uR >= border) & (uL <= w - 1 - border) & (vL >= border) & (vL <= h - 1 - border)
        ui = np.clip(np.nan_to_num(np.round(uL)).astype(np.int64), 0, w - 1)
        vi = np.clip(np.nan_to_num(np.round(vL)).astype(np.int64), 0, h - 1)
        alive &= inside & (np.abs(depths[k][vi, ui] - zk) <= 0.05 * zk)
        life += alive
    return life


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--spacing", type=int, default=16, help="px between the spread points")
    args = parser.parse_args()
    scene = make_scene(SceneConfig(steps=args.frames, seed=args.seed))
    cal = scene.config.calibration
    K, baseline = np.asarray(cal.K, dtype=float), float(cal.baseline)
    world_T_cam = scene.world_T_imu_true @ np.asarray(cal.imu_T_cam, dtype=float)
    planes = build_street_planes(scene.world_T_imu_true, np.random.default_rng([args.seed, RENDER_STREAM]))
    depths = [render_depth(planes, se3.inverse(T), K, cal.image_size) for T in world_T_cam]
    border = TrackerConfig().border_px
    print(f"default street, seed {args.seed}, {args.frames} frames; points every {args.spacing} px")
    print("| start frame | points | median life (frames) | share >= 10 frames | frames left |")
    print("|---|---|---|---|---|")
    starts = range(0, max(1, args.frames - 20), 5)
    for start in starts:
        life = visible_life(depths, world_T_cam, K, baseline, start, args.spacing, border)
        print(f"| {start} | {life.size} | {np.median(life):.0f} | {np.mean(life >= 10):.2f} | {args.frames - start} |")

    tracker = StereoTracker(TrackerConfig(), K, baseline)
    seen: dict[int, int] = {}
    for T in scene.world_T_imu_true:
        ids, _ = tracker.step(*render_pair(planes, T, cal))
        for i in ids.tolist():
            seen[i] = seen.get(i, 0) + 1
    lengths = np.array(list(seen.values()))
    print(f"tracker (default configuration): {lengths.size} tracks, median length {np.median(lengths):.0f}, "
          f"observation-weighted median {np.median(np.repeat(lengths, lengths)):.0f}, "
          f"share >= 10 frames {np.mean(lengths >= 10):.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
