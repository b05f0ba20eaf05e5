"""``vislam synth``: a synthetic scene with ground truth, and optionally its rendered stereo images."""

from __future__ import annotations

import argparse

from ...backend.errors import VislamError
from .. import outputs


def add_parser(sub) -> None:
    p = sub.add_parser("synth", help="make a synthetic scene with ground truth (feature file + gt_tum.txt)")
    p.add_argument("--scenario", choices=["street", "aerial"], default="street")
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True)
    p.add_argument("--force", action="store_true")
    p.add_argument("--render", action="store_true", help="also render rectified stereo images (KITTI odometry layout)")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from ...synth.scene import SceneConfig, make_scene, write_scene

    if args.render and args.scenario != "street":
        raise VislamError("--render: only the street scenario has a textured world so far")
    out = outputs.prepare_output_dir(args.out, args.force)
    scene = make_scene(SceneConfig(scenario=args.scenario, steps=args.steps, seed=args.seed))
    write_scene(scene, out)
    seq = scene.sequence
    wrote = "data.npz, gt_tum.txt, landmarks.npz"
    if args.render:
        from ...synth.render import write_kitti_sequence

        write_kitti_sequence(out, scene)
        wrote += ", image_0/, image_1/, calib.txt, times.txt, poses.txt (KITTI odometry layout)"
    print(f"{args.scenario} scene, seed {args.seed}: {seq.num_steps} steps, {seq.num_observations} observations "
          f"of {scene.landmark_ids.size} tracks; wrote {wrote} to {out}/")
    return 0
