"""When was each image taken? Repeated frames and image time stamps.

Real feature files hold each camera image until a newer one arrives: 153 steps of
ece276a_03.npz and 91 of ece276a_0027.npz repeat the previous step's pixels exactly. Against
ground truth (ece276a_0027), the step after such a repeat shows the scene one step *earlier*
than its stamp, and the lag shrinks to zero by the next repeat: the camera runs a little slower
than the stamps (1015 images over 1106 stamps) and the file resamples it by sample-and-hold.
Used at their stamps, those observations tell the filter the vehicle moved about 8 % less than
it did.

Policies (``FilterConfig.repeated_frames``):
- ``retime``: every distinct image gets its own time, evenly spaced over the sequence; the
  filter predicts to that time, updates, and reports poses at the data's own stamps.
- ``skip``: repeated steps are not used; the others are used at their stamps.
- ``use``: everything at its stamp (the course formulation).
"""

from __future__ import annotations

import numpy as np

from backend.sequence import Sequence


def repeated_steps(seq: Sequence) -> np.ndarray:
    """(N,) bool: step k > 0 repeats step k-1 (every feature seen in both has identical pixels)."""
    repeated = np.zeros(seq.num_steps, dtype=bool)
    prev_ids, prev_px = seq.observations(0)
    for k in range(1, seq.num_steps):
        ids, px = seq.observations(k)
        _, i_now, i_prev = np.intersect1d(ids, prev_ids, assume_unique=True, return_indices=True)
        if i_now.size and np.array_equal(px[i_now], prev_px[i_prev]):
            repeated[k] = True
        else:
            prev_ids, prev_px = ids, px
    return repeated


def image_times(time_stamps: np.ndarray, repeated: np.ndarray) -> np.ndarray:
    """(N,) time each step's image was taken (sample-and-hold of a camera slightly ahead).

    Measured on ece276a_0027 against ground truth: a repeated step r shows the image taken at
    its own stamp t_r, and so does step r-1 (the same pixels); between two repeats r1 < r2
    the images of steps r1+1 .. r2-1 are evenly spaced over (t_r1, t_r2] - each runs a little
    ahead of its stamp, by up to one frame just before a repeat. Before the first repeat the
    images are evenly spaced over [t_0, t_r]; after the last one, at the median spacing.
    Without repeats: the stamps.
    """
    times = time_stamps.astype(float).copy()
    reps = np.flatnonzero(repeated)
    if reps.size == 0:
        return times
    spacings = []
    starts = np.concatenate([[0], reps])  # each segment starts at an image with a known time
    for start, stop in zip(starts[:-1], starts[1:]):
        # steps start .. stop-1 carry images from t_start to t_stop
        count = stop - 1 - start
        if count <= 0:
            continue
        step = (time_stamps[stop] - time_stamps[start]) / count
        times[start + 1 : stop] = time_stamps[start] + step * np.arange(1, count + 1)
        if start > 0:
            spacings.append(step)
    last = reps[-1]
    if last + 1 < times.size:
        step = float(np.median(spacings)) if spacings else float(np.median(np.diff(time_stamps)))
        tail = time_stamps[last] + step * np.arange(1, times.size - last)
        times[last + 1 :] = np.minimum(tail, time_stamps[-1])
    return times
