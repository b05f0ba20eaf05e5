"""Whether feature tracks drift with their age (T1), and how fast (T3): decided on the tracks.

A two-view fit of steps k and k+h (D2, ``backend.run.two_view``) fits the motion and every point,
so white pixel noise leaves residuals of the same scale whatever the gap h; a track whose pixels
wander (a tracker that slides off its feature) leaves residuals that grow with h. Real drift is
heavy-tailed (most tracks hold, a few slide fast), so the test compares the pooled RMS of the
residuals (within ``TRIM_PX``: the tail included, gross mismatches not), not a robust scale that
would ignore the few, at the largest gap measured with the one at gap 1:

    ratio = RMS(h_max) / RMS(1),   drift  <=>  ratio > 1 + DRIFT_Z SE(ratio)                        (T1)

with SE by the delta method over the pairs (each pair's mean square, weighted by its degrees of
freedom). Significance alone decides: the walk below is as large as the growth measured, so a
barely significant drift costs a barely visible walk.

How fast (T3). Each point of a fit estimates its own variance, y_i = (sum of its squared
residuals) n / dof (N5 of ``backend.run.noise``), and a line y = a_h + b_h d over the points'
disparities d gives, per gap, the part of the error that is the same for every point (a_h) and
the part that grows with nearness (b_h d). A pixel random walk of variance q(d) per step and
coordinate grows the residuals' mean square by q(d) / ``WALK_GROWTH`` per step of gap, so

    q(d) = WALK_GROWTH (max(0, a_H - a_1) + max(0, b_H - b_1) d) / (H - 1)    px^2 per step        (T3)

(H = h_max). ``WALK_GROWTH`` says how much of a walk the two-view fit absorbs into the points and
the motion, which depends on the scene's geometry (synthetic streets 4.0, aerial scenes 2.7): it
is measured on the drive itself by re-fitting up to ``WALK_PAIRS`` of its gap-H pairs with a known
walk added (simulation-extrapolation, as the stereo offset's SIMEX refit): a displacement e ~
N(0, v I2) common to both images of each point at k+H, v the pairs' own mean square, grows their
mean square by m_v - m_0, so

    WALK_GROWTH = v / (m_v - m_0)                                                                  (T4)

(the test ``test_track_noise.py::test_the_walk_of_random_walk_tracks_is_found`` recovers planted
walks with it on streets and aerial scenes).
The filter turns q(d) into each landmark's random walk: a pixel walk of a point at depth z is a
lateral walk of (z / fx)^2 q(fx b / z) m^2 per step (``backend.estimator.ekf``, R3), and a
landmark is re-anchored after ``drift.reanchor_observations`` observations (R1). What made the
tracks (the file's ``tracker`` key) is reported beside the test, never used by it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import Choice, Config
from ..data.sequence import Sequence
from .noise import variance_line
from .two_view import TwoViewFit, fit_pairs, pooled_mean_square

__all__ = ["DriftDecision", "drift_test", "drift_walk", "walk_growth", "decide_track_drift"]

#: (T1): the residual scale must grow by more than this many standard errors between gap 1 and the largest gap.
DRIFT_Z = 4.0
#: Fewer pairs than this at either gap: the test says nothing.
MIN_PAIRS = 10
#: (T4): pairs re-fitted with a known walk to measure how much of it the fits absorb ...
WALK_PAIRS = 40
#: The noise and drift tests (``backend.run.decisions``) and the walk's re-fits take pairs down to this many
#: points (the stereo offset needs 12).
NOISE_MIN_POINTS = 5


@dataclass(frozen=True)
class DriftDecision:
    """Whether the filter models drifting tracks, the test (T1) and the walk (T3) behind it."""

    drifting: bool
    source: str  # "test" | "configured" | "not testable"
    ratio: float = float("nan")  # s(h_max) / s(1)
    ratio_se: float = float("nan")
    scales: tuple = ()  # (gap, pairs, pooled RMS px) per gap
    tracker: str = ""  # what the file says made the tracks (informs only)
    walk: float = 0.0  # (T3) px^2 per step of a track's pixel random walk at zero disparity
    walk_per_disparity: float = 0.0  # (T3) px^2 per step and px of disparity
    walk_growth: float = float("nan")  # (T4) the walk's share the fits show: v / (m_v - m_0)
    walk_configured: tuple = (False, False)  # (walk, walk_per_disparity) taken from the configuration

    def as_dict(self) -> dict:
        return {"drifting": self.drifting, "decided_by": self.source, "ratio": self.ratio, "ratio_se": self.ratio_se,
                "rms_by_gap": [{"gap": g, "pairs": n, "rms_px": s} for g, n, s in self.scales],
                "pixel_walk_px2_per_step": self.walk, "pixel_walk_px2_per_step_per_px": self.walk_per_disparity,
                "walk_growth_factor": self.walk_growth, "walk_configured": list(self.walk_configured),
                "tracker_key": self.tracker}

    def describe(self, config: Config | None = None) -> str:
        scales = ", ".join(f"gap {g}: {s:.2f}" for g, n, s in self.scales)
        if self.source == "test":
            why = (f"RMS of two-view residuals {scales} px, ratio {self.ratio:.2f} +- {self.ratio_se:.2f}")
        elif self.source == "configured":
            why = "configured"
        else:
            why = f"not testable ({scales or 'no step pairs with enough tracks'}), so modelled as drifting"
        text = f"track drift: {'yes' if self.drifting else 'no'} ({why})"
        if self.tracker:
            text += f"; the file says its tracks come from '{self.tracker}'"
        if self.drifting and config is not None:
            d = config.drift
            if d.landmark_random_walk is not None:
                walk = f"random walk {d.landmark_random_walk:g} m/sqrt(s) (configured)"
            elif any(self.walk_configured):
                walk = (f"pixel random walk {self.walk:.3g} + {self.walk_per_disparity:.3g} d px^2 a step "
                        f"({'configured' if all(self.walk_configured) else 'configured where set, the rest measured, T3'})")
            elif np.isfinite(self.walk_growth):
                walk = (f"pixel random walk {self.walk:.3g} + {self.walk_per_disparity:.3g} d px^2 a step "
                        f"(T3, disparity d px; the fits show 1/{self.walk_growth:.2f} of a walk, T4)")
            else:
                walk = "no random walk (too few step pairs to measure one, T3)"
            if config.estimator.full_state:
                text += f"; {walk}, no re-anchoring (estimator.full_state keeps every landmark)"
            else:
                text += (f"; landmarks re-anchored after {d.reanchor_observations} observations "
                         f"({d.reanchor_far_observations} below {d.reanchor_far_disparity:g} px disparity), {walk}")
        return text


def drift_test(fits_by_gap: dict[int, list[TwoViewFit]]) -> tuple[float, float, tuple]:
    """(T1): (ratio, its standard error, (gap, pairs, pooled RMS px) per gap); nan ratio when gap 1
    or the largest gap has fewer than ``MIN_PAIRS`` fits."""
    scales = []
    pooled = {}
    for gap in sorted(fits_by_gap):
        fits = fits_by_gap[gap]
        if fits:
            pooled[gap] = (pooled_mean_square(fits), len(fits))
            scales.append((gap, len(fits), float(np.sqrt(pooled[gap][0][0]))))
    gaps = [g for g in pooled if pooled[g][1] >= MIN_PAIRS]
    if 1 not in gaps or len(gaps) < 2:
        return float("nan"), float("nan"), tuple(scales)
    (m1, s1), _ = pooled[1]
    (mh, sh), _ = pooled[max(gaps)]
    ratio = np.sqrt(mh / m1)
    se = 0.5 * ratio * np.hypot(s1 / m1, sh / mh)
    return float(ratio), float(se), tuple(scales)


def walk_growth(seq: Sequence, fits: list[TwoViewFit], seed: int = 0) -> float:
    """(T4) v / (m_v - m_0) over up to ``WALK_PAIRS`` of the pairs ``fits`` (one gap), fitted again
    with e ~ N(0, v I2) added to both images' pixels of every point at their later step, v their
    pooled mean square m_0; nan when no pair fits again or the mean square does not grow."""
    if not fits:
        return float("nan")
    chosen = [fits[i] for i in np.unique(np.linspace(0, len(fits) - 1, min(WALK_PAIRS, len(fits))).round().astype(int))]
    v = pooled_mean_square(chosen)[0]
    walked = fit_pairs(seq, chosen[0].gap, len(chosen), offset=True, min_points=NOISE_MIN_POINTS,
                       steps=np.array([f.step for f in chosen], dtype=np.int64), seed=seed, walk=v)
    if not walked:
        return float("nan")
    steps = {f.step for f in walked}
    base = [f for f in chosen if f.step in steps]
    grown = pooled_mean_square(walked)[0] - pooled_mean_square(base)[0]
    return float(v / grown) if grown > 0 else float("nan")


def drift_walk(seq: Sequence, fits_by_gap: dict[int, list[TwoViewFit]]) -> tuple[float, float, float]:
    """(T3, T4): (walk at zero disparity px^2/step, walk per px of disparity px^2/step/px, the growth
    factor) from gap 1 and the largest gap with ``MIN_PAIRS`` fits; zeros (and nan) when not measurable."""
    gaps = sorted(g for g, fits in fits_by_gap.items() if len(fits) >= MIN_PAIRS)
    if 1 not in gaps or len(gaps) < 2:
        return 0.0, 0.0, float("nan")
    h = gaps[-1]
    first, last = variance_line(fits_by_gap[1])[0], variance_line(fits_by_gap[h])[0]
    growth = walk_growth(seq, fits_by_gap[h])
    if not (np.all(np.isfinite(first)) and np.all(np.isfinite(last)) and np.isfinite(growth)):
        return 0.0, 0.0, growth
    q0, qd = growth * np.maximum(0.0, last - first) / (h - 1)
    return float(q0), float(qd), growth


def decide_track_drift(config: Config, seq: Sequence, fits_by_gap: dict[int, list[TwoViewFit]]) -> DriftDecision:
    """``drift.track_drift``: "yes"/"no" as configured; "auto" by the test (T1), and drifting when the
    test cannot tell (the safe side: re-anchoring costs a little accuracy on clean tracks, while
    unmodelled drift makes the filter overconfident; the walk is then 0, nothing having measured it).
    The walk (T3, T4) is measured for a drifting sequence whenever the fits allow; ``drift.pixel_walk``
    and ``drift.pixel_walk_per_disparity``, where configured, are used instead."""
    ratio, se, scales = drift_test(fits_by_gap)
    setting = config.drift.track_drift
    if setting != Choice.AUTO:
        drifting, source = setting == Choice.YES, "configured"
    elif not np.isfinite(ratio):
        drifting, source = True, "not testable"
    else:
        drifting, source = bool(ratio > 1.0 + DRIFT_Z * se), "test"
    d = config.drift
    walk, per_disparity, growth = 0.0, 0.0, float("nan")
    if drifting and (d.pixel_walk is None or d.pixel_walk_per_disparity is None):
        walk, per_disparity, growth = drift_walk(seq, fits_by_gap)
    if d.pixel_walk is not None:  # configured values win over the measured ones
        walk = d.pixel_walk
    if d.pixel_walk_per_disparity is not None:
        per_disparity = d.pixel_walk_per_disparity
    return DriftDecision(drifting, source, ratio, se, scales, seq.tracker, walk, per_disparity, growth,
                         (d.pixel_walk is not None, d.pixel_walk_per_disparity is not None))
