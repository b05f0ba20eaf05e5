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

A SLAM run's scale is checked against the IMU's: the filter's displacement over step k in the
body frame at k, d_k = R_k^T (p_{k+1} - p_k), against the IMU's for the same step, m_k (the
translation of exp(tau_k [v_k; omega_k]^), what dead reckoning moves), as one scale

    s = sum_k <m_k, d_k> / sum_k |d_k|^2,                                                    (H4)

1 where they agree; the IMU's white noise enters m_k only, so s is unbiased by it. Its standard
error is that of a ratio of means over ``SCALE_BATCHES`` batches of consecutive steps (batch
means: the errors of a real IMU's speed and of a drifting track are correlated over seconds),
se(s)^2 = sum_b (N_b - s D_b)^2 / (B (B - 1) mean(D)^2), N_b and D_b the batch's sums above. A
filter whose scale follows a wrong disparity offset or baseline fails it: on the synthetic grid
(``vislam.synth.grid``) the two scenes whose -1 px offset went unfound give s = 0.894 +- 0.021 and
0.959 +- 0.003 (5.1 and 16 standard errors), every other scene, the shared KITTI drives and the
KITTI frames stay within 1 % or 2 standard errors (one at 6.4 standard errors and 0.1 %: the
effect bound). The run says so rather than reporting a trajectory at the wrong scale.
"""

from __future__ import annotations

import math
import warnings
from collections import deque
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..errors import HealthWarning
from ..geometry import se3

#: H3: a run whose gated share of observations is above this is called close to dead reckoning
MAX_GATED_SHARE = 0.9
#: H4: batches of consecutive steps the scale's standard error is taken over ...
SCALE_BATCHES = 10
#: ... of at least this many steps each; shorter runs are not tested
SCALE_MIN_BATCH_STEPS = 10
#: ... so that H4 tests from this many step pairs on
SCALE_MIN_STEPS = SCALE_BATCHES * SCALE_MIN_BATCH_STEPS
#: H4 fails beyond this many standard errors (a t with 9 degrees of freedom: p = 0.003) ...
SCALE_SIGNIFICANCE = 4.0
#: ... and this relative difference (1 m in 100 m), below which a scale error is not worth a warning
SCALE_MIN_EFFECT = 0.01


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


@dataclass(frozen=True)
class ScaleCheck:
    """H4: the IMU's displacement per step against the filter's, as one scale (1 where they agree)."""

    scale: float  # s of (H4); nan when not tested
    standard_error: float  # batch means over SCALE_BATCHES batches
    steps: int  # step pairs compared

    @property
    def tested(self) -> bool:
        return self.steps >= SCALE_MIN_STEPS and math.isfinite(self.standard_error)

    @property
    def z(self) -> float:
        """(s - 1) in standard errors (infinite for a difference without error)."""
        difference = self.scale - 1.0
        if not self.tested or difference == 0.0:
            return 0.0
        if self.standard_error == 0.0:
            return math.copysign(math.inf, difference)
        return difference / self.standard_error

    @property
    def significant(self) -> bool:
        """The scales differ beyond ``SCALE_SIGNIFICANCE`` standard errors."""
        return self.tested and abs(self.z) > SCALE_SIGNIFICANCE

    @property
    def failed(self) -> bool:
        """... and by more than ``SCALE_MIN_EFFECT``: worth a warning."""
        return self.significant and abs(self.scale - 1.0) > SCALE_MIN_EFFECT

    def as_dict(self) -> dict:
        return {"imu_over_filter": self.scale, "standard_error": self.standard_error, "steps": self.steps,
                "tested": self.tested, "significant": self.significant, "failed": self.failed}

    def describe(self) -> str:
        if not self.tested:
            return f"the filter's scale against the IMU's: not tested ({self.steps} step pairs, {SCALE_MIN_STEPS} needed)"
        return (f"the IMU moved {self.scale:.3f} +- {self.standard_error:.3f} times the filter's distance a step "
                f"({self.z:+.1f} standard errors from 1, over {self.steps} steps)")

    def message(self) -> Optional[str]:
        """The health message of a failed check, else None."""
        if not self.failed:
            return None
        longer = "longer" if self.scale < 1.0 else "shorter"
        return (f"the trajectory's scale disagrees with the IMU's: {self.describe()}, so the trajectory is "
                f"{100 * abs(1.0 / self.scale - 1.0):.1f} % {longer} than the IMU says; vision's scale comes from the "
                "disparities: check the stereo baseline and the disparity offset (conventions.stereo_offset, "
                "noise.stereo_offset_sigma), or the IMU's speed calibration")


def ratio_of_batches(N: np.ndarray, D: np.ndarray) -> tuple[float, float]:
    """s = sum_b N_b / sum_b D_b over B batches of consecutive items (N_b, D_b: each batch's sums, (B,))
    and its batch-means standard error sqrt(sum_b (N_b - s D_b)^2 / (B (B - 1))) / mean(D) (H4; the
    disparity offset's D4 of ``backend.run.stereo_offset``, a weighted mean: N_b = sum w beta, D_b = sum w)."""
    B = N.size
    s = float(N.sum() / D.sum())
    return s, float(np.sqrt(np.sum((N - s * D) ** 2) / (B * (B - 1))) / D.mean())


def scale_check(world_T_imu: np.ndarray, imu_steps: np.ndarray) -> ScaleCheck:
    """H4 from the filter's poses ``world_T_imu`` (N,4,4) and the IMU's displacement over each step in
    the body frame at its start, ``imu_steps`` (N-1,3); the last N-1 mod ``SCALE_BATCHES`` steps
    are left out so that the batches are equal."""
    T = np.asarray(world_T_imu, dtype=float)
    m = np.asarray(imu_steps, dtype=float).reshape(-1, 3)
    n = min(max(T.shape[0] - 1, 0), m.shape[0])
    n -= n % SCALE_BATCHES
    if n < SCALE_MIN_STEPS:
        return ScaleCheck(float("nan"), float("nan"), n)
    d = (se3.inverse(T[:n]) @ T[1 : n + 1])[:, :3, 3]  # the filter's step in the body frame at its start
    N = np.einsum("ki,ki->k", m[:n], d).reshape(SCALE_BATCHES, -1).sum(axis=1)
    D = np.einsum("ki,ki->k", d, d).reshape(SCALE_BATCHES, -1).sum(axis=1)
    if not D.sum() > 0:
        return ScaleCheck(float("nan"), float("nan"), n)
    return ScaleCheck(*ratio_of_batches(N, D), n)
