"""Repeated frames: steps whose pixels repeat the previous step's exactly.

Real feature files hold an image when no new one arrived, so some steps repeat the previous
step's pixels exactly while the IMU moves on. Around such a repeat the features of steps k and k+2
move by one step of true motion, not two, yet no lag accumulates elsewhere, so no simple timing
model fits; the filter offers policies (``conventions.repeated_frames``; BENCHMARKS.md compares
them on the real drives):

- ``use`` (default): every step at its stamp, as the course formulation does;
- ``skip``: a repeated step's observations are not used;
- ``cut``: a repeated step ends every track (its landmarks go to the map) and the IMU alone bridges
  the stall: right for the translation, but each cut loses heading continuity.
"""

from __future__ import annotations

import numpy as np

from ..compiled import jit, warms_up
from ..data.sequence import Sequence


def repeats_previous(ids: np.ndarray, pixels: np.ndarray, prev_ids: np.ndarray, prev_pixels: np.ndarray) -> bool:
    """True when every feature seen in both frames has identical pixels (and one at least is shared)."""
    found = _repeats_sorted(np.ascontiguousarray(ids, dtype=np.int64), np.ascontiguousarray(pixels, dtype=np.float64),
                            np.ascontiguousarray(prev_ids, dtype=np.int64),
                            np.ascontiguousarray(prev_pixels, dtype=np.float64))
    if found >= 0:
        return bool(found)
    _, i_now, i_prev = np.intersect1d(ids, prev_ids, assume_unique=True, return_indices=True)  # ids not sorted
    return bool(i_now.size) and np.array_equal(pixels[i_now], prev_pixels[i_prev])


@jit
def _repeats_sorted(ids, pixels, prev_ids, prev_pixels):
    """:func:`repeats_previous` by one merge of two increasing id lists (the sequence's order): 1 or 0,
    or -1 when either list is not increasing (the caller falls back to a set intersection)."""
    for a in (ids, prev_ids):
        for i in range(1, a.size):
            if a[i] <= a[i - 1]:
                return -1
    i = j = shared = 0
    while i < ids.size and j < prev_ids.size:
        if ids[i] < prev_ids[j]:
            i += 1
        elif ids[i] > prev_ids[j]:
            j += 1
        else:
            for c in range(4):
                if pixels[i, c] != prev_pixels[j, c]:
                    return 0
            shared += 1
            i += 1
            j += 1
    return 1 if shared else 0


def repeated_steps(seq: Sequence) -> np.ndarray:
    """(N,) bool: step k > 0 repeats the last step before it that was not a repeat (:func:`repeats_previous`)."""
    repeated = np.zeros(seq.num_steps, dtype=bool)
    prev_ids, prev_px = seq.observations(0)
    for k in range(1, seq.num_steps):
        ids, px = seq.observations(k)
        if repeats_previous(ids, px, prev_ids, prev_px):
            repeated[k] = True
        else:
            prev_ids, prev_px = ids, px
    return repeated


@warms_up
def _warm_up() -> None:
    ids = np.arange(2, dtype=np.int64)
    pixels = np.ones((2, 4))
    _repeats_sorted(ids, pixels, ids, pixels)
