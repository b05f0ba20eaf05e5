"""vislam's back end: the estimator and everything around it, one subpackage per job.

From the bottom up (a package imports only from the ones below it):

- ``errors``, ``compiled`` (the numba decorator and the kernels' warm-up), ``reading`` (input
  files read only when regular and not too large), ``options`` (typed tables of options, TOML) and
  ``config`` (every option with its default);
- ``geometry``: SE(3) maths and the stereo camera model;
- ``data``: the in-memory sequence and its validation, the course .npz format, TUM trajectories;
- ``estimator``: the EKF: state layout, error models (invariant, body), prediction, the joint
  update, covariance operations, landmark bookkeeping, health;
- ``run``: a whole run: conventions, IMU noise and track-drift decisions, repeated frames, and
  the one loop over a stream of steps;
- ``evaluation``: trajectory metrics (evo) and Monte Carlo consistency.
"""
