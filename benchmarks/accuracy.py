"""Accuracy of the estimator on the shared real drives and the demo scene: the defaults against alternatives.

Every feature of every drive, in-process, one row per configuration (the defaults, then each
alternative set over them with ``--set``-style assignments):

- ``ece276a_0027.npz`` (KITTI 07, velocities with 0.5 m/s white noise): ATE against ground truth;
- ``ece276a2019_0042.npz`` (KITTI 01 highway, 3.5 observations a step): ATE;
- ``ece276a_03.npz`` (KITTI-360, gyro bias, no ground truth): the largest tilt of the IMU's z axis
  from its first direction over the drive (the car drives on a near-level road);
- the ``vislam demo`` street (synthetic, 429 m): ATE, with the filter told the scene's noise.

ATE = translation RMSE after an SE(3) alignment (evo). The first row is dead reckoning.

Usage: python benchmarks/accuracy.py [--shared ../shared] [--only NAME ...]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from vislam.backend.config import Config
from vislam.backend.data.npz import load_sequence
from vislam.backend.data.tum import read_tum
from vislam.backend.evaluation.metrics import trajectory_errors
from vislam.backend.run.runner import run_sequence
from vislam.synth.scene import SceneConfig, make_scene

ROOT = Path(__file__).resolve().parents[1]

VARIANTS = {
    "defaults": [],
    "no stereo offset": ["conventions.stereo_offset=off"],
    "stereo offset with a rate term": ["conventions.stereo_offset=rate"],
    "no re-anchoring": ["drift.reanchor_observations=0", "drift.reanchor_far_observations=0"],
    "no landmark random walk": ["drift.landmark_random_walk=0"],
    "persistent RANSAC outliers rescued": ["update.persistent_outlier_steps=0"],
    "gate probability 0.99": ["update.gate_probability=0.99"],
    "velocity noise floor 0.05 m/s": ["noise.linear_velocity_sigma_floor=0.05"],
    "repeated frames skipped": ["conventions.repeated_frames=skip"],
    "body error model (FEJ)": ["estimator.error_model=body"],
    "body error model, inverse depth": ["estimator.error_model=body", "landmarks.parametrization=inverse-depth"],
}


def max_tilt_deg(poses: np.ndarray) -> float:
    z0 = poses[0, :3, 2]
    return float(np.degrees(np.arccos(np.clip(poses[:, :3, 2] @ z0, -1.0, 1.0))).max())


def ate(t, poses, gt) -> float:
    return trajectory_errors(t, poses, *gt).ate_rmse


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    parser.add_argument("--only", nargs="*", default=None, help="names of the variants to run (default: all)")
    args = parser.parse_args()
    data = args.shared / "data"
    if not data.is_dir():
        print(f"benchmarks need {data}", file=sys.stderr)
        return 1
    warnings.simplefilter("ignore")
    drives = {name: load_sequence(data / f"{name}.npz") for name in ("ece276a_0027", "ece276a2019_0042", "ece276a_03")}
    gts = {name: read_tum(data / "gt" / f"{name}_gt_tum.txt") for name in ("ece276a_0027", "ece276a2019_0042")}
    scene = make_scene(SceneConfig(scenario="street", seed=0, landmark_density=0.5))
    street_gt = (scene.sequence.time_stamps, scene.world_T_imu_true)
    print("| configuration | 0027 ATE m | 0042 ATE m | 03 max tilt deg | street ATE m | mean NIS 0027 / 0042 / 03 / street | seconds |")
    print("|---|---:|---:|---:|---:|---|---:|")
    first = True
    for name, assignments in VARIANTS.items():
        if args.only and name not in args.only:
            continue
        t0 = time.perf_counter()
        config = Config().with_assignments(assignments)
        r = {key: run_sequence(seq, config) for key, seq in drives.items()}
        street = run_sequence(scene.sequence, scene.config.filter_config().with_assignments(assignments))
        if first:
            print(f"| dead reckoning | {ate(r['ece276a_0027'].time_stamps, r['ece276a_0027'].dead_reckoning, gts['ece276a_0027']):.2f} "
                  f"| {ate(r['ece276a2019_0042'].time_stamps, r['ece276a2019_0042'].dead_reckoning, gts['ece276a2019_0042']):.2f} "
                  f"| {max_tilt_deg(r['ece276a_03'].dead_reckoning):.1f} "
                  f"| {ate(street.time_stamps, street.dead_reckoning, street_gt):.2f} | | |")
            first = False
        nis = " / ".join(f"{x.stats.mean_nis:.2f}" for x in (*r.values(), street))
        print(f"| {name}{' (' + ', '.join(assignments) + ')' if assignments else ''} "
              f"| {ate(r['ece276a_0027'].time_stamps, r['ece276a_0027'].world_T_imu, gts['ece276a_0027']):.2f} "
              f"| {ate(r['ece276a2019_0042'].time_stamps, r['ece276a2019_0042'].world_T_imu, gts['ece276a2019_0042']):.2f} "
              f"| {max_tilt_deg(r['ece276a_03'].world_T_imu):.1f} "
              f"| {ate(street.time_stamps, street.world_T_imu, street_gt):.3f} | {nis} | {time.perf_counter() - t0:.0f} |",
              flush=True)
    print("\n`python benchmarks/accuracy.py`")
    return 0


if __name__ == "__main__":
    sys.exit(main())
