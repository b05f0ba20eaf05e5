"""The inertial propagation on the real EuRoC V1_01 IMU record: accuracy of 1 s of propagation from
the ground-truth state over the moving flight, its consistency under two noise models, and speed.

    python benchmarks/inertial.py          (needs ../shared/euroc)

Prints a Markdown table for BENCHMARKS.md.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from vislam.backend.data.inertial import ImuNoiseDensities
from vislam.backend.estimator import inertial as ine
from vislam.backend.run.initialization import initialize_at_rest
from vislam.frontend.euroc import read_euroc

MAV0 = Path(__file__).resolve().parents[1].parent / "shared" / "euroc" / "V1_01_easy_first40" / "mav0"
GRAVITY = np.array([0.0, 0.0, -9.81])


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


if __name__ == "__main__":
    main()
