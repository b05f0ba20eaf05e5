"""vislam back end: SE(3) math, stereo camera model, sequence I/O and the EKF estimator."""
