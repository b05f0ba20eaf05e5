"""The EKF on SE(3), one job a module:

- ``ekf``: :class:`VisualInertialEKF`, the online API (predict, update), built from:
- ``layout`` (the state vector), ``state`` (mean, covariance, landmark bookkeeping),
  ``state_helper`` (:class:`StateHelper`, the only code that changes the covariance: propagate,
  update, augment, marginalize, repair),
- ``model`` (the error model's interface), ``invariant`` (right-invariant error, I1-I7, the
  default), ``body`` (right perturbation, B1-B4), ``inertial`` (a real IMU's SE_2(3) state, J1-J7)
  and ``landmarks`` (xyz / inverse depth, L1-L3),
- ``propagation`` (IMU kinematics, P1; dead reckoning), ``update`` (the joint update, U1-U5),
  ``covariance`` (the compiled augmentation and marginalization, A1-A2), ``tracks`` (which landmarks are in
  the state, re-anchoring, R1-R2), ``health`` (H1-H3), ``linalg`` (BLAS/LAPACK from compiled code).
"""
