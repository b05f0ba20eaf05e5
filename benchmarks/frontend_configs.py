"""Tracker configurations judged by what they are for: SLAM accuracy from pixels, real frames and renders together.

For each configuration (the defaults, then each alternative set over them):

- KITTI 01 frames 0-50 (real, ``../shared/images``) with the IMU of ``ece276a2019_0042.npz``:
  SLAM / dead-reckoning ATE (SE(3)-aligned) with the velocities as given ("clean") and the median
  over 6 draws of the 2020 files' noise (``kitti_frames.noisy_copy``, seeds 0-5);
- the rendered street (``vislam synth --scenario street --render``, 80 frames, seed 3): SLAM /
  dead-reckoning ATE, and against the renderer's truth the share of tracks that stray more than
  2 px from their true point at some frame (``tests/test_frontend.py``'s measure);
- track length on both: the observation-weighted median (the length of the track an observation
  belongs to, the median over observations) in frames.

The frames are tracked once per configuration; the filter then runs on the tracks in-process
(``run_sequence``: the decisions from the whole sequence, as ``vislam track`` then ``vislam run``).

Usage: python benchmarks/frontend_configs.py [--shared ../shared] [--only NAME ...]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from kitti_frames import noisy_copy  # noqa: E402
from rendered_honesty import observation_errors, stray_share  # noqa: E402

from vislam.backend.config import Config  # noqa: E402
from vislam.backend.data.tum import read_tum  # noqa: E402
from vislam.backend.evaluation.metrics import trajectory_errors  # noqa: E402
from vislam.backend.geometry import se3  # noqa: E402
from vislam.backend.run.runner import run_sequence  # noqa: E402
from vislam.frontend.config import TrackerConfig  # noqa: E402
from vislam.frontend.imu_input import ImuVelocities, read_imu  # noqa: E402
from vislam.frontend.track import open_stereo_directory, track_directory  # noqa: E402
from vislam.synth.render import RENDER_STREAM, build_street_planes, render_depth, write_kitti_sequence  # noqa: E402
from vislam.synth.scene import SceneConfig, make_scene  # noqa: E402

CONFIGS = {
    "defaults": {},
    "motion check 0.7 px, strict affine": {"motion_threshold_px": 0.7, "affine_max_residual": 0.5,
                                           "affine_max_shift_px": 1.0},
    "motion check 1.0 px": {"motion_threshold_px": 1.0},
    "patch scale <= 1.3": {"max_patch_scale": 1.3},
    "birth look-ahead 5 frames": {"birth_lookahead_frames": 5},
    "isotropy >= 0.2": {"min_isotropy": 0.2},
    "200 tracks": {"target_tracks": 200},
    "400 tracks": {"target_tracks": 400},
}
SEEDS = range(6)


def weighted_median_length(seq) -> float:
    counts = np.bincount(seq.obs_ids)
    lengths = counts[seq.obs_ids]
    return float(np.median(lengths)) if lengths.size else 0.0


def ate_pair(seq, gt_t, gt_poses) -> tuple[float, float]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = run_sequence(seq, Config())
    n = min(len(gt_poses), r.time_stamps.size)
    slam = trajectory_errors(r.time_stamps[:n], r.world_T_imu[:n], gt_t[:n], gt_poses[:n]).ate_rmse
    dr = trajectory_errors(r.time_stamps[:n], r.dead_reckoning[:n], gt_t[:n], gt_poses[:n]).ate_rmse
    return slam, dr


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    parser.add_argument("--only", nargs="*", default=None)
    args = parser.parse_args()
    images = args.shared / "images" / "kitti_odom01_f000000-000050"
    clean = args.shared / "data" / "ece276a2019_0042.npz"
    gt_t, gt_poses = read_tum(args.shared / "data" / "gt" / "ece276a2019_0042_gt_tum.txt")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        imus = [read_imu(clean, 51)]
        for seed in SEEDS:
            noisy_copy(clean, tmp / f"noisy{seed}.npz", seed)
            imus.append(read_imu(tmp / f"noisy{seed}.npz", 51))
        scene = make_scene(SceneConfig(steps=80, seed=3))
        street = tmp / "street"
        write_kitti_sequence(street, scene)
        cal = scene.config.calibration
        K, baseline = np.asarray(cal.K, float), float(cal.baseline)
        world_T_cam = scene.world_T_imu_true @ np.asarray(cal.imu_T_cam, float)
        planes = build_street_planes(scene.world_T_imu_true, np.random.default_rng([3, RENDER_STREAM]))
        depths = [render_depth(planes, se3.inverse(T), K, cal.image_size) for T in world_T_cam]
        truth = scene.sequence
        street_imu = ImuVelocities(truth.time_stamps, truth.linear_velocity, truth.angular_velocity, truth.imu_T_cam)
        kitti_stereo, street_stereo = open_stereo_directory(images), open_stereo_directory(street)
        print("| tracker configuration | KITTI clean SLAM / DR | KITTI noisy SLAM / DR (median of 6) "
              "| street SLAM / DR | street tracks > 2 px | track length, obs-weighted median: KITTI / street |")
        print("|---|---:|---:|---:|---:|---|")
        for name, values in CONFIGS.items():
            if args.only and name not in args.only:
                continue
            config = TrackerConfig.from_values(values)
            ratios = []
            kitti = None
            for imu in imus:
                seq = track_directory(kitti_stereo, imu, config) if kitti is None else kitti_with(kitti, imu)
                kitti = kitti or seq
                slam, dr = ate_pair(seq, gt_t, gt_poses)
                ratios.append(slam / dr)
            tracks = track_directory(street_stereo, street_imu, config)
            slam, dr = ate_pair(tracks, truth.time_stamps, scene.world_T_imu_true)
            stray = stray_share(observation_errors(tracks, depths, world_T_cam, K, baseline))
            label = name if not values else f"{name} ({', '.join(f'{k}={v}' for k, v in values.items())})"
            print(f"| {label} | {ratios[0]:.2f} | {np.median(ratios[1:]):.2f} | {slam / dr:.3f} | {100 * stray:.1f} % "
                  f"| {weighted_median_length(kitti):.0f} / {weighted_median_length(tracks):.0f} |", flush=True)
    return 0


def kitti_with(seq, imu):
    """The same tracks with another IMU's velocities."""
    import dataclasses
    return dataclasses.replace(seq, linear_velocity=imu.linear_velocity[:seq.num_steps].copy(),
                               angular_velocity=imu.angular_velocity[:seq.num_steps].copy())


if __name__ == "__main__":
    sys.exit(main())
