"""The noise a run's filter uses, identified from the data: pixels, IMU, and the IMU's offsets.

Pixel noise (N2). The two-view fits of step pairs (D2, ``backend.run.two_view``) leave residuals
that are the tracks' own error once motion and points are fitted: white noise, and for drifting
tracks whatever accumulated between the two frames. Their pooled RMS (residuals within the
fits' trim, over the degrees of freedom) over the gaps h = 1 .. h_max the filter's landmarks live
through keeps the heavy tail of real tracks that a robust scale leaves out:

    sigma_px^2 = sum_pairs sum_{|r| <= trim} r^2 / sum_pairs dof                                    (N2)

Without such pairs (too few tracks a step) the stereo rows give a floorless fallback, the robust
std of (vL - vR) / sqrt 2 (on a rectified pair both rows see the same point).

Pixel noise by disparity (N5). Some trackers' errors grow with a point's nearness (the course
files': their gap-1 residuals' variance grows about linearly with the disparity, the image motion
explaining nothing once disparity is in; vislam's own tracker and synthetic tracks show no
growth). Each point of a gap-1 fit estimates its own variance, y_i = (sum of its squared residuals)
n / dof (its share of the fit's degrees of freedom), and an ordinary least
squares line with heteroscedasticity-consistent (HC0) standard errors tells the growth:

    y_i = a + b d_i + e_i,   growth  <=>  b > DISPARITY_Z SE(b)                                   (N5)

(an intercept below its own standard error is held at that standard error, the slope refitted). The filter then gives observation i
the variance sigma_i^2 = f (a + b d_i) per coordinate, f = sigma_px^2 / (a + b dbar) (N2 at the
fits' mean disparity dbar, so that the drift allowance the pooled gaps add is kept as a share):
``noise.pixel_sigma`` = sqrt(f a), ``noise.pixel_variance_per_disparity`` = f b.

IMU white noise (N1): per axis from the second differences of the velocity samples,

    sigma = 1.4826 MAD(x_{k+1} - 2 x_k + x_{k-1}) / sqrt(6),

blind to errors that are smooth (scale, misalignment, the GPS/INS solution the velocities came from).

Holding a sample (N4): the velocity model moves by the sample x_k over the whole step while the
signal goes on to x_k+1; the error is about (x_k+1 - x_k)/2, an RMS the samples state themselves
(:func:`hold_error`). White noise is blind to it: exact velocities of an accelerating car have a
white noise of ~1e-5 m/s and a hold error of ~0.07 m/s at 10 Hz.

IMU against vision (N3). Each gap-1 fit is a camera motion; through the extrinsic it is the IMU
frame's twist u_vis = log(imu_T_cam (c_k+1_T_c_k)^-1 cam_T_imu) / tau, with covariance
Ad C Ad^T / tau^2 from the fit. The IMU's sample of that step (the velocity timing) relates to it as

    v_imu = v_vis + omega x r + c + n_v,   omega_imu = omega_vis + b + n_w                           (N3)

r: where the IMU's velocity is measured, relative to the frame the extrinsic defines (a lever arm
the file does not state); c: a constant velocity offset; b: the gyro bias. (r, c) come from a
generalized least squares with Huber weights and a weak prior (``LEVER_PRIOR_M``,
``OFFSET_PRIOR_M_S``: components the motion does not excite stay near zero), the noise per axis
from the residuals' robust variance less the vision twist's own. That difference is taken only where
vision is at most ``VISION_SHARE_MAX`` of the scatter: with vision's share s, an error of a factor f
in vision's variance (tracks that drift, jitter: what the fits' covariance does not hold) moves the
IMU's variance by (f - 1) s / (1 - s), a third at s = 1/4 and f = 2, but the whole of it at s = 1/2
(synthetic scenes with 0.05 m/s of white velocity noise at s 0.45-0.49: 1.0-6.4 times the truth, the
most with heavily drifting tracks, where the samples' white noise N1 is within 10 %). The correction
v <- v - omega x r - c is applied when (r, c) is significant (chi-square) and changes the
velocities by a visible amount (``backend.run.decisions`` also checks it against dead reckoning).

The samples' frame (N6). A file's velocities and rates may be given in a frame turned from the IMU
frame the extrinsic defines by a small rotation theta: a mounting the extrinsic does not state, or
a level frame (KITTI's OXTS vf vl vu and wf wl wu, "parallel to the earth's surface", which the
2019 course files keep: turned from the body by the vehicle's roll and pitch). To first order

    v_imu = v_vis + omega x r + c + v_vis x theta,   omega_imu = omega_vis + b + omega_vis x theta      (N6)

fitted jointly over the same pairs (generalized least squares, Huber weights, the priors of N3 and
``ROTATION_PRIOR_RAD`` for theta): the velocities pin theta's pitch and yaw, the rates in turns
its roll and pitch. Its standard errors are widened to the spread of ``BATCHES`` batches of
consecutive pairs where that is larger (D4's batch means: drifting tracks err alike over
neighbouring pairs, and a level frame's tilt follows the road). The samples stay as given. Where
theta is significant (its chi-square against 0 beyond the ``ROTATION_PROBABILITY`` quantile), its
second moment is the prior of the filter's considered rotation (V4 of
``backend.estimator.lever_arm``); where it is not, the filter carries none: a considered
parameter's uncertainty is never reduced, and 0.5 deg of yaw considered over a 300-step street
(its standard error there) takes the Monte Carlo pose NEES far below its band, where the filter
without it is consistent (its vision keeps measuring the direction of motion). On 144 synthetic
scenes with no rotation (street and aerial, 0.5 and 1 px, 3 geometries, 12 noise draws) the
chi-square's mean is 2.7 (3 expected), 2 exceed the 0.99 quantile (one noise draw of one
geometry), none the 0.999 quantile.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..chi2 import quantile as chi2_quantile
from ..data.sequence import Sequence
from ..estimator.update import pixel_variance
from ..geometry import se3
from .two_view import Tolerances, TwoViewFit, pooled_mean_square, tolerances

__all__ = ["estimate_white_noise", "rows_sigma", "PixelNoise", "pixel_noise", "DisparityNoise", "disparity_noise",
           "point_variances", "variance_line", "with_disparity_noise", "ImuVsVision", "imu_vs_vision", "ImuNoiseDecision", "VelocityCorrection"]

#: Prior standard deviations of the lever arm (m) and of the velocity offset (m/s) in (N3).
LEVER_PRIOR_M = 2.0
OFFSET_PRIOR_M_S = 1.0
#: Prior standard deviation (rad, per axis) of the rotation of the samples' frame (N6): 3 deg, a
#: vehicle's roll or pitch on a road's grade or a mounting set by eye; the gyro bias's (rad/s) in that fit.
ROTATION_PRIOR_RAD = float(np.radians(3.0))
BIAS_PRIOR_RAD_S = 0.1
#: (N6) the standard errors of theta come from this many contiguous batches of pairs where larger.
BATCHES = 10
#: (N6) the rotation is carried where its chi-square exceeds the quantile of this probability.
ROTATION_PROBABILITY = 0.999
#: (N3) needs at least this many step pairs, each fitted from this many points or more.
MIN_PAIRS = 30
MIN_POINTS = 12
#: A correction is applied when its chi-square exceeds the quantile of this probability ...
CORRECTION_PROBABILITY = 1.0 - 1e-6
#: ... and changes the velocities by more than this share of their white noise (RMS over the pairs).
MIN_EFFECT = 0.25


def estimate_white_noise(signal: np.ndarray) -> np.ndarray:
    """(N1) per-axis sigma of white noise on a smooth signal (N,3), from its second differences."""
    if signal.shape[0] < 5:
        return np.zeros(signal.shape[1])
    d2 = signal[2:] - 2.0 * signal[1:-1] + signal[:-2]
    mad = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0)
    return 1.4826 * mad / np.sqrt(6.0)


def hold_error(signal: np.ndarray) -> np.ndarray:
    """(N4) per-axis RMS error of holding each sample of ``signal`` (N,3) over its step: the velocity
    model moves by x_k over [t_k, t_k+1] where the signal goes from x_k to x_k+1, off by about
    (x_k+1 - x_k) / 2 when it changes linearly (the same for the timing "next"), so

        sigma_hold = sqrt(mean_k ((x_k+1 - x_k) / 2)^2),

    the samples' own changes: what a smooth, exact velocity still costs the model (white noise alone
    would say it costs nothing)."""
    if signal.shape[0] < 2:
        return np.zeros(signal.shape[1])
    return np.sqrt(np.mean((0.5 * np.diff(signal, axis=0)) ** 2, axis=0))


def rows_sigma(seq: Sequence, tolerance: Tolerances) -> float:
    """Robust std (px) of (vL - vR) / sqrt 2 over the observations whose rows agree within
    ``tolerance`` (the sequence's ``two_view.tolerances``; the rest are mismatches, not noise); nan
    without observations."""
    d = seq.obs_pixels[:, 1] - seq.obs_pixels[:, 3]
    d = d[np.abs(d) <= tolerance.rows_px]
    if d.size < 10:
        return float("nan")
    return float(np.sqrt(_robust_var(d)) / np.sqrt(2.0))


# ------------------------------------------------------------------------------------------ pixels
@dataclass(frozen=True)
class PixelNoise:
    """The pixel noise used (N2), with the measurements behind it."""

    sigma: float  # px per coordinate, used (at zero disparity where variance_per_disparity > 0)
    source: str  # "configured" | "two-view fits" | "stereo rows"
    gaps: tuple = ()  # (gap, pairs, robust scale px, RMS px) per gap measured
    rows_px: float = float("nan")  # the stereo rows' robust std
    used_gaps: int = 0  # the RMS pooled over gaps 1 .. used_gaps
    variance_per_disparity: float = 0.0  # px^2 per px of disparity (N5): sigma_i^2 = sigma^2 + this d_i
    disparity: "DisparityNoise | None" = None  # the test (N5) behind it
    pooled_sigma: float = float("nan")  # (N2) over the fits' points, before the disparity model
    tolerance: Tolerances = Tolerances()  # the fits' and the rows' (two_view.tolerances)

    def variance(self, disparity: np.ndarray) -> np.ndarray:
        """sigma_i^2 (N5) of observations of ``disparity`` (n,) px."""
        return pixel_variance(self.sigma**2, self.variance_per_disparity, disparity)

    def as_dict(self) -> dict:
        return {"sigma_px": self.sigma, "decided_by": self.source, "stereo_rows_px": self.rows_px,
                "pooled_over_gaps": self.used_gaps, "pooled_sigma_px": self.pooled_sigma,
                "variance_per_disparity_px2_per_px": self.variance_per_disparity,
                "row_tolerance_px": self.tolerance.rows_px, "trim_px": self.tolerance.trim_px,
                "disparity_test": None if self.disparity is None else self.disparity.as_dict(),
                "two_view": [{"gap": g, "pairs": n, "robust_px": s, "rms_px": r} for g, n, s, r in self.gaps]}

    def describe(self) -> str:
        text = self._describe_sigma()
        used, fixed = self.tolerance, Tolerances()
        wider = []  # the tolerances the rows' spread widened beyond the fixed ones
        if used.rows_px > fixed.rows_px:
            wider.append(f"matches whose rows agree within {used.rows_px:.3g} px")
        if used.trim_px > fixed.trim_px:
            wider.append(f"fits' residuals within {used.trim_px:.3g} px")
        if wider:
            text += f"; from {' and '.join(wider)} (the rows' own spread)"
        if self.disparity is not None:
            text += "; " + self.disparity.describe(self)
        return text

    def _describe_sigma(self) -> str:
        if self.variance_per_disparity > 0 and self.source != "configured":
            return (f"pixel noise: sigma_i^2 = {self.sigma:.3g}^2 + {self.variance_per_disparity:.3g} d_i px^2 "
                    f"(disparity d_i px, N5; {self.pooled_sigma:.3g} px {self._over_gaps()}; stereo rows "
                    f"{self.rows_px:.2f} px)")
        if self.source == "configured":
            if self.variance_per_disparity > 0:
                return (f"pixel noise: sigma_i^2 = {self.sigma:.3g}^2 + {self.variance_per_disparity:.3g} d_i px^2 "
                        "(configured)")
            return f"pixel noise: {self.sigma:.3g} px (configured)"
        if self.source == "stereo rows":
            return (f"pixel noise: {self.sigma:.3g} px, the stereo rows' spread (too few tracks seen twice for "
                    "two-view fits)")
        if self.source == NO_OBSERVATIONS:
            return f"pixel noise: {self.sigma:.3g} px (nothing to measure it from: no track seen twice, no stereo row)"
        return f"pixel noise: {self.sigma:.3g} px, the RMS of two-view fit residuals {self._over_gaps()}; stereo rows " \
               f"{self.rows_px:.2f} px"

    def _over_gaps(self) -> str:
        """Which gaps the pooled RMS (N2) is over, with each gap's RMS."""
        rms = ", ".join(f"{r:.2f}" for g, n, s, r in self.gaps if g <= self.used_gaps)
        if self.used_gaps <= 1:
            return f"of consecutive steps ({rms} px)"
        return f"pooled over step gaps 1-{self.used_gaps} ({rms} px)"


def gap_statistics(fits_by_gap: dict[int, list[TwoViewFit]]) -> tuple:
    """((gap, pairs, median robust scale, pooled RMS) for each gap with fits), from (D2) fits."""
    out = []
    for gap in sorted(fits_by_gap):
        fits = fits_by_gap[gap]
        if not fits:
            continue
        out.append((gap, len(fits), float(np.median([f.robust_scale() for f in fits])),
                    float(np.sqrt(pooled_mean_square(fits)[0]))))
    return tuple(out)


#: The source of a pixel noise that nothing in the data could measure
NO_OBSERVATIONS = "no observations to measure it: 1 px"


def pixel_noise(seq: Sequence, gaps: tuple, used_gaps: int, configured: float | None) -> PixelNoise:
    """(N2) the pooled RMS over the ``gaps`` statistics (:func:`gap_statistics`) up to ``used_gaps``;
    the stereo rows without fits; ``configured`` (not None) wins."""
    tolerance = tolerances(seq.obs_pixels)
    rows = rows_sigma(seq, tolerance)
    if configured is not None:
        return PixelNoise(float(configured), "configured", gaps, rows, used_gaps, tolerance=tolerance)
    used = [(n, r) for g, n, s, r in gaps if g <= used_gaps and np.isfinite(r)]
    if used:
        weights = np.array([n for n, _ in used], dtype=float)
        sigma = float(np.sqrt(np.sum(weights * np.array([r for _, r in used]) ** 2) / weights.sum()))
        return PixelNoise(sigma, "two-view fits", gaps, rows, used_gaps, tolerance=tolerance)
    if np.isfinite(rows) and rows > 0:
        return PixelNoise(rows, "stereo rows", gaps, rows, used_gaps, tolerance=tolerance)
    return PixelNoise(1.0, NO_OBSERVATIONS, gaps, rows, used_gaps, tolerance=tolerance)


#: (N5): the variance grows with disparity when the slope exceeds this many standard errors ...
DISPARITY_Z = 4.0
#: ... over at least this many points of gap-1 fits.
DISPARITY_MIN_POINTS = 200


@dataclass(frozen=True)
class DisparityNoise:
    """(N5): the gap-1 fits' per-point variance against the disparity, y = a + b d."""

    intercept: float  # a, px^2
    slope: float  # b, px^2 per px
    slope_se: float  # HC0 standard error of b
    points: int
    mean_disparity: float  # dbar, px
    growth: bool  # b > DISPARITY_Z SE(b)

    def as_dict(self) -> dict:
        return {"intercept_px2": self.intercept, "slope_px2_per_px": self.slope, "slope_se": self.slope_se,
                "points": self.points, "mean_disparity_px": self.mean_disparity, "grows": self.growth}

    def describe(self, pixels: "PixelNoise | None" = None) -> str:
        verdict = "grows" if self.growth else "does not grow"
        used = "" if self.growth or pixels is None else "; one sigma for every observation"
        return (f"its variance {verdict} with disparity (gap-1 residuals: {self.intercept:.3g} + {self.slope:.3g} d px^2, "
                f"slope {self.slope / self.slope_se if self.slope_se > 0 else float('inf'):.1f} standard errors, "
                f"{self.points} points{used})")


def point_variances(fits: list[TwoViewFit]) -> tuple[np.ndarray, np.ndarray]:
    """(y (n,), d (n,)): each fitted point's variance estimate, the sum of its squared residuals
    times its share n / dof of the fit's degrees of freedom, and its disparity (px)."""
    ys, ds = [], []
    for f in fits:
        if f.disparity is None or f.dof <= 0:
            continue
        r = f.residuals
        ys.append(np.sum(r**2, axis=1) * (r.shape[0] / f.dof))
        ds.append(f.disparity)
    if not ys:
        return np.zeros(0), np.zeros(0)
    return np.concatenate(ys), np.concatenate(ds)


def variance_line(fits: list[TwoViewFit]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The least-squares line y = a + b d of the fits' points' variances on their disparities
    (:func:`point_variances`): ((a, b), their HC0 standard errors, y (n,), d (n,)); nans with
    fewer than 3 points."""
    y, d = point_variances(fits)
    if y.size < 3:
        return np.full(2, np.nan), np.full(2, np.nan), y, d
    coef, se = _ols_hc0(np.column_stack([np.ones_like(d), d]), y)
    return coef, se, y, d


def disparity_noise(fits: list[TwoViewFit]) -> DisparityNoise | None:
    """(N5) from gap-1 fits that carry their points' disparities; None with fewer than
    ``DISPARITY_MIN_POINTS`` points."""
    coef, se, y, d = variance_line(fits)
    if y.size < DISPARITY_MIN_POINTS:
        return None
    a, b, b_se = float(coef[0]), float(coef[1]), float(se[1])
    if a < se[0]:  # an intercept within its standard error of zero or below: the line through (0, SE(a))
        a = float(se[0])
        coef, se = _ols_hc0(d[:, None], y - a)
        b, b_se = float(coef[0]), float(se[0])
    growth = bool(b > 0.0 and b > DISPARITY_Z * b_se)
    return DisparityNoise(a, b, b_se, int(y.size), float(d.mean()), growth)


def _ols_hc0(A: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares coefficients of y (n,) on the columns of A (n,p) and their heteroscedasticity-
    consistent (HC0, White's sandwich) standard errors."""
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    e = y - A @ coef
    bread = np.linalg.inv(A.T @ A)
    cov = bread @ ((A * (e**2)[:, None]).T @ A) @ bread
    return coef, np.sqrt(np.maximum(np.diag(cov), 0.0))


def with_disparity_noise(pixels: PixelNoise, test: DisparityNoise | None, configured: float | None) -> PixelNoise:
    """(N5) applied to the pooled noise ``pixels`` (N2): the configured slope wins (with the pixel
    sigma as given or pooled); else, where the test shows growth, sigma_i^2 = f (a + b d_i) with
    f = sigma_px^2 / (a + b dbar)."""
    base = replace(pixels, disparity=test, pooled_sigma=pixels.sigma)
    if configured is not None:
        return replace(base, variance_per_disparity=float(configured))
    if test is None or not test.growth or pixels.source != "two-view fits":
        return base
    f = pixels.sigma**2 / (test.intercept + test.slope * test.mean_disparity)
    return replace(base, sigma=float(np.sqrt(f * test.intercept)), variance_per_disparity=float(f * test.slope))


# ------------------------------------------------------------------------------------------ IMU
@dataclass(frozen=True)
class VelocityCorrection:
    """v <- v - omega x lever_arm - offset (N3): the IMU's velocity moved to the frame the extrinsic
    defines."""

    lever_arm: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) m, IMU frame
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) m/s

    @property
    def active(self) -> bool:
        return bool(np.any(self.lever_arm) or np.any(self.offset))

    def correct(self, linear_velocity: np.ndarray, angular_velocity: np.ndarray) -> np.ndarray:
        """The corrected linear velocities, (3,) or (N,3) like the inputs."""
        if not self.active:
            return linear_velocity
        return linear_velocity - np.cross(angular_velocity, self.lever_arm) - self.offset


#: (N3) measures the IMU's noise only where vision's own variance is at most this share of the scatter.
VISION_SHARE_MAX = 0.25


@dataclass(frozen=True)
class ImuVsVision:
    """(N3): the IMU's samples against the motion the two-view fits give."""

    pairs: int
    lever_arm: np.ndarray  # (3,) m
    offset: np.ndarray  # (3,) m/s
    covariance: np.ndarray  # (6,6) of (lever_arm, offset)
    chi2: float  # of (lever_arm, offset) against 0
    effect_rms: np.ndarray  # (3,) m/s, RMS of omega x r + c over the pairs
    linear_sigma: np.ndarray  # (3,) m/s white noise of the IMU, vision's own part removed
    angular_sigma: np.ndarray  # (3,) rad/s
    gyro_bias: np.ndarray  # (3,) rad/s, the mean difference
    vision_share: float  # the share of the residual variance that is vision's (median over axes)
    rotation: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) rad: theta of (N6)
    rotation_covariance: np.ndarray = field(default_factory=lambda: np.eye(3) * ROTATION_PRIOR_RAD**2)  # (3,3) rad^2

    def as_dict(self) -> dict:
        se = np.sqrt(np.diag(self.covariance))
        return {"pairs": self.pairs, "lever_arm_m": self.lever_arm.tolist(), "lever_arm_se_m": se[:3].tolist(),
                "velocity_offset_m_s": self.offset.tolist(), "velocity_offset_se_m_s": se[3:].tolist(),
                "chi2": self.chi2, "effect_rms_m_s": self.effect_rms.tolist(),
                "linear_sigma_m_s": self.linear_sigma.tolist(), "angular_sigma_rad_s": self.angular_sigma.tolist(),
                "gyro_bias_rad_s": self.gyro_bias.tolist(), "vision_share": self.vision_share,
                "frame_rotation_deg": np.degrees(self.rotation).tolist(),
                "frame_rotation_se_deg": np.degrees(np.sqrt(np.diag(self.rotation_covariance))).tolist(),
                "frame_rotation_chi2": self.rotation_chi2, "frame_rotation_significant": self.rotation_significant()}

    def measures_imu(self) -> bool:
        """Vision is at most ``VISION_SHARE_MAX`` of the scatter (N3): its noise sigmas are the IMU's."""
        return self.vision_share <= VISION_SHARE_MAX

    @property
    def rotation_chi2(self) -> float:
        """(N6) theta's chi-square against 0 with its covariance."""
        return float(self.rotation @ np.linalg.solve(self.rotation_covariance, self.rotation))

    def rotation_significant(self) -> bool:
        """(N6) theta is shown: its chi-square beyond the ``ROTATION_PROBABILITY`` quantile (3 dof)."""
        return self.rotation_chi2 > chi2_quantile(3, ROTATION_PROBABILITY)

    def significant(self, white_linear: np.ndarray) -> bool:
        """The correction is shown (chi-square beyond ``CORRECTION_PROBABILITY``) and matters (RMS effect
        beyond ``MIN_EFFECT`` of the white noise on some axis)."""
        return bool(self.chi2 > chi2_quantile(6, CORRECTION_PROBABILITY)
                    and np.any(self.effect_rms > MIN_EFFECT * np.maximum(white_linear, 1e-3)))


def _robust_var(x: np.ndarray) -> np.ndarray:
    return (1.4826 * np.median(np.abs(x - np.median(x, axis=0)), axis=0)) ** 2


def _gls(A: np.ndarray, weight: np.ndarray, y: np.ndarray, prior: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N3, N6) generalized least squares with diagonal weights and a prior information: the rows
    ``A`` (n,a,k), their weights ``weight`` and values ``y`` (n,a), ``prior`` (k,k); returns (x (k,),
    its covariance (k,k))."""
    cov = np.linalg.inv(np.einsum("nai,na,naj->ij", A, weight, A) + prior)
    return cov @ np.einsum("nai,na,na->i", A, weight, y), cov


def _lever_rows(omega: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N3) the rows of v_imu - v_vis in x = [r, c] for the pairs' rates ``omega`` (n,3): [omega^, I]
    (n,3,6), and the prior information of x (6,6) (``LEVER_PRIOR_M``, ``OFFSET_PRIOR_M_S``)."""
    A = np.zeros((omega.shape[0], 3, 6))
    A[:, :, :3] = se3.hat3(omega)
    A[:, :, 3:] = np.eye(3)
    return A, np.diag(np.r_[np.full(3, LEVER_PRIOR_M**-2), np.full(3, OFFSET_PRIOR_M_S**-2)])


def _huber(z: np.ndarray) -> np.ndarray:
    """Huber's weights of residuals ``z`` in standard deviations (tuning 1.345)."""
    return np.where(z <= 1.345, 1.0, 1.345 / np.maximum(z, 1e-12))


def imu_vs_vision(fits: list[TwoViewFit], seq: Sequence, imu_T_cam: np.ndarray, velocity_index: str) -> ImuVsVision | None:
    """(N3) from the gap-1 ``fits`` of ``seq`` with the extrinsic and velocity timing decided; None
    with fewer than ``MIN_PAIRS`` fits of ``MIN_POINTS`` points or more."""
    fits = [f for f in fits if f.gap == 1 and f.points >= MIN_POINTS]
    if len(fits) < MIN_PAIRS:
        return None
    cam_T_imu = se3.inverse(imu_T_cam)
    Ad = se3.adjoint(imu_T_cam)
    shift = 1 if velocity_index == "next" else 0
    n = len(fits)
    u_vis = np.empty((n, 6))
    var_vis = np.empty((n, 6))
    v_imu = np.empty((n, 3))
    w_imu = np.empty((n, 3))
    for i, f in enumerate(fits):
        tau = seq.time_stamps[f.step + 1] - seq.time_stamps[f.step]
        M = imu_T_cam @ se3.inverse(f.b_T_a) @ cam_T_imu
        u_vis[i] = se3.log_se3(M) / tau
        var_vis[i] = np.diag(Ad @ f.motion_covariance @ Ad.T) / tau**2
        v_imu[i] = seq.linear_velocity[f.step + shift]
        w_imu[i] = seq.angular_velocity[f.step + shift]
    # angular: a constant bias and the white noise
    dw = w_imu - u_vis[:, 3:]
    bias = np.median(dw, axis=0)
    vis_w = np.median(var_vis[:, 3:], axis=0)
    ang = np.sqrt(np.maximum(_robust_var(dw) - vis_w, 0.0))
    # linear: e = v_imu - v_vis = [omega]x r + c + noise, GLS with Huber weights and a weak prior
    e = v_imu - u_vis[:, :3]
    A, prior = _lever_rows(u_vis[:, 3:])
    vis_v = np.median(var_vis[:, :3], axis=0)
    noise_var = np.maximum(_robust_var(e) - vis_v, 1e-6)
    theta = np.zeros(6)
    huber = np.ones((n, 3))
    for _ in range(5):
        theta, cov = _gls(A, huber / (var_vis[:, :3] + noise_var), e, prior)
        res = e - np.einsum("nai,i->na", A, theta)
        noise_var = np.maximum(_robust_var(res) - vis_v, 1e-6)
        huber = _huber(np.abs(res) / np.sqrt(var_vis[:, :3] + noise_var))
    effect = np.sqrt(np.mean(np.einsum("nai,i->na", A, theta) ** 2, axis=0))
    chi2 = float(theta @ np.linalg.solve(cov, theta))
    total = _robust_var(res)
    share = float(np.median(vis_v / np.maximum(total, 1e-12)))
    steps = np.array([f.step for f in fits])
    rotation, rotation_cov = frame_rotation(u_vis, var_vis, v_imu, w_imu, noise_var, ang**2, steps)
    return ImuVsVision(n, theta[:3].copy(), theta[3:].copy(), cov, chi2, effect, np.sqrt(noise_var), ang, bias, share,
                       rotation, rotation_cov)


def frame_rotation(u_vis: np.ndarray, var_vis: np.ndarray, v_imu: np.ndarray, w_imu: np.ndarray,
                   linear_var: np.ndarray, angular_var: np.ndarray, steps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N6) the rotation theta (3,) rad of the samples' frame and its covariance (3,3), from the pairs'
    vision twists ``u_vis`` (n,6) with variances ``var_vis`` (n,6) and the IMU's samples ``v_imu``,
    ``w_imu`` (n,3) whose white noise variances per axis are ``linear_var``, ``angular_var`` (3,):
    x = [r, c, b, theta] by generalized least squares with Huber weights and the priors of N3, N6.
    Each axis's standard error is widened to the spread of the estimates of ``BATCHES`` contiguous
    batches of pairs (in the order of their ``steps`` (n,)) where that is the larger, as D4 does for
    the disparity offset: drifting tracks err alike over neighbouring pairs."""
    n = u_vis.shape[0]
    v, w = u_vis[:, :3], u_vis[:, 3:]
    A = np.zeros((n, 6, 12))
    prior = np.zeros((12, 12))
    A[:, :3, 0:6], prior[0:6, 0:6] = _lever_rows(w)  # omega x r + c (N3)
    A[:, :3, 9:12] = se3.hat3(v)  # v x theta
    A[:, 3:, 6:9] = np.eye(3)  # b
    A[:, 3:, 9:12] = A[:, :3, 0:3]  # omega x theta
    prior[6:12, 6:12] = np.diag(np.r_[np.full(3, BIAS_PRIOR_RAD_S**-2), np.full(3, ROTATION_PRIOR_RAD**-2)])
    y = np.concatenate([v_imu - v, w_imu - w], axis=1)  # (n,6)
    var = var_vis + np.r_[linear_var, np.maximum(angular_var, 1e-10)]
    huber = np.ones((n, 6))
    for _ in range(5):
        x, cov = _gls(A, huber / var, y, prior)
        huber = _huber(np.abs(y - np.einsum("nai,i->na", A, x)) / np.sqrt(var))
    cov = 0.5 * (cov[9:12, 9:12] + cov[9:12, 9:12].T)
    parts = [p for p in np.array_split(np.argsort(steps, kind="stable"), min(BATCHES, n)) if p.size]
    if len(parts) >= 2:
        weight = huber / var
        batches = np.array([_gls(A[p], weight[p], y[p], prior)[0][9:12] for p in parts])
        batch_var = np.var(batches, axis=0, ddof=1) / len(parts)
        widen = np.sqrt(np.maximum(batch_var / np.maximum(np.diag(cov), 1e-30), 1.0))
        cov = cov * np.outer(widen, widen)
    return x[9:12].copy(), cov


@dataclass(frozen=True)
class ImuNoiseDecision:
    """The IMU noise the filter uses, per axis, and where each number came from."""

    linear_sigma: np.ndarray  # (3,) m/s, used
    angular_sigma: np.ndarray  # (3,) rad/s, used
    linear_source: str  # "configured" | "IMU against vision" | "innovation likelihood" | "white noise"
    angular_source: str
    white_linear: np.ndarray  # (3,) N1
    white_angular: np.ndarray  # (3,)
    vision: ImuVsVision | None = None  # N3, where measured
    likelihood: dict = field(default_factory=dict)  # candidate linear sigma -> log-likelihood per observation
    hold_linear: np.ndarray | None = None  # (3,) N4
    hold_angular: np.ndarray | None = None

    def as_dict(self) -> dict:
        return {
            "linear_velocity_sigma": self.linear_sigma.tolist(), "linear_decided_by": self.linear_source,
            "angular_velocity_sigma": self.angular_sigma.tolist(), "angular_decided_by": self.angular_source,
            "white_noise_linear": self.white_linear.tolist(), "white_noise_angular": self.white_angular.tolist(),
            "hold_linear": None if self.hold_linear is None else self.hold_linear.tolist(),
            "hold_angular": None if self.hold_angular is None else self.hold_angular.tolist(),
            "against_vision": None if self.vision is None else self.vision.as_dict(),
            "likelihood_per_observation": dict(self.likelihood),
        }

    def describe(self) -> str:
        def fmt(a):
            return "[" + ", ".join(f"{x:.3g}" for x in a) + "]"

        unused = ""
        if self.vision is not None and not self.vision.measures_imu():
            unused = (f"; against vision not used: vision is {100 * self.vision.vision_share:.0f} % of the scatter "
                      f"(at most {100 * VISION_SHARE_MAX:.0f} % measures the IMU, N3)")
        return (f"IMU noise: linear {fmt(self.linear_sigma)} m/s ({self.linear_source}), angular "
                f"{fmt(self.angular_sigma)} rad/s ({self.angular_source}); white noise of the samples alone "
                f"{fmt(self.white_linear)} m/s, {fmt(self.white_angular)} rad/s{unused}")
