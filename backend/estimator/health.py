"""The filter's health: is it consistent with its own noise model, and is P still a covariance?

The normalized innovation squared of a used observation is chi2(4) for a consistent filter, so
its mean per observation over the last ``nis_window`` steps should be near 4 (a little less: the
gate truncates it). An episode of trouble starts when that mean leaves [4/f, 4 f]
(f = ``nis_warn_factor``) or more than half the observations are gated, and ends when it is back
inside [4/sqrt f, 4 sqrt f] with at most 40 % gated (hysteresis: no flapping at the edge).     (H1)

P must stay positive definite over the states the filter estimates; it is checked every 100
steps, and where it is not its eigenvalues are clipped and the episode is reported.            (H2)

A run that was meant to see is checked at its end: no valid observation at all, none used, or
more than ``MAX_GATED_SHARE`` of them gated means the trajectory is (close to) dead reckoning,
and the run says so rather than presenting it as visual-inertial.                                (H3)
"""

from __future__ import annotations

import warnings
from collections import deque
from dataclasses import dataclass, field
from typing import Optional

from ..errors import HealthWarning

#: H3: a run whose gated share of observations is above this is called close to dead reckoning
MAX_GATED_SHARE = 0.9


@dataclass
class HealthMonitor:
    """Watches the NIS (H1) and collects one message per episode of trouble (H1, H2); ``silent``:
    collects without warning (a trial run of the decisions, not the run a user asked for)."""

    window: int
    warn_factor: float
    messages: list[str] = field(default_factory=list)
    silent: bool = False
    _nis: deque = field(default_factory=deque)
    _count: deque = field(default_factory=deque)
    _gated: deque = field(default_factory=deque)
    _total_count: int = 0  # sums of _count and _gated (integers: exact)
    _total_gated: int = 0
    _inconsistent: bool = False

    def add_nis(self, step: int, nis_sum: float, count: int, gated: int = 0) -> None:
        """One step's NIS sum over ``count`` used observations, and how many were gated.

        The NIS of used observations is truncated by the gate, so a far too small pixel_sigma
        shows as a high gated share rather than a high NIS: both are watched.
        """
        self._nis.append(nis_sum)
        self._count.append(count)
        self._gated.append(gated)
        self._total_count += count
        self._total_gated += gated
        if len(self._nis) > self.window:
            self._nis.popleft()
            self._total_count -= self._count.popleft()
            self._total_gated -= self._gated.popleft()
        total = self._total_count
        seen = total + self._total_gated
        if len(self._nis) < self.window or seen < 20:  # every observation gated counts: that is the worst case
            return
        mean = sum(self._nis) / total if total else float("nan")  # summed afresh: no rounding drift
        gated_share = self._total_gated / seen
        in_band = total > 0 and 4.0 / self.warn_factor <= mean <= 4.0 * self.warn_factor
        bad = not in_band or gated_share > 0.5
        if bad and not self._inconsistent:
            nis = f"mean NIS per observation {mean:.2f} (expected about 4)" if total else "no observation used"
            if not total or gated_share > 0.5 or mean > 4.0:
                advice = ("the data moved away from the noise the run identified (a change of scene, a tracker "
                          "losing lock): check the frames around it; a larger noise.pixel_sigma or IMU noise trades "
                          "accuracy for consistency")
            else:
                advice = ("the observations agree better than the noise model says: the reported covariance is "
                          "larger than it needs to be (a smaller configured noise.pixel_sigma would tighten it)")
            self.report(
                f"step {step}: filter inconsistent with its noise model: {nis} and {100 * gated_share:.0f} % gated "
                f"over the last {self.window} steps; {advice}"
            )
            self._inconsistent = True
        elif self._inconsistent:  # the episode ends well inside the band (hysteresis: no flapping at its edge)
            f = self.warn_factor**0.5
            self._inconsistent = not (total > 0 and 4.0 / f <= mean <= 4.0 * f and gated_share <= 0.4)

    def report(self, message: str) -> None:
        self.messages.append(message)
        if not self.silent:
            warnings.warn(message, HealthWarning, stacklevel=3)


def vision_check(observations: int, used: int, gated: int, slam: bool = True) -> Optional[str]:
    """H3: the message when the vision of a run that was meant to see did (almost) nothing, else None.

    ``observations``: valid observations in the input; ``used`` and ``gated``: in joint updates;
    ``slam``: the poses were to be corrected (else mapping: only the landmarks).
    """
    alone, mostly = (("the trajectory is dead reckoning alone", "the trajectory is close to dead reckoning")
                     if slam else ("the map holds stereo triangulations alone", "the map is mostly stereo triangulations"))
    check = "check the calibration, the rectification, the time stamps and pixel_sigma"
    if observations == 0:
        return f"no valid stereo observation in the input: {alone}"
    if used == 0:
        return f"none of the {observations} observations was used ({gated} gated): {alone}; {check}"
    share = gated / (used + gated)
    if share > MAX_GATED_SHARE:
        return f"{100 * share:.1f} % of the observations were gated (only {used} used): {mostly}; {check}"
    return None
