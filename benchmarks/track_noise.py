"""The error model of real tracks, measured on the data: pixel noise by disparity (N5), drift (T1),
the tracks' pixel walk (T3) and its calibration (T4), checked against the filter's own likelihood.

Tables (BENCHMARKS.md, "The error model of real tracks"):
1. per drive: the gap-1 line of the points' variance on their disparity (N5) and its verdict, the
   drift ratio (T1), the walk q(d) = q_0 + q_d d (T3) with the growth factor the drive's own
   refits measure (T4);
2. synthetic tracks with a planted random walk (streets and aerial scenes): the walk measured at
   the median disparity against the planted one, and the growth factor;
3. the filter's innovation likelihood over the first 300 steps (L2, mean per observation) with the
   measured walk scaled by 0, 1/4, 1 and 4 and with the constant walk of 0.05 m/sqrt(s): where the
   measured walk (x1) is the most likely, the data agree with T3-T4 about its size.

Usage: python benchmarks/track_noise.py [--tables 1,2,3] [--shared ../shared]
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from vislam.backend import compiled
from vislam.backend.config import Config
from vislam.backend.data.npz import load_sequence
from vislam.backend.run.decisions import decide
from vislam.backend.run.likelihood import log_likelihood
from vislam.synth.scene import SceneConfig, make_scene
from vislam.synth.track_errors import TrackErrors

DRIVES = ["ece276a_0027.npz", "ece276a_03.npz", "ece276a2019_0042.npz"]
SCALES = (0.0, 0.25, 1.0, 4.0)


def _sequences(shared: Path, frames: Path | None):
    for name in DRIVES:
        yield name, load_sequence(shared / "data" / name)
    if frames is not None:
        yield frames.name, load_sequence(frames)


def table_drives(shared: Path, frames: Path | None) -> None:
    print("| data | N5: gap-1 variance a + b d px^2 (b / SE) | grows | T1: ratio +- SE | drifting | T3: walk q_0 + q_d d px^2 a step | T4: growth factor |")
    print("|---|---|---|---|---|---|---|")
    for name, seq in _sequences(shared, frames):
        d = decide(seq, Config().validate())
        t = d.pixels.disparity
        n5 = "too few points" if t is None else f"{t.intercept:.4f} + {t.slope:.5f} d ({t.slope / t.slope_se:.1f})"
        grows = "" if t is None else ("yes" if t.growth else "no")
        dr = d.drift
        ratio = "n/a" if not np.isfinite(dr.ratio) else f"{dr.ratio:.2f} +- {dr.ratio_se:.2f}"
        print(f"| {name} | {n5} | {grows} | {ratio} | {'yes' if dr.drifting else 'no'} ({dr.source}) "
              f"| {dr.walk:.4f} + {dr.walk_per_disparity:.5f} d | {dr.walk_growth:.2f} |", flush=True)


def table_planted() -> None:
    print("| scene | planted walk px^2 a step | measured at the median disparity | ratio | T4: growth factor |")
    print("|---|---|---|---|---|")
    for scenario in ("street", "aerial"):
        for seed in (3, 4):
            for walk in (0.2, 0.4):
                seq = make_scene(SceneConfig(scenario=scenario, steps=300, seed=seed,
                                             track_errors=TrackErrors(pixel_sigma=0.3, drift_walk=walk))).sequence
                dr = decide(seq, Config().validate()).drift
                d = np.median(seq.obs_pixels[:, 0] - seq.obs_pixels[:, 2])
                q = dr.walk + dr.walk_per_disparity * d
                print(f"| {scenario} seed {seed} | {walk ** 2:.3f} | {q:.4f} | {q / walk ** 2:.2f} | {dr.walk_growth:.2f} |",
                      flush=True)


def table_likelihood(shared: Path, frames: Path | None) -> None:
    print("| data | walk x0 | x1/4 | x1 (the default) | x4 | constant 0.05 m/sqrt(s) |")
    print("|---|---|---|---|---|---|")
    for name, seq in _sequences(shared, frames):
        base = decide(seq, Config().validate())
        if not base.drift.drifting or not (base.drift.walk or base.drift.walk_per_disparity):
            print(f"| {name} | no walk measured ({base.drift.source}) | | | | |", flush=True)
            continue
        cells = []
        for s in SCALES:
            config = Config().with_assignments([f"drift.pixel_walk={s * base.drift.walk}",
                                                f"drift.pixel_walk_per_disparity={s * base.drift.walk_per_disparity}"])
            cells.append(log_likelihood(seq, decide(seq, config.validate()), config)[0])
        config = Config().with_assignments(["drift.landmark_random_walk=0.05"])
        cells.append(log_likelihood(seq, decide(seq, config.validate()), config)[0])
        best = int(np.argmax(cells))
        print(f"| {name} | " + " | ".join(f"**{c:.4f}**" if i == best else f"{c:.4f}" for i, c in enumerate(cells)) + " |",
              flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tables", default="1,2,3")
    parser.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    parser.add_argument("--frames", type=Path, default=None,
                        help="also a feature file tracked by vislam (e.g. `vislam track` of the 51 KITTI frames)")
    args = parser.parse_args(argv)
    if not (args.shared / "data").is_dir():
        print(f"{args.shared / 'data'} is missing: this benchmark needs the shared drives", file=sys.stderr)
        return 1
    warnings.simplefilter("ignore", RuntimeWarning)
    compiled.warm_up()
    tables = {int(t) for t in args.tables.split(",")}
    if 1 in tables:
        print("\n## Table 1: what the tracks say, per drive\n")
        table_drives(args.shared, args.frames)
    if 2 in tables:
        print("\n## Table 2: planted random walks\n")
        table_planted()
    if 3 in tables:
        print("\n## Table 3: the innovation likelihood (L2) of the walk's size\n")
        table_likelihood(args.shared, args.frames)
    return 0


if __name__ == "__main__":
    sys.exit(main())
