"""Geometry: SO(3)/SE(3) Lie-group maths (``se3``) and the rectified stereo camera (``camera``)."""
