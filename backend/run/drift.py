"""Whether feature tracks drift with their age (T1), and how fast (T3): decided on the tracks.

A two-view fit of steps k and k+h (D2, ``backend.run.two_view``) fits the motion and every point,
so white pixel noise leaves residuals of the same scale whatever the gap h; a track whose pixels
wander (a tracker that slides off its feature) leaves residuals that grow with h. Real drift is
heavy-tailed (most tracks hold, a few slide fast), so the test compares the pooled RMS of the
residuals (within the fits' trim: the tail included, gross mismatches not), not a robust scale that
would ignore the few, at each longer gap h measured (``backend.run.decisions.DRIFT_GAPS``) with the
one at gap 1:

    ratio_h = RMS(h) / RMS(1),   drift  <=>  max_h (ratio_h - 1) / SE(ratio_h) > DRIFT_Z             (T1)

with SE by the delta method over the pairs (each pair's mean square, weighted by its degrees of
freedom). Tracks drift at different paces: the course files' residuals grow within 2-3 steps and
then slowly (0027: RMS 0.36, 0.44, 0.49, 0.55 px at gaps 1, 2, 3, 10), vislam's tracker on rendered
streets only over longer lives (0.17, 0.16, 0.17, 0.20 px): a long gap sees a slow drift that
gaps up to 3 hide. Significance alone decides: the walk below is as large as the growth measured,
so a barely significant drift costs a barely visible walk.

How fast (T3). Each point of a fit estimates its own variance, y_i = (sum of its squared
residuals) n / dof (N5 of ``backend.run.noise``), and a line y = a_h + b_h d over the points'
disparities d gives, per gap, the part of the error that is the same for every point (a_h) and
the part that grows with nearness (b_h d). A pixel random walk of variance q(d) per step and
coordinate grows the residuals' mean square by q(d) / ``WALK_GROWTH`` per step of gap, so

    q_H(d) = WALK_GROWTH_H (max(0, a_H - a_1) + max(0, b_H - b_1) d) / (H - 1)    px^2 per step    (T3)

at the shortest gap H whose growth is significant (T1): the pace over the first steps of a
landmark's life, where the filter's walk starts again at each re-anchoring (the course files' growth
slows down after 2-3 steps; on rendered streets only the long gap sees any). ``WALK_GROWTH`` says
how much of a walk the two-view fit absorbs into the points and the motion, which depends on the
scene's geometry and the gap (synthetic streets 3.5 at gap 2, 4.0 at 3, 6.4 at 10; aerial scenes
2.6-3.9): it is measured on the drive itself by re-fitting up to ``WALK_PAIRS`` of its gap-H pairs
with a known walk added (simulation-extrapolation, SIMEX): a displacement e ~
N(0, v I2) common to both images of each point at k+H, v the pairs' own mean square, grows their
mean square by m_v - m_0, so

    WALK_GROWTH_H = v / (m_v - m_0)                                                                (T4)

(the test ``test_track_noise.py::test_the_walk_of_random_walk_tracks_is_found`` recovers planted
walks with it on streets and aerial scenes within 25 % at gap 2; at gap 10 it counts more of a walk
as absorbed than the tracks show, and the walk comes out 1.4-1.8 times the planted one:
``::test_a_slow_walk_is_found_at_the_long_gap``).
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

__all__ = ["DriftDecision", "Walk", "growth_tests", "drift_test", "drift_walk", "walk_growth", "decide_track_drift"]

#: (T1): the residual scale must grow by more than this many standard errors from gap 1 to a longer gap.
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
    ratio: float = float("nan")  # s(h) / s(1) at the gap h where the growth is most significant
    ratio_se: float = float("nan")
    gap: int = 0  # that gap h
    scales: tuple = ()  # (gap, pairs, pooled RMS px) per gap
    tracker: str = ""  # what the file says made the tracks (informs only)
    walk: float = 0.0  # (T3) px^2 per step of a track's pixel random walk at zero disparity
    walk_per_disparity: float = 0.0  # (T3) px^2 per step and px of disparity
    walk_growth: float = float("nan")  # (T4) the walk's share the fits show: v / (m_v - m_0)
    walk_gap: int = 0  # (T3) the gap H whose growth gave the walk (0: none measured)
    walk_configured: tuple = (False, False)  # (walk, walk_per_disparity) taken from the configuration

    def as_dict(self) -> dict:
        return {"drifting": self.drifting, "decided_by": self.source, "ratio": self.ratio, "ratio_se": self.ratio_se,
                "ratio_gap": self.gap, "rms_by_gap": [{"gap": g, "pairs": n, "rms_px": s} for g, n, s in self.scales],
                "pixel_walk_px2_per_step": self.walk, "pixel_walk_px2_per_step_per_px": self.walk_per_disparity,
                "walk_growth_factor": self.walk_growth, "walk_gap": self.walk_gap,
                "walk_configured": list(self.walk_configured),
                "tracker_key": self.tracker}

    def describe(self, config: Config | None = None) -> str:
        scales = ", ".join(f"gap {g}: {s:.2f}" for g, n, s in self.scales)
        if self.source == "test":
            why = (f"RMS of two-view residuals {scales} px, ratio {self.ratio:.2f} +- {self.ratio_se:.2f} at gap {self.gap}")
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
                        f"(T3, disparity d px, from gaps 1 and {self.walk_gap}; the fits show 1/{self.walk_growth:.2f} "
                        "of a walk, T4)")
            else:
                walk = "no random walk (too few step pairs to measure one, T3)"
            if config.estimator.full_state:
                text += f"; {walk}, no re-anchoring (estimator.full_state keeps every landmark)"
            else:
                text += (f"; landmarks re-anchored after {d.reanchor_observations} observations "
                         f"({d.reanchor_far_observations} below {d.reanchor_far_disparity:g} px disparity), {walk}")
        return text


def growth_tests(fits_by_gap: dict[int, list[TwoViewFit]]) -> tuple[dict[int, tuple[float, float]], tuple]:
    """(T1) per longer gap h: (ratio_h, its standard error), where gap 1 and h have ``MIN_PAIRS``
    fits or more (empty otherwise); and (gap, pairs, pooled RMS px) per gap with fits."""
    scales = []
    pooled = {}
    for gap in sorted(fits_by_gap):
        fits = fits_by_gap[gap]
        if fits:
            pooled[gap] = (pooled_mean_square(fits), len(fits))
            scales.append((gap, len(fits), float(np.sqrt(pooled[gap][0][0]))))
    gaps = [g for g in pooled if pooled[g][1] >= MIN_PAIRS]
    if 1 not in gaps:
        return {}, tuple(scales)
    (m1, s1), _ = pooled[1]
    tests = {}
    for h in gaps[1:]:
        (mh, sh), _ = pooled[h]
        ratio = np.sqrt(mh / m1)
        tests[h] = (float(ratio), float(0.5 * ratio * np.hypot(s1 / m1, sh / mh)))
    return tests, tuple(scales)


def _z(test: tuple[float, float]) -> float:
    ratio, se = test
    return (ratio - 1.0) / se if se > 0 else -np.inf


def _most_significant(tests: dict[int, tuple[float, float]]) -> tuple[float, float, int]:
    """(ratio, its standard error, gap) of the most significant of :func:`growth_tests`' tests;
    (nan, nan, 0) without any."""
    if not tests:
        return float("nan"), float("nan"), 0
    h = max(tests, key=lambda g: _z(tests[g]))
    return tests[h][0], tests[h][1], h


def drift_test(fits_by_gap: dict[int, list[TwoViewFit]]) -> tuple[float, float, int, tuple]:
    """(T1): (ratio, its standard error, the gap h of the most significant growth, (gap, pairs,
    pooled RMS px) per gap); nan ratio (gap 0) when gap 1 or every longer gap has fewer than
    ``MIN_PAIRS`` fits."""
    tests, scales = growth_tests(fits_by_gap)
    return (*_most_significant(tests), scales)


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


@dataclass(frozen=True)
class Walk:
    """(T3, T4): a drifting track's pixel random walk q(d) = walk + per_disparity d px^2 a step."""

    walk: float = 0.0  # px^2 per step at zero disparity
    per_disparity: float = 0.0  # px^2 per step and px of disparity
    growth: float = float("nan")  # (T4) WALK_GROWTH_H of the gap used
    gap: int = 0  # the gap H it was measured at (0: not measurable)


def drift_walk(seq: Sequence, fits_by_gap: dict[int, list[TwoViewFit]], tests: dict[int, tuple[float, float]]) -> Walk:
    """(T3, T4) from gap 1 and the shortest longer gap whose growth is significant in ``tests``
    (:func:`growth_tests` of ``fits_by_gap``, T1); zero (gap 0) when none is, or its walk cannot be
    measured."""
    significant = sorted(h for h, test in tests.items() if _z(test) > DRIFT_Z)
    if not significant:
        return Walk()
    first = variance_line(fits_by_gap[1])[0]
    if not np.all(np.isfinite(first)):
        return Walk()
    for h in significant:
        last = variance_line(fits_by_gap[h])[0]
        if not np.all(np.isfinite(last)):
            continue
        growth = walk_growth(seq, fits_by_gap[h])
        if np.isfinite(growth):
            q0, qd = growth * np.maximum(0.0, last - first) / (h - 1)
            return Walk(float(q0), float(qd), growth, h)
    return Walk()


def decide_track_drift(config: Config, seq: Sequence, fits_by_gap: dict[int, list[TwoViewFit]]) -> DriftDecision:
    """``drift.track_drift``: "yes"/"no" as configured; "auto" by the test (T1), and drifting when the
    test cannot tell (the safe side: re-anchoring costs a little accuracy on clean tracks, while
    unmodelled drift makes the filter overconfident; the walk is then 0, nothing having measured it).
    The walk (T3, T4) is measured for a drifting sequence whenever the fits allow; ``drift.pixel_walk``
    and ``drift.pixel_walk_per_disparity``, where configured, are used instead."""
    tests, scales = growth_tests(fits_by_gap)
    ratio, se, gap = _most_significant(tests)
    setting = config.drift.track_drift
    if setting != Choice.AUTO:
        drifting, source = setting == Choice.YES, "configured"
    elif not np.isfinite(ratio):
        drifting, source = True, "not testable"
    else:
        drifting, source = bool(ratio > 1.0 + DRIFT_Z * se), "test"
    d = config.drift
    measured = Walk()
    if drifting and (d.pixel_walk is None or d.pixel_walk_per_disparity is None):
        measured = drift_walk(seq, fits_by_gap, tests)
    walk = measured.walk if d.pixel_walk is None else d.pixel_walk  # configured values win over the measured ones
    per_disparity = measured.per_disparity if d.pixel_walk_per_disparity is None else d.pixel_walk_per_disparity
    return DriftDecision(drifting, source, ratio, se, gap, scales, seq.tracker, walk, per_disparity, measured.growth,
                         measured.gap, (d.pixel_walk is not None, d.pixel_walk_per_disparity is not None))
