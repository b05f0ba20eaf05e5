"""The stereo pair's disparity offset, identified from the tracks rather than assumed zero.

A rectified pair whose right image is offset (a principal-point difference after rectification)
or exposed a few milliseconds apart from the left one (the rig turns between the two exposures)
measures every disparity off by an amount the calibration does not say. On a highway, where
most points have a disparity of 5-10 px, 1 px of it makes every depth 10-20 % too long, and the
filter's scale with it. The model, per step k,

    d_measured = d_true + beta_k,    beta_k = beta_0 + kappa * omega_y(k)                       (D1)

with ``omega_y`` the angular rate about the camera's y axis (rad/s; from the IMU through
``cam_T_imu``): ``beta_0`` (px) a constant offset, ``kappa = fx dt`` (px s/rad) the first-order
effect of a right image exposed ``dt`` seconds after the left one while the rig turns.

Identification, from vision alone (no IMU translation, no ground truth): for a spread of steps,
a two-view bundle adjustment of the points seen at k and k+1: each point's true (u, v, disparity)
at k, the free rigid motion k -> k+1 and ``beta_k`` minimize the robust (Huber, 1 px) error of
all eight measured pixels (both images, both frames; Gauss-Newton, points eliminated by the
Schur complement); pairs whose rows disagree are left out, and after a first fit the points
with a residual beyond the trim are dropped and the fit repeated (gross mismatches)              (D2)

A wrong offset warps depth non-uniformly (``z = fx b / (d - beta)``), which no rigid motion
explains; so ``beta_k`` is observable where the step's points span a range of disparities.
Then ``beta_k`` is regressed on ``omega_y(k)`` by a Huber-reweighted fit with weights in
proportion to the pairs' points, its standard errors from the scatter of the ``beta_k``          (D3)

Not by the pairs' inverse variances: a pair's variance is evaluated at its own ``beta_k``, and
noise that raises ``beta_k`` shrinks the disparities, lengthens the depths and raises the
information on ``beta`` with it, so those weights follow the pairs' errors. Over 264 random
scenes (``vislam.synth.grid``: the grid and random seeds 700-739, 800-839, 900-979, 1000-1079)
the inverse-variance mean came out too high by +0.03 px on average on streets and +0.17 to
+2.0 px on aerial scenes (disparities of 5-20 px, 0.25-1 px of noise), the points' mean by
-0.05 to +0.14 px: RMS errors 0.061 against 0.051 px (streets), 1.39 against 0.30 px (aerial).
The pixel noise's own bias of the points' mean (a point's depth is among the unknowns of every
pair: the incidental parameter problem) is a tenth of a pixel at 1 px of noise on aerial
scenes, under its standard error, and is not removed: a SIMEX correction (the pairs fitted
again with added noise) measured it at -0.15 px where the points' mean was off by -0.10 px
(white noise), and on the 264 scenes, where the tracks' other errors dominate, it raised the
RMS error from 0.22 to 0.26 px.

The pairs' errors are not independent: a track's drift, the frames' jitter or a part of the
drive with few near points move the ``beta_k`` of neighbouring pairs together, which the
scatter does not see. The standard errors are therefore widened by the spread of the means of
``BATCHES`` contiguous batches of pairs (batch means), where it is the larger:

    se^2 = max(se_scatter^2, B / (B - 1) sum_b W_b^2 (m_b - m)^2 / (sum_b W_b)^2)                 (D4)

with ``W_b`` a batch's points and ``m_b`` its weighted mean; the rate model's standard errors are
widened by the same ratio measured on its own residuals (a planted rate term is, to the constant
model, an error that follows the turns and so persists over neighbouring pairs).
On the 264 scenes the error of the estimate in its standard errors has a mean square of 1.10
with the batches (1.68 from the scatter alone; 1 is honest), and on the real drives the
batches are the larger by 2.8 (0027) and 4.8 times (``ece276a_03.npz``: -0.65 +- 0.19 px, the scatter alone
+- 0.04).

``conventions.stereo_offset = "constant"`` (the default) removes the weighted mean of ``beta_k``
when it differs from 0 by more than ``SIGNIFICANCE`` standard errors and ``MIN_EFFECT_PX``;
``"rate"`` removes ``beta_0 + kappa omega_y`` when ``kappa`` is significant likewise (at the
drive's spread of rates), else the constant; ``"off"`` estimates nothing. Both terms are always
estimated and reported. The constant is the default because it is what the data supports: on
KITTI 01 (frames 0-50, one steady turn) and KITTI-360 (03) the offset is a constant (-1.4 and
-0.66 px; on 03 dead reckoning's own reprojection test has its best offset at -0.6 to -0.75 px),
while the rate term found on KITTI 07 (ece276a_0027: -2.3 +- 1.2 px s/rad, 4-6 standard errors
from the pairs' scatter alone, 2 with D4's batches) made the estimate worse over six draws of its
velocity noise (BENCHMARKS.md). The run removes an offset only if the
IMU does not contradict it (``backend.run.runner.checked_offset``: dead reckoning's reprojection
test C1 must not get worse). The correction moves the right pixel: ``uR <- uR + beta_k``.

Where the two-view estimate leaves the scale open (what it leaves undecided moves the depth of the
median point, ``o * median(1/d)``, by more than ``SCALE_MIN_EFFECT``: ``o = se`` where the offset is
removed, ``o = |beta| + se`` where it is not significant and stays in the pixels; or no estimate
was made),
the IMU measures the offset a second time: the filter over the first steps (at most 300, at least
the 101 H4 needs: not an image stream's first 100 frames) is run with trial offsets and its scale
s(beta) checked against the IMU's (H4 of ``backend.estimator.health``): a secant search on
f(beta) = s(beta) - 1, the first trial at the offset the tracks decided, the second a step that
would move a vision-only scale (ds/dbeta ~ -mean(1/d)) by the first error or at least two of its
standard errors, each candidate within ``SIGNIFICANCE`` standard errors of the two-view estimate,
ended within one standard error of 1 or after ``SCALE_SEARCH_RUNS`` runs. Through the two trials
closest to 1 (the trials share the data, so their difference is far more precise than either),

    beta_imu = beta_1 + (1 - s_1) / slope,   slope < 0,
    se(beta_imu) = hypot(c_t se(s_1) / |slope|, MIN_EFFECT_PX)                                   (D5)

with ``c_t = sqrt(9/7)`` the standard deviation of a t with the batch means' 9 degrees of freedom,
and ``MIN_EFFECT_PX`` in quadrature: a run's scale carries errors over its whole length that batch
means do not see (on street scenes with 1 px of noise and no offset the IMU put it at +0.07 and
+0.10 px, 3 and 4 of its standard errors without that term, on 2 of 8 noise draws; applied, they
took the 8 runs' pose NEES from 6.6 to 8.0). The slope is the filter's own: where vision hardly
moves the filter's scale the IMU says little about the offset, however precise its scale. The two
measurements are combined by their inverse variances,

    beta = (beta_imu / se_imu^2 + beta_tv / se_tv^2) / (1 / se_imu^2 + 1 / se_tv^2),
    se(beta) = (1 / se_imu^2 + 1 / se_tv^2)^(-1/2)                                              (D6)

(the IMU's alone where the tracks gave no estimate), and ``beta`` is applied where it exceeds
``FUSED_SIGNIFICANCE`` of its standard errors and ``MIN_EFFECT_PX``, with ``se(beta)`` as the
residual offset's prior sigma (O1 of ``backend.estimator.offset``; the filter considers it where
the tracks do not drift); else none. Not a test of the scale first: at 3 standard errors of scale
(a 4 % error on a random aerial scene, +0.7 px planted, two-view +0.86 +- 0.67 px) the run was 2.8
times dead reckoning's error and NEES 1565. ``FUSED_SIGNIFICANCE = 2`` is chosen on random scenes
700-739 and checked on 800-839 and the grid (BENCHMARKS.md): 0 and 1 apply offsets where none is
planted and cost the median scene; 3 and 4 leave more scenes with a planted offset worse than dead
reckoning. The trial runs carry no residual offset state,
so that s(beta) is the mean offset's alone: a consider state, there only for a nonzero offset,
makes s jump at 0 and flattens it (on a random aerial scene a search then ended at +0.35 px where
-1 was planted). What the IMU cannot tell apart: an IMU whose speed is off moves beta_imu as an
offset would (a speed 3 % high reads as the offset that makes vision 3 % longer).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from ..config import Config
from ..data.sequence import Sequence
from ..estimator.health import SCALE_MIN_EFFECT, SCALE_MIN_STEPS, ScaleCheck, ratio_of_batches
from .two_view import fit_pairs

__all__ = ["StereoOffset", "OffsetMeasurement", "identify_stereo_offset", "camera_rate_y", "offset_by_imu_scale"]

#: A term is applied when its estimate exceeds this many standard errors (``auto``).
SIGNIFICANCE = 4.0
#: ... and changes a disparity by more than this (px) at the drive's rates: below it a correction is immaterial.
MIN_EFFECT_PX = 0.05
#: At most this many steps enter the identification (spread evenly over the sequence).
MAX_STEPS = 300
#: The offset is estimated from at least this many step pairs, else not at all.
MIN_STEPS = 10
#: A step needs this many points seen at k and k+1 (``backend.run.two_view``).
MIN_POINTS = 12
#: D4: the contiguous batches of step pairs whose means measure the estimate's standard error.
BATCHES = 10
#: D5: trial runs of the search for the offset that makes the filter's scale the IMU's, at most.
SCALE_SEARCH_RUNS = 4
#: D6: the offset fused from the tracks' and the IMU's measurements is applied beyond this many of its
#: standard errors (and ``MIN_EFFECT_PX``)
FUSED_SIGNIFICANCE = 2.0
#: D5: the standard deviation of a t with the 9 degrees of freedom of H4's batch means, by which its
#: standard error is widened to a normal one
T_WIDENING = math.sqrt(9.0 / 7.0)


@dataclass
class StereoOffset:
    """The disparity offset model (D1) applied to a run, with the numbers behind it."""

    beta0_px: float = 0.0  # applied constant offset
    kappa_px_s: float = 0.0  # applied px per rad/s of omega_y
    estimate: dict = field(default_factory=dict)  # beta0, kappa with their standard errors, steps used
    source: str = "off"  # "auto, constant" | "auto, rate" | "off"
    sigma_px: float | None = None  # the applied offset's standard error where it is not the tracks' alone (D6)

    @property
    def active(self) -> bool:
        return self.beta0_px != 0.0 or self.kappa_px_s != 0.0

    @property
    def residual_sigma(self) -> float:
        """px: the standard error of the applied offset, what it may leave (O1 of
        ``backend.estimator.offset``): the fused one (D6) where the IMU's scale entered, else the
        tracks'; 0 where none is applied."""
        e = self.estimate
        if self.active and self.sigma_px is not None:
            return float(self.sigma_px)
        if not self.active or "beta_mean_px" not in e:
            return 0.0
        se = e["beta0_se"] if self.kappa_px_s != 0.0 else e["beta_mean_se"]
        return float(se) if np.isfinite(se) else 0.0

    def offsets(self, omega_y: np.ndarray | float) -> np.ndarray | float:
        """beta_k (px) for camera-y angular rates ``omega_y`` (rad/s)  (D1)."""
        return self.beta0_px + self.kappa_px_s * omega_y

    def correct(self, pixels: np.ndarray, omega_y: float) -> np.ndarray:
        """Pixels (n,4) with the right column moved by beta_k: d_true = d_measured - beta_k."""
        if not self.active or pixels.shape[0] == 0:
            return pixels
        out = np.array(pixels, dtype=float, copy=True)
        out[:, 2] += self.offsets(omega_y)
        return out

    def corrected(self, seq: Sequence, imu_T_cam: np.ndarray) -> Sequence:
        """``seq`` with every step's right pixels moved by its beta_k (D1)."""
        if not self.active:
            return seq
        omega = camera_rate_y(seq.angular_velocity, imu_T_cam)
        pixels = seq.obs_pixels.copy()
        pixels[:, 2] += np.repeat(self.offsets(omega), np.diff(seq.obs_ptr))
        return dataclasses.replace(seq, obs_pixels=pixels)

    def as_dict(self) -> dict:
        return {"beta0_px": self.beta0_px, "kappa_px_per_rad_s": self.kappa_px_s, "decided_by": self.source,
                "estimate": self.estimate}

    def describe(self) -> str:
        e = self.estimate
        if self.source == "off" and not e:
            return "stereo disparity offset: not estimated (conventions.stereo_offset = off)"
        if "rejected" in e and not self.active:
            return f"stereo disparity offset: none applied ({self.source}; {e['rejected']}{self._scale_text()})"
        if "beta_mean_px" not in e:
            found = (f"not identifiable from the tracks ({e.get('steps', 0)} step pairs with enough points seen at k "
                     f"and k+1, {MIN_STEPS} needed){self._scale_text()}")
            if not self.active:
                return f"stereo disparity offset: {found}; none applied"
            return f"stereo disparity offset removed ({self.source}): {self._applied_text()}; {found}"
        fx = e.get("fx", 1.0)
        found = f"{e['beta_mean_px']:+.2f} +- {e['beta_mean_se']:.2f} px on average"
        if "rejected" in e:
            found += f" ({e['rejected']})"
        if np.isfinite(e["kappa_se"]):
            late = 1e3 * e["kappa_px_s"] / fx
            found += (f", split into a constant {e['beta0_px']:+.2f} +- {e['beta0_se']:.2f} px (beta_0) and "
                      f"{e['kappa_px_s']:+.2f} +- {e['kappa_se']:.2f} px per rad/s of turn (kappa: the right image "
                      f"taken {abs(late):.2f} ms {'after' if late >= 0 else 'before'} the left)")
        found += f"; from {e['steps']} step pairs"
        if e["batch_means_se_px"] > e["scatter_se_px"]:
            found += (f" (standard errors from {BATCHES} batches of consecutive pairs, whose means spread more than "
                      f"the pairs' scatter says: +- {e['scatter_se_px']:.2f} px)")
        found += self._scale_text()
        if not self.active:
            return f"stereo disparity offset: none applied ({self.source}; estimated {found})"
        return f"stereo disparity offset removed ({self.source}): {self._applied_text()}; estimated {found}"

    def _applied_text(self) -> str:
        if self.kappa_px_s == 0.0:
            b = self.beta0_px
            return f"the pair measures disparities {abs(b):.2f} px {'short' if b < 0 else 'long'}: d_true = d {-b:+.2f} px"
        return f"d_true = d - ({self.beta0_px:+.2f} px {self.kappa_px_s:+.2f} px s/rad * omega_y)"

    def _scale_text(self) -> str:
        """What the filter's scale against the IMU's said (D5, D6), where it was checked."""
        check = self.estimate.get("imu_scale")
        if not check or not check.get("trials"):
            return ""
        first = check["trials"][0]
        text = (f"; the filter's scale over the first {check['steps']} steps against the IMU's (D5): the IMU moved "
                f"{first['imu_over_filter']:.3f} +- {first['standard_error']:.3f} times the filter's distance a step "
                f"at {first['beta_px']:+.2f} px")
        if "imu_px" not in check:
            return f"{text}; no offset from it ({check.get('why', '')})"
        text += (f", so the IMU puts the offset at {check['imu_px']:+.2f} +- {check['imu_se_px']:.2f} px "
                 f"({len(check['trials'])} trials)")
        if check["with_tracks"]:
            text += (f", combined with the tracks' estimate {check['fused_px']:+.2f} +- "
                     f"{check['fused_se_px']:.2f} px (D6)")
        if not check["applied"]:
            text += f": within {FUSED_SIGNIFICANCE:g} standard errors of none"
        return text


@dataclass(frozen=True)
class OffsetMeasurement:
    """A measurement of the disparity offset: the tracks' (D3), the IMU's scale's (D5) or both (D6)."""

    px: float
    se_px: float  # its standard error

    def combined(self, other: "OffsetMeasurement") -> "OffsetMeasurement":
        """The inverse-variance mean of two independent measurements (D6)."""
        w, w_other = self.se_px**-2, other.se_px**-2
        return OffsetMeasurement((w * self.px + w_other * other.px) / (w + w_other), (w + w_other) ** -0.5)


def camera_rate_y(angular_velocity: np.ndarray, imu_T_cam: np.ndarray) -> np.ndarray:
    """omega about the camera's y axis (N,) from IMU-frame angular rates (N,3): R_cam_imu w."""
    R_cam_imu = np.asarray(imu_T_cam, dtype=float)[:3, :3].T
    return np.asarray(angular_velocity, dtype=float).reshape(-1, 3) @ R_cam_imu[1]


def _regress(A: np.ndarray, beta: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted, Huber-reweighted least squares beta ~ A c (D3): (c, standard errors), with relative
    weights (variances ``s^2 / weight`` for an unknown ``s``, ``s^2`` the reduced chi-square)."""
    w0 = np.asarray(weight, dtype=float)
    w = w0.copy()
    p = A.shape[1]
    for _ in range(20):
        coef = np.linalg.solve(A.T @ (A * w[:, None]) + 1e-12 * np.eye(p), A.T @ (w * beta))
        r = (beta - A @ coef) * np.sqrt(w0)
        scale = max(1.4826 * float(np.median(np.abs(r))), 1e-12)
        a = np.abs(r) / scale
        w = w0 * np.where(a <= 1.345, 1.0, 1.345 / np.maximum(a, 1e-12))
    r = (beta - A @ coef) * np.sqrt(w0)
    chi2 = float(np.sum(w / w0 * r**2) / max(r.size - p, 1))
    return coef, np.sqrt(np.diag(np.linalg.inv(A.T @ (A * w[:, None])) * chi2))


def batch_means_se(beta: np.ndarray, weight: np.ndarray, batches: int = BATCHES) -> float:
    """(D4) the standard error of the weighted mean of ``beta`` (n,), in step order, with weights
    ``weight`` (n,), from the spread of the weighted means of ``batches`` contiguous batches (H4's
    ratio of batch sums, :func:`~backend.estimator.health.ratio_of_batches`); nan with fewer than two
    batches."""
    parts = [p for p in np.array_split(np.arange(beta.size), min(batches, beta.size)) if p.size]
    if len(parts) < 2:
        return math.nan
    sums = np.array([weight[p] @ beta[p] for p in parts])
    return ratio_of_batches(sums, np.array([weight[p].sum() for p in parts]))[1]


def identify_stereo_offset(seq: Sequence, imu_T_cam: np.ndarray, model: str = "constant",
                           max_steps: int = MAX_STEPS) -> StereoOffset:
    """The offset (D1) of ``seq`` with the extrinsic ``imu_T_cam``, estimated (D2-D3) and applied as
    ``model`` says (:func:`offset_from_fits`); "off" estimates nothing."""
    if str(model) == "off":
        return StereoOffset(source="off")
    return offset_from_fits(seq, imu_T_cam, model, fit_pairs(seq, 1, max_steps, offset=True, min_points=MIN_POINTS))


def offset_from_fits(seq: Sequence, imu_T_cam: np.ndarray, model: str, fits: list) -> StereoOffset:
    """(D3) from the gap-1 two-view fits with the offset (D2) of ``seq`` that hold ``MIN_POINTS``
    points or more: "constant" the weighted mean of beta_k, "rate" beta_0 + kappa omega_y (the rate
    term only where it is significant, else the constant), each only where it is significant
    (``SIGNIFICANCE`` standard errors and ``MIN_EFFECT_PX``); "off" estimates nothing."""
    model = str(model)
    if model == "off":
        return StereoOffset(source="off")
    fits = sorted((f for f in fits if f.gap == 1 and f.points >= MIN_POINTS and np.isfinite(f.beta_variance)),
                  key=lambda f: f.step)  # in step order: D4's batches are consecutive pairs
    ks = np.array([f.step for f in fits], dtype=np.int64)
    beta = np.array([f.beta for f in fits])
    source = f"auto, {model}"
    if ks.size < MIN_STEPS:
        return StereoOffset(estimate={"steps": int(ks.size)}, source=source)
    omega = camera_rate_y(seq.angular_velocity, imu_T_cam)
    g = 0.5 * (omega[ks] + omega[np.minimum(ks + 1, omega.size - 1)])
    spread = float(np.std(g))
    points = np.array([f.points for f in fits], dtype=float)
    (mean,), (scatter_se,) = _regress(np.ones_like(g)[:, None], beta, points)
    batch_se = batch_means_se(beta, points)
    mean_se = float(max(scatter_se, batch_se)) if np.isfinite(batch_se) else float(scatter_se)
    estimate = {"beta_mean_px": float(mean), "beta_mean_se": mean_se, "steps": int(ks.size),
                "omega_y_std": spread, "fx": float(seq.K[0, 0]), "scatter_se_px": float(scatter_se),
                "batch_means_se_px": float(batch_se)}
    coef, se = np.array([mean, 0.0]), np.array([mean_se, np.inf])
    if spread >= 1e-3:
        A = np.stack([np.ones_like(g), g], axis=1)
        coef, se = _regress(A, beta, points)
        r = beta - A @ coef  # what the rate model leaves, batched as the mean (D4)
        se = se * max(1.0, batch_means_se(r, points) / _regress(np.ones((r.size, 1)), r, points)[1][0])
    estimate.update(beta0_px=float(coef[0]), beta0_se=float(se[0]), kappa_px_s=float(coef[1]), kappa_se=float(se[1]))
    rate_shown = np.isfinite(se[1]) and abs(coef[1]) > max(SIGNIFICANCE * se[1], MIN_EFFECT_PX / max(spread, 1e-12))
    if model == "rate" and rate_shown:
        return StereoOffset(float(coef[0]), float(coef[1]), estimate, source)
    if abs(mean) > max(SIGNIFICANCE * mean_se, MIN_EFFECT_PX):
        return StereoOffset(float(mean), 0.0, estimate, source)
    return StereoOffset(0.0, 0.0, estimate, source)


def offset_by_imu_scale(seq: Sequence, decisions, config: Config) -> StereoOffset:
    """(D5, D6) the offset of ``decisions`` (a ``backend.run.decisions.Decisions``), or where the tracks
    leave the scale open, the one fused from theirs and the IMU's scale over the first steps of
    ``seq``; what was tried is kept in its estimate (``imu_scale``: each trial's offset and check, the
    IMU's and the fused offset with their standard errors)."""
    from .likelihood import LIKELIHOOD_STEPS, first_steps_scale  # runs the filter: the layer above

    offset = decisions.stereo_offset
    steps = min(seq.num_steps, LIKELIHOOD_STEPS)
    if steps - 1 < SCALE_MIN_STEPS:  # too few steps for H4 to test (a stream's first frames)
        return offset
    e = offset.estimate
    d = seq.obs_pixels[:, 0] - seq.obs_pixels[:, 2] - offset.beta0_px
    d = d[d > 0]
    se = float(e.get("beta_mean_se", np.inf))
    estimated = bool(np.isfinite(se))  # the tracks gave an estimate (D3)
    # what the tracks leave open: the applied offset's standard error, or the offset they left in place
    open_px = se if offset.active or not estimated else abs(float(e["beta_mean_px"])) + se
    if d.size == 0 or (estimated and not open_px * float(np.median(1.0 / d)) > SCALE_MIN_EFFECT):
        return offset
    center = float(e["beta_mean_px"]) if estimated else offset.beta0_px
    half = SIGNIFICANCE * se if estimated else 0.5 * float(np.median(d))
    # the tracks' measurement for D6, unless dead reckoning refused it (``decisions.decide``'s guard)
    tracks = OffsetMeasurement(center, se) if estimated and "rejected" not in e else None
    mean_only = config.with_values({"noise.stereo_offset_sigma": 0.0})  # no residual offset state in the trials
    tried: list[tuple[float, ScaleCheck]] = []  # (offset px, its check), in the order run

    def trial(beta: float) -> ScaleCheck:
        candidate = offset if beta == offset.beta0_px else StereoOffset(beta, offset.kappa_px_s, e, offset.source)
        check = first_steps_scale(seq, dataclasses.replace(decisions, stereo_offset=candidate), mean_only)
        tried.append((beta, check))
        return check

    def kept(o: StereoOffset, **record) -> StereoOffset:
        record = {"steps": int(steps), "trials": [{"beta_px": float(b), **c.as_dict()} for b, c in tried], **record}
        return dataclasses.replace(o, estimate=dict(o.estimate, imu_scale=record))

    first = trial(offset.beta0_px)
    if not first.tested:
        return kept(offset, why="the first trial could not be tested")
    ratio = float(np.mean(1.0 / d))  # -ds/dbeta of a vision-only scale
    step = (first.scale - 1.0) / ratio
    least = 2.0 * first.standard_error / ratio
    if abs(step) < least:  # a step the scale moves by: the slope is measured, not assumed
        step = least if center >= offset.beta0_px else -least
    beta = offset.beta0_px + step
    for _ in range(SCALE_SEARCH_RUNS):
        beta = float(np.clip(beta, center - half, center + half))
        if any(beta == b for b, _ in tried):
            break
        check = trial(beta)
        if not check.tested or abs(check.scale - 1.0) <= check.standard_error:
            break
        slope, beta = _secant(tried[-1], tried[-2])
        if not slope < 0.0:  # the scale falls as the offset rises: else the offset does not explain it
            break
    imu = _imu_offset(tried)
    if isinstance(imu, str):
        return kept(offset, why=imu)
    fused = imu if tracks is None else imu.combined(tracks)
    applied = abs(fused.px) > max(FUSED_SIGNIFICANCE * fused.se_px, MIN_EFFECT_PX)
    numbers = {"imu_px": imu.px, "imu_se_px": imu.se_px, "fused_px": fused.px, "fused_se_px": fused.se_px,
               "with_tracks": tracks is not None, "applied": bool(applied)}
    if not applied:
        return kept(dataclasses.replace(offset, beta0_px=0.0, sigma_px=None), **numbers)
    how = "fused with" if tracks is not None else "set by"  # the IMU's alone where the tracks gave none
    return kept(StereoOffset(fused.px, offset.kappa_px_s, e, f"{offset.source}, {how} the IMU's scale (D6)",
                             sigma_px=fused.se_px), **numbers)


def _imu_offset(tried: list[tuple[float, ScaleCheck]]) -> OffsetMeasurement | str:
    """(D5) the offset with which the filter's scale is the IMU's and its standard error (px), through
    the two tested trials closest to a scale of 1; or why there is none."""
    tested = sorted((t for t in tried if t[1].tested), key=lambda t: abs(t[1].z))
    if len(tested) < 2:
        return "fewer than two trials could be tested"
    slope, root = _secant(tested[0], tested[1])
    if not slope < 0.0:
        return f"the filter's scale does not fall as the offset rises ({slope:+.4f} per px)"
    return OffsetMeasurement(root, float(np.hypot(T_WIDENING * tested[0][1].standard_error / abs(slope),
                                                  MIN_EFFECT_PX)))


def _secant(trial: tuple[float, ScaleCheck], other: tuple[float, ScaleCheck]) -> tuple[float, float]:
    """The line s(beta) through two trials (offset px, check): (its slope per px, the offset at which it
    is 1, reached from ``trial``)."""
    (b1, c1), (b2, c2) = trial, other
    slope = float((c1.scale - c2.scale) / (b1 - b2))
    return slope, (float(b1 + (1.0 - c1.scale) / slope) if slope != 0.0 else math.nan)
