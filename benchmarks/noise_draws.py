"""SLAM accuracy on KITTI 07 over several draws of the velocity noise (BENCHMARKS.md, accuracy).

``ece276a_0027.npz`` carries one draw of white velocity noise, so its single ATE moves by about a
metre under any small change of the filter. This script keeps the
file's feature tracks and rebuilds the velocities from ground truth: the body twist between
consecutive ground-truth poses, xi_k = log(T_k^-1 T_{k+1}) / tau_k, stamped k+1 as the file's
convention says (velocity_index = next). Each draw adds white noise of 0.5 m/s and 0.05 rad/s per
axis and a constant gyro bias N(0, 0.005^2) rad/s per axis (the 2020 files' noise), with
``numpy.random.default_rng(seed)``. The filter runs with the given configuration, the conventions
fixed as measured on the file (extrinsic as given, velocity k+1).

``--noise-scale 0`` keeps the true velocities (one draw is enough then); with
``--set noise.linear_velocity_sigma=0.5 --set noise.angular_velocity_sigma=0.05`` the filter still weighs them
as noisy, which measures where the feature tracks alone pull the estimate.

Usage: python benchmarks/noise_draws.py [--draws 6] [--noise-scale 1] [--shared ../shared] [--set TABLE.KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from vislam.backend.geometry import se3
from vislam.backend.config import Config
from vislam.backend.errors import VislamError
from vislam.backend.evaluation.metrics import trajectory_errors
from vislam.backend.run.runner import run_sequence
from vislam.backend.data.sequence import Sequence
from vislam.backend.data.npz import load_sequence
from vislam.backend.data.tum import read_tum

LINEAR_SIGMA, ANGULAR_SIGMA, BIAS_SIGMA = 0.5, 0.05, 0.005


def true_velocities(seq: Sequence, gt_poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The file's velocities with steps 1..n (n ground-truth poses) replaced by the exact twists."""
    linear, angular = seq.linear_velocity.copy(), seq.angular_velocity.copy()
    n = gt_poses.shape[0]
    tau = np.diff(seq.time_stamps[:n])
    twists = np.array([se3.log_se3(se3.inverse(gt_poses[k]) @ gt_poses[k + 1]) for k in range(n - 1)]) / tau[:, None]
    linear[1:n], angular[1:n] = twists[:, :3], twists[:, 3:]
    return linear, angular


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=6)
    parser.add_argument("--noise-scale", type=float, default=1.0, help="multiplies the three noise sigmas")
    parser.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    parser.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE")
    args = parser.parse_args()
    try:
        seq = load_sequence(args.shared / "data" / "ece276a_0027.npz")
        gt_t, gt = read_tum(args.shared / "data" / "gt" / "ece276a_0027_gt_tum.txt")
        base = Config.from_values({"conventions.imu_flip": "no", "conventions.velocity_index": "next"})
        config = base.with_assignments(args.set)
    except VislamError as e:  # missing ../shared, a bad --set
        print(f"noise_draws: error: {e}", file=sys.stderr)
        return 2
    linear, angular = true_velocities(seq, gt)
    a = args.noise_scale
    print(f"ece276a_0027.npz, velocities from ground truth + noise ({a * LINEAR_SIGMA:g} m/s, {a * ANGULAR_SIGMA:g} rad/s "
          f"white, gyro bias sigma {a * BIAS_SIGMA:g} rad/s); overrides: {' '.join(args.set) or 'none'}")
    print("| draw (seed) | dead reckoning ATE (m) | SLAM ATE (m) | filter s |")
    print("|---|---|---|---|")
    slam, dr = [], []
    for seed in range(args.draws):
        rng = np.random.default_rng(seed)
        noisy = dataclasses.replace(
            seq,
            linear_velocity=linear + a * rng.normal(0.0, LINEAR_SIGMA, linear.shape),
            angular_velocity=angular + a * (rng.normal(0.0, ANGULAR_SIGMA, angular.shape) + rng.normal(0.0, BIAS_SIGMA, 3)),
        )
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # NIS health messages
            result = run_sequence(noisy, config)
        seconds = time.perf_counter() - t0
        slam.append(trajectory_errors(result.time_stamps, result.world_T_imu, gt_t, gt).ate_rmse)
        dr.append(trajectory_errors(result.time_stamps, result.dead_reckoning, gt_t, gt).ate_rmse)
        print(f"| {seed} | {dr[-1]:.2f} | {slam[-1]:.2f} | {seconds:.1f} |", flush=True)
    print(f"| mean | {np.mean(dr):.2f} | {np.mean(slam):.2f} (min {np.min(slam):.2f}, max {np.max(slam):.2f}) | |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
