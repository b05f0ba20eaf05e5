"""A real IMU: the inertial propagation on the real EuRoC V1_01 IMU record (1 s from the ground-truth
state over the moving flight: accuracy, consistency under two noise models, speed), and whole
`vislam run` processes on synthetic flights and drives with a real IMU and on the EuRoC slice.

    python benchmarks/inertial.py          (needs ../shared/euroc)

Prints Markdown tables for BENCHMARKS.md.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from vislam.backend.config import Config
from vislam.backend.data.inertial import ImuNoiseDensities
from vislam.backend.estimator import inertial as ine
from vislam.backend.run.initialization import initialize_at_rest
from vislam.frontend.euroc import read_euroc

MAV0 = Path(__file__).resolve().parents[1].parent / "shared" / "euroc" / "V1_01_easy_first40" / "mav0"
GRAVITY = np.array([0.0, 0.0, -9.81])
#: The runs whose fastest filter is reported (the machine's speed varies between runs)
RUNS = 2


def main() -> None:
    t_start = time.perf_counter()
    data = read_euroc(MAV0)
    imu, gt = data.imu.samples, data.ground_truth
    read_s = time.perf_counter() - t_start
    ini = initialize_at_rest(imu, gt.times[0], GRAVITY, imu.noise)
    up_true = gt.world_T_imu[0, :3, :3].T @ [0.0, 0.0, 1.0]
    tilt = np.degrees(np.arccos(np.clip(up_true @ ini.measured["gravity_in_imu"], -1, 1)))
    m = ini.measured
    models = {"sensor.yaml (datasheet)": imu.noise,
              "measured at rest (Z5)": ImuNoiseDensities(m["accelerometer_density_at_rest"],
                                                         imu.noise.accelerometer_random_walk,
                                                         m["gyroscope_density_at_rest"],
                                                         imu.noise.gyroscope_random_walk, "at rest")}
    print(f"EuRoC V1_01 ({imu.num_samples} IMU samples at {imu.rate_hz:.1f} Hz, read in {read_s:.2f} s). "
          f"At rest: gravity {tilt:.2f} deg from the ground truth's (reported +- {m['tilt_sigma_deg']:.2f} deg per "
          f"axis), gyro bias error {np.abs(ini.mean.gyro_bias - gt.gyro_bias[0]).max():.4f} rad/s; "
          f"densities at rest: gyro {m['gyroscope_density_at_rest']:.2e} rad/s/sqrt(Hz), accelerometer "
          f"{m['accelerometer_density_at_rest']:.2e} m/s^2/sqrt(Hz).\n")
    print("| noise densities | instants | position error median / p90 m | expected sqrt(tr Q_pos) median m "
          "| position NEES mean / median | inside 95 % | rotation error median deg | propagation s per s of IMU |")
    print("|---|---|---|---|---|---|---|---|")
    t = gt.times
    for name, noise in models.items():
        pos, nees, exp, rot = [], [], [], []
        spent, span = 0.0, 0.0
        for i in range(0, len(t) - 21, 10):
            if t[i] - t[0] < 6.0:
                continue
            T0 = gt.world_T_imu[i]
            start = ine.InertialMean(T0.copy(), gt.velocity[i].copy(), gt.gyro_bias[i].copy(), gt.accel_bias[i].copy())
            c = time.perf_counter()
            pred, prop = ine.propagate(start, imu, t[i], t[i + 20], noise, GRAVITY)
            spent += time.perf_counter() - c
            span += t[i + 20] - t[i]
            e = gt.world_T_imu[i + 20, :3, 3] - pred.world_T_imu[:3, 3]
            pos.append(np.linalg.norm(e))
            nees.append(e @ np.linalg.solve(prop.Q[:3, :3], e))
            exp.append(np.sqrt(np.trace(prop.Q[:3, :3])))
            rot.append(np.degrees(Rotation.from_matrix(gt.world_T_imu[i + 20, :3, :3].T @ pred.world_T_imu[:3, :3]).magnitude()))
        pos, nees = np.array(pos), np.array(nees)
        print(f"| {name} | {pos.size} | {np.median(pos):.4f} / {np.quantile(pos, 0.9):.4f} | {np.median(exp):.4f} | "
              f"{nees.mean():.2f} / {np.median(nees):.2f} | {np.mean(nees < 7.815) * 100:.0f} % | {np.median(rot):.3f} | "
              f"{spent / span * 1e3:.2f} ms ({span / spent:.0f}x real time) |")


def _vislam_run(data: str, out: Path, gt: str | None = None, *sets: str) -> tuple[float, dict, float]:
    """(wall seconds of the whole process, its summary.json, the path length of its trajectory in m) of
    ``vislam run data`` (``sets``: --set values)."""
    cmd = [sys.executable, "-m", "vislam.tools.cli", "run", data, "--out", str(out), "--no-progress", "--quiet"]
    if gt:
        cmd += ["--gt", gt]
    for value in sets:
        cmd += ["--set", value]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True)
    wall = time.perf_counter() - t0
    p = np.loadtxt(out / "trajectory.txt")[:, 1:4]
    return wall, json.loads((out / "summary.json").read_text()), float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def runs() -> None:
    """Whole processes: synthetic room flight and street drive (60 s; seeds 0-1 starting at rest, seed 0
    moving from the first frame) and the EuRoC slice, each with the default window of clones and with
    landmarks in the state; the fastest filter of ``RUNS``."""
    from vislam.synth.inertial_scene import InertialSceneConfig, make_inertial_scene, write_inertial_scene

    print("\n| input | state | start | frames | observations per frame | ATE m | dead reckoning ATE m | position NEES mean / "
          "inside 95 % | NIS | filter s (real-time factor) | whole process s (real-time factor) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        jobs = []
        for scenario in ("room", "street"):
            for seed, rest in ((0, 2.0), (1, 2.0), (0, None)):
                scene = make_inertial_scene(InertialSceneConfig(scenario=scenario, duration=60.0, seed=seed,
                                                                start_at_rest=rest))
                d = write_inertial_scene(scene, Path(tmp) / f"{scenario}{seed}{rest}")
                start = "at rest" if rest else "in motion"
                jobs.append((f"synthetic {scenario}, seed {seed}, 60 s, starting {start}", str(d / "data.npz"),
                             str(d / "gt_tum.txt")))
        jobs.append(("EuRoC V1_01 first 40 pairs (at rest, raw images)", str(MAV0), None))
        at_rest = []
        for i, (name, data, gt) in enumerate(jobs):
            for state, sets in ((f"window of {Config().estimator.window} clones (default)", ()),
                                ("landmarks", ("estimator.window=0",))):
                wall, s, path = min((_vislam_run(data, Path(tmp) / f"out{i}{state[0]}{k}", gt, *sets) for k in range(RUNS)),
                                    key=lambda x: x[1]["timing"]["filter_seconds"])
                _row(name, state, wall, s)
                if data == str(MAV0):
                    at_rest.append(f"{state} {1e3 * path:.1f} mm ({s['observations']['still_frames']} frames still)")
    gt = read_euroc(MAV0).ground_truth
    p = gt.world_T_imu[(gt.times >= gt.times[0]) & (gt.times <= gt.times[0] + 1.96), :3, 3]
    print(f"\nEuRoC's 40 pairs at rest: the path of the estimate {', '.join(at_rest)}; of the ground truth "
          f"{1e3 * np.linalg.norm(np.diff(p, axis=0), axis=1).sum():.1f} mm.")


def _row(name: str, state: str, wall: float, s: dict) -> None:
    e, t = s["errors"], s["timing"]
    nees = e["nees"]["position"]
    seconds = t["sequence_seconds"]
    init = s["decisions"]["initialization"]
    print(f"| {name} | {state} | {init['how']} | {s['steps']} | {s['observations']['valid'] / s['steps']:.0f} | "
          f"{e['estimate']['ate_rmse']:.4f} | {e['dead_reckoning']['ate_rmse']:.3f} | "
          f"{nees['mean']:.2f} / {100 * nees['share_inside_95']:.0f} % | {s['mean_nis_per_observation']:.2f} | "
          f"{t['filter_seconds']:.2f} ({seconds / t['filter_seconds']:.1f}x) | {wall:.2f} ({seconds / wall:.1f}x) |")


if __name__ == "__main__":
    main()
    runs()
