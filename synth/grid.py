"""A seeded grid of synthetic scenes for evaluating filters on data nobody tuned on.

:data:`GRID` lists scene specifications (:class:`GridSpec`) over the factors scenario
(street / aerial), seed, steps (200-400), white pixel noise (0.25-1 px), track drift (off / on /
heavy), repeated frames (off / on), disparity offset (0 / -1 px), gross outliers (0 / 3 %),
frame jitter (off / on), velocity noise (low / mid / high) and velocity timing (this / next).
Each spec's name is made of its values, so it stays the same as long as the spec does, and the
name alone decides its part:

    part(name) = "held_out" if int(sha256(name)[:8], 16) mod 3 == 0 else "tuning"

The held-out scenes are never to be tuned on: options are chosen on ``tuning`` and reported on
``held_out``. ``scenes(part)`` yields ``(name, SceneConfig)``; every scene is a pure function of
its config (``make_scene``).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from .scene import SceneConfig
from .track_errors import KITTI_LIKE, TrackErrors

__all__ = ["GridSpec", "GRID", "PARTS", "DRIFT_LEVELS", "VELOCITY_NOISE", "part_of", "spec", "specs", "scenes",
           "random_spec"]

PARTS = ("tuning", "held_out")

#: Track drift levels: off; "on" the kitti-like drift and bad tracks; "heavy" about three times that
DRIFT_LEVELS: dict[str, dict[str, float]] = {
    "off": {},
    "on": {key: getattr(KITTI_LIKE, key) for key in ("drift_share", "drift_median", "drift_log_sigma", "drift_walk",
                                                     "bad_share")},
    "heavy": dict(drift_share=0.9, drift_median=0.15, drift_log_sigma=1.2, drift_walk=0.1, bad_share=0.05),
}
#: Velocity noise levels: (linear m/s, angular rad/s) per axis; "mid" is the scenes' default
VELOCITY_NOISE: dict[str, tuple[float, float]] = {"low": (0.05, 0.002), "mid": (0.2, 0.01), "high": (0.5, 0.02)}
#: The jitter switched on: first-order Gauss-Markov, 2e-4 rad per axis, correlation 0.5 from step to step
JITTER = dict(jitter_rotation=2e-4, jitter_correlation=0.5)
#: The repeated frames switched on: one every ~12 steps
REPEAT_INTERVAL = 12.0


@dataclass(frozen=True)
class GridSpec:
    """One scene of the grid."""

    scenario: str  # "street" | "aerial"
    seed: int
    steps: int
    pixel_sigma: float  # px
    drift: str  # a key of DRIFT_LEVELS
    repeats: bool
    disparity_offset: float  # px
    outlier_share: float
    jitter: bool
    velocity_noise: str  # a key of VELOCITY_NOISE
    velocity_index: str  # "this" | "next"

    @property
    def name(self) -> str:
        """e.g. ``street-s101-n300-px0.5-drift_on-rep_on-beta-1-out3-jit_off-vel_mid-next``."""
        return (f"{self.scenario}-s{self.seed}-n{self.steps}-px{self.pixel_sigma:g}-drift_{self.drift}"
                f"-rep_{'on' if self.repeats else 'off'}-beta{self.disparity_offset:g}"
                f"-out{100 * self.outlier_share:g}-jit_{'on' if self.jitter else 'off'}"
                f"-vel_{self.velocity_noise}-{self.velocity_index}")

    @property
    def part(self) -> str:
        return part_of(self.name)

    def track_errors(self) -> TrackErrors:
        return TrackErrors(pixel_sigma=self.pixel_sigma, outlier_share=self.outlier_share,
                           disparity_offset=self.disparity_offset,
                           repeat_interval=REPEAT_INTERVAL if self.repeats else 0.0,
                           **DRIFT_LEVELS[self.drift], **(JITTER if self.jitter else {}))

    def scene_config(self) -> SceneConfig:
        linear, angular = VELOCITY_NOISE[self.velocity_noise]
        return SceneConfig(scenario=self.scenario, steps=self.steps, seed=self.seed, linear_sigma=linear,
                           angular_sigma=angular, velocity_index=self.velocity_index,
                           track_errors=self.track_errors())


def part_of(name: str) -> str:
    """The part a scene's name puts it in (module docstring)."""
    return PARTS[1] if int(hashlib.sha256(name.encode("utf-8")).hexdigest()[:8], 16) % 3 == 0 else PARTS[0]


#: The grid: every level of every factor appears in several scenes, on both scenarios.
GRID: tuple[GridSpec, ...] = (
    #        scenario  seed steps  px    drift    rep    beta  out   jit    vel     timing
    GridSpec("street", 101, 300, 0.25, "off", False, 0.0, 0.0, False, "mid", "next"),
    GridSpec("street", 102, 300, 0.5, "on", True, -1.0, 0.0, True, "mid", "next"),
    GridSpec("street", 103, 400, 0.25, "on", True, -1.0, 0.03, True, "high", "next"),
    GridSpec("street", 104, 200, 1.0, "heavy", False, 0.0, 0.03, False, "low", "this"),
    GridSpec("street", 105, 300, 0.5, "heavy", True, -1.0, 0.0, True, "mid", "this"),
    GridSpec("street", 106, 400, 0.25, "off", True, 0.0, 0.03, False, "high", "next"),
    GridSpec("street", 107, 250, 0.75, "on", False, -1.0, 0.0, False, "low", "next"),
    GridSpec("street", 108, 350, 0.5, "on", True, 0.0, 0.03, True, "mid", "this"),
    GridSpec("street", 109, 300, 1.0, "off", False, -1.0, 0.03, True, "high", "this"),
    GridSpec("street", 110, 200, 0.25, "heavy", True, -1.0, 0.0, False, "mid", "next"),
    GridSpec("street", 111, 400, 0.5, "on", False, 0.0, 0.0, True, "low", "next"),
    GridSpec("street", 112, 300, 0.75, "heavy", True, 0.0, 0.03, True, "high", "next"),
    GridSpec("street", 113, 350, 0.25, "on", True, -1.0, 0.03, False, "mid", "this"),
    GridSpec("street", 114, 250, 0.5, "off", True, -1.0, 0.0, True, "low", "next"),
    GridSpec("aerial", 201, 300, 0.25, "off", False, 0.0, 0.0, False, "mid", "next"),
    GridSpec("aerial", 202, 300, 0.5, "on", True, -1.0, 0.0, True, "mid", "this"),
    GridSpec("aerial", 203, 400, 0.25, "on", False, -1.0, 0.03, False, "high", "next"),
    GridSpec("aerial", 204, 200, 1.0, "heavy", True, 0.0, 0.03, True, "low", "next"),
    GridSpec("aerial", 205, 350, 0.5, "heavy", False, -1.0, 0.0, False, "mid", "this"),
    GridSpec("aerial", 206, 250, 0.75, "on", True, 0.0, 0.03, True, "high", "this"),
    GridSpec("aerial", 207, 300, 0.25, "off", True, -1.0, 0.03, True, "low", "next"),
    GridSpec("aerial", 208, 400, 0.5, "on", True, 0.0, 0.0, False, "mid", "next"),
    GridSpec("aerial", 209, 200, 0.75, "heavy", False, -1.0, 0.03, True, "high", "next"),
    GridSpec("aerial", 210, 300, 1.0, "on", True, -1.0, 0.0, False, "low", "this"),
)


def specs(part: str) -> tuple[GridSpec, ...]:
    """The specs of one part ("tuning" or "held_out"), in GRID's order."""
    if part not in PARTS:
        raise ValueError(f"part must be one of {', '.join(PARTS)}, got {part!r}")
    return tuple(spec for spec in GRID if spec.part == part)


def spec(name: str) -> GridSpec:
    """The grid scene named ``name``, or the one whose name starts with it (``"aerial-s210"``)."""
    found = [s for s in GRID if s.name == name] or [s for s in GRID if s.name.startswith(name)]
    if len(found) != 1:
        raise ValueError(f"{name!r} names {len(found)} grid scenes, not one")
    return found[0]


def scenes(part: str) -> Iterator[tuple[str, SceneConfig]]:
    """(name, SceneConfig) of every scene of one part, in GRID's order."""
    for spec in specs(part):
        yield spec.name, spec.scene_config()


#: The levels :func:`random_spec` draws from (each uniformly, in this order); the offsets add -0.5 and +0.7 px
#: to the grid's
RANDOM_LEVELS = {
    "scenario": ("street", "aerial"), "steps": (200, 250, 300, 350, 400), "pixel_sigma": (0.25, 0.5, 0.75, 1.0),
    "drift": ("off", "on", "heavy"), "repeats": (False, True), "disparity_offset": (0.0, 0.0, -1.0, -0.5, 0.7),
    "outlier_share": (0.0, 0.03), "jitter": (False, True), "velocity_noise": ("low", "mid", "high"),
    "velocity_index": ("this", "next"),
}


def random_spec(seed: int) -> GridSpec:
    """A scene spec off the grid: every factor drawn from :data:`RANDOM_LEVELS` by a generator seeded
    with ``seed`` (the same seed, the same spec), for checks on scenes no option was chosen on."""
    rng = np.random.default_rng(seed)
    draw = {key: levels[int(rng.integers(len(levels)))] for key, levels in RANDOM_LEVELS.items()}
    return GridSpec(seed=seed, **draw)
