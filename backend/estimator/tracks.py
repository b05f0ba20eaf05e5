"""Which landmarks are in the state, and for how long: the bookkeeping of each step (compiled).

Each landmark in the state carries a row of counts (``backend.estimator.state``): its track id
(the feature column of the data), the steps in a row it was not used, the observations since it
was anchored and how many it may have, and the steps in a row the RANSAC rejected its track.
A step's observations go to the landmarks of their track ids (:func:`plan_update`); a track not
seen any more ends, and its landmark is marginalized into the map (A2 of
``backend.estimator.covariance``, exact for a Gaussian); an observation of a new track starts a
landmark when its disparity and depth allow (:func:`admit_landmarks`).

Re-anchoring (drifting tracks). Feature tracks of some front ends drift with their age: the
image motion of an old track falls short of the true motion, which biases both the scale and the
rotation a long-lived landmark tells the filter. With ``drift.track_drift`` a landmark lives for
at most ``reanchor_observations`` observations (``reanchor_far_observations`` when it was
anchored with a disparity below ``reanchor_far_disparity``: distant points drift little and hold
the rotation):                                                                               (R1)

    count > limit  =>  marginalize the landmark (A2), start a new one from the track's current
                       stereo pair (A1), which is used once, for the initialization.

Marginalization is exact and the new landmark's cross covariance comes from the augmentation, so
nothing is counted twice (tested equal to cutting the track into separate tracks). The first
segment of each track is shortened so that landmarks born together are not all re-anchored at
once:                                                                                        (R2)

    count_0 = 1 + (id mod limit)     (a track's first landmark; 1 for a re-anchored one)

A per-track test (optional, ``drift.track_test_probability``; Tsotsos, Chiuso and Soatto, "Robust
Inference for Visual-Inertial Sensor Fusion", ICRA 2015): under the filter's model each used
observation's innovation, whitened by its 3x3 block of S (e = L^-1 r, S_ii = L L^T, U1), is
N(0, I3) and white over the track's life, re-anchorings included; a track that drifts keeps
pushing its innovations one way. Over its n used observations so far

    T = |sum_i e_i|^2 / n  ~  chi2(3),   T > chi2_3^-1(1 - p)  (n >= n_min)  =>  the landmark is
    dropped and the track's later observations are ignored                                      (R4)

(:class:`TrackTest`).
"""

from __future__ import annotations

import numpy as np

from .. import chi2
from ..compiled import jit, warms_up


class TrackTest:
    """(R4) the running sum of each track's whitened innovations and the tracks it rejected, by
    track id (the feature column), over re-anchorings."""

    def __init__(self, probability: float, min_observations: int) -> None:
        self.threshold = chi2.quantile(3, 1.0 - probability)
        self.min_observations = int(min_observations)
        self.sums = np.zeros((0, 3))
        self.counts = np.zeros(0, dtype=np.int64)
        self.rejected = np.zeros(0, dtype=bool)

    def _grow(self, ids: np.ndarray) -> None:
        """Room for track ids up to ``ids.max()``: at least doubled, so a run's new tracks cost
        amortized constant copying (unseen tracks: zero sums and counts, not rejected)."""
        n = int(ids.max()) + 1 if ids.size else 0
        if n > self.rejected.size:
            extra = max(n, 2 * self.rejected.size) - self.rejected.size
            self.sums = np.concatenate([self.sums, np.zeros((extra, 3))])
            self.counts = np.concatenate([self.counts, np.zeros(extra, dtype=np.int64)])
            self.rejected = np.concatenate([self.rejected, np.zeros(extra, dtype=bool)])

    def admitted(self, ids: np.ndarray) -> np.ndarray:
        """(k,) bool: the observations of ``ids`` whose track has not been rejected."""
        self._grow(ids)
        return ~self.rejected[ids]

    def add(self, ids: np.ndarray, whitened: np.ndarray) -> np.ndarray:
        """Add the whitened innovations ``whitened`` (k,3) of the tracks ``ids`` (k,) (distinct);
        returns (k,) bool: the tracks (R4) rejects now (marked rejected)."""
        self._grow(ids)
        self.sums[ids] += whitened
        self.counts[ids] += 1
        n = self.counts[ids]
        T = np.einsum("ka,ka->k", self.sums[ids], self.sums[ids]) / n
        out = (n >= self.min_observations) & (T > self.threshold)
        self.rejected[ids[out]] = True
        return out


@jit
def slots_of(ids, ids_sorted, ids_order):
    """State slots of ``ids`` (-1 where not in the state), for the state's ids sorted (``ids_sorted``)
    and their slots (``ids_order``)."""
    n = ids_sorted.size
    slots = np.empty(ids.size, dtype=np.int64)
    for j in range(ids.size):
        lo, hi = 0, n  # bisection: the first position with ids_sorted[pos] >= ids[j]
        while lo < hi:
            mid = (lo + hi) // 2
            if ids_sorted[mid] < ids[j]:
                lo = mid + 1
            else:
                hi = mid
        slots[j] = ids_order[lo] if lo < n and ids_sorted[lo] == ids[j] else -1
    return slots


@jit
def plan_update(ids, ids_sorted, ids_order, obs_count, obs_limit, reanchor, full_state):
    """Where a step's observations go (``VisualInertialEKF.update``), for the state's landmark ids sorted
    (``ids_sorted``, at slots ``ids_order``). Returns the slot of each observation's landmark (-1:
    new); the landmarks that leave before the joint update: the tracks not seen (``ended``, unless
    ``full_state``) and with ``reanchor`` those seen beyond their ``obs_limit`` observations
    (counted in ``obs_count`` in place); the observations that restart such a track; their number."""
    slots = slots_of(ids, ids_sorted, ids_order)
    ended = np.zeros(ids_sorted.size, dtype=np.bool_)
    if not full_state:
        ended[:] = True
    restart = np.zeros(ids.size, dtype=np.bool_)
    for j in range(ids.size):
        if slots[j] >= 0:
            ended[slots[j]] = False
    leaving = ended.copy()
    expired = 0
    for j in range(ids.size):
        s = slots[j]
        if reanchor and s >= 0:
            obs_count[s] += 1
            if obs_count[s] > obs_limit[s]:
                leaving[s] = True
                restart[j] = True
                expired += 1
    return slots, leaving, ended, restart, expired


@jit
def admit_landmarks(ids, pixels, restart, min_disparity, max_depth, fx_baseline, reanchor, far_disparity,
                    near_limit, far_limit):
    """Which new features start landmarks: disparity > ``min_disparity`` and depth fx b / d <=
    ``max_depth`` (the others wait for a later observation). Returns their indices, and for each
    the observations it lives for before re-anchoring (``far_limit`` when anchored below
    ``far_disparity``: distant points drift little) and the count of its anchoring observation:
    1, or with ``reanchor`` 1 + id mod limit on a track's first landmark (not ``restart``), so that
    landmarks born together are not all re-anchored at once (R2)."""
    ok = np.empty(ids.size, dtype=np.int64)
    n = 0
    for j in range(ids.size):
        d = pixels[j, 0] - pixels[j, 2]
        if d > min_disparity and fx_baseline / d <= max_depth:
            ok[n] = j
            n += 1
    ok = ok[:n]
    counts = np.ones(n, dtype=np.int64)
    limits = np.empty(n, dtype=np.int64)
    for i in range(n):
        j = ok[i]
        limits[i] = far_limit if pixels[j, 0] - pixels[j, 2] < far_disparity else near_limit
        if reanchor and not restart[j] and limits[i] < np.iinfo(np.int64).max:
            counts[i] += ids[j] % limits[i]
    return ok, counts, limits


@jit
def plan_removal(mask, ended, outlier_run):
    """Index arrays of a marginalization of the landmark slots ``mask``: the removed slots, the kept
    ones, the new slot of each old one (-1: removed), and the removed ones whose tracks go on (not
    ``ended``, an empty array meaning none ended) with a RANSAC rejection run to keep."""
    n = mask.size
    r = 0
    for i in range(n):
        if mask[i]:
            r += 1
    removed = np.empty(r, dtype=np.int64)
    keep = np.empty(n - r, dtype=np.int64)
    remap = np.empty(n, dtype=np.int64)
    r = 0
    for i in range(n):
        if mask[i]:
            removed[r] = i
            remap[i] = -1
            r += 1
        else:
            keep[i - r] = i
            remap[i] = i - r
    counted = np.empty(removed.size, dtype=np.int64)
    c = 0
    for s in removed:
        if outlier_run[s] > 0 and not (ended.size and ended[s]):
            counted[c] = s
            c += 1
    return removed, keep, remap, counted[:c]


@warms_up(only="landmarks")
def _warm_up() -> None:
    ids = np.arange(2, dtype=np.int64)
    counts = np.ones(2, dtype=np.int64)
    plan_update(ids, ids, ids, counts, counts.copy(), True, False)  # slots_of runs inside it
    pixels = np.array([[600.0, 180.0, 560.0, 180.0]] * 2)
    admit_landmarks(ids, pixels, np.zeros(2, dtype=np.bool_), 1.0, np.inf, 350.0, True, 6.0, 3, 25)
    mask = np.array([True, False])
    plan_removal(mask, mask, counts)
    plan_removal(mask, np.zeros(0, dtype=np.bool_), counts)
