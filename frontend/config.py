"""The one place for every option of the stereo tracker (:mod:`frontend.tracker`).

`TrackerConfig` is a typed dataclass with the defaults; :func:`load_tracker_config` reads it from
TOML (a ``[tracker]`` table) and :func:`apply_tracker_overrides` sets single keys from
``KEY=VALUE`` strings (``vislam track --set target_tracks=200``). Key names do not collide with
:class:`backend.config.FilterConfig`, so one ``--set`` list can be split between the two with
:func:`split_overrides`. Invalid values raise :class:`~backend.errors.ConfigError`.

The defaults are tuned for the EKF, which gates its own outliers and gains most from long,
unbroken tracks: on rendered streets (tests/test_frontend.py) 6.5 % of tracks stray more than 2 px
from their true point at some frame, median error 0.17 px, and SLAM error is 0.07-0.09 of dead
reckoning's. For clean tracks instead (0.9 % beyond 2 px, median 0.11 px; tracks cut sooner, SLAM
error 0.25-0.35 of dead reckoning's) set ``motion_threshold_px = 0.7``,
``affine_max_residual = 0.5``, ``affine_max_shift_px = 1.0``.

Two birth options are off by default (measured on the same street, 50 frames; SLAM ATE over
dead reckoning's on five rendered streets of 80 frames, seeds 0-4, default 0.09-0.22, mean 0.14):
``birth_lookahead_frames = 5`` starts only corners that stay in view 5 frames at the last camera
motion: median track length 4 instead of 2, SLAM/DR mean 0.13, but 10.4 % of tracks beyond 2 px
and median error 0.22 px (longer tracks drift more); ``min_isotropy = 0.2`` skips corners whose
patch has edges nearly all in one direction: length 3, 4.9 % beyond 2 px, 0.16 px, but SLAM/DR
mean 0.28. ``max_patch_scale`` ends a track whose patch area has grown or shrunk beyond that
factor since its first frame: 3 gives 5.3 % beyond 2 px at SLAM/DR 0.18, 1.3 gives 1.7 % at 0.55
(default 10, the earlier fixed bound: 6.5 %, 0.15; BENCHMARKS.md, front end).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from backend.config import coerce_value, parse_assignment, read_toml, replace_validated
from backend.errors import ConfigError

__all__ = [
    "TrackerConfig",
    "FUNDAMENTAL_METHODS",
    "tracker_config_from_dict",
    "load_tracker_config",
    "apply_tracker_overrides",
    "split_overrides",
]

FUNDAMENTAL_METHODS = ("magsac", "ransac", "off")


@dataclass
class TrackerConfig:
    """Tracker options. Units: pixels (px), grey levels; images are 8-bit grey, rectified."""

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
    fundamental_method: str = "magsac"  # magsac (cv2.USAC_MAGSAC) | ransac (cv2.FM_RANSAC) | off
    fundamental_threshold_px: float = 1.0  # px: distance to the epipolar line
    fundamental_confidence: float = 0.999

    # --- execution
    threads: int = 2  # cv2.setNumThreads while tracking (0: OpenCV's default)

    def validate(self) -> "TrackerConfig":
        """Raise ConfigError on an invalid value; return self."""
        for f in fields(self):
            _coerce(f.name, getattr(self, f.name))  # type check (bool, int, float or str)
        if self.fundamental_method not in FUNDAMENTAL_METHODS:
            raise ConfigError(
                f"config key 'fundamental_method': must be one of {', '.join(FUNDAMENTAL_METHODS)}, "
                f"got {self.fundamental_method!r}"
            )
        for name in ("target_tracks", "grid_cols", "grid_rows", "lk_iterations", "gftt_block_size"):
            _at_least(name, getattr(self, name), 1)
        for name in ("cell_budget", "border_px", "lk_levels", "lk_levels_tracked", "threads", "subpix_window",
                     "affine_window", "affine_iterations", "stereo_seed_scale", "confirm_frames",
                     "birth_lookahead_frames"):
            _at_least(name, getattr(self, name), 0)
        positive = [
            "gftt_quality", "min_distance_px", "lk_epsilon", "fb_threshold_px",
            "stereo_row_tolerance_px", "stereo_min_disparity_px", "stereo_max_disparity_px",
            "stereo_back_threshold_px", "fundamental_threshold_px", "affine_max_residual", "affine_max_shift_px",
            "pose_ransac_px", "birth_threshold_px",
        ]
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"config key '{name}': must be a finite number > 0, got {value!r}")
        for name in ("gftt_min_response", "new_point_disparity_px", "motion_threshold_px"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"config key '{name}': must be a finite number >= 0, got {value!r}")
        if not (math.isfinite(self.max_patch_scale) and self.max_patch_scale > 1):
            raise ConfigError(f"config key 'max_patch_scale': must be a finite number > 1, got {self.max_patch_scale!r}")
        if not (math.isfinite(self.min_isotropy) and 0 <= self.min_isotropy < 1):
            raise ConfigError(f"config key 'min_isotropy': must lie in [0, 1), got {self.min_isotropy!r}")
        if self.gftt_quality >= 1:
            raise ConfigError(f"config key 'gftt_quality': must lie in (0, 1), got {self.gftt_quality!r}")
        if self.lk_window < 3 or self.lk_window % 2 == 0:
            raise ConfigError(f"config key 'lk_window': must be an odd integer >= 3, got {self.lk_window!r}")
        if self.affine_window and (self.affine_window < 5 or self.affine_window % 2 == 0):
            raise ConfigError(f"config key 'affine_window': must be 0 (off) or an odd integer >= 5, got {self.affine_window!r}")
        if self.stereo_seed_scale not in (0, 2, 4, 8):
            raise ConfigError(f"config key 'stereo_seed_scale': must be 0 (off), 2, 4 or 8, got {self.stereo_seed_scale!r}")
        if self.gftt_block_size % 2 == 0:
            raise ConfigError(f"config key 'gftt_block_size': must be odd, got {self.gftt_block_size!r}")
        if self.stereo_max_disparity_px <= self.stereo_min_disparity_px:
            raise ConfigError(
                "config keys 'stereo_min_disparity_px' < 'stereo_max_disparity_px' required, got "
                f"{self.stereo_min_disparity_px!r} and {self.stereo_max_disparity_px!r}"
            )
        if not 0.5 < self.fundamental_confidence < 1.0:
            raise ConfigError(
                f"config key 'fundamental_confidence': must lie in (0.5, 1), got {self.fundamental_confidence!r}"
            )
        return self

    @property
    def cells(self) -> int:
        return self.grid_cols * self.grid_rows

    @property
    def per_cell_budget(self) -> int:
        """The effective per-cell budget (``cell_budget`` or its automatic value)."""
        return self.cell_budget or max(1, math.ceil(2 * self.target_tracks / self.cells))

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def describe(self) -> str:
        """Multi-line listing printed at the start of a run (OpenVINS style)."""
        width = max(len(f.name) for f in fields(self))
        return "\n".join(f"  {f.name:<{width}} = {getattr(self, f.name)!r}" for f in fields(self))


def _at_least(name: str, value: Any, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ConfigError(f"config key '{name}': must be an integer >= {low}, got {value!r}")


_LABEL = "tracker config key"
_KEYS = {f.name for f in fields(TrackerConfig)}


def _coerce(name: str, value: Any) -> Any:
    return coerce_value(TrackerConfig, name, value, _LABEL)


def tracker_config_from_dict(values: dict[str, Any], base: TrackerConfig | None = None) -> TrackerConfig:
    """A TrackerConfig with ``values`` applied over ``base`` (default: the defaults), validated."""
    return replace_validated(TrackerConfig, values, base, _LABEL)


def load_tracker_config(path: str | Path, base: TrackerConfig | None = None) -> TrackerConfig:
    """Read the ``[tracker]`` table of a TOML file (other tables, e.g. ``[filter]``, are ignored);
    a file without that table gives ``base`` (or the defaults)."""
    path = Path(path)
    table = read_toml(path).get("tracker", {})
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: key 'tracker' must be a table")
    try:
        return tracker_config_from_dict(table, base)
    except ConfigError as exc:
        raise ConfigError(f"{path}: [tracker] {exc}") from None


def apply_tracker_overrides(config: TrackerConfig, assignments: list[str]) -> TrackerConfig:
    """Apply ``KEY=VALUE`` strings (command line ``--set``) to a copy of ``config``."""
    return tracker_config_from_dict(dict(parse_assignment(a) for a in assignments), config)


def split_overrides(assignments: list[str]) -> tuple[list[str], list[str]]:
    """(assignments for the filter, assignments for the tracker): a key of TrackerConfig goes to
    the tracker, every other key (unknown ones included, refused there) to the filter."""
    filter_part, tracker_part = [], []
    for item in assignments:
        key, _ = parse_assignment(item)
        (tracker_part if key in _KEYS else filter_part).append(item)
    return filter_part, tracker_part
