"""The one place for every noise, prior and threshold of the estimator.

`FilterConfig` is a typed dataclass; :func:`load_config` reads it from TOML (flat keys or a
``[filter]`` table) and :func:`apply_overrides` sets single keys from ``KEY=VALUE`` strings as
given on the command line (``vislam run --set pixel_sigma=1.5``). Unknown keys and values of
the wrong type are refused with a :class:`~backend.errors.ConfigError`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Optional

from backend.errors import ConfigError
from backend.landmarks import PARAMETRIZATIONS

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

MODES = ("slam", "mapping", "dead-reckoning")
IMU_FLIP_CHOICES = ("auto", "yes", "no")
VELOCITY_INDEX_CHOICES = ("auto", "this", "next")
REPEATED_FRAME_CHOICES = ("use", "skip", "cut")
ERROR_MODELS = ("invariant", "body")
TRACK_DRIFT_CHOICES = ("auto", "yes", "no")


@dataclass
class FilterConfig:
    """Estimator options. Units: metres, seconds, radians, pixels. ``None`` = estimate from data."""

    # --- what to estimate
    mode: str = "slam"  # slam | mapping (poses from dead reckoning held fixed) | dead-reckoning
    full_state: bool = False  # keep every landmark in the state (course formulation) instead of marginalizing ended tracks
    max_state_mib: float = 256.0  # refuse --full-state when the dense covariance would exceed this (~1900 landmarks)
    estimate_gyro_bias: bool = True  # 3 gyro-bias states (random walk)
    gyro_bias_min_observations: float = 10.0  # ... only with at least this many stereo observations per step on average

    # --- data conventions (checked by backend.conventions)
    imu_flip: str = "auto"  # auto | yes | no: flip the IMU's y and z axes, diag(1,-1,-1,1) @ imu_T_cam
    velocity_index: str = "auto"  # auto | this | next: velocity stamped k (this) or k+1 (next) drives step k -> k+1
    convention_horizon: int = 3  # steps between triangulation and reprojection in the convention test
    online_convention_steps: int = 100  # image input (one pass): the test runs on the first frames, from 20 on
    # every 10 until one variant fits >= 10 % better than all others, at most this many frames

    # --- IMU noise: white noise per axis of the velocity measurements (None: estimated from the data)
    linear_velocity_sigma: Optional[float] = None  # m/s
    angular_velocity_sigma: Optional[float] = None  # rad/s
    linear_velocity_sigma_floor: float = 0.5  # m/s: an estimated white noise below this is raised to it (model error of clean-looking velocities)
    angular_velocity_sigma_floor: float = 0.002  # rad/s, likewise
    gyro_bias_sigma0: float = 0.005  # rad/s: prior standard deviation of the gyro bias
    gyro_bias_random_walk: float = 2e-4  # rad/s/sqrt(s)
    initial_pose_sigma: float = 1e-6  # the world frame is the first pose

    # --- camera
    pixel_sigma: float = 1.5  # px, per coordinate of z = [uL, vL, uR, vR]
    image_width: Optional[float] = None  # px; None: 2.5 cx (the files carry no image size)
    image_height: Optional[float] = None  # px; None: 2.5 cy

    # --- landmarks
    landmark_parametrization: str = "xyz"  # xyz | inverse-depth (anchored) (backend.landmarks)
    unbiased_triangulation: bool = True  # xyz: start at E[triangulation] under pixel_sigma (unscented), not at the biased point
    min_disparity: float = 0.0  # px: a landmark is initialized only from an observation with larger disparity
    max_depth: Optional[float] = 1000.0  # m: ... and nearer than this (xyz variance grows as depth^4; None: no limit)
    gate_probability: float = 0.999  # chi-square (4 dof) Mahalanobis gate per observation
    ransac_threshold_px: float = 2.0  # 1-point RANSAC inlier threshold (px, norm of the 4-vector); 0: off
    persistent_outlier_steps: int = 10  # a track RANSAC rejects this many steps in a row is no longer rescued (0: always)
    error_model: str = "invariant"  # invariant (right-invariant, xyz landmarks; backend.invariant) | body (mu exp(xi^))
    first_estimate_jacobians: bool = True  # body error model: linearize at each landmark's first estimate (FEJ)
    max_consecutive_gated: int = 3  # a landmark gated this many times in a row is dropped (bad initialization)
    track_drift: str = "auto"  # auto | yes | no: model tracks that drift with age (the two below); auto: not for vislam's or synthetic tracks
    landmark_random_walk: float = 0.05  # m/sqrt(s): with track drift, each xyz landmark's position random-walks
    repeated_frames: str = "use"  # use | skip | cut: steps repeating the previous step's pixels (backend.timing)
    reanchor_observations: int = 3  # with track drift, a landmark is re-triangulated after this many observations (0: never)
    reanchor_far_observations: int = 25  # ... or this many when it was anchored with disparity < reanchor_far_disparity (0: never)
    reanchor_far_disparity: float = 6.0  # px

    # --- health checks
    nis_window: int = 50  # steps in the moving NIS average
    nis_warn_factor: float = 3.0  # warn when the windowed NIS per observation leaves [4/f, 4 f]

    # --- execution
    blas_threads: int = 1  # BLAS threads; small matrices run 5-20x slower with more than one

    def validate(self) -> "FilterConfig":
        """Raise ConfigError on an invalid value; return self."""
        _choice("mode", self.mode, MODES)
        _choice("imu_flip", self.imu_flip, IMU_FLIP_CHOICES)
        _choice("velocity_index", self.velocity_index, VELOCITY_INDEX_CHOICES)
        _choice("landmark_parametrization", self.landmark_parametrization, PARAMETRIZATIONS)
        _choice("repeated_frames", self.repeated_frames, REPEATED_FRAME_CHOICES)
        _choice("error_model", self.error_model, ERROR_MODELS)
        _choice("track_drift", self.track_drift, TRACK_DRIFT_CHOICES)
        if self.error_model == "invariant" and self.landmark_parametrization != "xyz":
            raise ConfigError(
                "config key 'error_model': 'invariant' needs landmark_parametrization 'xyz'; "
                f"use error_model 'body' with {self.landmark_parametrization!r}"
            )
        positive = [
            "pixel_sigma", "linear_velocity_sigma_floor", "angular_velocity_sigma_floor",
            "gyro_bias_sigma0", "gyro_bias_random_walk", "initial_pose_sigma",
            "nis_warn_factor", "max_state_mib",
        ]
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"config key '{name}': must be a finite number > 0, got {value!r}")
        for name in ("linear_velocity_sigma", "angular_velocity_sigma", "image_width", "image_height", "max_depth"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ConfigError(f"config key '{name}': must be > 0 or unset, got {value!r}")
        if self.nis_warn_factor <= 1:
            raise ConfigError(f"config key 'nis_warn_factor': must be > 1, got {self.nis_warn_factor!r}")
        if (self.image_width is None) != (self.image_height is None):
            raise ConfigError("config keys 'image_width' and 'image_height': set both or neither")
        if not 0.5 < self.gate_probability < 1.0:
            raise ConfigError(f"config key 'gate_probability': must lie in (0.5, 1), got {self.gate_probability!r}")
        if not (math.isfinite(self.landmark_random_walk) and self.landmark_random_walk >= 0):
            raise ConfigError(f"config key 'landmark_random_walk': must be a finite number >= 0, got {self.landmark_random_walk!r}")
        for name in ("reanchor_observations", "reanchor_far_observations", "persistent_outlier_steps"):
            if getattr(self, name) < 0:
                raise ConfigError(f"config key '{name}': must be an integer >= 0 (0: never), got {getattr(self, name)!r}")
        if not (math.isfinite(self.reanchor_far_disparity) and self.reanchor_far_disparity >= 0):
            raise ConfigError(f"config key 'reanchor_far_disparity': must be a finite number >= 0, got {self.reanchor_far_disparity!r}")
        if self.min_disparity < 0:
            raise ConfigError(f"config key 'min_disparity': must be >= 0, got {self.min_disparity!r}")
        for name in ("convention_horizon", "online_convention_steps", "nis_window", "blas_threads", "max_consecutive_gated"):
            if getattr(self, name) < 1:
                raise ConfigError(f"config key '{name}': must be an integer >= 1, got {getattr(self, name)!r}")
        return self

    @property
    def image_size(self) -> tuple[float, float] | None:
        """(width, height) for the loader's outside-the-image check, or None to infer it from K."""
        return None if self.image_width is None else (self.image_width, self.image_height)

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def describe(self) -> str:
        """Multi-line listing printed at the start of a run (OpenVINS style)."""
        width = max(len(f.name) for f in fields(self))
        return "\n".join(f"  {f.name:<{width}} = {getattr(self, f.name)!r}" for f in fields(self))


def _choice(name: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ConfigError(f"config key '{name}': must be one of {', '.join(choices)}, got {value!r}")


def coerce_value(cls: type, name: str, value: Any, label: str = "config key") -> Any:
    """Convert a TOML or command-line value to the declared type of field ``name`` of the config
    dataclass ``cls`` (bool, int, float, str, Optional of those). Shared by every component's config."""
    types = {f.name: str(f.type) for f in fields(cls)}
    if name not in types:
        raise ConfigError(f"unknown {label} '{name}' (known: {', '.join(sorted(types))})")
    declared = types[name]
    optional = declared.startswith("Optional")
    if isinstance(value, str):
        text = value.strip()
        if optional and text.lower() in ("none", "null", "auto", ""):
            return None
        if "bool" in declared:
            if text.lower() in ("1", "true", "yes", "on"):
                return True
            if text.lower() in ("0", "false", "no", "off"):
                return False
            raise ConfigError(f"config key '{name}': expected true or false, got {value!r}")
        if "int" in declared:
            try:
                return int(text)
            except ValueError:
                raise ConfigError(f"config key '{name}': expected an integer, got {value!r}") from None
        if "float" in declared:
            try:
                return float(text)
            except ValueError:
                raise ConfigError(f"config key '{name}': expected a number, got {value!r}") from None
        return text
    if value is None and optional:
        return None
    if "bool" in declared:
        if not isinstance(value, bool):
            raise ConfigError(f"config key '{name}': expected true or false, got {value!r}")
        return value
    if "int" in declared:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"config key '{name}': expected an integer, got {value!r}")
        return value
    if "float" in declared:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"config key '{name}': expected a number, got {value!r}")
        return float(value)
    if not isinstance(value, str):
        raise ConfigError(f"config key '{name}': expected a string, got {value!r}")
    return value


def replace_validated(cls: type, values: dict[str, Any], base=None, label: str = "config key"):
    """A ``cls`` instance with ``values`` (coerced) applied over ``base`` (default: the defaults), validated."""
    config = dataclasses.replace(base) if base is not None else cls()
    for name, value in values.items():
        setattr(config, name, coerce_value(cls, name, value, label))
    return config.validate()


def read_toml(path: str | Path) -> dict[str, Any]:
    """The tables of a TOML configuration file; ConfigError naming the file otherwise."""
    path = Path(path)
    try:
        with open(path, "rb") as handle:
            return tomllib.load(handle)
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None


def parse_assignment(item: str) -> tuple[str, str]:
    """``KEY=VALUE`` of the command line's ``--set`` -> (key with - as _, value)."""
    if "=" not in item:
        raise ConfigError(f"--set {item!r}: expected KEY=VALUE")
    key, value = item.split("=", 1)
    return key.strip().replace("-", "_"), value


def config_from_dict(values: dict[str, Any], base: FilterConfig | None = None) -> FilterConfig:
    """A FilterConfig with ``values`` applied over ``base`` (default: the defaults)."""
    return replace_validated(FilterConfig, values, base)


def load_config(path: str | Path, base: FilterConfig | None = None) -> FilterConfig:
    """Read a TOML file: keys at the top level or in a ``[filter]`` table (a ``[tracker]`` table is
    the front end's and is skipped here)."""
    path = Path(path)
    data = {k: v for k, v in read_toml(path).items() if k != "tracker"}  # the front end's table (frontend.config)
    table = data.get("filter", data)
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: key 'filter' must be a table")
    if "filter" in data and len(data) > 1:
        others = ", ".join(sorted(k for k in data if k != "filter"))
        raise ConfigError(f"{path}: keys outside the [filter] table ({others}); put every key inside it")
    try:
        return config_from_dict(table, base)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def apply_overrides(config: FilterConfig, assignments: list[str]) -> FilterConfig:
    """Apply ``KEY=VALUE`` strings (command line ``--set``)."""
    return config_from_dict(dict(parse_assignment(a) for a in assignments), config)


def to_toml(config: FilterConfig) -> str:
    """Serialize as a ``[filter]`` TOML table (unset optional keys are written as comments)."""
    lines = ["[filter]"]
    for f in fields(config):
        value = getattr(config, f.name)
        if value is None:
            lines.append(f"# {f.name} =   # unset: estimated from the data")
        elif isinstance(value, bool):
            lines.append(f"{f.name} = {'true' if value else 'false'}")
        elif isinstance(value, str):
            lines.append(f'{f.name} = "{value}"')
        else:
            lines.append(f"{f.name} = {value!r}")
    return "\n".join(lines) + "\n"
