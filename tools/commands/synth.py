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
    p.add_argument("--scenario", choices=["street", "aerial", "room"], default=None,
                   help="street or aerial (body velocities), room or street with --imu inertial (default: street)")
    p.add_argument("--steps", type=int, default=500, help="steps of a velocity scene (default: 500)")
    p.add_argument("--seed", type=int, default=0, help="seed of the trajectory and the points (default: 0)")
    p.add_argument("--imu", choices=["velocity", "inertial"], default="velocity",
                   help="velocity: body velocities per step (the course layout); inertial: a real IMU's samples "
                        "(200 Hz ADIS16448-like, random-walk biases, 2 s at rest at the start; 20 Hz tracks at 0.5 px, "
                        "2 %% outliers) in the inertial layout (default: velocity)")
    p.add_argument("--duration", type=float, default=60.0, help="seconds of an inertial scene (default: 60)")
    p.add_argument("-o", "--out", required=True, help="output directory (refused if non-empty, unless --force)")
    p.add_argument("--force", action="store_true", help="write into a non-empty output directory")
    p.add_argument("--render", action="store_true", help="also render rectified stereo images of the street: the KITTI "
                                                         "odometry layout; with --imu inertial an EuRoC ASL folder mav0/ "
                                                         "(images, IMU samples, ground truth) that vislam run reads")
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

    if args.imu == "inertial":
        return _inertial(args)
    args.scenario = args.scenario or "street"
    if args.scenario == "room":
        raise VislamError("--scenario room: a scene with a real IMU's samples: add --imu inertial")

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


def _inertial(args: argparse.Namespace) -> int:
    """``--imu inertial``: a flight (room) or drive (street) with a real IMU's samples (``synth.inertial_scene``)."""
    from ...backend.data.files import output_directory
    from ...synth.inertial_scene import (InertialSceneConfig, check_inertial_scene, make_inertial_scene,
                                         write_inertial_scene)

    scenario = args.scenario or "room"
    check_inertial_scene(scenario, args.duration)
    if args.track_errors != "none" or args.errors:
        raise VislamError("--imu inertial: no --track-errors or --errors yet (white pixel noise and outliers)")
    if args.render and scenario != "street":
        raise VislamError("--render: only the street scenario has a textured world so far")
    config = InertialSceneConfig(scenario=scenario, duration=args.duration, seed=args.seed)
    wrote = "data.npz (inertial layout), gt_tum.txt, gt_states.npz, landmarks.npz"
    with output_directory(args.out, args.force) as staging:
        scene = make_inertial_scene(config)
        write_inertial_scene(scene, staging)
        if args.render:
            from ...synth.asl import write_euroc_folder
            from .. import console

            frames = scene.sequence.num_steps
            console.sayer(args.quiet)(f"rendering {frames} stereo pairs into an EuRoC ASL folder (mav0/)")
            with console.progress_bar(frames, "render", "frame", console.progress_off(args)) as progress:
                write_euroc_folder(scene, staging, progress=progress)
            wrote += (", mav0/ (EuRoC ASL layout: the rendered pairs, the IMU's samples, the ground truth; "
                      f"vislam run {args.out}/mav0)")
    seq = scene.sequence
    if not args.quiet:
        print(f"{scenario} scene with a real IMU, seed {args.seed}: {seq.num_steps} frames at {config.frame_rate:g} Hz, "
              f"{seq.imu.num_samples} IMU samples at {config.imu_rate:g} Hz, {seq.num_observations} observations of "
              f"{seq.num_features} tracks; wrote {wrote} to {args.out}/")
    return 0
