"""SLAM from pixels on the 51 real KITTI frames: images -> vislam's tracker -> filter, clean and noisy IMU.

``../shared/images/kitti_odom01_f000000-000050`` lines up with ``ece276a2019_0042.npz`` (frame i =
step i). The IMU is that file's, as given ("clean"), or with white noise of 0.5 m/s and 0.05 rad/s
per axis and a gyro bias of (0.01, -0.01, 0.01) rad/s added to every step ("noisy": the 2020
files' noise; ``numpy.random.default_rng(seed)``, linear then angular noise, (500, 3) each).
Each runs ``vislam run IMAGES --imu IMU --gt GT`` in-process and prints the ATE (SE(3)-aligned)
of SLAM and of dead reckoning over frames 0-50, their ratio, and the
filter's mean NIS; then the same ATE after a Sim(3) alignment (Umeyama with scale, evo) and the
scale it applies. On these frames the ground truth is ~5 % shorter than what both the images and
the IMU show (BENCHMARKS.md, front end), and the Sim(3) columns show what remains once that one
number is taken out.

Usage: python benchmarks/kitti_frames.py [--seed 0] [--seeds N] [--shared ../shared] [--set TABLE.KEY=VALUE ...]
(``--seeds N``: noisy rows for seeds 0 .. N-1 instead of the one ``--seed``.)
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import tempfile
import warnings
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from vislam.backend.evaluation.metrics import alignment_scale, trajectory_errors
from vislam.tools.cli import main as vislam
from vislam.backend.data.tum import read_tum

BIAS = np.array([0.01, -0.01, 0.01])


def noisy_copy(src: Path, dst: Path, seed: int) -> None:
    """The course file with the 2020 files' velocity noise and a gyro bias added (2019 layout kept)."""
    with np.load(src, allow_pickle=False) as d:
        data = {k: d[k] for k in d.files}
    rng = np.random.default_rng(seed)
    n = data["linear_velocity"].shape[1]
    data["linear_velocity"] = data["linear_velocity"] + rng.normal(0.0, 0.5, (n, 3)).T
    data["rotational_velocity"] = data["rotational_velocity"] + rng.normal(0.0, 0.05, (n, 3)).T + BIAS[:, None]
    np.savez_compressed(dst, **data)


def run(images: Path, imu: Path, gt: Path, overrides: list[str]) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        args = ["run", str(images), "--imu", str(imu), "--out", str(out), "--gt", str(gt), "--quiet"]
        for kv in overrides:
            args += ["--set", kv]
        with warnings.catch_warnings(), redirect_stdout(io.StringIO()):
            warnings.simplefilter("ignore")
            code = vislam(args)
        if code != 0:
            raise SystemExit(f"vislam {' '.join(args)} exited {code}")
        summary = json.loads((out / "summary.json").read_text())
        sim3 = {name: sim3_ate(out / f"{name}.txt", gt) for name in ("trajectory", "dead_reckoning")}
    errors = summary["errors"]
    return {"slam": errors["estimate"]["ate_rmse"], "dr": errors["dead_reckoning"]["ate_rmse"],
            "nis": summary["mean_nis_per_observation"], "slam_sim3": sim3["trajectory"],
            "dr_sim3": sim3["dead_reckoning"]}


def sim3_ate(estimate: Path, gt: Path) -> tuple[float, float]:
    """(ATE RMSE after a Sim(3) alignment, the scale applied to the estimate)."""
    poses = (*read_tum(estimate), *read_tum(gt))
    return trajectory_errors(*poses, sim3=True).ate_rmse, alignment_scale(*poses)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--seeds", type=int, default=0, help="noisy rows for seeds 0 .. N-1")
    parser.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="TABLE.KEY=VALUE")
    args = parser.parse_args()
    images = args.shared / "images" / "kitti_odom01_f000000-000050"
    clean = args.shared / "data" / "ece276a2019_0042.npz"
    gt = args.shared / "data" / "gt" / "ece276a2019_0042_gt_tum.txt"
    if not images.is_dir() or not clean.is_file():
        print(f"needs {images} and {clean}", file=sys.stderr)
        return 1
    seeds = range(args.seeds) if args.seeds > 0 else [args.seed]
    with tempfile.TemporaryDirectory() as tmp:
        print(f"overrides: {args.overrides or 'none'}")
        print("| IMU | SLAM ATE m | dead reckoning ATE m | SLAM / DR | mean NIS "
              "| Sim(3): SLAM ATE m (scale) | Sim(3): DR ATE m (scale) | Sim(3): SLAM / DR |")
        print("|---|---|---|---|---|---|---|---|")
        rows = [("clean", clean)]
        for seed in seeds:
            noisy = Path(tmp) / f"noisy{seed}.npz"
            noisy_copy(clean, noisy, seed)
            rows.append((f"noisy (seed {seed})", noisy))
        for name, imu in rows:
            r = run(images, imu, gt, args.overrides)
            (s_ate, s_scale), (d_ate, d_scale) = r["slam_sim3"], r["dr_sim3"]
            print(f"| {name} | {r['slam']:.3f} | {r['dr']:.3f} | {r['slam'] / r['dr']:.2f} | {r['nis']:.2f} "
                  f"| {s_ate:.3f} ({s_scale:.3f}) | {d_ate:.3f} ({d_scale:.3f}) | {s_ate / d_ate:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
