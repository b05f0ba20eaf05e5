"""``vislam check``: validate a feature file and test its conventions, printing every number."""

from __future__ import annotations

import argparse


def add_parser(sub) -> None:
    p = sub.add_parser("check", help="validate a feature file and test its conventions (extrinsic, velocity timing); "
                                     "with a real IMU's samples, the start at rest and the noise")
    p.add_argument("data", help="feature + IMU file in the course .npz layout (velocities or the inertial layout)")
    p.add_argument("--imu-input", dest="imu_input", choices=["auto", "velocity", "inertial"], default="auto",
                   help="a file with both IMU inputs: which one to check (default: auto, which refuses such a file)")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    import numpy as np

    from ...backend.config import Config
    from ...backend.data.npz import load_sequence
    from ...backend.run.decisions import decide

    seq = load_sequence(args.data, imu=args.imu_input)
    defaults = Config()
    per_step = np.diff(seq.obs_ptr)
    print(f"{args.data}: {'inertial' if seq.inertial else seq.layout} layout, {seq.num_steps} steps over "
          f"{seq.time_stamps[-1] - seq.time_stamps[0]:.1f} s, {seq.num_features} features, "
          f"{seq.num_observations} observations ({per_step.mean():.1f} per step, max {per_step.max()})")
    if seq.inertial:
        from ...backend.run.inertial import decide_inertial

        imu = seq.imu
        print(f"IMU: {imu.num_samples} samples at {imu.rate_hz:.1f} Hz over "
              f"{imu.time_stamps[-1] - imu.time_stamps[0]:.1f} s; noise densities "
              + (", ".join(f"{k} {v:g}" for k, v in imu.noise.as_dict().items() if k != "source")
                 if imu.noise is not None else "not given"))
        print(decide_inertial(seq, defaults).describe())
        return 0
    decisions = decide(seq, defaults)
    print(f"read: {seq.dropped_text() or 'every observation kept'}; steps repeating the previous frame: "
          f"{decisions.repeated_frames}")
    print("reprojection test (median px, triangulated at k, dead reckoning to k+"
          f"{defaults.conventions.horizon}):")
    for key, value in decisions.conventions.errors_px.items():
        print(f"  {key:<28} {value:8.2f}")
    print(decisions.describe(decisions.config_for(defaults)))
    return 0
