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

# 1. everything at once: conventions and noise decided from the data, then every step
result = vislam.run_sequence(seq)
print("run_sequence: final position", np.round(result.world_T_imu[-1][:3, 3], 3),
      f"{result.map_positions.shape[0]} landmarks, {result.stats.real_time_factor:.0f}x real time")

# 2. the online API: one predict and one update per time stamp, with the decisions of step 1
conventions, noise = result.conventions, result.imu_noise
ekf = vislam.VisualInertialEKF(vislam.StereoCamera(seq.K, seq.baseline), conventions.imu_T_cam, result.config,
                               vislam.ImuNoise(noise.linear_sigma, noise.angular_sigma))
next_velocity = conventions.velocity_index == "next"  # which sample drives step k -> k+1 (the course files': k+1)
previous = None
for t, v, w, ids, pixels in seq.steps():  # t (s), velocities (3,) m/s and rad/s, track ids (n,), pixels (n, 4)
    pixels = conventions.stereo_offset.correct(pixels, float(conventions.imu_T_cam[:3, 1] @ w))  # the pair's offset
    if previous is not None:
        t0, v0, w0 = previous
        ekf.predict(t - t0, *((v, w) if next_velocity else (v0, w0)))  # mu <- mu exp(dt u^); P by the error model
    ekf.update(ids, pixels)  # gate, RANSAC, joint update, new landmarks, ended tracks to the map
    previous = (t, v, w)
print("online API:   final position", np.round(ekf.world_T_imu[:3, 3], 3))
