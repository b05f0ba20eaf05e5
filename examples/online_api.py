"""vislam from Python: a whole file with run_sequence, then the online API one step at a time.

Usage: python examples/online_api.py [DATA.npz]   (without a file: a synthetic street scene)
"""

import sys

import numpy as np

import vislam

if len(sys.argv) > 1:
    seq = vislam.load_sequence(sys.argv[1])
else:
    from vislam.synth.scene import SceneConfig, make_scene

    seq = make_scene(SceneConfig(steps=200, seed=0)).sequence

# 1. everything at once: what the data says decided from the whole file, then every step
result = vislam.run_sequence(seq)
print("run_sequence: final position", np.round(result.world_T_imu[-1][:3, 3], 3),
      f"{result.map_positions.shape[0]} landmarks, {result.stats.real_time_factor:.0f}x real time")

# 2. the online API: the same decisions, then one call per time stamp (velocity timing, IMU corrections,
# stereo offset and repeated frames are applied by OnlineRun)
config = vislam.Config()
decisions = vislam.decide(seq, config)  # conventions, noise, offsets, drift: each with its test's numbers
print(decisions.describe())
run = vislam.OnlineRun(vislam.StereoCamera(seq.K, seq.baseline), decisions, config)
for t, v, w, ids, pixels in seq.steps():  # t (s), velocities (3,) m/s and rad/s, track ids (n,), pixels (n, 4)
    run.step(t, v, w, ids, pixels)  # predict into t, then gate, RANSAC, joint update, new landmarks
sigma = np.sqrt(np.diag(run.ekf.pose_covariance)[:3])  # of world_T_imu = mu exp(xi^), xi = [rho; phi]
print("online API:   final position", np.round(run.ekf.world_T_imu[:3, 3], 3), "+-", np.round(sigma, 3), "m (body axes)")
