"""``vislam synth``: a synthetic scene with ground truth, and optionally its rendered stereo images.

``--track-errors PRESET`` and ``--errors KEY=VALUE`` choose the observations' errors
(``synth.track_errors.TrackErrors``: preset < ``--errors``, applied in order).
"""

from __future__ import annotations

import argparse

from ...backend.errors import VislamError
from ...synth.track_errors import PRESETS, TrackErrors

#: PNG bytes per pixel of the rendered street at the renderer's compression level 1 (measured: 240 MB
#: for 500 pairs of 1241 x 376), for the size notice before rendering.
PNG_BYTES_PER_PIXEL = 0.52


def add_parser(sub) -> None:
    p = sub.add_parser("synth", help="make a synthetic scene with ground truth (feature file + gt_tum.txt)",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       epilog="track-error options for --errors, KEY (default): meaning\n  "
                              + "\n  ".join(TrackErrors.help_lines()))
    p.add_argument("--scenario", choices=["street", "aerial"], default="street")
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True)
    p.add_argument("--force", action="store_true")
    p.add_argument("--render", action="store_true", help="also render rectified stereo images (KITTI odometry layout)")
    p.add_argument("--track-errors", dest="track_errors", choices=sorted(PRESETS), default="none",
                   help="errors of the tracks: none (white pixel noise of 0.5 px only) or kitti-like ("
                        + ", ".join(f"{k}={v:g}" for k, v in PRESETS["kitti-like"].as_dict().items() if v)
                        + ") (default: none)")
    p.add_argument("--errors", action="append", default=[], metavar="KEY=VALUE",
                   help="one track-error option over the preset, e.g. drift_share=0.5 (repeatable; keys below)")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    p.add_argument("--no-progress", dest="no_progress", action="store_true", help="no progress bar")
    p.set_defaults(func=main)


def track_errors(args: argparse.Namespace) -> TrackErrors:
    """The preset of ``--track-errors`` with the ``--errors`` assignments applied (ConfigError naming the key)."""
    return PRESETS[args.track_errors].with_assignments(args.errors)


def main(args: argparse.Namespace) -> int:
    from ...backend.data.files import output_directory
    from ...synth.scene import SceneConfig, check_scene_size, make_scene, write_scene

    if args.render and args.scenario != "street":
        raise VislamError("--render: only the street scenario has a textured world so far")
    errors = track_errors(args)
    if args.render and errors.effects():
        raise VislamError(f"--render: rendered images do not show the track errors {', '.join(errors.effects())} "
                          f"(drift and bad tracks come from a tracker on images; repeats, jitter and a disparity "
                          f"offset are not rendered): drop --render or those options")
    config = SceneConfig(scenario=args.scenario, steps=args.steps, seed=args.seed,
                         track_errors=errors)  # refused before any work
    check_scene_size(config)
    with output_directory(args.out, args.force) as staging:  # checked before any work
        scene = make_scene(config)
        write_scene(scene, staging)
        wrote = "data.npz, gt_tum.txt, landmarks.npz"
        if errors.effects():
            wrote += ", scene.json, track_errors.npz"
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
    if errors.effects():
        print(f"track errors: {errors.describe()}; {track_error_summary(scene)}")
    return 0


def track_error_summary(scene) -> str:
    """What the scene's track errors drew, in one line (the numbers of scene.json)."""
    from ...synth.scene import scene_facts

    facts = scene_facts(scene)["track_errors"]
    speed = facts["drift_speed_px_per_step"]
    parts = [f"{len(facts['repeated_steps'])} repeated steps",
             f"{facts['drifting_tracks']} of {facts['tracks']} tracks drift"
             + (f" (median {speed['p50']:.3f}, 99th percentile {speed['p99']:.3f} px/step)" if speed else ""),
             f"{facts['bad_tracks']['jump']} jumping and {facts['bad_tracks']['fast']} fast bad tracks",
             f"disparity offset {facts['disparity_offset_px']:g} px",
             f"jitter rms {facts['jitter_rms']['rotation_rad']:.2g} rad, {facts['jitter_rms']['translation_m']:.2g} m"]
    return "; ".join(parts)
