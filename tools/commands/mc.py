"""``vislam mc``: Monte Carlo consistency (NEES and NIS) of the filter on a synthetic scene.

``vislam mc --scenario street --runs 20 --steps 300 --out DIR`` runs the filter on ``runs`` noise
realizations of one scene (``backend.evaluation.consistency``) and writes ``consistency.json`` and
``nees.png``. The filter's noise defaults to the scene's (the filter on its own model);
``--config`` and ``--set TABLE.KEY=VALUE`` change the filter as for ``vislam run``.
"""

from __future__ import annotations

import argparse
import os
import sys

from ...backend.data.files import output_directory
from ...backend.errors import ConfigError
from .. import options, outputs


def add_parser(sub) -> None:
    p = sub.add_parser("mc", help="Monte Carlo consistency (NEES, NIS) of the filter on a synthetic scene")
    p.add_argument("--scenario", choices=["street", "aerial"], default="street")
    p.add_argument("--runs", type=int, default=20, help="noise realizations (default 20)")
    p.add_argument("--steps", type=int, default=300, help="steps per run (default 300)")
    p.add_argument("--seed", type=int, default=0,
                   help="geometry seed; run i uses the noise seed SEED+i (default 0)")
    p.add_argument("--landmark-density", type=float, default=1.0, help="scales the scene's landmark density")
    p.add_argument("--workers", type=int, default=None, help="worker processes (default: every core)")
    p.add_argument("--out", required=True, help="output directory (refused if non-empty, unless --force)")
    p.add_argument("--force", action="store_true", help="write into a non-empty output directory")
    options.add_config_options(p)
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from ...synth.scene import SceneConfig, check_scene_size
    from ..plots import plot_consistency

    if args.runs < 1:
        raise ConfigError(f"--runs must be >= 1, got {args.runs}")
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {args.workers}")
    scene_config = SceneConfig(scenario=args.scenario, steps=args.steps, seed=args.seed,
                               landmark_density=args.landmark_density)
    # the scene's noise (pixel, velocity; its tracks are exact: tracker "synthetic") < --config < --set
    config = options.filter_config(args, base=scene_config.filter_config())
    check_scene_size(scene_config)  # memory bounds, before any work
    with output_directory(args.out, args.force) as staging:  # checked before any work
        result = _monte_carlo(args, scene_config, config)
        outputs.write_json(staging / "consistency.json", result)
        plot_consistency(staging / "nees.png", result)
    print("\n".join(result.summary_lines()))
    return 0


def _monte_carlo(args: argparse.Namespace, scene_config, config):
    """The runs, on every core (or ``--workers``), with a progress bar."""
    from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

    from tqdm import tqdm

    from ...backend.evaluation.consistency import monte_carlo
    from ...synth.scene import SceneFactory

    workers = args.workers or os.cpu_count() or 1
    executor = (ProcessPoolExecutor(max_workers=min(workers, args.runs)) if workers > 1
                else ThreadPoolExecutor(max_workers=1))  # one worker: no process start-up
    print(f"vislam mc: {args.runs} runs of the {args.scenario} scene (geometry seed {args.seed}, {args.steps} steps), "
          f"noise seeds {args.seed}..{args.seed + args.runs - 1}, {workers} worker(s)", file=sys.stderr)
    bar = tqdm(total=args.runs, unit="run", file=sys.stderr, desc="monte carlo")
    try:
        result = monte_carlo(SceneFactory(scene_config), config, args.runs, seed0=args.seed, executor=executor,
                             progress=lambda done: bar.update(done - bar.n))
    finally:
        bar.close()
        executor.shutdown(wait=True, cancel_futures=True)
    return result
