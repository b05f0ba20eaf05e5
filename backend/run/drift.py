"""Whether feature tracks drift with their age, and so whether the filter models it (R1)."""

from __future__ import annotations

from ..config import Choice, Config
from ..data.sequence import SYNTHETIC_TRACKER, VISLAM_TRACKER


def decide_track_drift(config: Config, tracker: str) -> tuple[Config, str]:
    """Resolve ``drift.track_drift = "auto"`` for tracks made by ``tracker`` (``Sequence.tracker``).

    Tracks from another front end (the course files) drift with their age, so their landmarks
    random-walk (``drift.landmark_random_walk``) and are re-anchored (R1 of
    ``backend.estimator.tracks``); vislam's own tracker aligns every patch to its track's first
    patch and synthetic tracks are exact projections: there the drift model only discards
    information. Returns the config with ``drift.track_drift`` "yes" or "no" and one line saying why.
    """
    drift = config.drift
    if drift.track_drift == Choice.AUTO:
        exact = tracker in (VISLAM_TRACKER, SYNTHETIC_TRACKER)
        config = config.with_values({"drift.track_drift": Choice.NO if exact else Choice.YES})
        drift = config.drift
        source = "auto: " + (f"tracks from the {tracker} tracker, which do not drift" if exact
                             else "tracks from another tracker, which drift with age")
    else:
        source = "configured"
    if drift.track_drift == Choice.NO:
        return config, f"track drift: not modelled ({source})"
    walk = f"landmark random walk {drift.landmark_random_walk:g} m/sqrt(s)"
    if config.estimator.full_state:
        return config, f"track drift: {walk}, no re-anchoring (estimator.full_state keeps every landmark) ({source})"
    return config, (f"track drift: {walk}; re-anchoring after {drift.reanchor_observations} observations "
                    f"({drift.reanchor_far_observations} when anchored below {drift.reanchor_far_disparity:g} px "
                    f"disparity; 0: never) ({source})")
