"""vislam front end: OpenCV stereo tracking of rectified image pairs into course-layout observations,
and the readers of the datasets people have.

Modules: ``config`` (TrackerConfig), ``images`` (KITTI-layout directories), ``imu_input`` (IMU
CSV / course .npz, extrinsic), ``kitti_raw`` (KITTI raw calibration, stamps, OXTS records and
poses), ``raw_drive`` (a KITTI raw drive: frames, OXTS velocities, ground truth), ``euroc`` (an EuRoC
ASL folder: cameras, stereo rectification, the IMU's samples, ground truth), ``kalibr`` (Kalibr's
camchain.yaml and imu.yaml), ``bag`` (ROS 1 bags and ROS 2 bag folders: topics, stamps, the IMU's
samples, stereo pairs), ``tracker``
(StereoTracker.step), ``detect`` (grid corners), ``affine`` (drift-free patch refinement),
``motion`` (camera motion, rigid-motion checks), ``draw`` (debug pictures), ``track``
(track_directory, iter_tracks, image_steps).
"""
