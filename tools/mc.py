"""`vislam mc`: Monte Carlo consistency (NEES and NIS) of the filter on a synthetic scene.

``vislam mc --scenario street --runs 20 --steps 300 --out DIR`` runs the filter on ``runs`` noise
realizations of one scene (backend.consistency) and writes ``consistency.json`` and ``nees.png``.
The filter's pixel_sigma defaults to the scene's (the filter on its own model); ``--config`` and
``--set KEY=VALUE`` change the filter as for ``vislam run``.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

__all__ = ["add_parsers", "cmd_mc", "plot_consistency"]


def _filter_config(args: argparse.Namespace, scene_config):
    """Defaults with the scene's noise (pixel, velocity; its tracks are exact: tracker "synthetic") < --config TOML < --set KEY=VALUE."""
    from backend.config import apply_overrides, load_config

    base = scene_config.filter_config()
    config = load_config(args.config, base) if getattr(args, "config", None) else base
    return apply_overrides(config, list(getattr(args, "set", None) or [])).validate()


def plot_consistency(path: str | os.PathLike, result) -> None:
    """Two panels over the steps: the run-averaged pose NEES with its 95 % band (log y), and the
    NIS per observation with its band for one step's observations of all runs."""
    from tools.plots import _new_figure, _save

    steps = np.arange(result.steps)
    fig = _new_figure((9.0, 6.5))
    ax = fig.add_subplot(2, 1, 1)
    lo, hi = result.pose_nees_band
    nees = np.asarray(result.pose_nees_mean, dtype=float)
    positive = nees > 0
    ax.plot(steps[positive], nees[positive], color="tab:blue", linewidth=1.0,
            label=f"pose NEES, average of {result.runs} runs")
    ax.axhspan(lo, hi, color="tab:green", alpha=0.2, label=f"95 % band [{lo:.2f}, {hi:.2f}]")
    ax.axhline(6.0, color="tab:green", linewidth=0.8, linestyle="--", label="expectation 6")
    ax.axvline(result.skip, color="0.5", linewidth=0.6, linestyle=":")
    ax.set_yscale("log")
    ax.set_ylabel("pose NEES (6 dof)")
    ax.set_title(f"{100 * result.pose_nees_in_band:.0f} % of steps {result.skip}..{result.steps - 1} in the band")
    ax.grid(True, which="both", linewidth=0.3)
    ax.legend(loc="best", fontsize="small")

    ax = fig.add_subplot(2, 1, 2, sharex=ax)
    nis = np.asarray(result.nis_per_step, dtype=float)
    ax.plot(steps, nis, color="tab:purple", linewidth=0.8, label="NIS per observation (all runs)")
    ax.axhline(4.0, color="tab:green", linewidth=0.8, linestyle="--", label="expectation 4")
    nlo, nhi = result.nis_band
    ax.axhline(result.nis_mean, color="tab:red", linewidth=0.8,
               label=f"mean {result.nis_mean:.3f} (band [{nlo:.3f}, {nhi:.3f}])")
    ax.set_xlabel("step")
    ax.set_ylabel("NIS / observation (4 dof)")
    ax.grid(True, linewidth=0.3)
    ax.legend(loc="best", fontsize="small")
    fig.tight_layout()
    _save(fig, path)


def cmd_mc(args: argparse.Namespace) -> int:
    from backend.consistency import monte_carlo
    from backend.errors import ConfigError
    from synth.scene import SceneConfig
    from tools import outputs

    if args.runs < 1:
        raise ConfigError(f"--runs must be >= 1, got {args.runs}")
    if getattr(args, "workers", None) is not None and args.workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {args.workers}")
    scene_config = SceneConfig(
        scenario=args.scenario,
        steps=args.steps,
        seed=args.seed,
        landmark_density=getattr(args, "landmark_density", 1.0),
    )
    config = _filter_config(args, scene_config)
    out = outputs.prepare_output_dir(args.out, args.force)
    workers = getattr(args, "workers", None) or os.cpu_count() or 1
    executor = None
    if workers > 1:
        from concurrent.futures import ProcessPoolExecutor

        executor = ProcessPoolExecutor(max_workers=min(workers, args.runs))
    else:
        from concurrent.futures import ThreadPoolExecutor  # one worker: no process start-up

        executor = ThreadPoolExecutor(max_workers=1)

    from tqdm import tqdm

    print(f"vislam mc: {args.runs} runs of the {args.scenario} scene (geometry seed {args.seed}, {args.steps} steps), "
          f"noise seeds {args.seed}..{args.seed + args.runs - 1}, {workers} worker(s)", file=sys.stderr)
    bar = tqdm(total=args.runs, unit="run", file=sys.stderr, desc="monte carlo")
    try:
        result = monte_carlo(scene_config, config, args.runs, seed0=args.seed, executor=executor,
                             progress=lambda done: bar.update(done - bar.n))
    finally:
        bar.close()
        executor.shutdown(wait=True, cancel_futures=True)
    outputs.write_json(out / "consistency.json", result)
    plot_consistency(out / "nees.png", result)
    print("\n".join(result.summary_lines()))
    return 0


def add_parsers(sub) -> None:
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
    p.add_argument("--config", metavar="TOML", help="filter configuration file")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override one filter config key (repeatable); pixel_sigma defaults to the scene's")
    p.set_defaults(func=cmd_mc)


if __name__ == "__main__":  # pragma: no cover
    sys.exit("use the vislam command")
