"""Data: the in-memory sequence and its validation (``sequence``), the course .npz format (``npz``),
TUM trajectories (``tum``), line-oriented text input (``textio``) and the atomic writer (``files``)."""
