"""Random generators for the synthetic scenes (one independent stream per purpose)."""

from __future__ import annotations

import numpy as np

#: Stream numbers: changing the noise settings never changes the trajectory or the map, and each
#: track error (``synth.track_errors``) draws from its own stream.
STREAMS = {"trajectory": 0, "landmarks": 1, "pixels": 2, "tracks": 3, "outliers": 4, "imu": 5,
           "repeats": 6, "jitter": 7, "drift": 8, "bad_tracks": 9}


def generator(seed, stream: str | None = None) -> np.random.Generator:
    """A Generator from an int seed (optionally one named stream of it) or a Generator as is."""
    if isinstance(seed, np.random.Generator):
        return seed
    seed = int(seed)
    if seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed}")
    if stream is None:
        return np.random.default_rng(seed)
    return np.random.default_rng([seed, STREAMS[stream]])
