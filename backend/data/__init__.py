"""Data: the in-memory sequence and its validation (``sequence``), the course .npz format (``npz``),
TUM trajectories (``tum``), a run's pose covariances (``covariance``), line-oriented text input
(``textio``) and the atomic writer (``files``)."""
