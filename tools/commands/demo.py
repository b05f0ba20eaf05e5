"""``vislam demo``: a synthetic street scene, end to end: data and ground truth, SLAM, evaluation."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
import warnings

import numpy as np

from ...backend.errors import HealthWarning
from .. import console, outputs


def add_parser(sub) -> None:
    p = sub.add_parser("demo", help="synthetic street scene -> SLAM -> evaluation, every output (the README's first command)")
    p.add_argument("-o", "--out", default="vislam-demo", help="output directory (default ./vislam-demo)")
    p.add_argument("--seed", type=int, default=0, help="seed of the synthetic scene and its noise (default: 0)")
    p.add_argument("--force", action="store_true", help="write into a non-empty output directory (a previous demo's)")
    p.set_defaults(func=main)


def landmark_errors(scene, ids: np.ndarray, positions: np.ndarray, world_T_imu: np.ndarray, within: float = 20.0):
    """Median distance between mapped and true landmarks (by id), for landmarks first seen
    within ``within`` metres of the camera; and how many were compared."""
    true = dict(zip(scene.landmark_ids.tolist(), range(scene.landmark_ids.size)))
    rows = np.array([true.get(i, -1) for i in ids.tolist()], dtype=np.int64)
    ok = rows >= 0
    err = np.linalg.norm(positions[ok] - scene.landmark_positions[rows[ok]], axis=1)
    # distance to the nearest estimated pose as a proxy for "seen from within"
    path = world_T_imu[:, :3, 3]
    near = np.min(np.linalg.norm(scene.landmark_positions[rows[ok]][:, None] - path[None, ::5], axis=2), axis=1) <= within
    return (float(np.median(err[near])) if near.any() else float("nan")), int(near.sum())


def main(args: argparse.Namespace) -> int:
    from ...backend.data.files import output_directory
    from ..output_process import output_process
    from ..report import format_summary, print_health

    t0 = time.perf_counter()
    out = Path(args.out)
    # checked before any work; the helper writing figures and point clouds ends before the staging is removed
    with output_directory(args.out, args.force) as staging, output_process() as helper:
        summary, scene_dir, median_err, compared = _demo(args, staging, helper)
    print(format_summary(summary))
    print_health(summary)
    print(f"landmarks within 20 m: median error {median_err:.3f} m over {compared}")
    print(f"demo done in {time.perf_counter() - t0:.1f} s; outputs in {out}/ (scene and ground truth in {out / scene_dir}/)")
    return 0


def _demo(args: argparse.Namespace, out: Path, helper=None):
    from ...backend.run.runner import run_sequence
    from ...synth.scene import SceneConfig, make_scene, write_scene
    from ..report import write_run_outputs

    scene = make_scene(SceneConfig(scenario="street", seed=args.seed, landmark_density=0.5))
    scene_dir = out / "scene"
    scene_dir.mkdir()
    write_scene(scene, scene_dir)
    seq = scene.sequence
    print(f"demo: synthetic street, {seq.num_steps} steps, {seq.num_observations} observations, "
          f"velocity noise and gyro bias as configured in synth.scene.SceneConfig")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", HealthWarning)  # listed in the summary, shown by print_health
        # the default run: conventions, noise and drift decided from the data, as for any input
        result = run_sequence(seq, say=console.sayer(False))
    gt = (seq.time_stamps, scene.world_T_imu_true)
    summary = write_run_outputs(result, out, "synthetic:street", gt, helper=helper)
    median_err, compared = landmark_errors(scene, result.map_ids, result.map_positions, result.world_T_imu)
    summary["landmark_error_median_m_within_20m"] = median_err
    outputs.write_json(out / "summary.json", summary)
    return summary, scene_dir.name, median_err, compared
