"""Everything a run decides from the data before its first step: one frozen :class:`Decisions`.

:func:`decide` looks at a sequence (a whole file, or the first frames of a stream) and answers,
each by a test whose numbers it keeps:

1. the extrinsic's axes and the velocity timing (C1, ``backend.run.conventions``);
2. which steps repeat the previous frame (``backend.run.timing``);
3. two-view fits of step pairs at gaps 1-3 (D2, ``backend.run.two_view``), from which
   - the stereo pair's disparity offset (D1, D3, ``backend.run.stereo_offset``), removed only if
     dead reckoning's reprojection (C1) does not get worse;
   - whether the tracks drift (T1, ``backend.run.drift``) and how fast (T3);
   - the pixel noise (N2, ``backend.run.noise``) of consecutive frames (over the gaps the filter's
     landmarks live through where drift has no measured walk), and its growth with disparity (N5);
   - the IMU against vision (N3): the lever arm and velocity offset of the IMU's velocities,
     removed when significant and dead reckoning agrees, and the IMU's noise per axis;
4. the IMU noise: configured, else against vision (N3) where enough step pairs exist, else the
   filter's own innovation likelihood over the first steps (sparse tracks), with the white noise
   of the samples (N1) as the smallest candidate: no floor is set by hand; a sigma from the white
   noise alone covers the error of holding a sample over its step (N4) where the likelihood
   prefers it;
5. whether the gyro bias is estimated (enough stereo observations a step to tell it from drift);
6. last, with every other decision taken, where the two-view offset leaves the scale open: the
   offset with which the filter's scale over the first steps is the IMU's (D5, H4).

:class:`~vislam.backend.run.online.OnlineRun` applies the record; ``decisions.describe()`` says
it, a line per decision, and ``as_dict()`` goes to summary.json. The configuration's explicit
values always win over the data.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..config import Choice, Config, Mode
from ..data.sequence import Sequence
from ..estimator.lever_arm import carried_prior
from .conventions import ConventionDecision, MatchedPairs, decide_conventions, matched_pairs, reprojection_error
from .drift import NOISE_MIN_POINTS, DriftDecision, decide_track_drift
from .noise import (
    LEVER_PRIOR_M, ROTATION_PRIOR_RAD, ImuNoiseDecision, ImuVsVision, PixelNoise, VelocityCorrection, disparity_noise, estimate_white_noise,
    gap_statistics, hold_error, imu_vs_vision, pixel_noise, with_disparity_noise,
)
from .stereo_offset import StereoOffset, offset_by_imu_scale, offset_from_fits
from .timing import repeated_steps
from .two_view import fit_pairs

__all__ = ["Decisions", "GyroBias", "decide"]

#: Two-view fits per gap: gap 1 serves the offset and the IMU test, the longer gaps the drift test
#: (T1, T3); gaps up to 3 are those the pixel noise may pool over (N2), the longest sees slow drift.
DRIFT_GAPS = (1, 2, 3, 10)
PAIRS_GAP1 = 300
PAIRS_LONGER = 100
#: A correction must not make dead reckoning's reprojection (C1) worse by more than this factor.
GUARD_TOLERANCE = 1.05


@dataclass(frozen=True)
class GyroBias:
    """Whether the filter estimates the gyro bias, and why."""

    estimated: bool
    reason: str = ""

    def as_dict(self) -> dict:
        return {"estimated": self.estimated, "reason": self.reason}


@dataclass(frozen=True)
class Decisions:
    """What a run decided from the data (module docstring), applied by ``OnlineRun``."""

    conventions: ConventionDecision
    stereo_offset: StereoOffset
    velocity: VelocityCorrection
    imu: ImuNoiseDecision
    pixels: PixelNoise
    drift: DriftDecision
    gyro_bias: GyroBias
    repeated_frames: int  # steps repeating the previous frame in the data decided on
    steps: int  # steps the decisions were made from
    velocity_guard: dict = field(default_factory=dict)  # dead reckoning's reprojection with and without the correction

    @property
    def imu_T_cam(self) -> np.ndarray:
        return self.conventions.imu_T_cam

    @property
    def offset_sigma(self) -> float:
        """px: the prior sigma of the residual disparity offset the filter carries (O1, O4 of
        ``backend.estimator.offset``): the applied offset's standard error, where one was applied
        and the tracks do not drift (T1); else 0, no such state. Where none was applied the data
        give no reason for one. With drifting tracks a constant offset is not told apart from the
        right image's share of their drift: on ece276a_0027 the filter estimating it takes it to
        -0.8 px against the two-view fits' -0.03 +- 0.08 px (ATE 2.47 -> 5.4 m), and on the 51 KITTI
        frames (vislam's tracks, drifting) carrying the applied offset's 0.04 px costs the
        trajectory's scale (ATE 0.065 -> 0.076 m, dead reckoning 0.069 m)."""
        return 0.0 if self.drift.drifting else self.stereo_offset.residual_sigma

    def offset_sigma_for(self, config: Config | None) -> float:
        """px: the residual disparity offset's prior sigma a run with ``config`` uses: the configured
        ``noise.stereo_offset_sigma``, else :attr:`offset_sigma`."""
        configured = None if config is None else config.noise.stereo_offset_sigma
        return self.offset_sigma if configured is None else configured

    @property
    def lever_covariance(self) -> np.ndarray:
        """(3,3) m^2: the prior of the residual lever arm of the IMU's velocities the filter carries
        (V3 of ``backend.estimator.lever_arm``), the second moment of what N3 leaves: its covariance
        where its correction was applied, that plus r r^T where N3 measured r and the velocities stay
        as given, N3's own prior (``LEVER_PRIOR_M`` per axis) where the tracks could not measure it.
        (A component the motion does not excite, as a street's height for its yaw, keeps about that
        prior: it moves no pose either.)"""
        v = self.imu.vision
        if v is None:
            return LEVER_PRIOR_M**2 * np.eye(3)
        moment = v.covariance[:3, :3]
        if not self.velocity.active:
            moment = moment + np.outer(v.lever_arm, v.lever_arm)
        return 0.5 * (moment + moment.T)

    @property
    def rotation_covariance(self) -> np.ndarray:
        """(3,3) rad^2: the prior of the rotation of the IMU samples' frame the filter considers with the
        lever arm (V4 of ``backend.estimator.lever_arm``), the second moment of N6's estimate (the samples
        stay as given): theta theta^T plus its covariance where theta is significant, 0 (none carried)
        where it is not, ``ROTATION_PRIOR_RAD`` per axis where the tracks could not measure it."""
        v = self.imu.vision
        if v is None:
            return ROTATION_PRIOR_RAD**2 * np.eye(3)
        if not v.rotation_significant():
            return np.zeros((3, 3))
        moment = v.rotation_covariance + np.outer(v.rotation, v.rotation)
        return 0.5 * (moment + moment.T)

    def lever_covariance_for(self, config: Config | None) -> np.ndarray | None:
        """The considered block's prior a run with ``config`` gives its filter: (3,3) m^2 of the lever arm,
        or (6,6) with the samples' frame rotation (rad^2) after it (V4); each part configured by
        ``noise.lever_arm_sigma`` (m) and ``noise.imu_rotation_sigma`` (deg) (sigma^2 I; 0: none), else
        :attr:`lever_covariance` and :attr:`rotation_covariance`; None for a run whose poses take no
        vision or with both parts 0."""
        if config is not None and config.estimator.mode != Mode.SLAM:
            return None
        lever_sigma = None if config is None else config.noise.lever_arm_sigma
        rotation_sigma = None if config is None else config.noise.imu_rotation_sigma
        lever = self.lever_covariance if lever_sigma is None else lever_sigma**2 * np.eye(3)
        rotation = self.rotation_covariance if rotation_sigma is None else np.radians(rotation_sigma)**2 * np.eye(3)
        if not rotation.any():
            return lever if lever.any() else None
        prior = np.zeros((6, 6))
        prior[:3, :3], prior[3:, 3:] = lever, rotation
        prior = carried_prior(prior, config is not None and config.estimator.estimate_lever_arm)
        return prior if prior.any() else None

    def config_for(self, config: Config) -> Config:
        """``config`` with the decided values the filter reads (pixel noise, drift and its walk, gyro bias,
        the residual disparity offset's prior unless configured; the lever arm's prior goes to the filter
        itself, :meth:`lever_covariance_for`)."""
        values = {"noise.stereo_offset_sigma": self.offset_sigma_for(config),
                  "noise.pixel_sigma": self.pixels.sigma,
                  "noise.pixel_variance_per_disparity": self.pixels.variance_per_disparity,
                  "drift.track_drift": Choice.YES if self.drift.drifting else Choice.NO,
                  "drift.pixel_walk": self.drift.walk, "drift.pixel_walk_per_disparity": self.drift.walk_per_disparity,
                  "estimator.estimate_gyro_bias": self.gyro_bias.estimated}
        return config.with_values(values)

    def describe(self, config: Config | None = None) -> str:
        lines = [self.conventions.describe(), self.stereo_offset.describe(), self._offset_state_text(config),
                 self._velocity_text(), self._lever_text(config),
                 self.imu.describe(), self.pixels.describe(), self.drift.describe(config)]
        if not self.gyro_bias.estimated:
            lines.append(f"gyro bias: not estimated ({self.gyro_bias.reason})")
        if self.repeated_frames:
            lines.append(f"repeated frames: {self.repeated_frames} of the first {self.steps} steps repeat the previous "
                         "frame exactly")
        return "\n".join(lines)

    def _offset_state_text(self, config: Config | None) -> str:
        """The residual disparity offset in the filter (O1), as ``config_for`` sets it."""
        sigma = self.offset_sigma_for(config)
        if sigma:
            how = "estimated" if config is None or config.estimator.estimate_stereo_offset else "considered"
            return f"residual disparity offset: a filter state, {how}, prior sigma {sigma:.3f} px (O1)"
        if self.offset_sigma:
            why = "noise.stereo_offset_sigma = 0"
        elif self.stereo_offset.residual_sigma:
            why = "the tracks drift (T1)"
        else:
            why = "no offset applied"
        return f"residual disparity offset: not a filter state ({why})"

    def _lever_text(self, config: Config | None) -> str:
        """The residual lever arm and the samples' frame rotation in the filter (V2-V4), as
        :meth:`lever_covariance_for` gives them."""
        prior = self.lever_covariance_for(config)
        if prior is None:
            return ("IMU lever arm and frame rotation: not in the covariance (noise.lever_arm_sigma = "
                    "noise.imu_rotation_sigma = 0, or no SLAM run)")
        lines = [self._lever_part(config, prior[:3, :3])]
        v = self.imu.vision
        if prior.shape[0] > 3:
            lines.append(self._rotation_part(config, prior[3:, 3:]))
        elif config is not None and config.estimator.estimate_lever_arm:
            lines.append("IMU samples' frame rotation: not in the covariance (an estimated lever arm carries none, V4)")
        elif v is not None and (config is None or config.noise.imu_rotation_sigma is None):
            lines.append(f"IMU samples' frame rotation: not in the covariance (N6's estimate "
                         f"[{', '.join(f'{x:+.2f}' for x in np.degrees(v.rotation))}] deg, chi2 {v.rotation_chi2:.1f}: "
                         "not significant, V4)")
        return "\n".join(lines)

    def _rotation_part(self, config: Config | None, prior: np.ndarray) -> str:
        """The line of the samples' frame rotation the filter considers with prior ``prior`` (3,3) rad^2 (V4)."""
        sigma = ", ".join(f"{s:.2f}" for s in np.degrees(np.sqrt(np.diag(prior))))
        v = self.imu.vision
        if config is not None and config.noise.imu_rotation_sigma is not None:
            why = "configured"
        elif v is None:
            why = "not measured by the tracks: N6's prior"
        else:
            est = ", ".join(f"{x:+.2f}" for x in np.degrees(v.rotation))
            se = ", ".join(f"{x:.2f}" for x in np.degrees(np.sqrt(np.diag(v.rotation_covariance))))
            why = f"N6's estimate [{est}] +- [{se}] deg, the samples as given"
        return f"IMU samples' frame rotation: considered in the covariance, prior sigmas [{sigma}] deg ({why}, V4)"

    def _lever_part(self, config: Config | None, prior: np.ndarray) -> str:
        """The line of the residual lever arm the filter carries with prior ``prior`` (3,3) m^2 (V2, V3)."""
        if not prior.any():
            return "IMU lever arm: not in the covariance (noise.lever_arm_sigma = 0)"
        sigma = ", ".join(f"{s:.2f}" for s in np.sqrt(np.diag(prior)))
        how = "estimated" if config is not None and config.estimator.estimate_lever_arm else "considered"
        if config is not None and config.noise.lever_arm_sigma is not None:
            why = "configured"
        elif self.imu.vision is None:
            why = "not measured by the tracks: N3's prior"
        elif self.velocity.active:
            why = "the applied correction's standard error"
        else:
            why = "N3's estimate and its standard error, the velocities as given"
        return f"IMU lever arm: {how} in the covariance, prior sigmas [{sigma}] m ({why}, V3)"

    def _velocity_text(self) -> str:
        v = self.imu.vision
        if v is None:
            return "IMU lever arm and velocity offset: not tested (too few step pairs with enough tracks)"
        est = (f"lever arm [{', '.join(f'{x:+.2f}' for x in v.lever_arm)}] m, offset "
               f"[{', '.join(f'{x:+.3f}' for x in v.offset)}] m/s (chi2 {v.chi2:.0f}, {v.pairs} step pairs)")
        if self.velocity.active:
            guard = self.velocity_guard
            extra = (f"; dead reckoning's reprojection {guard['without']:.2f} -> {guard['with']:.2f} px"
                     if guard else "")
            return f"IMU velocities corrected (v - omega x r - c): {est}{extra}"
        why = self.velocity_guard.get("rejected", "not significant")
        return f"IMU velocities as given ({why}): estimated {est}"

    def as_dict(self) -> dict:
        return {
            "steps_decided_from": self.steps,
            "conventions": self.conventions.as_dict(),
            "stereo_offset": {**self.stereo_offset.as_dict(), "state_prior_sigma_px": self.offset_sigma},
            "velocity_correction": {"lever_arm_m": self.velocity.lever_arm.tolist(),
                                    "offset_m_s": self.velocity.offset.tolist(), "applied": self.velocity.active,
                                    "lever_arm_state_prior_m2": self.lever_covariance.tolist(),
                                    "frame_rotation_state_prior_rad2": self.rotation_covariance.tolist(),
                                    "dead_reckoning_reprojection_px": self.velocity_guard},
            "imu_noise": self.imu.as_dict(),
            "pixel_noise": self.pixels.as_dict(),
            "track_drift": self.drift.as_dict(),
            "gyro_bias": self.gyro_bias.as_dict(),
            "repeated_frames": self.repeated_frames,
        }


def _offset_model(config: Config) -> str:
    """The stereo offset model to estimate: none for dead reckoning, which uses no vision."""
    return "off" if config.estimator.mode == Mode.DEAD_RECKONING else str(config.conventions.stereo_offset)


def _guarded(seq: Sequence, conventions: ConventionDecision, horizon: int, without: float | None,
             corrected: Sequence, pairs: MatchedPairs | None = None) -> tuple[bool, dict]:
    """Dead reckoning's reprojection (C1) with and without a correction: (keep it, the numbers);
    ``pairs``: the corrected sequence's ``matched_pairs`` when the correction left its pixels as they were."""
    if without is None:
        without = reprojection_error(seq, conventions.imu_T_cam, conventions.velocity_index, horizon)
    with_ = reprojection_error(corrected, conventions.imu_T_cam, conventions.velocity_index, horizon, pairs=pairs)
    numbers = {"without": float(without), "with": float(with_)}
    keep = not (np.isfinite(without) and np.isfinite(with_) and with_ > GUARD_TOLERANCE * without)
    return keep, numbers


def _velocity_correction(seq: Sequence, conventions: ConventionDecision, vision: ImuVsVision | None,
                         white: np.ndarray, config: Config,
                         pairs: MatchedPairs | None = None) -> tuple[VelocityCorrection, dict]:
    setting = config.conventions.velocity_correction
    if vision is None or setting == Choice.NO or config.estimator.mode == Mode.DEAD_RECKONING:
        return VelocityCorrection(), {}
    if setting == Choice.AUTO and not vision.significant(white):
        return VelocityCorrection(), {}
    correction = VelocityCorrection(vision.lever_arm.copy(), vision.offset.copy())
    corrected = dataclasses.replace(seq, linear_velocity=correction.correct(seq.linear_velocity, seq.angular_velocity))
    keep, numbers = _guarded(seq, conventions, config.conventions.horizon, conventions.chosen_error_px, corrected,
                             pairs)  # the velocities changed, not the pixels: the same matched pairs
    if keep or setting == Choice.YES:
        return correction, numbers
    numbers["rejected"] = (f"the correction made dead reckoning's reprojection worse ({numbers['without']:.2f} -> "
                           f"{numbers['with']:.2f} px)")
    return VelocityCorrection(), numbers


#: The source of an IMU sigma taken from the samples' white noise alone (N1)
WHITE_NOISE = "white noise of the samples"


def _imu_noise(config: Config, white_lin: np.ndarray, white_ang: np.ndarray,
               vision: ImuVsVision | None) -> ImuNoiseDecision:
    """Per kind (linear, angular): the configured value wins; else (N3) where vision is at most
    ``VISION_SHARE_MAX`` of the scatter, at least the white noise; else the white noise (N1)."""
    usable = vision is not None and vision.measures_imu()

    def one(configured, measured, white) -> tuple[np.ndarray, str]:
        if configured:
            return np.full(3, float(configured)), "configured"
        if usable:
            return np.maximum(measured, white), "IMU against vision"
        return white, WHITE_NOISE

    lin, lin_src = one(config.noise.linear_velocity_sigma, vision and vision.linear_sigma, white_lin)
    ang, ang_src = one(config.noise.angular_velocity_sigma, vision and vision.angular_sigma, white_ang)
    return ImuNoiseDecision(np.maximum(lin, 1e-6), np.maximum(ang, 1e-7), lin_src, ang_src, white_lin, white_ang,
                            vision)


def decide(seq: Sequence, config: Config, imu_velocities: tuple[np.ndarray, np.ndarray] | None = None) -> Decisions:
    """The decisions (module docstring) from ``seq``; ``imu_velocities`` (linear (N,3), angular (N,3)):
    the whole stream's samples for the white noise (N1) when ``seq`` holds only its first frames."""
    c = config.conventions
    pairs = matched_pairs(seq, c.horizon)  # the reprojection test's points (C1), for every test of the pixels as given
    conventions = decide_conventions(seq, c.imu_flip, c.velocity_index, c.horizon, pairs)
    repeated = repeated_steps(seq)
    vision_used = config.estimator.mode != Mode.DEAD_RECKONING
    fits = {gap: fit_pairs(seq, gap, PAIRS_GAP1 if gap == 1 else PAIRS_LONGER, offset=True,
                           min_points=NOISE_MIN_POINTS, skip=repeated) for gap in DRIFT_GAPS} if vision_used else {}
    # the stereo offset (D1-D3) from the gap-1 fits with enough points, kept only if dead reckoning agrees
    offset = offset_from_fits(seq, conventions.imu_T_cam, _offset_model(config), fits.get(1, []))
    if offset.active:
        keep, numbers = _guarded(seq, conventions, c.horizon, conventions.chosen_error_px,
                                 offset.corrected(seq, conventions.imu_T_cam))
        offset.estimate["dead_reckoning_reprojection_px"] = numbers
        if not keep:
            offset = StereoOffset(0.0, 0.0, dict(offset.estimate, rejected=(
                f"an estimated offset of {offset.estimate['beta_mean_px']:+.2f} px made dead reckoning's reprojection "
                f"worse ({numbers['without']:.2f} -> {numbers['with']:.2f} px), so it is not removed")), offset.source)
    drift = decide_track_drift(config, seq, fits)
    gaps = gap_statistics(fits)
    # the white noise of consecutive frames; drift beyond it is the walk's (T3), or, where no walk was
    # measured (or a constant one is configured), the RMS over the gaps a landmark lives through
    walk_measured = (drift.walk > 0 or drift.walk_per_disparity > 0) and config.drift.landmark_random_walk is None
    lives = min(max(config.drift.reanchor_observations, 1), 3)
    pixels = pixel_noise(seq, gaps, lives if drift.drifting and not walk_measured else 1, config.noise.pixel_sigma)
    pixels = with_disparity_noise(pixels, disparity_noise(fits.get(1, [])), config.noise.pixel_variance_per_disparity)
    lin, ang = (seq.linear_velocity, seq.angular_velocity) if imu_velocities is None else imu_velocities
    white_lin, white_ang = estimate_white_noise(np.asarray(lin)), estimate_white_noise(np.asarray(ang))
    vision = imu_vs_vision(fits.get(1, []), seq, conventions.imu_T_cam, conventions.velocity_index) if vision_used else None
    velocity, guard = _velocity_correction(seq, conventions, vision, white_lin, config, pairs)
    imu = _imu_noise(config, white_lin, white_ang, vision)
    per_step = seq.num_observations / max(seq.num_steps, 1)
    est = config.estimator
    if not est.estimate_gyro_bias:
        bias = GyroBias(False, "estimator.estimate_gyro_bias = false")
    elif per_step < est.gyro_bias_min_observations:
        bias = GyroBias(False, f"{per_step:.1f} observations per step < estimator.gyro_bias_min_observations = "
                               f"{est.gyro_bias_min_observations:g}: too few to tell a bias from track drift")
    else:
        bias = GyroBias(True)
    decisions = Decisions(conventions, offset, velocity, imu, pixels, drift, bias, int(repeated.sum()), seq.num_steps,
                          guard)
    if vision_used and (imu.linear_source != "configured" or imu.angular_source != "configured") and vision is None:
        decisions = _imu_by_likelihood(seq, decisions, config)
    decisions = _hold_decision(seq, decisions, config, hold_error(np.asarray(lin)), hold_error(np.asarray(ang)),
                               vision_used)
    if c.stereo_offset_by_imu and config.estimator.mode == Mode.SLAM and _offset_model(config) != "off":  # (D5)
        decisions = dataclasses.replace(decisions, stereo_offset=offset_by_imu_scale(seq, decisions, config))
    return decisions


#: The source of an IMU sigma floored by the hold error (N4)
HOLD = "at least the samples' change over a step (N4)"


def _at_least_hold(decisions: Decisions, hold_lin: np.ndarray, hold_ang: np.ndarray, why: str = "") -> Decisions:
    """Per axis, an IMU sigma taken from the samples' white noise (N1, blind to smooth changes) at
    least the error of holding a sample over its step (N4); others are kept."""
    imu = decisions.imu

    def floor(sigma, source, hold):
        if source != WHITE_NOISE or not np.any(hold > sigma):
            return sigma, source
        return np.maximum(sigma, hold), f"{source}, {HOLD}{why}"

    lin, lin_src = floor(imu.linear_sigma, imu.linear_source, hold_lin)
    ang, ang_src = floor(imu.angular_sigma, imu.angular_source, hold_ang)
    return dataclasses.replace(decisions, imu=dataclasses.replace(
        imu, linear_sigma=lin, angular_sigma=ang, linear_source=lin_src, angular_source=ang_src))


def _hold_decision(seq: Sequence, decisions: Decisions, config: Config, hold_lin: np.ndarray, hold_ang: np.ndarray,
                   vision_used: bool) -> Decisions:
    """Whether an IMU sigma from the white noise alone (N1) must also cover the hold error (N4).
    Sigmas measured against vision (N3) or by the likelihood's search (L2) already include it, and
    a configured one is the user's: only N1 ones are floored. Motion sampled from a continuous
    trajectory makes the hold error real; a sequence whose truth moves by exactly the held samples
    (piecewise-constant twists, as some simulators make) has none. The filter's own innovation
    likelihood over the first steps (L2) tells them apart: the floor is kept where it is the more
    likely of the two; without vision (dead reckoning) it is kept (continuous motion)."""
    imu = dataclasses.replace(decisions.imu, hold_linear=hold_lin, hold_angular=hold_ang)
    decisions = dataclasses.replace(decisions, imu=imu)
    floored = _at_least_hold(decisions, hold_lin, hold_ang)
    if floored.imu.linear_source == imu.linear_source and floored.imu.angular_source == imu.angular_source:
        return decisions  # nothing to floor
    if not vision_used:
        return floored
    from .likelihood import log_likelihood

    ll_white, _ = log_likelihood(seq, decisions, config)
    ll_hold, _ = log_likelihood(seq, floored, config)
    table = dict(imu.likelihood, **{"white noise (N1)": ll_white, "at least the hold error (N4)": ll_hold})
    if ll_hold > ll_white:
        chosen = _at_least_hold(decisions, hold_lin, hold_ang, "; the more likely (L2)").imu
    else:

        def tag(source: str) -> str:
            return f"{source} (the hold error N4 less likely, L2)" if source == WHITE_NOISE else source

        chosen = dataclasses.replace(imu, linear_source=tag(imu.linear_source), angular_source=tag(imu.angular_source))
    return dataclasses.replace(decisions, imu=dataclasses.replace(chosen, likelihood=table))


#: Candidate IMU sigmas of (L2): the white noise times these factors, up to the caps.
LIKELIHOOD_FACTORS = 3.0 ** np.arange(0, 9)
LINEAR_CAP_M_S, ANGULAR_CAP_RAD_S = 5.0, 0.5


#: The search of (L2) over a noise's factors stops after this many candidates in a row below the best.
LIKELIHOOD_PAST_PEAK = 2
#: ... each below it by more than this many log-likelihood units over the observations compared (a
#: likelihood ratio of e^2 = 7.4); smaller differences are ties. Where the pixels' noise dwarfs the
#: IMU's, the likelihood is flat over the smallest factors: on ece276a2019_0042 with pixel_sigma 1.55
#: the factors 1, 3 and 9 scored -4.38811, -4.38821, -4.38870 per observation (0.03 and 0.2 units in
#: all), and the search ended at the samples' white noise (3 mm/s, position NEES 50000), where at
#: 1.5 px it went on to 27 (0.074 m/s, NEES 360).
LIKELIHOOD_TIE = 2.0


def _past_the_peak(scores: list, observations: int = 0) -> bool:
    """Whether the last ``LIKELIHOOD_PAST_PEAK`` of ``scores`` (mean log-likelihoods per observation
    over ``observations``) all fall below the best before them by more than ``LIKELIHOOD_TIE`` units
    in all (the likelihood over a noise's factor rises to one peak and falls: the rest cannot win)."""
    n = LIKELIHOOD_PAST_PEAK
    tie = LIKELIHOOD_TIE / observations if observations > 0 else 0.0
    return len(scores) > n and max(scores[-n:]) < max(scores[:-n]) - tie


def _imu_by_likelihood(seq: Sequence, decisions: Decisions, config: Config) -> Decisions:
    """Where vision cannot measure the IMU (N3: too few tracks a step), the IMU sigmas that maximize
    the filter's own innovation likelihood (L2) over the first steps: first the linear sigma over
    the white noise (N1) times 1, 3, 9, ... until two in a row fall below the best by more than a
    tie (``LIKELIHOOD_TIE``), then the angular one at that linear sigma (a candidate already run is
    not run again); a configured value is kept. The smallest candidate is the samples' own white
    noise: no floor by hand."""
    from .likelihood import log_likelihood, with_imu

    imu = decisions.imu
    table: dict = {}
    best = decisions
    scored: dict = {}  # the score of each pair of sigmas already run

    def search(kind: str, white: np.ndarray, cap: float) -> Decisions:
        base = np.maximum(white, 1e-4 if kind == "linear" else 1e-5)
        scores = []
        for f in LIKELIHOOD_FACTORS:
            sigma = np.minimum(base * f, cap)
            candidate = with_imu(best, **{f"{kind}_sigma": sigma})
            key = (candidate.imu.linear_sigma.tobytes(), candidate.imu.angular_sigma.tobytes())
            if key not in scored:
                scored[key] = log_likelihood(seq, candidate, config)
            score, count = scored[key]
            table[f"{kind} x{f:g}"] = score
            scores.append((score, candidate))
            if sigma.max() >= cap or _past_the_peak([s for s, _ in scores], count):
                break
        return max(scores, key=lambda x: x[0])[1]

    if imu.linear_source != "configured":
        best = search("linear", imu.white_linear, LINEAR_CAP_M_S)
    if imu.angular_source != "configured":
        best = search("angular", imu.white_angular, ANGULAR_CAP_RAD_S)
    new = best.imu
    return dataclasses.replace(best, imu=dataclasses.replace(
        new, likelihood=table,
        linear_source=imu.linear_source if imu.linear_source == "configured" else "innovation likelihood",
        angular_source=imu.angular_source if imu.angular_source == "configured" else "innovation likelihood"))
