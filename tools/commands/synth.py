"""``vislam synth``: a synthetic scene with ground truth, and optionally its rendered stereo images."""

from __future__ import annotations

import argparse

from ...backend.errors import VislamError

#: PNG bytes per pixel of the rendered street at the renderer's compression level 1 (measured: 240 MB
#: for 500 pairs of 1241 x 376), for the size notice before rendering.
PNG_BYTES_PER_PIXEL = 0.52


def add_parser(sub) -> None:
    p = sub.add_parser("synth", help="make a synthetic scene with ground truth (feature file + gt_tum.txt)")
    p.add_argument("--scenario", choices=["street", "aerial"], default="street")
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True)
    p.add_argument("--force", action="store_true")
    p.add_argument("--render", action="store_true", help="also render rectified stereo images (KITTI odometry layout)")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    p.add_argument("--no-progress", dest="no_progress", action="store_true", help="no progress bar")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from ...backend.data.files import output_directory
    from ...synth.scene import SceneConfig, check_scene_size, make_scene, write_scene

    if args.render and args.scenario != "street":
        raise VislamError("--render: only the street scenario has a textured world so far")
    config = SceneConfig(scenario=args.scenario, steps=args.steps, seed=args.seed)  # refused before any work
    check_scene_size(config)
    with output_directory(args.out, args.force) as staging:  # checked before any work
        scene = make_scene(config)
        write_scene(scene, staging)
        wrote = "data.npz, gt_tum.txt, landmarks.npz"
        if args.render:
            from ...synth.render import write_kitti_sequence
            from .. import console

            cal, frames = scene.config.calibration, scene.sequence.num_steps
            size_mb = PNG_BYTES_PER_PIXEL * 2 * cal.width * cal.height * frames / 1e6
            console.sayer(args.quiet)(f"rendering {frames} stereo pairs of {cal.width} x {cal.height}: "
                                      f"about {size_mb:.0f} MB of PNG images")
            with console.progress_bar(frames, "render", "frame", console.progress_off(args)) as progress:
                write_kitti_sequence(staging, scene, progress=progress)
            wrote += ", image_0/, image_1/, calib.txt, times.txt, poses.txt (KITTI odometry layout)"
    seq = scene.sequence
    if args.quiet:
        return 0
    print(f"{args.scenario} scene, seed {args.seed}: {seq.num_steps} steps, {seq.num_observations} observations "
          f"of {scene.landmark_ids.size} tracks; wrote {wrote} to {args.out}/")
    return 0
