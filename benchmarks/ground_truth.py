"""Does the ground truth agree with the sensors? The premise of every NEES figure, checked.

A run's NEES is its covariance against ground truth; where the ground truth itself disagrees with
the sensors, no honest filter meets it. This script measures each drive's ground truth against two
independent sources, step by step:

- the tracks alone: the two-view fit (D2 of ``backend.run.two_view``) of every ordinary step pair
  (k, k+1) with 12 points or more (pairs at a repeated frame left out: ``backend.run.timing``), its
  camera motion taken to the IMU frame by the file's extrinsic;
- the IMU alone: the step's rotation exp(w dt) and translation v dt of the samples, stamped as the
  convention test decides (C1), with no bias removed.

Each is compared with the ground truth's relative pose of the same steps: the ratio of rotation
angles (a least-squares slope through the origin, over the steps turning more than 0.5 deg, of the
measured rotation's component along the truth's axis on the truth's angle; a constant gyro bias
averages out over left and right turns) and of translation lengths, each with its standard error. Synthetic
street drives, whose truth is exact, give the method's own error (kitti-like track errors: drift,
bad tracks, a -0.5 px disparity offset left in). Last, the filter's default run is evaluated
against the ground truth as given and against the ground truth whose every step's rotation angle is
scaled by the tracks' ratio (the same relative translations): how much of the run's error and NEES
the disagreement makes.

A second table tests the frame of the velocities (``velocity frame``): KITTI's OXTS gives vf, vl,
vu "parallel to the earth's surface" (a level, heading-aligned frame), not along the body's axes.
With the ground truth's attitude, the elevation angle of the velocity over windows of 1 s is
compared with that of the ground truth's own motion: as body-frame velocities (rotated by the
ground truth's attitude) and as level-frame velocities (the world frame's tilt from the level
fitted, two angles). The smaller residual names the frame; the dead reckoning of both shows the
cost. The rates get the same test where it is sharpest, in turns (the truth turning faster than
0.1 rad/s): the file's roll and pitch rates against the truth's body rates (its relative rotations),
taken as body-frame rates and as level-frame ones (wf wl wu) turned into the body by the truth's
attitude and the world tilt the velocities gave (not fitted to the rates). Last, the file's velocities against the ground truth's own body velocity (central differences
of its poses), in the first 5 s and after, with the truth's sideslip angle in the first 5 s.

A third table asks the same of 03, which has no ground truth, with the default run's trajectory in
the truth's place (its attitude is vision's, the velocities enter it only through the filter):
which frame the velocities' elevation follows, and where the vertical then lies. The drives' own
tilt target, "the largest tilt of the IMU's z axis from its first direction" (``honesty.py``),
assumes the first frame's z axis vertical; the table gives the angle between the two and the
largest tilt from the vertical, for the ground truths of 0027 and 0042 as well.

Usage: python benchmarks/ground_truth.py [--shared ../shared]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

ROOT = Path(__file__).resolve().parents[1]

from vislam.backend.config import Config
from vislam.backend.data.npz import load_sequence
from vislam.backend.data.tum import read_tum
from vislam.backend.estimator.propagation import dead_reckoning, step_velocities
from vislam.backend.evaluation.consistency import trajectory_nees
from vislam.backend.evaluation.metrics import trajectory_errors
from vislam.backend.geometry import se3
from vislam.backend.run.conventions import decide_conventions
from vislam.backend.run.runner import run_sequence
from vislam.backend.run.timing import repeated_steps
from vislam.backend.run.two_view import fit_pairs

sys.path.insert(0, str(ROOT / "benchmarks"))
from honesty import max_tilt_deg  # noqa: E402

DRIVES = ("ece276a_0027", "ece276a2019_0042")
#: Steps turning less than this (deg) do not enter the rotation ratio (their angle is mostly noise)
MIN_TURN_DEG = 0.5
#: Half-width (steps) of the windows of the velocity-frame test
HALF_WINDOW = 5


def slope(measured: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Least-squares slope through the origin of ``measured`` on ``truth`` (n,), and its standard error."""
    if truth.size < 2:
        return float("nan"), float("nan")
    s = float(measured @ truth / (truth @ truth))
    r = measured - s * truth
    return s, float(np.sqrt(r @ r / (truth.size - 1) / (truth @ truth)))


def relative(poses: np.ndarray, k: np.ndarray) -> np.ndarray:
    """(n,4,4) poses[k]^-1 poses[k+1]."""
    return se3.inverse(poses[k]) @ poses[k + 1]


def rotations(T: np.ndarray) -> np.ndarray:
    """(n,3) rotation vectors log(R) of the poses T (n,4,4)."""
    return np.array([se3.log_so3(R) for R in T[:, :3, :3]])


def turn_ratio(measured: np.ndarray, truth: np.ndarray) -> tuple[float, float, int]:
    """Slope (and its standard error) of the measured rotation vectors' component along the truth's
    axis on the truth's angle, over the steps turning more than MIN_TURN_DEG; their number. (The
    component, not the length: noise across the axis would lengthen every measured rotation.)"""
    angle = np.linalg.norm(truth, axis=1)
    m = angle > np.radians(MIN_TURN_DEG)
    along = np.einsum("ij,ij->i", measured[m], truth[m]) / angle[m]
    return (*slope(along, angle[m]), int(m.sum()))


def rotation(w) -> np.ndarray:
    """exp(w^) (3,3) of the rotation vector w (3,)."""
    return se3.exp_so3_and_left_jacobian(np.asarray(w, dtype=float))[0]


def sensor_ratios(seq, truth: np.ndarray, velocity_index: str) -> dict:
    """Rotation and translation ratios (tracks / truth, IMU / truth) over the ordinary step pairs."""
    n = min(seq.num_steps, truth.shape[0])
    repeated = repeated_steps(seq)
    fits = [f for f in fit_pairs(seq, gap=1, max_pairs=seq.num_steps, skip=repeated)
            if f.step + 1 < n and not (f.step > 0 and repeated[f.step])]  # a repeated step k holds the step before's content
    out = {"pairs": len(fits)}
    v, w = step_velocities(seq.linear_velocity, seq.angular_velocity, velocity_index)
    dt = np.diff(seq.time_stamps)
    steps = np.flatnonzero(~repeated[1:n] & ~repeated[:n - 1])
    true_steps = relative(truth, steps)
    out["imu_rotation"] = turn_ratio(w[steps] * dt[steps, None], rotations(true_steps))[:2]
    out["imu_translation"] = slope(np.linalg.norm(v[steps] * dt[steps, None], axis=1),
                                   np.linalg.norm(true_steps[:, :3, 3], axis=1))
    if fits:
        C, Ci = seq.imu_T_cam, se3.inverse(seq.imu_T_cam)
        k = np.array([f.step for f in fits])
        seen = np.array([C @ se3.inverse(f.b_T_a) @ Ci for f in fits])  # imu_k_T_imu_k+1
        true_k = relative(truth, k)
        *out["tracks_rotation"], out["tracks_turning_pairs"] = turn_ratio(rotations(seen), rotations(true_k))
        out["tracks_translation"] = slope(np.linalg.norm(seen[:, :3, 3], axis=1), np.linalg.norm(true_k[:, :3, 3], axis=1))
    return out


def scaled_rotations(truth: np.ndarray, scale: float) -> np.ndarray:
    """The trajectory whose every step has the truth's translation and its rotation angle times ``scale``."""
    out = [truth[0]]
    for k in range(truth.shape[0] - 1):
        step = se3.inverse(truth[k]) @ truth[k + 1]
        moved = np.eye(4)
        moved[:3, :3] = rotation(scale * se3.log_so3(step[:3, :3]))
        moved[:3, 3] = step[:3, 3]
        out.append(out[-1] @ moved)
    return np.array(out)


def against(result, gt_t: np.ndarray, gt_poses: np.ndarray) -> tuple[float, float, float]:
    """A run's ATE, position NEES mean and share inside the 95 % ellipsoid against ``gt_poses``."""
    ate = trajectory_errors(result.time_stamps, result.world_T_imu, gt_t, gt_poses).ate_rmse
    nees = trajectory_nees(result.time_stamps, result.world_T_imu, result.pose_covariance, gt_t, gt_poses).position
    return ate, nees.mean, nees.share_inside_95


def velocity_frame(seq, truth: np.ndarray, velocity_index: str) -> dict:
    """Residual (deg) of the velocity's elevation against the truth's motion, body- and level-frame."""
    n = min(seq.num_steps, truth.shape[0])
    v, _ = step_velocities(seq.linear_velocity, seq.angular_velocity, velocity_index)
    dt = np.diff(seq.time_stamps)
    h = HALF_WINDOW
    centers = np.arange(h, n - h)
    moved = truth[centers + h, :3, 3] - truth[centers - h, :3, 3]
    body = np.array([sum(truth[j, :3, :3] @ v[j] * dt[j] for j in range(c - h, c + h)) for c in centers])
    level = np.array([v[c - h:c + h].mean(0) for c in centers])
    fast = np.linalg.norm(moved, axis=1) > 2 * h * dt.mean()  # faster than 1 m/s

    def elevation(d):
        return np.degrees(np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])))

    body_res = (elevation(moved) - elevation(body))[fast]

    def level_res(tilt):
        R = rotation([tilt[0], tilt[1], 0.0])  # level_R_world
        return (elevation(moved @ R.T) - elevation(level))[fast]

    tilt = least_squares(level_res, [0.0, 0.0]).x
    # the file's velocity against the truth's own body velocity (central differences), first 5 s and after
    k = np.arange(1, n - 1)
    truth_body = np.einsum("kji,kj->ki", truth[k, :3, :3], truth[k + 1, :3, 3] - truth[k - 1, :3, 3])
    truth_body /= (seq.time_stamps[k + 1] - seq.time_stamps[k - 1])[:, None]
    diff = v[k] - truth_body  # the sample driving step k -> k+1 against the truth's velocity at k
    early = seq.time_stamps[k] - seq.time_stamps[0] < 5.0
    return {"body_deg": float(np.std(body_res)), "level_deg": float(np.std(level_res(tilt))),
            "tilt_deg": np.degrees(tilt), "windows": int(fast.sum()),
            "early": np.sqrt(np.mean(diff[early] ** 2, axis=0)), "later": np.sqrt(np.mean(diff[~early] ** 2, axis=0)),
            "early_slip_deg": float(np.degrees(np.median(np.arctan2(truth_body[early, 1], truth_body[early, 0]))))}


def body_R_level(level_R_world: np.ndarray, world_R_imu: np.ndarray) -> np.ndarray:
    """(3,3) the rotation of a level, heading-aligned frame into the body of attitude ``world_R_imu``,
    the world tilted from the level by ``level_R_world``."""
    Rg = level_R_world @ world_R_imu
    return Rg.T @ rotation([0.0, 0.0, np.arctan2(Rg[1, 0], Rg[0, 0])])


def rate_frame(seq, truth: np.ndarray, tilt_deg: np.ndarray, velocity_index: str) -> dict:
    """RMS (rad/s) of the file's roll and pitch rates against the truth's body rates in turns, as
    body-frame and as level-frame rates (turned by the truth's attitude and ``tilt_deg``)."""
    n = min(seq.num_steps, truth.shape[0])
    _, w = step_velocities(seq.linear_velocity, seq.angular_velocity, velocity_index)
    dt = np.diff(seq.time_stamps)[:n - 1]
    truth_w = np.array([se3.log_so3(truth[k, :3, :3].T @ truth[k + 1, :3, :3]) for k in range(n - 1)]) / dt[:, None]
    R0 = rotation(np.radians([tilt_deg[0], tilt_deg[1], 0.0]))
    level = np.array([body_R_level(R0, truth[k, :3, :3]) @ w[k] for k in range(n - 1)])
    turning = np.abs(truth_w[:, 2]) > 0.1
    return {"turning": int(turning.sum()),
            "body": np.sqrt(np.mean((w[:n - 1] - truth_w)[turning, :2] ** 2, axis=0)),
            "level": np.sqrt(np.mean((level - truth_w)[turning, :2] ** 2, axis=0))}


def level_dead_reckoning(seq, tilt_deg: np.ndarray, velocity_index: str) -> np.ndarray:
    """Dead reckoning with the velocities and rates taken in the level frame (KITTI's vf vl vu, wf wl wu)."""
    v, w = step_velocities(seq.linear_velocity, seq.angular_velocity, velocity_index)
    R0 = rotation(np.radians([tilt_deg[0], tilt_deg[1], 0.0]))
    T = np.eye(4)
    out = [T]
    for k, dt in enumerate(np.diff(seq.time_stamps)):
        R = body_R_level(R0, T[:3, :3])
        T = T @ se3.exp_se3(np.r_[R @ v[k], R @ w[k]] * dt)
        out.append(T)
    return np.array(out)


def synthetic(seed: int):
    from vislam.synth.scene import SceneConfig, make_scene
    from vislam.synth.track_errors import KITTI_LIKE

    scene = make_scene(SceneConfig(scenario="street", steps=500, seed=seed).with_track_errors(KITTI_LIKE))
    return scene.sequence, scene.world_T_imu_true


def _fmt(x, digits=4):
    """A ratio and its standard error, or n/a."""
    return "n/a" if x is None or not np.isfinite(x[0]) else f"{x[0]:.{digits}f} +- {x[1]:.{digits}f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    args = parser.parse_args()
    t0 = time.perf_counter()
    cases = []
    for name in DRIVES:
        seq = load_sequence(args.shared / "data" / f"{name}.npz")
        gt_t, gt = read_tum(args.shared / "data" / "gt" / f"{name}_gt_tum.txt")
        cases.append((name, seq, gt_t, gt))
    for seed in (3, 5):
        seq, truth = synthetic(seed)
        cases.append((f"synthetic street, seed {seed}, kitti-like tracks", seq, seq.time_stamps, truth))

    print("| data | ordinary step pairs fitted (turning) | rotation: tracks / truth | rotation: IMU / truth "
          "| translation: tracks / truth | translation: IMU / truth | default run against the truth: ATE m, "
          "NEES mean / inside | against the truth turned by the tracks' ratio |")
    print("|---|---|---|---|---|---|---|---|")
    frames = []
    for name, seq, gt_t, gt in cases:
        index = decide_conventions(seq).velocity_index
        r = sensor_ratios(seq, gt, index)
        result = run_sequence(seq, Config())
        ate, nees, inside = against(result, gt_t, gt)
        ratio = r.get("tracks_rotation")
        if ratio is not None and np.isfinite(ratio[0]):
            ate2, nees2, inside2 = against(result, gt_t, scaled_rotations(gt, ratio[0]))
            turned = f"{ate2:.2f}, {nees2:.1f} / {inside2:.0%}"
        else:
            turned = "n/a (no step pair with 12 points)"
        print(f"| {name} | {r['pairs']} ({r.get('tracks_turning_pairs', 0)}) | {_fmt(ratio)} "
              f"| {_fmt(r['imu_rotation'])} | {_fmt(r.get('tracks_translation'))} "
              f"| {_fmt(r['imu_translation'])} | {ate:.2f}, {nees:.1f} / {inside:.0%} | {turned} |")
        if not name.startswith("synthetic"):
            frames.append((name, seq, gt_t, gt, index))

    print()
    print("| drive | windows | elevation residual: body frame (deg) | level frame (deg), world's tilt fitted (roll, pitch deg) "
          "| dead reckoning ATE m: body | level | velocity - truth's body velocity, RMS x y z m/s: first 5 s | after "
          "| truth's sideslip, first 5 s (median deg) | steps turning | roll, pitch rate - truth's, RMS rad/s: as body "
          "rates | as level-frame rates |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    tilt_rows = []
    for name, seq, gt_t, gt, index in frames:
        f = velocity_frame(seq, gt, index)
        tilt_rows.append((name, "ground truth", gt, f))
        body = trajectory_errors(seq.time_stamps, dead_reckoning(seq.time_stamps, seq.linear_velocity,
                                                                 seq.angular_velocity, index), gt_t, gt).ate_rmse
        level = trajectory_errors(seq.time_stamps, level_dead_reckoning(seq, f["tilt_deg"], index), gt_t, gt).ate_rmse
        rates = rate_frame(seq, gt, f["tilt_deg"], index)
        print(f"| {name} | {f['windows']} | {f['body_deg']:.3f} | {f['level_deg']:.3f} "
              f"({f['tilt_deg'][0]:.2f}, {f['tilt_deg'][1]:.2f}) | {body:.2f} | {level:.2f} "
              f"| {' '.join(f'{x:.2f}' for x in f['early'])} | {' '.join(f'{x:.2f}' for x in f['later'])} "
              f"| {f['early_slip_deg']:.1f} | {rates['turning']} | {' '.join(f'{x:.4f}' for x in rates['body'])} "
              f"| {' '.join(f'{x:.4f}' for x in rates['level'])} |")
    print()
    print("| drive | trajectory | windows | elevation residual: body frame (deg) | level frame (deg), world's tilt "
          "(roll, pitch deg) | the vertical from the first z axis (deg) | largest tilt of the z axis: from its first "
          "direction | from the vertical (deg) |")
    print("|---|---|---|---|---|---|---|---|")
    seq03 = load_sequence(args.shared / "data" / "ece276a_03.npz")
    run03 = run_sequence(seq03, Config())
    tilt_rows.append(("ece276a_03", "the default run", run03.world_T_imu,
                      velocity_frame(seq03, run03.world_T_imu, run03.conventions.velocity_index)))
    for name, label, poses, f in tilt_rows:
        up = rotation([*np.radians(f["tilt_deg"]), 0.0]).T[:, 2]  # world_R_level e_z
        first_z = np.degrees(np.arccos(np.clip(poses[0, :3, 2] @ up, -1.0, 1.0)))
        print(f"| {name} | {label} | {f['windows']} | {f['body_deg']:.3f} | {f['level_deg']:.3f} "
              f"({f['tilt_deg'][0]:.2f}, {f['tilt_deg'][1]:.2f}) | {first_z:.2f} | {max_tilt_deg(poses):.1f} "
              f"| {max_tilt_deg(poses, up):.1f} |")
    print(f"\n{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
