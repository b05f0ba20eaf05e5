"""Monte Carlo consistency against the pixel noise, with and without the second-order terms (U7).

For each scenario (street, aerial), white pixel noise (0.5, 1 px) and geometry seed (0, 1, 2, chosen
before any run), ``--runs`` noise realizations of a 300-step scene (``vislam.synth.scene``, the
filter told the scene's own noise, each run's gyro bias drawn from the prior, as ``vislam mc
--true-noise``), with the defaults and with ``update.second_order = false``. Columns: the
run-averaged pose NEES over steps 10-299 (expected 6) and the share of steps inside its 95 % band,
the landmark NEES (expected 3), the NIS per observation (expected 4) and the runs' mean position
error (unaligned: the world frame is the first pose).

Usage: python benchmarks/pixel_noise_consistency.py [--runs 12] [--seeds 0,1,2] [--workers 2]
"""

from __future__ import annotations

import argparse
import concurrent.futures
import time

from vislam.backend.evaluation.consistency import average_band, monte_carlo
from vislam.synth.scene import SceneConfig, SceneFactory

VARIANTS = {"second-order terms (default)": [], "first order (update.second_order=false)": ["update.second_order=false"]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=12)
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    lo, hi = average_band(6, args.runs)
    print(f"{args.runs} runs of {args.steps} steps; the pose NEES band of a {args.runs}-run average [{lo:.2f}, {hi:.2f}]")
    print()
    print("| scenario | pixel noise px | seed | variant | pose NEES | steps in band | landmark NEES | NIS | position error m |")
    print("|---|---|---|---|---|---|---|---|---|")
    t0 = time.perf_counter()
    with concurrent.futures.ProcessPoolExecutor(args.workers) as pool:
        for scenario in ("street", "aerial"):
            for sigma in (0.5, 1.0):
                for seed in seeds:
                    scene = SceneConfig(scenario=scenario, steps=args.steps, seed=seed, pixel_sigma=sigma)
                    for label, assignments in VARIANTS.items():
                        config = scene.filter_config().with_assignments(assignments)
                        r = monte_carlo(SceneFactory(scene), config, runs=args.runs, seed0=0, executor=pool)
                        print(f"| {scenario} | {sigma:g} | {seed} | {label} | {r.pose_nees_time_average:.2f} | "
                              f"{100 * r.pose_nees_in_band:.0f} % | {r.landmark_nees_mean:.2f} | {r.nis_mean:.3f} | "
                              f"{r.ate_estimate.mean():.3f} |", flush=True)
    print()
    print(f"{time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
