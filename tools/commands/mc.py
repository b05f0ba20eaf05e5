"""``vislam mc``: Monte Carlo consistency (NEES and NIS) of the filter on a synthetic scene.

``vislam mc --scenario street --runs 20 --steps 300 --out DIR`` runs the filter on ``runs`` noise
realizations of one scene (``backend.evaluation.consistency``) and writes ``consistency.json`` and
``nees.png``; a warning line is printed when the landmark NEES mean lies outside the 95 % band of
the run average (:func:`landmark_nees_check`). The filter decides its noise from each run's data,
as ``vislam run`` does (``--true-noise``: told the scene's own noise instead, the filter on its own
model); ``--config`` and ``--set TABLE.KEY=VALUE`` change the filter as for ``vislam run``.
"""

from __future__ import annotations

import argparse
import math
import os

from ...backend.data.files import output_directory
from ...backend.errors import ConfigError
from .. import console, options, outputs


#: The most runs of one Monte Carlo: the band of a mean NEES is already 1 % wide at 10 000 runs
MAX_RUNS = 100_000


def add_parser(sub) -> None:
    p = sub.add_parser("mc", help="Monte Carlo consistency (NEES, NIS) of the filter on a synthetic scene")
    p.add_argument("--scenario", choices=["street", "aerial", "room"], default=None,
                   help="street or aerial (body velocities), room or street with --imu inertial (default: street; "
                        "room with --imu inertial)")
    p.add_argument("--imu", choices=["velocity", "inertial"], default="velocity",
                   help="velocity: body velocities per step; inertial: a real IMU's samples (vislam synth --imu "
                        "inertial's scenes without gross outliers, the accelerometer bias drawn from the filter's "
                        "prior each run)")
    p.add_argument("--runs", type=int, default=20, help="noise realizations (default 20)")
    p.add_argument("--steps", type=int, default=300, help="steps per run of a velocity scene (default 300)")
    p.add_argument("--duration", type=float, default=10.0, help="seconds per run of an inertial scene (default 10)")
    p.add_argument("--seed", type=int, default=0,
                   help="geometry seed; run i uses the noise seed SEED+i (default 0)")
    p.add_argument("--landmark-density", type=float, default=1.0, help="scales the scene's landmark density")
    p.add_argument("--workers", type=int, default=None, help="worker processes (default: every core)")
    p.add_argument("--ray", metavar="ADDRESS", help="run on a Ray cluster ('auto', 'ray://host:port', or 'local')")
    p.add_argument("--true-noise", dest="true_noise", action="store_true",
                   help="tell the filter the scene's pixel and velocity noise (default: identified from each run's data)")
    p.add_argument("-o", "--out", required=True, help="output directory (refused if non-empty, unless --force)")
    p.add_argument("--force", action="store_true", help="write into a non-empty output directory")
    options.add_config_options(p)
    console.add_verbosity_options(p)
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from ...synth.scene import SceneConfig, SceneFactory, check_scene_size
    from ..plots import plot_consistency

    if not 1 <= args.runs <= MAX_RUNS:
        raise ConfigError(f"--runs must be from 1 to {MAX_RUNS}, got {args.runs}")
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {args.workers}")
    if args.imu == "inertial":
        from ...synth.inertial_scene import InertialSceneConfig, InertialSceneFactory, check_inertial_scene

        args.scenario = args.scenario or "room"
        check_inertial_scene(args.scenario, args.duration)
        if args.true_noise:
            raise ConfigError("--imu inertial: no --true-noise (the noise is decided from each run's data)")
        # no gross outliers: a landmark started from one (its track's first observation) would enter the
        # map's NEES with a position nothing supports; the filter's own model is what is tested here
        factory = InertialSceneFactory(InertialSceneConfig(scenario=args.scenario, duration=args.duration,
                                                           seed=args.seed, outlier_share=0.0))
        config = options.filter_config(args)
    else:
        args.scenario = args.scenario or "street"
        if args.scenario == "room":
            raise ConfigError("--scenario room: a scene with a real IMU's samples: add --imu inertial")
        scene_config = SceneConfig(scenario=args.scenario, steps=args.steps, seed=args.seed,
                                   landmark_density=args.landmark_density)
        # the noise identified from the data (or the scene's own, --true-noise) < --config < --set
        config = options.filter_config(args, base=scene_config.filter_config() if args.true_noise else None)
        check_scene_size(scene_config)  # memory bounds, before any work
        factory = SceneFactory(scene_config)
    with output_directory(args.out, args.force) as staging:  # checked before any work
        result = _monte_carlo(args, factory, config)
        check = landmark_nees_check(result)
        data = result.as_dict()
        data["landmark_nees"].update(check)
        outputs.write_json(staging / "consistency.json", data)
        notes = (pose_nees_line(result), landmark_nees_line(result, check))
        plot_consistency(staging / "nees.png", result, notes=notes)
    if not args.quiet:
        print("\n".join(summary_lines(result, check)))
    return 0


def landmark_nees_check(result) -> dict:
    """The landmark NEES average against the 95 % band of the average of one chi2(3) value per run.

    A run's landmarks share the pose errors they were seen with, so each run counts as one
    independent sample: the band is the pose NEES band's construction with 3 dof and R runs
    (``consistency.average_band(3, R)``), wider than the band of all landmarks as if independent.

    Parameters
    ----------
    result : ``backend.evaluation.consistency.ConsistencyResult``

    Returns
    -------
    dict
        ``expectation`` (3), ``band_of_run_average`` [lo, hi] and ``in_band_of_run_average``
        (bool; None without mapped landmarks), for consistency.json's ``landmark_nees``.
    """
    from ...backend.evaluation.consistency import average_band

    lo, hi = average_band(3, int(result.runs))
    mean = float(result.landmark_nees_mean)
    in_band = bool(lo <= mean <= hi) if result.landmark_count > 0 and math.isfinite(mean) else None
    return {"expectation": 3.0, "band_of_run_average": [lo, hi], "in_band_of_run_average": in_band}


def pose_nees_line(result) -> str:
    """One line (the plot's note): the pose NEES's time average and the verdict of the runs' time
    averages (E1 of ``backend.evaluation.consistency``), as on the screen."""
    return f"pose NEES time average {result.pose_nees_time_average:.2f}; {result.pose_nees_verdict()}"


def landmark_nees_line(result, check: dict) -> str:
    """One line (the plot's note): the landmark NEES mean and its verdict, as on the screen."""
    if check["in_band_of_run_average"] is None:
        return "landmark NEES: no landmark mapped"
    from ...backend.evaluation.consistency import consistency_verdict

    return (f"landmark NEES mean {result.landmark_nees_mean:.2f}; "
            + consistency_verdict(3.0, result.per_run_landmark_nees, "the map's covariances"))


def summary_lines(result, check: dict) -> list[str]:
    """``result.summary_lines()``, then a warning when the landmark NEES is outside its run-average band."""
    lines = list(result.summary_lines())
    if check["in_band_of_run_average"] is False:
        lo, hi = check["band_of_run_average"]
        state = ("the map's covariances are too small (overconfident)" if result.landmark_nees_mean > hi
                 else "the map's covariances are too large (pessimistic)")
        lines.append(f"warning: landmark NEES mean {result.landmark_nees_mean:.2f} is outside the 95 % band "
                     f"[{lo:.2f}, {hi:.2f}] of the {result.runs}-run average of chi2(3) (expectation 3): {state}")
    return lines


def _monte_carlo(args: argparse.Namespace, factory, config):
    """The runs, on every core (or ``--workers``) or a Ray cluster (``--ray``), with a progress bar."""
    from concurrent.futures import ThreadPoolExecutor
    from contextlib import nullcontext

    from ...backend.evaluation.consistency import monte_carlo
    from ...backend.estimator.window import window_in_use
    from ..pool import compile_for_workers, executor

    workers = args.workers or os.cpu_count() or 1
    where = f"Ray at {args.ray}" if args.ray else f"{workers} worker(s)"
    console.sayer(args.quiet)(
        f"vislam mc: {args.runs} runs of the {args.scenario} scene (geometry seed {args.seed}, "
        + (f"{args.duration:g} s, a real IMU" if args.imu == "inertial" else f"{args.steps} steps") + "), "
        f"noise seeds {args.seed}..{args.seed + args.runs - 1}, {where}\n" + console.configuration_text(args.verbose, config))
    one_thread = workers == 1 and not args.ray  # one worker: no process start-up
    if not one_thread and not args.ray:
        inertial = args.imu == "inertial"
        compile_for_workers(console.sayer(args.quiet), inertial=inertial, window=window_in_use(config, inertial))
    pool = nullcontext(ThreadPoolExecutor(max_workers=1)) if one_thread else executor(args.workers, args.ray, args.runs)
    with pool as runner, console.progress_bar(args.runs, "monte carlo", "run", console.progress_off(args)) as progress:
        done = [0]

        def advance(finished: int) -> None:
            while done[0] < finished:
                done[0] += 1
                progress(done[0])

        try:
            result = monte_carlo(factory, config, args.runs, seed0=args.seed, executor=runner,
                                 progress=advance)
        finally:
            if one_thread:
                runner.shutdown(wait=True, cancel_futures=True)
    return result
