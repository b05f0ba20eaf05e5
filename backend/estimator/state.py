"""The filter's state: its mean, its covariance, and the bookkeeping of the landmarks in it.

The mean is the pose ``mu`` = world_T_imu (4,4), the gyro bias (3,) and the parameters ``theta``
(n,3) of the n landmarks in the state, in slot order; ``P`` (D,D), D = core + 3n (core 9, or 10
with the disparity offset), is the covariance of the error state (``backend.estimator.layout``;
its meaning is the error model's; + 3 with the lever arm of V1 (6 with V4's rotation), whose rows, where it is considered,
hold its sensitivity instead: ``covariance_of``, V2). Per landmark
the state also keeps ``track``, rows of counts (``TRACK_ROWS``): the track id, the steps in a row
it was not used, the observations since it was anchored and how many it may have (R1 of
``backend.estimator.tracks``), and the steps in a row the RANSAC rejected its track; and, where
the error model reads them, ``theta_first`` (the first estimates, for FEJ) and ``anchors``
(inverse depth). Adding and removing landmarks keeps all of them in the same slot order. A state
with a sliding window holds pose clones after the core instead of landmarks (``clones``). Only
``backend.estimator.state_helper.StateHelper`` changes P.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .layout import BIAS, CORE, LEVER_ROWS

TRACK_ROWS = ID, GATED, COUNT, LIMIT, OUTLIER = range(5)  # rows of FilterState.track


@dataclass
class FilterState:
    """Mean, covariance and landmark bookkeeping of the filter (module docstring)."""

    mu: np.ndarray = field(default_factory=lambda: np.eye(4))  # world_T_imu
    gyro_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    P: np.ndarray = field(default_factory=lambda: np.zeros((CORE, CORE)))
    theta: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # landmark parameters, slot order
    track: np.ndarray = field(default_factory=lambda: np.zeros((len(TRACK_ROWS), 0), dtype=np.int64))
    theta_first: np.ndarray | None = None  # (n,3) first estimates (FEJ), where the model reads them
    anchors: np.ndarray | None = None  # (n,4,4) anchor frames (inverse depth), where the model reads them
    #: RANSAC rejection runs of tracks that left the state but may go on (track id -> count, nonzero)
    outlier_stash: dict = field(default_factory=dict)
    _ids_sorted: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # for slots_of
    _ids_order: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    #: rows of P before the landmark slots: ``layout.CORE`` (pose, gyro bias), or
    #: ``inertial.CORE_INERTIAL`` (with velocity and accelerometer bias)
    core: int = CORE
    velocity: np.ndarray | None = None  # (3,) world frame, the inertial state only
    accel_bias: np.ndarray | None = None  # (3,) the inertial state only
    #: (w,4,4) world_T_imu of the pose clones of a sliding window (``backend.estimator.window``), oldest
    #: first, P's rows core + 6 j .. + 5 for clone j (such a state holds no landmark); None: no window
    clones: np.ndarray | None = None
    #: P's row of the residual disparity offset (``layout.OFFSET``, O1 of ``backend.estimator.offset``);
    #: None: not estimated
    offset_row: int | None = None
    offset: float = 0.0  # px: its mean, added to every right-image column before use (O1)
    offset_considered: bool = False  # the offset is a consider state: never updated, its variance kept (O4)
    #: P's first row of the residual lever arm of the IMU's velocities (3 rows, V1 of
    #: ``backend.estimator.lever_arm``); None: not in the state
    lever_row: int | None = None
    lever_arm: np.ndarray = field(default_factory=lambda: np.zeros(3))  # m: its mean (0 unless estimated)
    lever_considered: bool = False  # considered: P's lever rows hold its sensitivity S P_rr, its prior P_rr (V2)
    #: (k,k) P_rr^+ of a considered lever arm (its prior's pseudo-inverse, held), k = 3, or 6 with the
    #: rotation of the samples' frame (V4)
    lever_information: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.P.shape[0] < self.core:
            self.P = np.zeros((self.core, self.core))

    # the rows of track, as views (kernels change the counts in place)
    @property
    def ids(self) -> np.ndarray:
        """Track id (the feature column) of each landmark."""
        return self.track[ID]

    @property
    def gated_run(self) -> np.ndarray:
        """Steps in a row each landmark was not used (gated or rejected)."""
        return self.track[GATED]

    @property
    def obs_count(self) -> np.ndarray:
        """Observations since each landmark was anchored (R1)."""
        return self.track[COUNT]

    @property
    def obs_limit(self) -> np.ndarray:
        """... after which it is re-anchored (R1)."""
        return self.track[LIMIT]

    @property
    def outlier_run(self) -> np.ndarray:
        """Steps in a row the RANSAC rejected each landmark's track (U5)."""
        return self.track[OUTLIER]

    @property
    def num_landmarks(self) -> int:
        return self.track.shape[1]

    @property
    def index(self) -> tuple[np.ndarray, np.ndarray]:
        """(the landmark ids sorted, their slots): the look-up of ``tracks.slots_of`` and ``tracks.plan_update``."""
        return self._ids_sorted, self._ids_order

    def considered_rows(self) -> np.ndarray:
        """Rows of P the update holds (their block and mean): a considered disparity offset (O4,
        Schmidt), a considered lever arm (V2)."""
        rows = [self.offset_row] if self.offset_row is not None and self.offset_considered else []
        if self.lever_share:
            rows += range(self.lever_row, self.lever_row + self.lever_dim)
        return np.array(rows, dtype=np.int64)

    @property
    def lever_dim(self) -> int:
        """Rows of the lever arm's block: 3, or 6 with a considered rotation of the samples' frame (V4)."""
        return LEVER_ROWS if self.lever_information is None else self.lever_information.shape[0]

    @property
    def carries_rotation(self) -> bool:
        """The considered block holds the samples' frame rotation after the lever arm (V4)."""
        return self.lever_dim > LEVER_ROWS

    @property
    def lever_share(self) -> bool:
        """P holds a considered lever arm's sensitivity, whose share the covariance adds (V2)."""
        return self.lever_row is not None and self.lever_considered

    def covariance_of(self, rows: np.ndarray | slice) -> np.ndarray:
        """(k,k) covariance of the states ``rows`` (k,) or a slice: P's block, plus a considered lever
        arm's share S P_rr S^T = P[rows, r] P_rr^-1 P[r, rows] (V2; P holds its sensitivity there, not
        its covariance with the estimate)."""
        if isinstance(rows, slice):
            block = self.P[rows, rows].copy()
        else:
            rows = np.asarray(rows, dtype=np.int64)
            block = self.P[rows[:, None], rows]
        if self.lever_share:
            C = self.P[rows, self.lever_row:self.lever_row + self.lever_dim]
            block += C @ self.lever_information @ C.T
        return block

    def considered_state(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(the covariance (c+3k, c+3k) of the core and the landmarks ``slots`` (k,) with a considered
        lever arm's share (V2), their slots in it: 0..k-1); without one, (P, ``slots``) as they are."""
        slots = np.asarray(slots, dtype=np.int64)
        if not self.lever_share or not slots.size:
            return self.P, slots
        rows = np.concatenate([np.arange(self.core), (self.core + 3 * slots[:, None] + np.arange(3)).ravel()])
        return np.ascontiguousarray(self.covariance_of(rows)), np.arange(slots.size, dtype=np.int64)

    def estimated(self, pose: bool, bias: bool) -> np.ndarray:
        """(D,) mask of the states the filter estimates (the pose and the bias may be held fixed)."""
        mask = np.ones(self.P.shape[0], dtype=bool)
        if not pose:
            mask[:self.core] = False
        elif not bias:
            mask[BIAS] = False
        if self.lever_share:  # (V2): sensitivity rows, not covariance
            mask[self.lever_row:self.lever_row + self.lever_dim] = False
        return mask

    def _reindex(self) -> None:
        self._ids_order = np.argsort(self.ids, kind="stable")
        self._ids_sorted = self.ids[self._ids_order]

    # ---------------------------------------------------------------- landmark bookkeeping
    # (P's rows and columns are StateHelper's: augment and marginalize call these)
    def append_landmarks(self, ids: np.ndarray, theta: np.ndarray, counts: np.ndarray, limits: np.ndarray,
                         anchors: np.ndarray | None = None) -> None:
        """Append landmarks ``ids`` with parameters ``theta`` (n,3) after the last slot, as P's rows
        were (A1); their observation counts and limits (R1, R2); a track's RANSAC rejection run
        comes back from the stash."""
        n = ids.size
        stash = self.outlier_stash
        runs = (np.array([stash.pop(i, 0) for i in ids.tolist()], dtype=np.int64) if stash
                else np.zeros(n, dtype=np.int64))
        rows = np.empty((len(TRACK_ROWS), n), dtype=np.int64)
        rows[ID], rows[GATED], rows[COUNT], rows[LIMIT], rows[OUTLIER] = ids, 0, counts, limits, runs
        self.track = np.concatenate([self.track, rows], axis=1)
        self.theta = np.concatenate([self.theta, theta])
        if self.theta_first is not None:
            self.theta_first = np.concatenate([self.theta_first, theta])
        if self.anchors is not None:
            self.anchors = np.concatenate([self.anchors, anchors])
        self._reindex()

    def stash_outlier_runs(self, slots: np.ndarray) -> None:
        """Keep the RANSAC rejection runs of landmarks ``slots`` (leaving, their tracks may go on) by track id."""
        if slots.size:
            self.outlier_stash.update(zip(self.ids[slots].tolist(), self.outlier_run[slots].tolist()))

    def keep_landmarks(self, keep: np.ndarray) -> None:
        """Keep the landmarks of slots ``keep`` (increasing), in that order, as P's rows were (A2)."""
        self.track = np.take(self.track, keep, axis=1)  # C-ordered (a[:, idx] is not): contiguous rows
        self.theta = self.theta[keep]
        if self.theta_first is not None:
            self.theta_first = self.theta_first[keep]
        if self.anchors is not None:
            self.anchors = self.anchors[keep]
        self._reindex()
