"""Do images, IMU and ground truth agree in scale on the 51 KITTI frames? (BENCHMARKS.md, front end)

1. Calibration: baseline from calib.txt P1 against the .npz file's `b`.
2. Stereo scale: OpenCV SGBM disparities of the road ahead give the camera height
   h = b (v - cy) / d per image row (KITTI mounts its cameras 1.65 m above the road).
3. Motion scale: the course file's own feature tracks, triangulated at step k and reprojected at
   k+1 under the ground-truth (or dead-reckoning) translation scaled by s; the median error per s.

Usage: python benchmarks/kitti_scale_check.py [SHARED_DIR]   (default ../shared)
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from vislam.backend.run.conventions import matched_pairs, reprojection_error
from vislam.backend.estimator.propagation import dead_reckoning
from vislam.backend.data.npz import load_sequence
from vislam.frontend.images import open_stereo_directory

shared = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT.parent / "shared"
stereo = open_stereo_directory(shared / "images" / "kitti_odom01_f000000-000050")
full = load_sequence(shared / "data" / "ece276a2019_0042.npz")
gt = np.load(shared / "data" / "gt" / "ece276a2019_0042_gt_aligned.npz")["world_T_imu"]
print(f"1. baseline: calib.txt {stereo.baseline:.6f} m, ece276a2019_0042.npz {full.baseline:.6f} m; "
      f"fx {stereo.K[0, 0]:.3f} vs {full.K[0, 0]:.3f}")

fy, cy = stereo.K[1, 1], stereo.K[1, 2]
sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=128, blockSize=7, P1=8 * 49, P2=32 * 49,
                             uniquenessRatio=10, mode=cv2.STEREO_SGBM_MODE_HH)
print("2. camera height above the road from SGBM disparities (rows 250-360, columns 520-720):")
for index, left, right in stereo.frames():
    if index % 10:
        continue
    disparity = sgbm.compute(left, right).astype(float) / 16.0
    heights = []
    for v in range(250, 370, 10):
        band = disparity[v - 2 : v + 3, 520:720]
        band = band[band > 0]
        if band.size >= 50:
            heights.append(stereo.baseline * (v - cy) / np.median(band))
    print(f"   frame {index:2d}: median {np.median(heights):.3f} m (rows from {heights[0]:.2f} to {heights[-1]:.2f} m)")

scales = (0.9, 1.0, 1.05, 1.1, 1.15, 1.2)
print("3. median reprojection error (px) of the file's own tracks, k -> k+1, translation scaled by s:")
print("   steps  poses  " + "  ".join(f"s={s:<5g}" for s in scales))
for n in (51, 500):
    seq = full.subset(n)
    pairs = matched_pairs(seq, 1)
    dr = dead_reckoning(seq.time_stamps, seq.linear_velocity, seq.angular_velocity, "next")
    for name, poses in (("GT", gt[:n]), ("IMU", dr)):
        errors = []
        for s in scales:
            scaled = poses.copy()
            scaled[:, :3, 3] *= s
            errors.append(reprojection_error(seq, seq.imu_T_cam, "next", 1, pairs=pairs, poses=scaled))
        print(f"   {n:5d}  {name:5s}  " + "  ".join(f"{e:7.3f}" for e in errors))
    if n == 51:
        length = lambda P: np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1).sum()  # noqa: E731
        print(f"   path length over steps 0-50: GT {length(gt[:n]):.1f} m, IMU dead reckoning {length(dr):.1f} m")
