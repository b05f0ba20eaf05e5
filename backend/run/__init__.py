"""A whole run: everything decided from the data before the first step, in one record
(``decisions``: ``conventions`` (extrinsic axes, velocity timing), ``timing`` (repeated frames),
``two_view`` (two-view bundle adjustment of step pairs), ``stereo_offset`` (the disparity offset),
``drift`` (track drift), ``noise`` (pixel and IMU noise, the IMU against vision), ``likelihood``
(the filter's innovation likelihood over the first steps)); the start of a real IMU
(``initialization``: at rest or in motion) and its run (``inertial``); and the loop over a stream
of steps (``runner`` over ``online.OnlineRun``)."""
