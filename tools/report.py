"""Everything `vislam run` writes into its output directory, and the summary it prints.

| file | content |
|---|---|
| trajectory.txt | TUM `t tx ty tz qx qy qz qw`, world_T_imu, the data's own stamps (evo reads it) |
| dead_reckoning.txt | the same for IMU-only dead reckoning |
| pose_covariance.npz | `time_stamps` (N,), the trajectory's, and `covariance` (N,6,6) of xi = [rho; phi], world_T_imu = mu exp(xi^) (body frame) |
| imu_states.txt | a real IMU's run: `t vx vy vz bgx bgy bgz bax bay baz` per step, world velocity (m/s), gyro (rad/s) and accelerometer (m/s^2) biases |
| map.npz | `ids`, `positions` (K,3), `covariances` (K,3,3) |
| map.ply | landmarks coloured by uncertainty (viridis on log10 of the largest sigma: dark = certain, yellow = uncertain) |
| trajectory.ply | the path as a line set coloured by time |
| trajectory.png | top-down plot: estimate, dead reckoning, landmarks; with ground truth each SE(3)-aligned to it (title: ATE RMSE) and the ground truth over the run's time span |
| ate_over_time.png | with ground truth: position error of each pose after SE(3) alignment, estimate and dead reckoning |
| summary.json | counts, timings, decisions, configuration and (with ground truth) errors: ATE, RPE, NEES |
| config.toml | the configuration used (every table; [tracker] from images), loadable with --config |
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..backend.data.covariance import POSE_COVARIANCE_FILE, TRAJECTORY_FILE, write_pose_covariance
from ..backend.data.files import atomic_write
from ..backend.data.tum import write_tum
from ..backend.evaluation.consistency import trajectory_nees
from ..backend.evaluation.metrics import trajectory_errors
from ..backend.run.online import RunResult
from . import clock, outputs, plots


def evaluate(result: RunResult, gt_t: np.ndarray, gt_poses: np.ndarray) -> dict:
    """ATE (SE(3)-aligned) and RPE of the estimate and of dead reckoning against ground truth, and the
    NEES of the estimate's pose covariance (``backend.evaluation.consistency.trajectory_nees``; an
    inertial run's world is gravity-aligned: only the first pose's yaw and position are removed)."""
    est = trajectory_errors(result.time_stamps, result.world_T_imu, gt_t, gt_poses)
    dr = trajectory_errors(result.time_stamps, result.dead_reckoning, gt_t, gt_poses)
    nees = trajectory_nees(result.time_stamps, result.world_T_imu, result.pose_covariance, gt_t, gt_poses,
                           gravity_aligned=result.inertial)
    return {"estimate": est.as_dict(), "dead_reckoning": dr.as_dict(), "nees": nees.as_dict()}


def summary_dict(result: RunResult, source: str, errors: Optional[dict] = None, tracker=None) -> dict:
    stats = result.stats
    config = result.config.as_dict()
    if tracker is not None:
        config[tracker.TABLE] = tracker.as_dict()
    summary = {
        "input": source,
        "mode": result.config.estimator.mode.value,
        "steps": stats.steps,
        "observations": {
            "valid": stats.observations,
            "used": stats.observations_used,
            "gated": stats.observations_gated,
            "gated_share": stats.gated_share,
            "dropped_by_loader": stats.observations_dropped_input,
            "repeated_frames": stats.repeated_frames,
            "still_frames": stats.still_frames,
        },
        "landmarks": {
            "initialized": stats.landmarks_initialized,
            "dropped_as_outliers": stats.landmarks_dropped,
            "tracks_rejected_by_test": stats.tracks_rejected,
            "reanchored": stats.landmarks_reanchored,
            "frozen_steps": stats.frozen_steps,
            "mapped": stats.landmarks_mapped,
            "active_mean": stats.active_landmarks_mean,
            "active_max": stats.active_landmarks_max,
        },
        "mean_nis_per_observation": stats.mean_nis,
        "expected_nis_per_observation": stats.nis_expected,
        "scale_against_imu": None if stats.scale is None else stats.scale.as_dict(),
        "gyro_bias_final": result.gyro_bias,
        "disparity_offset_final": None if result.disparity_offset is None else result.disparity_offset.as_dict(),
        "lever_arm_final": None if result.lever_arm is None else result.lever_arm.as_dict(),
        **({"accel_bias_final": result.accel_biases[-1], "velocity_final": result.velocity[-1]} if result.inertial else {}),
        "timing": {
            "run_seconds": stats.total_seconds,
            "filter_seconds": stats.filter_seconds,
            "load_seconds": stats.load_seconds,
            "input_seconds": stats.input_seconds,
            "setup_seconds": stats.setup_seconds,
            "kernel_seconds": stats.kernel_seconds,
            "predict_seconds": stats.seconds_predict,
            "update_seconds": stats.seconds_update,
            "bookkeeping_seconds": stats.seconds_bookkeeping,
            "sequence_seconds": stats.sequence_seconds,
            "real_time_factor": stats.real_time_factor,
            "step_ms": {"median": stats.step_ms_median, "p99": stats.step_ms_p99, "max": stats.step_ms_max},
        },
        "decisions": result.decisions.as_dict(),
        "health": stats.health_messages,
        "config": config,
    }
    if errors is not None:
        summary["errors"] = errors
    return summary


def write_run_outputs(
    result: RunResult,
    out_dir: Path,
    source: str,
    gt: Optional[tuple[np.ndarray, np.ndarray]] = None,
    tracker=None,
    notes: Sequence[str] = (),
    helper=None,
) -> dict:
    """Write every output file (each atomically) and return the summary dict; ``tracker``: the
    front end's options of a run from images (recorded in summary.json and config.toml);
    ``notes``: what the readers accepted with a remark (listed in summary.json); ``helper``: a
    ``tools.output_process.OutputProcess`` that writes the PNG and PLY files meanwhile (None: here)."""
    t0 = time.perf_counter()
    curves = {"estimate": (result.time_stamps, result.world_T_imu),
              "dead reckoning": (result.time_stamps, result.dead_reckoning)}
    slow = [(outputs.write_map_ply, (out_dir / "map.ply", result.map_positions, result.map_covariances), {}),
            (plots.plot_trajectories_topdown, (out_dir / "trajectory.png", curves, gt, result.map_positions),
             {"title": f"{Path(source).name}: {result.config.estimator.mode}"})]
    if gt is not None:
        slow.append((plots.write_error_plot, (out_dir / "ate_over_time.png", curves, *gt), {}))
    slow.append((outputs.write_trajectory_ply, (out_dir / "trajectory.ply", result.world_T_imu, result.time_stamps), {}))
    if helper is not None:
        for function, args, kwargs in slow:
            helper.submit(function, *args, **kwargs)
    errors = evaluate(result, *gt) if gt is not None else None
    notes = list(notes)
    write_tum(out_dir / TRAJECTORY_FILE, result.time_stamps, result.world_T_imu,
                      header="world_T_imu estimated by vislam")
    write_tum(out_dir / "dead_reckoning.txt", result.time_stamps, result.dead_reckoning,
                      header="world_T_imu by IMU dead reckoning")
    write_pose_covariance(out_dir / POSE_COVARIANCE_FILE, result.time_stamps, result.pose_covariance)
    if result.inertial:
        outputs.write_imu_states(out_dir / "imu_states.txt", result.time_stamps, result.velocity, result.gyro_biases,
                                 result.accel_biases)
    outputs.write_map_npz(out_dir / "map.npz", result.map_ids, result.map_positions, result.map_covariances)
    written = helper.results() if helper is not None else [f(*args, **kwargs) for f, args, kwargs in slow]
    if not written[0]:  # write_map_ply's answer
        notes.append("no landmark was mapped: map.ply not written (map.npz is empty)")
    summary = summary_dict(result, source, errors, tracker)
    summary["notes"] = notes
    summary["timing"].update(process_timing(summary["timing"], time.perf_counter() - t0))
    outputs.write_json(out_dir / "summary.json", summary)
    toml = result.config.to_toml() + ("\n" + tracker.to_toml() if tracker is not None else "")
    with atomic_write(out_dir / "config.toml") as tmp:
        tmp.write_text(toml)
    return summary


def process_timing(timing: dict, outputs_seconds: float) -> dict:
    """The whole command's figures beside a run's parts (``timing`` of :func:`summary_dict`): the wall
    seconds the user waited up to the summary (``tools.clock``: from the process's start for the
    ``vislam`` command, start-up and imports included), the start-up before the command (None when
    not counted), the outputs, and the real-time factor of the whole."""
    whole = clock.process_seconds()
    return {
        "process_seconds": whole,
        "startup_seconds": clock.startup_seconds(),
        "outputs_seconds": outputs_seconds,
        "process_real_time_factor": timing["sequence_seconds"] / max(whole, 1e-9),
    }


def real_time_text(factor: float) -> str:
    """A real-time factor as the user reads it: whole above 10, one decimal above 1, two below."""
    if not math.isfinite(factor):
        return "n/a"
    return f"{factor:.0f}x" if factor >= 10 else f"{factor:.1f}x" if factor >= 1 else f"{factor:.2f}x"


def nees_text(summary: dict, what: str) -> str:
    """One line of a NEES summary (``NeesSummary.as_dict()``; ``what``: "position" or "pose")."""
    dof, steps, skipped = summary["dof"], summary["steps"], summary["skipped_steps"]
    head = f"{what} NEES ({dof} dof)"
    if not steps:
        return (f"{head}: no step to count: the pose covariance is zero at all {skipped} matched steps "
                "(held fixed: dead reckoning or mapping)")
    share = summary["share_inside_95"]
    line = (f"{head}: mean {_number(summary['mean'])}, median {_number(summary['median'])}, "
            f"{100 * share:.1f} % inside the 95 % ellipsoid (<= {summary['quantile_95']:.2f}); expected {dof} "
            f"and 95 %; {steps} steps ({skipped} skipped at the start: the reference pose, zero covariances)")
    if summary["infinite_steps"]:
        line += f"; {summary['infinite_steps']} steps with a singular covariance (NEES inf)"
    return line


def _number(value) -> str:
    """A mean or median read back from JSON, where inf became null."""
    return "inf" if value is None else f"{value:.2f}"


def _nis_text(mean_nis: float, expected: float = 4.0) -> str:
    if not math.isfinite(mean_nis):
        return "n/a (no observation used)"
    return f"{mean_nis:.2f}" + ("" if expected == 4.0 else f" (expected {expected:.2f}: the window's features)")


def _timing_text(t: dict) -> str:
    """The time a user waited (the whole process, when known) and its parts."""
    if "process_seconds" not in t:
        return (f"run {t['run_seconds']:.2f} s for {t['sequence_seconds']:.1f} s of data "
                f"({real_time_text(t['real_time_factor'])} real time)")
    startup = t.get("startup_seconds")
    parts = {"start-up": startup or 0.0, "kernels": t["kernel_seconds"],
             "input": t["load_seconds"] + t["input_seconds"], "decisions": t["setup_seconds"],
             "filter": t["filter_seconds"], "outputs": t["outputs_seconds"]}
    parts["imports on the way"] = max(t["process_seconds"] - sum(parts.values()), 0.0)
    if startup is None:
        del parts["start-up"]
    return (f"{t['process_seconds']:.2f} s for {t['sequence_seconds']:.1f} s of data "
            f"({real_time_text(t['process_real_time_factor'])} real time; "
            + ", ".join(f"{name} {seconds:.2f}" for name, seconds in parts.items()) + " s)")


def format_summary(summary: dict, out_dir: Optional[Path] = None) -> str:
    """A few lines for the terminal (the health warnings go apart, to stderr: :func:`print_health`)."""
    t = summary["timing"]
    obs = summary["observations"]
    lm = summary["landmarks"]
    lines = [
        f"steps {summary['steps']}, observations used {obs['used']} (gated {100 * obs['gated_share']:.1f} %), "
        f"landmarks mapped {lm['mapped']} (active mean {lm['active_mean']:.1f}, max {lm['active_max']})",
        _timing_text(t) + "; mean NIS per observation " + _nis_text(summary['mean_nis_per_observation'],
                                                                    summary.get('expected_nis_per_observation', 4.0)),
    ]
    if obs.get("still_frames"):
        lines.append(f"standing still at {obs['still_frames']} of {summary['steps']} frames (the tracks, the IMU and the "
                     "filter's velocity agreed): v = 0 measured there (update.zero_velocity)")
    if lm.get("tracks_rejected_by_test"):
        lines.append(f"the per-track test rejected {lm['tracks_rejected_by_test']} tracks (their innovations kept one "
                     "direction beyond drift.track_test_probability, R4): their landmarks dropped, their later "
                     "observations not used")
    if t.get("kernel_seconds", 0.0) >= 2.0:
        where = "counted above as kernels" if "process_seconds" in t else "not in the wall time above"
        lines.append(f"compiled the filter's kernels in {t['kernel_seconds']:.1f} s first (once after an install; "
                     f"cached for later runs; {where})")
    if "errors" in summary:
        e, d = summary["errors"]["estimate"], summary["errors"]["dead_reckoning"]
        lines.append(
            f"ATE RMSE (SE(3)-aligned): estimate {e['ate_rmse']:.2f} m, dead reckoning {d['ate_rmse']:.2f} m "
            f"over {e['path_length']:.0f} m; {rpe_label(e)}: "
            f"{e['rpe_trans_rmse']:.2f} m / {e['rpe_rot_rmse_deg']:.2f} deg"
        )
        if "nees" in summary["errors"]:
            lines.append(nees_text(summary["errors"]["nees"]["position"], "position"))
    for note in summary.get("notes", []):
        lines.append(f"note: {note}")
    if out_dir is not None:
        lines.append(f"outputs in {out_dir}/")
    return "\n".join(lines)


def path_labels(paths: list[str]) -> dict[str, str]:
    """A short label per path (inputs of ``batch``, estimates of ``eval``): its file name, with as many
    parent folders as it takes to tell files of the same name apart (``a/0027.npz``, ``b/0027.npz``)."""
    unique = list(dict.fromkeys(paths))
    parts = {p: Path(p).parts or (p,) for p in unique}
    depth = max(len(v) for v in parts.values()) if parts else 1
    for k in range(1, depth + 1):
        labels = {p: "/".join(parts[p][-k:]) for p in unique}
        if len(set(labels.values())) == len(unique):
            return labels
    return {p: p for p in unique}


def file_stem(label: str) -> str:
    """``label`` as a file or folder name: characters other than letters, digits and ``._=+-``
    replaced by '_' ("" becomes "_")."""
    import re

    return re.sub(r"[^A-Za-z0-9._=+-]", "_", label) or "_"


def rpe_label(errors: dict, requested_m: float = 100.0) -> str:
    """'RPE per 100 m', or where the ground truth's path was shorter than the ``requested_m`` metres
    of a segment (``backend.evaluation.metrics`` then counts frames) 'RPE per 10 frames (the ground
    truth's path, 45 m, is shorter than 100 m)'."""
    label = f"RPE per {errors['rpe_delta']:g} {errors['rpe_unit']}"
    if errors["rpe_unit"] == "frames":
        label += (f" (the ground truth's path, {errors['path_length']:.0f} m, is shorter than the {requested_m:g} m "
                  "segments asked for, or has no pair that far apart)")
    return label


def print_health(summary: dict) -> None:
    """The run's health warnings, a line each on stderr (shown with --quiet too: they say the result
    is not what was asked for)."""
    print_warnings(summary["health"])


def print_warnings(messages: Sequence[str]) -> None:
    """Warnings, a line each on stderr ("warning: ...")."""
    import sys

    for message in messages:
        print(f"warning: {message}", file=sys.stderr)
