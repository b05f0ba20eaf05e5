"""The one place for every option of the stereo tracker (:mod:`frontend.tracker`): the ``[tracker]`` table.

:class:`TrackerConfig` is a typed table of options (``backend.options``): read from the
``[tracker]`` table of a TOML file (:meth:`TrackerConfig.load`) and from ``--set tracker.KEY=VALUE``
(``vislam track --set tracker.target_tracks=200``); invalid values raise
:class:`~vislam.backend.errors.ConfigError`.

The defaults serve the EKF, which gates its own outliers and gains most from long, unbroken
tracks: each track is refined against its own first patch (``affine_*``, drift-free), checked
forward-backward, by stereo back-matching and by a fundamental-matrix RANSAC, and ends when its
patch changes scale beyond ``max_patch_scale``. Stricter settings give cleaner but shorter tracks:
``motion_threshold_px = 0.7``, ``affine_max_residual = 0.5``, ``affine_max_shift_px = 1.0``.
Two birth options are off by default: ``birth_lookahead_frames`` starts only corners that stay in
view that many frames at the last camera motion, ``min_isotropy`` skips corners whose patch has
edges nearly all in one direction. BENCHMARKS.md measures these settings against each other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..backend.config import StrChoice
from ..backend.errors import ConfigError
from ..backend.options import OptionTable

__all__ = ["TrackerConfig", "FundamentalMethod"]


class FundamentalMethod(StrChoice):
    """The robust estimator of the fundamental matrix over a frame's temporal matches."""

    MAGSAC = "magsac"  # cv2.USAC_MAGSAC
    RANSAC = "ransac"  # cv2.FM_RANSAC
    OFF = "off"


@dataclass
class TrackerConfig(OptionTable):
    """Tracker options. Units: pixels (px), grey levels; images are 8-bit grey, rectified."""

    TABLE = "tracker"

    # --- how many tracks, where
    target_tracks: int = 300  # live stereo tracks to keep; detection tops up to this
    grid_cols: int = 8  # detection grid: columns ...
    grid_rows: int = 4  # ... and rows of cells
    cell_budget: int = 0  # max live tracks per cell; 0: 2 * target_tracks / cells (rounded up)
    border_px: int = 8  # points nearer than this to an image edge (left or right image) are dropped
    confirm_frames: int = 0  # a track is emitted (gets its id) once followed this many frames (0: at once)

    # --- detection (frontend.detect: Shi-Tomasi on the half-size image, ranked per grid cell)
    gftt_quality: float = 0.01  # corner response >= this times the strongest in the cell
    gftt_min_response: float = 2e-4  # ... and >= this (minimum eigenvalue on the half-size image)
    gftt_block_size: int = 3  # half-size px: averaging window of the corner response
    min_distance_px: float = 15.0  # px: new corners keep this far from live tracks and each other
    min_isotropy: float = 0.0  # new corners' tracking patch (affine_window): smallest gradient eigenvalue >= this times the largest (0: any)
    birth_lookahead_frames: int = 0  # new corners must stay in view this many frames at the last camera motion (0: next frame)

    # --- Lucas-Kanade (cv2.calcOpticalFlowPyrLK): temporal and stereo, each checked by tracking back
    lk_window: int = 15  # px, odd
    lk_levels: int = 3  # pyramid levels above the image for new points (0: no pyramid)
    lk_levels_tracked: int = 1  # ... for tracks, whose motion and disparity are predicted
    lk_iterations: int = 30  # per level
    lk_epsilon: float = 0.01  # px: iteration stops when the step is smaller
    predict_flow: bool = True  # seed temporal LK with each track's predicted motion (else zero motion)
    fb_threshold_px: float = 0.5  # px: forward-backward (temporal) round-trip error allowed
    subpix_window: int = 2  # px: half-size of the cv2.cornerSubPix window on new corners (0: off)

    # --- drift-free refinement: affine alignment of each track's first patch (frontend.affine)
    affine_window: int = 15  # px, odd: patch size (0: off, plain frame-to-frame LK)
    affine_iterations: int = 10  # Gauss-Newton iterations at most
    affine_max_residual: float = 0.7  # normalized patch difference (0 same .. 2 opposite) allowed
    affine_max_shift_px: float = 2.0  # px: refinement may move an LK result this far
    max_patch_scale: float = 10.0  # patch area scale |det A| vs the first frame must lie in [1/this, this]

    # --- stereo (left -> right along the row, then back)
    stereo_row_tolerance_px: float = 1.0  # px: |vL - vR| allowed
    stereo_min_disparity_px: float = 0.1  # px: uL - uR must exceed this (> 0: in front of the rig)
    stereo_max_disparity_px: float = 200.0  # px: ... and be at most this
    stereo_back_threshold_px: float = 0.5  # px: right -> left back-check error allowed
    stereo_seed_scale: int = 4  # new points' disparity guess: block matching at 1/scale size (2, 4, 8; 0: off)
    new_point_disparity_px: float = 0.0  # px: disparity guess for new points without any other

    # --- camera motion (frontend.motion): PnP pose from the previous frame's stereo points
    pose_ransac_px: float = 1.0  # px: inlier threshold of the PnP RANSAC (the pose predicts the next frame)
    motion_threshold_px: float = 0.0  # px: end tracks off their fixed-point motion by more, either image (0: off)
    verify_births: bool = False  # new points must project onto themselves in the previous frame ...
    birth_threshold_px: float = 1.0  # px: ... within this

    # --- temporal outliers: fundamental-matrix RANSAC over the frame's temporal matches
    fundamental_method: FundamentalMethod = FundamentalMethod.MAGSAC
    fundamental_threshold_px: float = 1.0  # px: distance to the epipolar line
    fundamental_confidence: float = 0.999

    # --- execution
    threads: int = 2  # cv2.setNumThreads while tracking (0: OpenCV's default)

    def check(self) -> None:
        self.require_at_least(1, "target_tracks", "grid_cols", "grid_rows", "lk_iterations", "gftt_block_size")
        self.require_at_least(0, "cell_budget", "border_px", "lk_levels", "lk_levels_tracked", "threads",
                              "subpix_window", "affine_window", "affine_iterations", "stereo_seed_scale",
                              "confirm_frames", "birth_lookahead_frames")
        self.require_positive("gftt_quality", "min_distance_px", "lk_epsilon", "fb_threshold_px",
                              "stereo_row_tolerance_px", "stereo_min_disparity_px", "stereo_max_disparity_px",
                              "stereo_back_threshold_px", "fundamental_threshold_px", "affine_max_residual",
                              "affine_max_shift_px", "pose_ransac_px", "birth_threshold_px")
        self.require_at_least(0.0, "gftt_min_response", "new_point_disparity_px", "motion_threshold_px")
        self.require("max_patch_scale", math.isfinite(self.max_patch_scale) and self.max_patch_scale > 1,
                     "must be a finite number > 1")
        self.require("min_isotropy", math.isfinite(self.min_isotropy) and 0 <= self.min_isotropy < 1,
                     "must lie in [0, 1)")
        self.require("gftt_quality", self.gftt_quality < 1, "must lie in (0, 1)")
        self.require("lk_window", self.lk_window >= 3 and self.lk_window % 2 == 1, "must be an odd integer >= 3")
        self.require("affine_window", not self.affine_window or (self.affine_window >= 5 and self.affine_window % 2 == 1),
                     "must be 0 (off) or an odd integer >= 5")
        self.require("stereo_seed_scale", self.stereo_seed_scale in (0, 2, 4, 8), "must be 0 (off), 2, 4 or 8")
        self.require("gftt_block_size", self.gftt_block_size % 2 == 1, "must be odd")
        if self.stereo_max_disparity_px <= self.stereo_min_disparity_px:
            raise ConfigError(
                "config keys 'tracker.stereo_min_disparity_px' < 'tracker.stereo_max_disparity_px' required, got "
                f"{self.stereo_min_disparity_px!r} and {self.stereo_max_disparity_px!r}"
            )
        self.require("fundamental_confidence", 0.5 < self.fundamental_confidence < 1.0, "must lie in (0.5, 1)")

    @property
    def cells(self) -> int:
        return self.grid_cols * self.grid_rows

    @property
    def per_cell_budget(self) -> int:
        """The effective per-cell budget (``cell_budget`` or its automatic value)."""
        return self.cell_budget or max(1, math.ceil(2 * self.target_tracks / self.cells))

    @property
    def min_image_side(self) -> int:
        """Smallest image width and height (px) these options can track in: a Lucas-Kanade window
        (``lk_window``) and a first patch (``affine_window``) must fit in the image, a point must
        keep ``border_px`` from every edge in both images with a positive disparity between
        them (``2 border_px + 2``), and ``cv2.cornerSubPix`` needs ``2 subpix_window + 5``."""
        subpix = 2 * self.subpix_window + 5 if self.subpix_window else 1
        return max(self.lk_window, self.affine_window, 2 * self.border_px + 2, subpix)
