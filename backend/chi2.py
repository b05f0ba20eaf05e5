"""The chi-square distribution of an integer number of degrees of freedom: its upper tail and quantile.

Gates, bands and tests use chi-square quantiles at every run's start; scipy's (``scipy.special.chdtri``)
costs its import, 0.16 s of a run's start-up (scipy's array-API layer with it), so they are computed
here, in closed form. With k = 2m + a degrees of freedom (a = 0 or 1) and y = x/2 (Abramowitz & Stegun
26.4.4, 26.4.5):

    Q(x; 2m)     = e^-y sum_{i<m} y^i / i!
    Q(x; 2m + 1) = erfc(sqrt y) + e^-y sum_{i<m} y^(i + 1/2) / Gamma(i + 3/2)                 (X1)

(each term from its logarithm, so no power or factorial overflows). The quantile x_p, Q(x_p) = 1 - p,
is found by Newton's method on Q from the Wilson-Hilferty approximation (the standard library's
normal quantile in it), kept inside a bracket that bisection narrows where a step would leave it;
Q'(x) = -f(x), the density
f(x) = x^(k/2 - 1) e^-y / (2^(k/2) Gamma(k/2)).                                                     (X2)
``tests/test_chi2.py`` compares both with scipy's.
"""

from __future__ import annotations

import math
from functools import lru_cache
from statistics import NormalDist

import numpy as np

__all__ = ["upper_tail", "quantile"]

#: Relative tolerance of the quantile (X2)
TOLERANCE = 1e-13


def _check_dof(dof: int) -> int:
    k = int(dof)
    if k != dof or k < 1:
        raise ValueError(f"degrees of freedom must be a positive integer, got {dof!r}")
    return k


def upper_tail(x: float, dof: int) -> float:
    """Q(x; k) = P(chi2_k > x) (X1); 1 for x <= 0."""
    return _upper_tail(x, _check_dof(dof))


def _upper_tail(x: float, k: int) -> float:
    if x <= 0.0:
        return 1.0
    y = 0.5 * x
    m, odd = divmod(k, 2)
    a = 0.5 if odd else 0.0
    out = math.erfc(math.sqrt(y)) if odd else 0.0
    if m:
        i = np.arange(m, dtype=float)
        log_gamma = np.array([math.lgamma(j + a + 1.0) for j in range(m)])  # each exact: a running sum drifts
        out += float(np.exp((i + a) * math.log(y) - y - log_gamma).sum())
    return min(out, 1.0)


def _density(x: float, k: int) -> float:
    return math.exp((0.5 * k - 1.0) * math.log(x) - 0.5 * x - 0.5 * k * math.log(2.0) - math.lgamma(0.5 * k))


def quantile(dof: int, probability: float) -> float:
    """x with P(chi2_k <= x) = ``probability`` (scipy's ``chi2.ppf(p, k)``, ``chdtri(k, 1 - p)``) (X2).
    Remembered by (k, p): gates ask for the same few every frame."""
    k = _check_dof(dof)
    p = float(probability)
    if not 0.0 < p < 1.0:
        raise ValueError(f"probability must lie in (0, 1), got {probability!r}")
    return _quantile(k, p)


@lru_cache(maxsize=4096)
def _quantile(k: int, p: float) -> float:
    target = 1.0 - p
    # Wilson-Hilferty: chi2_k / k ~ (1 - 2/(9k) + z sqrt(2/(9k)))^3, z the normal quantile
    z = NormalDist().inv_cdf(p)
    c = 2.0 / (9.0 * k)
    x = k * max(1.0 - c + z * math.sqrt(c), 1e-3) ** 3
    lo, hi = 0.0, math.inf
    for _ in range(200):
        q = _upper_tail(x, k)
        if q > target:
            lo = x
        else:
            hi = x
        f = _density(x, k)
        step = (q - target) / f if f > 0.0 else math.inf
        new = x + step
        if not lo < new < hi:
            new = 0.5 * (lo + hi) if math.isfinite(hi) else 2.0 * x + 1.0
        if abs(new - x) <= TOLERANCE * max(new, 1e-300):
            return new
        x = new
    return x

