"""``vislam check``: validate a feature file and test its conventions, printing every number."""

from __future__ import annotations

import argparse


def add_parser(sub) -> None:
    p = sub.add_parser("check", help="validate a feature file and test its conventions (extrinsic, velocity timing)")
    p.add_argument("data")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    import numpy as np

    from ...backend.config import Config
    from ...backend.data.npz import load_sequence
    from ...backend.run.decisions import decide

    seq = load_sequence(args.data)
    defaults = Config()
    decisions = decide(seq, defaults)
    per_step = np.diff(seq.obs_ptr)
    print(f"{args.data}: {seq.layout} layout, {seq.num_steps} steps over "
          f"{seq.time_stamps[-1] - seq.time_stamps[0]:.1f} s, {seq.num_features} features, "
          f"{seq.num_observations} observations ({per_step.mean():.1f} per step, max {per_step.max()})")
    print(f"dropped by the loader: {seq.dropped}; steps repeating the previous frame: {decisions.repeated_frames}")
    print("reprojection test (median px, triangulated at k, dead reckoning to k+"
          f"{defaults.conventions.horizon}):")
    for key, value in decisions.conventions.errors_px.items():
        print(f"  {key:<28} {value:8.2f}")
    print(decisions.describe(decisions.config_for(defaults)))
    return 0
