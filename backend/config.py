"""The one place for every option of the estimator and of a run, with its default.

:class:`Config` is a typed dataclass of tables, one per component (as OpenVINS groups its
options): ``[estimator]`` what is estimated, ``[noise]`` the noise model, ``[update]`` gating and
outliers, ``[landmarks]`` their parametrization and initialization, ``[drift]`` the model of
drifting feature tracks, ``[health]`` the consistency check, ``[conventions]`` the data
conventions a run decides, ``[input]`` the loader and ``[execution]`` threads. It is read from
TOML (:meth:`Config.load`) and from ``--set TABLE.KEY=VALUE`` (:meth:`Config.with_assignments`);
the front end's ``[tracker]`` table lives in ``frontend.config``. Units: metres, seconds,
radians, pixels; ``None`` (unset) means "estimate from the data".

Choices are enums whose values are the strings of the TOML file and the command line.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Optional

from .errors import ConfigError
from .options import OptionSet, OptionTable

__all__ = [
    "Config", "EstimatorOptions", "NoiseOptions", "UpdateOptions", "LandmarkOptions", "DriftOptions",
    "HealthOptions", "ConventionOptions", "InputOptions", "ExecutionOptions",
    "StrChoice", "Mode", "ErrorModel", "Parametrization", "Choice", "VelocityIndex", "RepeatedFrames",
    "StereoOffsetModel",
]


class StrChoice(str, enum.Enum):
    """A choice whose value is its string in TOML, on the command line and when printed."""

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)

    __hash__ = str.__hash__  # a dict keyed by the strings finds the members too


class Mode(StrChoice):
    """What is estimated."""

    SLAM = "slam"  # pose and landmarks
    MAPPING = "mapping"  # landmarks only; the poses of dead reckoning held fixed
    DEAD_RECKONING = "dead-reckoning"  # the IMU alone


class ErrorModel(StrChoice):
    """How the estimate's error is parametrized (``backend.estimator.invariant`` / ``.body``)."""

    INVARIANT = "invariant"  # right-invariant error of pose and world-xyz landmarks, SE_{K+1}(3)
    BODY = "body"  # the course's right perturbation mu exp(xi^)


class Parametrization(StrChoice):
    """Landmark parameters (``backend.estimator.landmarks``)."""

    XYZ = "xyz"  # world position
    INVERSE_DEPTH = "inverse-depth"  # anchored inverse depth


class Choice(StrChoice):
    """A yes/no decision that may be left to the data."""

    AUTO = "auto"
    YES = "yes"
    NO = "no"


class VelocityIndex(StrChoice):
    """Which velocity sample drives the step k -> k+1."""

    AUTO = "auto"
    THIS = "this"  # the one stamped k
    NEXT = "next"  # the one stamped k+1


class StereoOffsetModel(StrChoice):
    """Which disparity offset a run removes (``backend.run.stereo_offset``, D1)."""

    CONSTANT = "constant"  # one offset for the whole input, when the data shows one
    RATE = "rate"  # a constant plus a term in the turn rate (a right image exposed late), each when shown
    OFF = "off"  # none; nothing estimated


class RepeatedFrames(StrChoice):
    """What to do with a step whose pixels repeat the previous step's (``backend.run.timing``)."""

    FREEZE = "freeze"  # the content froze: landmarks move with the camera for the step (I8); IMU + motion prior
    USE = "use"  # use the repeated pixels as a new frame
    SKIP = "skip"  # do not use them
    CUT = "cut"  # end every track (the IMU alone bridges the step)


@dataclass
class EstimatorOptions(OptionTable):
    """What the filter estimates, and how its error is modelled."""

    TABLE = "estimator"
    mode: Mode = Mode.SLAM
    error_model: ErrorModel = ErrorModel.INVARIANT
    full_state: bool = False  # keep every landmark in the state (course formulation) instead of marginalizing ended tracks
    max_state_mib: float = 256.0  # refuse full_state when the dense covariance would exceed this (~1900 landmarks)
    estimate_stereo_offset: bool = False  # the residual disparity offset (noise.stereo_offset_sigma) estimated
    # (O1-O3); false: a consider state, its uncertainty carried into the poses and landmarks, its mean held (O4)
    estimate_lever_arm: bool = False  # the residual lever arm of the IMU's velocities (noise.lever_arm_sigma)
    # estimated (V1); false: considered, the estimate as without it and its share in the covariance (V2)
    estimate_gyro_bias: bool = True  # 3 gyro-bias states (random walk) ...
    gyro_bias_min_observations: float = 10.0  # ... only with at least this many stereo observations per step on average
    first_estimate_jacobians: bool = True  # body error model: linearize at each landmark's first estimate (FEJ)
    window: int = 13  # a real IMU's SLAM run: a sliding window of this many pose clones and no landmark in the state (MSCKF, backend.estimator.window: 6-8x the landmarks' speed on a 20 Hz flight; the trajectory is each pose as its clone leaves, W8); 0: landmarks in the state (velocity and mapping runs always)

    def check(self) -> None:
        self.require_positive("max_state_mib")
        self.require_at_least(0.0, "gyro_bias_min_observations")
        self.require("window", self.window == 0 or self.window >= 2, "must be 0 (off) or at least 2 clones")


@dataclass
class NoiseOptions(OptionTable):
    """The noise model: pixels, IMU velocities (white noise per axis), gyro bias, initial pose."""

    TABLE = "noise"
    pixel_sigma: Optional[float] = None  # px, per coordinate of z = [uL, vL, uR, vR]; unset: identified (N2)
    pixel_variance_per_disparity: Optional[float] = None  # px^2 per px: sigma_i^2 = pixel_sigma^2 + this d_i (N5); unset: identified; 0: white
    linear_velocity_sigma: Optional[float] = None  # m/s; unset: identified from the data (N1, N3)
    angular_velocity_sigma: Optional[float] = None  # rad/s; unset: identified from the data (N1, N3)
    gyro_bias_sigma0: float = 0.005  # rad/s: prior standard deviation of the gyro bias
    gyro_bias_random_walk: float = 2e-4  # rad/s/sqrt(s)
    initial_pose_sigma: float = 1e-6  # the world frame is the first pose
    stereo_offset_sigma: Optional[float] = None  # px: prior sigma of the residual disparity offset the filter
    # estimates (O1 of backend.estimator.offset); unset: from the stereo offset's decision; 0: not estimated
    lever_arm_sigma: Optional[float] = None  # m: prior sigma per axis of the residual lever arm of the IMU's
    # velocities the filter carries (V1 of backend.estimator.lever_arm); unset: from N3's decision (V3); 0: none
    imu_rotation_sigma: Optional[float] = None  # deg: prior sigma per axis of the rotation of the IMU samples'
    # frame the filter considers with the lever arm (V4 of backend.estimator.lever_arm); unset: from N6's decision; 0: none

    def check(self) -> None:
        self.require_positive("gyro_bias_sigma0", "gyro_bias_random_walk", "initial_pose_sigma")
        self.require_positive("pixel_sigma", "linear_velocity_sigma", "angular_velocity_sigma", optional=True)
        for key in ("pixel_variance_per_disparity", "stereo_offset_sigma", "lever_arm_sigma", "imu_rotation_sigma"):
            if getattr(self, key) is not None:
                self.require_at_least(0.0, key)


@dataclass
class UpdateOptions(OptionTable):
    """The joint update: Mahalanobis gate, 1-point RANSAC, persistent outliers."""

    TABLE = "update"
    gate_probability: float = 0.999  # chi-square (4 dof) Mahalanobis gate per observation
    ransac_threshold_px: float = 2.0  # 1-point RANSAC inlier threshold (px, norm of the 4-vector); 0: off
    persistent_outlier_steps: int = 10  # a track RANSAC rejects this many steps in a row is no longer rescued (0: always)
    max_consecutive_gated: int = 3  # a landmark gated this many times in a row is dropped (bad initialization)
    huber_probability: float = 0.0  # Huber weights (U8): an observation whose NIS exceeds this chi-square (4 dof) quantile, below the gate, counts with its noise variance times sqrt(NIS / quantile); 0: off
    second_order: bool = True  # the stereo prediction's second-order terms: residual less 1/2 tr(H_j Sigma_q), S plus their covariance (U7, backend.estimator.update)
    zero_velocity: bool = True  # a real IMU's SLAM run: at frames where the IMU, the tracks and the filter's velocity say the rig stands still, v = 0 is measured before the frame's observations (backend.estimator.zero_velocity, Z6-Z9)

    def check(self) -> None:
        self.require("gate_probability", 0.5 < self.gate_probability < 1.0, "must lie in (0.5, 1)")
        self.require("huber_probability", self.huber_probability == 0.0 or 0.5 < self.huber_probability < 1.0,
                     "must be 0 (off) or lie in (0.5, 1)")
        self.require_at_least(0.0, "ransac_threshold_px", "persistent_outlier_steps")
        self.require_at_least(1, "max_consecutive_gated")


@dataclass
class LandmarkOptions(OptionTable):
    """Landmark parameters and when a new one is started."""

    TABLE = "landmarks"
    parametrization: Parametrization = Parametrization.XYZ
    unbiased_triangulation: bool = True  # xyz: start at E[triangulation] under pixel_sigma (unscented), not at the biased point
    min_disparity: float = 0.0  # px: a landmark is initialized only from an observation with larger disparity
    max_depth: Optional[float] = 1000.0  # m: ... and nearer than this (xyz variance grows as depth^4; unset: no limit)

    def check(self) -> None:
        self.require_at_least(0.0, "min_disparity")
        self.require_positive("max_depth", optional=True)


@dataclass
class DriftOptions(OptionTable):
    """Feature tracks that drift with their age: landmark random walk and re-anchoring."""

    TABLE = "drift"
    track_drift: Choice = Choice.AUTO  # model drifting tracks; auto: by the test on the tracks (T1, backend.run.drift)
    landmark_random_walk: Optional[float] = None  # m/sqrt(s): with track drift, every xyz landmark random-walks this much; unset: by its depth from the pixel walk (R3)
    pixel_walk: Optional[float] = None  # px^2 per step: a drifting track's pixel random walk at zero disparity (T3); unset: measured
    pixel_walk_per_disparity: Optional[float] = None  # px^2 per step and px of disparity (T3); unset: measured
    reanchor_observations: int = 3  # with track drift, a landmark is re-triangulated after this many observations (0: never)
    reanchor_far_observations: int = 25  # ... this many when anchored with disparity < reanchor_far_disparity (0: never)
    reanchor_far_disparity: float = 6.0  # px
    track_test_probability: float = 0.0  # (R4) a track whose whitened innovations, summed over its life, exceed this chi-square (3 dof) tail is dropped for good (runs with landmarks in the state: not a real IMU's window); 0: off
    track_test_min_observations: int = 3  # (R4) ... tested from this many of its observations on

    def check(self) -> None:
        self.require_at_least(0.0, "reanchor_observations", "reanchor_far_observations", "reanchor_far_disparity")
        self.require("track_test_probability", 0.0 <= self.track_test_probability < 0.5,
                     "must be 0 (off) or a tail probability in (0, 0.5)")
        self.require_at_least(1, "track_test_min_observations")
        for key in ("landmark_random_walk", "pixel_walk", "pixel_walk_per_disparity"):
            if getattr(self, key) is not None:
                self.require_at_least(0.0, key)


@dataclass
class HealthOptions(OptionTable):
    """The filter's consistency check (``backend.estimator.health``)."""

    TABLE = "health"
    nis_window: int = 50  # steps in the moving NIS average
    nis_warn_factor: float = 3.0  # warn when the windowed NIS per observation leaves [4/f, 4 f]

    def check(self) -> None:
        self.require_at_least(1, "nis_window")
        self.require("nis_warn_factor", self.nis_warn_factor > 1 and self.nis_warn_factor < float("inf"),
                     "must be a finite number > 1")


@dataclass
class ConventionOptions(OptionTable):
    """Data conventions a run decides from the data (``backend.run.conventions``, ``.stereo_offset``, ``.timing``)."""

    TABLE = "conventions"
    imu_flip: Choice = Choice.AUTO  # flip the IMU's y and z axes, diag(1,-1,-1,1) @ imu_T_cam
    velocity_index: VelocityIndex = VelocityIndex.AUTO  # velocity stamped k (this) or k+1 (next) drives step k -> k+1
    horizon: int = 3  # steps between triangulation and reprojection in the convention test
    online_steps: int = 100  # image input: the test runs on the first frames, from 20 on every 10, until
    # one variant fits >= 10 % better than all others, at most this many frames
    repeated_frames: RepeatedFrames = RepeatedFrames.FREEZE  # steps repeating the previous step's pixels
    stereo_offset: StereoOffsetModel = StereoOffsetModel.CONSTANT  # disparity offset identified from the tracks and
    # removed when significant (backend.run.stereo_offset): constant d_true = d - beta; rate: beta_0 + kappa omega_y; off
    stereo_offset_by_imu: bool = True  # where the tracks leave the offset open (> 1 % of scale), the one with which
    # the filter's scale over the first steps is the IMU's (D5); false: the tracks' estimate alone
    velocity_correction: Choice = Choice.AUTO  # the IMU's lever arm and velocity offset against vision (N3):
    # auto: removed when significant and dead reckoning agrees; yes: always removed; no: not estimated

    def check(self) -> None:
        self.require_at_least(1, "horizon", "online_steps")


@dataclass
class InputOptions(OptionTable):
    """The loader of feature files."""

    TABLE = "input"
    image_width: Optional[float] = None  # px; unset: 2.5 cx (the files carry no image size)
    image_height: Optional[float] = None  # px; unset: 2.5 cy

    def check(self) -> None:
        self.require_positive("image_width", "image_height", optional=True)
        if (self.image_width is None) != (self.image_height is None):
            raise ConfigError("config keys 'input.image_width' and 'input.image_height': set both or neither")

    @property
    def image_size(self) -> tuple[float, float] | None:
        """(width, height) for the loader's outside-the-image check, or None to infer it from K."""
        return None if self.image_width is None else (self.image_width, self.image_height)


@dataclass
class ExecutionOptions(OptionTable):
    """How the work runs."""

    TABLE = "execution"
    blas_threads: int = 1  # BLAS threads; the filter's ~200x200 matrices run 5-20x slower with more than one

    def check(self) -> None:
        self.require_at_least(1, "blas_threads")


#: Keys of the earlier flat configuration whose name changed with their table
_RENAMED = {
    "landmark_parametrization": "landmarks.parametrization",
    "convention_horizon": "conventions.horizon",
    "online_convention_steps": "conventions.online_steps",
}


@dataclass
class Config(OptionSet):
    """Every option of the estimator and of a run, by component (module docstring)."""

    estimator: EstimatorOptions = field(default_factory=EstimatorOptions)
    noise: NoiseOptions = field(default_factory=NoiseOptions)
    update: UpdateOptions = field(default_factory=UpdateOptions)
    landmarks: LandmarkOptions = field(default_factory=LandmarkOptions)
    drift: DriftOptions = field(default_factory=DriftOptions)
    health: HealthOptions = field(default_factory=HealthOptions)
    conventions: ConventionOptions = field(default_factory=ConventionOptions)
    input: InputOptions = field(default_factory=InputOptions)
    execution: ExecutionOptions = field(default_factory=ExecutionOptions)

    def check(self) -> None:
        if self.estimator.error_model == ErrorModel.INVARIANT and self.landmarks.parametrization != Parametrization.XYZ:
            raise ConfigError(
                "config key 'estimator.error_model': 'invariant' needs landmarks.parametrization 'xyz'; "
                f"use error_model 'body' with {self.landmarks.parametrization.value!r}"
            )

    @classmethod
    def moved(cls, key: str) -> str | None:
        if key in _RENAMED:
            return _RENAMED[key]
        for name, table in cls.table_types().items():
            if key in table.keys():
                return f"{name}.{key}"
        return None
