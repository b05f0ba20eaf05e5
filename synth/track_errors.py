"""Errors of synthetic feature tracks that look like a real tracker's, with their true values.

:class:`TrackErrors` is every error of the observations (its defaults: white noise of 0.5 px and
nothing else); :data:`PRESETS` names sets of values. The model, for the point p of track t seen at
step k, ``a`` frames after the track's first observation (z = [uL, vL, uR, vR], px):

    C_k = W_k T_k,  W_0 = I,  W_k = W_{k-1} T_{k-1} T_k^-1 if step k repeats, else W_{k-1}      (R)
    cam'_T_world_k = exp(xi_k^) cam_T_imu C_k^-1                                               (J)
    z = Ks pi(cam'_T_world_k p) - [0, 0, beta, 0] + sigma n + [e_t(a), e_t(a)]                 (Z)
    e_t(a) = a v_t + sigma_w sum_{i=1..a} m_{t,i} + [a >= a_t] j_t                             (E)

* repeated frames (R): T_k is the true world_T_imu; the repeated steps k (gaps between them
  uniform on the integers [max(2, round(2 m / 3)), max(2, round(4 m / 3))], m = repeat_interval)
  hold step k-1's observations exactly (ids and pixels), and the content after them misses the
  motion k-1 -> k: C_{k+1} = C_{k-1} T_k^-1 T_{k+1}, as if the world had moved with the camera.
  The IMU and the ground truth stay on T_k.
* frame jitter (J): xi_k = [rho_k (m), phi_k (rad)] in the camera frame, first-order Gauss-Markov
  xi_k = c xi_{k-1} + sqrt(1 - c^2) s n_k, xi_0 = s n_0, s = (jitter_translation x3,
  jitter_rotation x3), c = jitter_correlation (0: white); a repeated step shows its frame's xi.
* disparity offset (Z): d_measured = d_true + beta (beta = disparity_offset; uR moves by -beta).
* white noise (Z): sigma = pixel_sigma, n ~ N(0, I_4).
* drift (E), common to both images (the track slides in the left image, its stereo match
  follows): v_t = s_t (cos theta_t, sin theta_t) px/step, s_t = drift_median exp(drift_log_sigma
  g_t) (log-normal, heavy-tailed) for a share drift_share of the tracks, else 0; theta_t uniform;
  a random walk of sigma_w = drift_walk px/sqrt(step) on every track (m ~ N(0, I_2)).
* bad tracks: a share bad_share of the tracks, half of them (kind ``JUMP``) jump by j_t
  (|j_t| = bad_jump U(0.5, 1.5), uniform direction) at an age a_t uniform on 1 .. length-1
  (tracks of 2 or more observations), the other half (kind ``FAST``) drift at |v_t| = bad_drift U(0.5, 1.5) instead of v_t.
* a track ends at its first observation whose pixels leave the image (the tracker lost it);
  gross outliers (a share outlier_share of the observations) get a uniform random pixel.

Each effect draws from its own random stream (``synth._random``), so switching one on leaves the
others' random numbers as they are; what it can change is which observations exist (repeats and
jitter move the content, drift ends tracks early) and so which number falls on which observation.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
from dataclasses import dataclass, field, fields
from typing import Any, Iterable, Mapping, NamedTuple

import numpy as np

from ..backend.errors import ConfigError
from ..backend.options import OptionTable

__all__ = [
    "TrackErrors",
    "TrackErrorTruth",
    "PRESETS",
    "KITTI_LIKE",
    "DRIFTING_TRACKER",
    "GOOD",
    "JUMP",
    "FAST",
    "repeated_steps",
    "content_poses",
    "jitter_series",
    "jittered_poses",
    "track_offsets",
]

#: ``Sequence.tracker`` of a synthetic scene whose tracks drift (drift, random walk or bad tracks);
#: a scene with exact tracks keeps ``backend.data.sequence.SYNTHETIC_TRACKER``.
DRIFTING_TRACKER = "synthetic-drifting"

#: Kinds of track in ``TrackErrorTruth.bad``
GOOD, JUMP, FAST = 0, 1, 2


def _help(text: str) -> dict:
    return {"help": text}


@dataclass(frozen=True)
class TrackErrors:
    """Every error of a synthetic scene's observations (the model: this module's docstring).

    The defaults are the scene's white noise alone; ``TrackErrors.from_values`` and
    ``with_assignments`` read ``KEY=VALUE`` strings and TOML values as the ``[track_errors]`` table.
    """

    pixel_sigma: float = field(default=0.5, metadata=_help("px: white noise of each of uL vL uR vR"))
    outlier_share: float = field(default=0.0, metadata=_help("share of observations replaced by a random pixel"))
    drift_share: float = field(default=0.0, metadata=_help("share of tracks with a drift velocity"))
    drift_median: float = field(default=0.05, metadata=_help("px/step: median drift speed (log-normal)"))
    drift_log_sigma: float = field(default=1.2, metadata=_help("sigma of ln(drift speed): the tail's weight"))
    drift_walk: float = field(default=0.0, metadata=_help("px/sqrt(step): random walk of every track"))
    bad_share: float = field(default=0.0, metadata=_help("share of bad tracks (half jump, half drift fast)"))
    bad_jump: float = field(default=5.0, metadata=_help("px: typical jump of a bad track (x U(0.5, 1.5))"))
    bad_drift: float = field(default=1.0, metadata=_help("px/step: typical speed of a fast bad track (x U(0.5, 1.5))"))
    disparity_offset: float = field(default=0.0, metadata=_help("px: beta in d_measured = d_true + beta"))
    repeat_interval: float = field(default=0.0, metadata=_help("steps: mean gap between repeated frames (0: none)"))
    jitter_rotation: float = field(default=0.0, metadata=_help("rad: frame jitter of the camera's rotation, per axis"))
    jitter_translation: float = field(default=0.0, metadata=_help("m: frame jitter of the camera's position, per axis"))
    jitter_correlation: float = field(default=0.0, metadata=_help("jitter's correlation from step to step (0: white)"))

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
                raise _bad(f.name, "must be a finite number", value)
            object.__setattr__(self, f.name, float(value))
        for key in ("outlier_share", "drift_share", "bad_share"):
            if not 0.0 <= getattr(self, key) <= 1.0:
                raise _bad(key, "must be in [0, 1]", getattr(self, key))
        for key in ("pixel_sigma", "drift_log_sigma", "drift_walk", "bad_jump", "bad_drift", "jitter_rotation",
                    "jitter_translation"):
            if getattr(self, key) < 0.0:
                raise _bad(key, "must be >= 0", getattr(self, key))
        if not self.drift_median > 0.0:
            raise _bad("drift_median", "must be > 0 px/step", self.drift_median)
        if not (self.repeat_interval == 0.0 or self.repeat_interval >= 2.0):
            raise _bad("repeat_interval", "must be 0 (no repeats) or >= 2 steps", self.repeat_interval)
        if not 0.0 <= self.jitter_correlation < 1.0:
            raise _bad("jitter_correlation", "must be in [0, 1)", self.jitter_correlation)

    # -- which effects are on
    @property
    def drifts(self) -> bool:
        """Whether tracks drift (a drift velocity, a random walk or bad tracks)."""
        return self.drift_share > 0.0 or self.drift_walk > 0.0 or self.bad_share > 0.0

    @property
    def jitters(self) -> bool:
        return self.jitter_rotation > 0.0 or self.jitter_translation > 0.0

    def effects(self) -> tuple[str, ...]:
        """The options beyond white noise and outliers that are on (empty: the exact-track scene)."""
        on = [key for key in ("drift_share", "drift_walk", "bad_share", "disparity_offset", "repeat_interval",
                              "jitter_rotation", "jitter_translation") if getattr(self, key) != 0.0]
        return tuple(on)

    # -- reading and writing
    @classmethod
    def from_values(cls, values: Mapping[str, Any], base: "TrackErrors | None" = None) -> "TrackErrors":
        """``values`` (key -> number or string) over ``base`` (default: the defaults); ConfigError
        naming the key for an unknown key or a value of the wrong type or range."""
        table = _option_table()
        start = table(**(base or cls()).as_dict())
        return cls(**table.from_values(dict(values), start).as_dict())

    def with_assignments(self, assignments: Iterable[str]) -> "TrackErrors":
        """A copy with ``KEY=VALUE`` (or ``track_errors.KEY=VALUE``) strings applied."""
        values = {}
        for item in assignments:
            key, eq, value = item.partition("=")
            if not eq:
                raise ConfigError(f"track errors: {item!r}: expected KEY=VALUE (keys: {', '.join(self.keys())})")
            key = key.strip().replace("-", "_")
            values[key[len(_TABLE) + 1:] if key.startswith(_TABLE + ".") else key] = value
        return TrackErrors.from_values(values, self)

    @classmethod
    def keys(cls) -> list[str]:
        return [f.name for f in fields(cls)]

    def as_dict(self) -> dict[str, float]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def describe(self) -> str:
        """One line: the options that differ from the defaults (``key=value``), or the default's white noise."""
        default = TrackErrors()
        changed = [f"{k}={v:g}" for k, v in self.as_dict().items() if v != getattr(default, k)]
        return ", ".join(changed) if changed else f"pixel_sigma={self.pixel_sigma:g} (white noise only)"

    @classmethod
    def help_lines(cls) -> list[str]:
        """``key (default): what it is`` per option, for the command's help."""
        default = cls()
        return [f"{f.name} ({getattr(default, f.name):g}): {f.metadata['help']}" for f in fields(cls)]


_TABLE = "track_errors"


def _bad(key: str, what: str, value) -> ConfigError:
    return ConfigError(f"synthetic scene: {key} {what}, got {value!r}")


@functools.lru_cache(maxsize=None)
def _option_table() -> type[OptionTable]:
    """TrackErrors' fields as the ``[track_errors]`` OptionTable (coercion of strings and TOML values,
    unknown keys named); its check is TrackErrors' own."""

    def check(self) -> None:
        TrackErrors(**self.as_dict())

    specs = [(f.name, float, field(default=f.default)) for f in fields(TrackErrors)]
    return dataclasses.make_dataclass("TrackErrorTable", specs, bases=(OptionTable,),
                                      namespace={"TABLE": _TABLE, "check": check})


#: Values measured on the KITTI course feature files: white noise 0.25 px; 70 % of tracks drift,
#: median 0.05 px/step, ~3 % of those faster than 0.5 px/step; a random walk of 0.05 px/sqrt(step);
#: 2 % bad tracks; beta -0.5 px; a repeated frame every ~12 steps; 2e-4 rad of white frame jitter.
KITTI_LIKE = TrackErrors(
    pixel_sigma=0.25,
    drift_share=0.7,
    drift_median=0.05,
    drift_log_sigma=1.2,
    drift_walk=0.05,
    bad_share=0.02,
    disparity_offset=-0.5,
    repeat_interval=12.0,
    jitter_rotation=2e-4,
)

#: The named sets of values (``vislam synth --track-errors``)
PRESETS: dict[str, TrackErrors] = {"none": TrackErrors(), "kitti-like": KITTI_LIKE}


class TrackErrorTruth(NamedTuple):
    """The drawn values of a scene's track errors (K tracks by id, N steps)."""

    repeated: np.ndarray  # (N,) bool: step k holds step k-1's observations
    world_T_imu_content: np.ndarray  # (N,4,4) C_k, the poses the observations were projected from (before jitter)
    jitter: np.ndarray  # (N,6) xi_k = [rho (m), phi (rad)] of the frame each step shows
    drift_velocity: np.ndarray  # (K,2) px/step v_t in (u, v), both images
    bad: np.ndarray  # (K,) int8: GOOD, JUMP or FAST
    jump: np.ndarray  # (K,2) px j_t (zero unless JUMP)
    jump_step: np.ndarray  # (K,) int64: step of the first jumped observation; -1: none, or the track ended before


# ----------------------------------------------------------------------------------------------
# the draws


def repeated_steps(num_steps: int, interval: float, rng: np.random.Generator) -> np.ndarray:
    """(N,) bool: the repeated steps (R); gaps uniform on [max(2, round(2m/3)), max(2, round(4m/3))]."""
    repeated = np.zeros(int(num_steps), dtype=bool)
    if interval <= 0.0:
        return repeated
    low = max(2, int(round(2.0 * interval / 3.0)))
    high = max(low, int(round(4.0 * interval / 3.0)))
    positions = np.cumsum(rng.integers(low, high + 1, size=int(num_steps) // low + 2))
    repeated[positions[positions < num_steps]] = True
    return repeated


def content_poses(world_T_imu: np.ndarray, repeated: np.ndarray) -> np.ndarray:
    """(N,4,4) C_k = W_k T_k of (R); C_k = C_{k-1} exactly at a repeated step."""
    from ..backend.geometry import se3

    T = np.asarray(world_T_imu, dtype=float)
    C = T.copy()
    W = np.eye(4)
    bounds = [*np.flatnonzero(repeated).tolist(), T.shape[0]]
    for k, end in zip(bounds[:-1], bounds[1:]):
        W = W @ T[k - 1] @ se3.inverse(T[k])
        C[k + 1:end] = W @ T[k + 1:end]
        C[k] = C[k - 1]
    return C


def jitter_series(num_steps: int, rotation: float, translation: float, correlation: float,
                  rng: np.random.Generator) -> np.ndarray:
    """(N,6) xi_k = [rho, phi] of (J): stationary first-order Gauss-Markov, per-axis std
    ``translation`` (m) and ``rotation`` (rad), correlation ``correlation`` from step to step."""
    scale = np.array([translation] * 3 + [rotation] * 3)
    white = rng.standard_normal((int(num_steps), 6)) * scale
    xi = white.copy()
    if correlation > 0.0:
        innovation = math.sqrt(1.0 - correlation * correlation)
        for k in range(1, xi.shape[0]):
            xi[k] = correlation * xi[k - 1] + innovation * white[k]
    return xi


def jittered_poses(world_T_imu: np.ndarray, xi: np.ndarray, imu_T_cam: np.ndarray) -> np.ndarray:
    """(N,4,4) world_T_imu' with cam_T_imu world_T_imu'^-1 = exp(xi^) cam_T_imu world_T_imu^-1 (J),
    i.e. world_T_imu' = world_T_imu imu_T_cam exp(-xi^) cam_T_imu."""
    from ..backend.geometry import se3

    imu_T_cam = np.asarray(imu_T_cam, dtype=float)
    cam_T_imu = se3.inverse(imu_T_cam)
    return np.asarray(world_T_imu, dtype=float) @ imu_T_cam @ se3.exp_se3_batch(-np.asarray(xi)) @ cam_T_imu


class TrackOffsets(NamedTuple):
    offsets: np.ndarray  # (n,2) px e_t(a) of each observation, added to (uL, vL) and (uR, vR)
    drift_velocity: np.ndarray  # (T,2) px/step, per track index
    bad: np.ndarray  # (T,) int8
    jump: np.ndarray  # (T,2) px
    jump_age: np.ndarray  # (T,) int64; the track's length when it does not jump


def track_offsets(track: np.ndarray, age: np.ndarray, length: np.ndarray, errors: TrackErrors,
                  rng_drift: np.random.Generator, rng_bad: np.random.Generator) -> TrackOffsets:
    """The offsets e_t(a) of (E) for observations (n,) sorted by track, then age (``track``: index
    0..T-1, ``age``: 0 at a track's first observation, ``length``: (T,) observations per track)."""
    n, num = track.shape[0], length.shape[0]
    velocity = np.zeros((num, 2))
    walk = np.zeros((n, 2))
    if errors.drift_share > 0.0 or errors.drift_walk > 0.0:
        share, log_speed = rng_drift.random(num), rng_drift.standard_normal(num)
        angle = rng_drift.uniform(0, 2 * np.pi, num)
        steps = rng_drift.standard_normal((n, 2))
        speed = errors.drift_median * np.exp(errors.drift_log_sigma * log_speed)
        speed[share >= errors.drift_share] = 0.0
        velocity = speed[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
        steps[age == 0] = 0.0
        walk = np.cumsum(errors.drift_walk * steps, axis=0)
        walk -= walk[np.flatnonzero(age == 0)][track]  # the sum over this track's own steps only
    bad = np.zeros(num, dtype=np.int8)
    jump = np.zeros((num, 2))
    jump_age = length.astype(np.int64).copy()
    if errors.bad_share > 0.0:
        share, kind, size, angle, position = rng_bad.random((5, num))
        direction = np.stack([np.cos(2 * np.pi * angle), np.sin(2 * np.pi * angle)], axis=1)
        picked = share < errors.bad_share
        fast = picked & (kind >= 0.5)
        jumps = picked & (kind < 0.5) & (length >= 2)
        bad[fast], bad[jumps] = FAST, JUMP
        velocity[fast] = (errors.bad_drift * (0.5 + size[fast]))[:, None] * direction[fast]
        jump[jumps] = (errors.bad_jump * (0.5 + size[jumps]))[:, None] * direction[jumps]
        jump_age[jumps] = 1 + np.floor(position[jumps] * (length[jumps] - 1)).astype(np.int64)
    offsets = age[:, None] * velocity[track] + walk + (age >= jump_age[track])[:, None] * jump[track]
    return TrackOffsets(offsets, velocity, bad, jump, jump_age)
