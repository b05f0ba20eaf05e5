"""vislam front end: OpenCV stereo tracking of rectified image pairs (see issue 4; not built yet)."""
