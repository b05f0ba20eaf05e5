"""Whether feature tracks drift with their age, decided by a test on the tracks (T1).

A two-view fit of steps k and k+h (D2, ``backend.run.two_view``) fits the motion and every point,
so white pixel noise leaves residuals of the same scale whatever the gap h; a track whose pixels
wander (a tracker that slides off its feature) leaves residuals that grow with h. Real drift is
heavy-tailed (most tracks hold, a few slide fast), so the test compares the pooled RMS of the
residuals (within ``TRIM_PX``: the tail included, gross mismatches not), not a robust scale that
would ignore the few, at the largest gap measured with the one at gap 1:

    ratio = RMS(h_max) / RMS(1),   drift  <=>  ratio > 1 + max(MIN_GROWTH, 4 SE(ratio))           (T1)

with SE by the delta method over the pairs (each pair's mean square, weighted by its degrees of
freedom).
Drifting tracks are modelled by the filter (``backend.estimator.tracks``, R1): a landmark is
re-anchored after ``drift.reanchor_observations`` observations and its position random-walks
(``drift.landmark_random_walk``). What made the tracks (the file's ``tracker`` key) is reported
beside the test, never used by it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import Choice, Config
from .two_view import TwoViewFit, pooled_mean_square

__all__ = ["DriftDecision", "drift_test", "decide_track_drift"]

#: The residual scale must grow by more than this share between gap 1 and the largest gap.
MIN_GROWTH = 0.1
#: Fewer pairs than this at either gap: the test says nothing.
MIN_PAIRS = 10


@dataclass(frozen=True)
class DriftDecision:
    """Whether the filter models drifting tracks, and the test (T1) behind it."""

    drifting: bool
    source: str  # "test" | "configured" | "not testable"
    ratio: float = float("nan")  # s(h_max) / s(1)
    ratio_se: float = float("nan")
    scales: tuple = ()  # (gap, pairs, pooled RMS px) per gap
    tracker: str = ""  # what the file says made the tracks (informs only)

    def as_dict(self) -> dict:
        return {"drifting": self.drifting, "decided_by": self.source, "ratio": self.ratio, "ratio_se": self.ratio_se,
                "rms_by_gap": [{"gap": g, "pairs": n, "rms_px": s} for g, n, s in self.scales],
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
            if config.estimator.full_state:
                text += (f"; random walk {d.landmark_random_walk:g} m/sqrt(s), no re-anchoring "
                         "(estimator.full_state keeps every landmark)")
            else:
                text += (f"; landmarks re-anchored after {d.reanchor_observations} observations "
                         f"({d.reanchor_far_observations} below {d.reanchor_far_disparity:g} px disparity), random walk "
                         f"{d.landmark_random_walk:g} m/sqrt(s)")
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


def decide_track_drift(config: Config, fits_by_gap: dict[int, list[TwoViewFit]], tracker: str = "") -> DriftDecision:
    """``drift.track_drift``: "yes"/"no" as configured; "auto" by the test (T1), and drifting when the
    test cannot tell (the safe side: re-anchoring costs a little accuracy on clean tracks, while
    unmodelled drift makes the filter overconfident)."""
    ratio, se, scales = drift_test(fits_by_gap)
    setting = config.drift.track_drift
    if setting != Choice.AUTO:
        return DriftDecision(setting == Choice.YES, "configured", ratio, se, scales, tracker)
    if not np.isfinite(ratio):
        return DriftDecision(True, "not testable", ratio, se, scales, tracker)
    return DriftDecision(bool(ratio > 1.0 + max(MIN_GROWTH, 4.0 * se)), "test", ratio, se, scales, tracker)
