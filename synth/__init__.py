"""vislam synthetic feature scenes with ground truth (no image rendering).

``make_scene(SceneConfig(scenario="street" | "aerial", steps, seed, ...))`` builds a
:class:`~vislam.backend.data.sequence.Sequence` (noisy stereo features with per-track ids, noisy IMU
velocities) together with the true poses, twists and landmark positions by id;
``write_scene(scene, out_dir)`` writes ``data.npz``, ``gt_tum.txt`` and ``landmarks.npz``.
Depends on ``backend`` only.
"""

from .observe import Calibration, kitti_calibration
from .scene import Scene, SceneConfig, make_scene, write_scene

__all__ = ["Calibration", "kitti_calibration", "Scene", "SceneConfig", "make_scene", "write_scene"]
