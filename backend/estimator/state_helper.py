"""The only code that changes the filter's covariance (OpenVINS's ``StateHelper``).

Every change of ``FilterState.P`` is one of these operations, each one function of
:class:`StateHelper`:

- ``set_prior``: the core's covariance before the first step.
- ``propagate``: P <- F P F^T + G Q G^T by the error model's :class:`Transition` (I2, I8, B1, J6, W2),
  then the landmarks' random walk (P_mm += q I).
- ``update``: the joint update with the gate, RANSAC and rescue (U2-U5); considered rows held (O4, V2).
- ``augment``: new landmarks from their stereo pixels (A1), with the disparity offset's columns (O3).
- ``marginalize``: landmarks leave the state (A2).
- ``repair``: eigenvalues clipped when P lost positive definiteness (H2).
- ``clone``, ``update_window``, ``drop_oldest_clone``: a sliding window's pose clones join (W1),
  update (W6) and leave (W7) (``backend.estimator.window``).
- ``update_dense``: a few rows on the core (a zero velocity, Z9 of ``backend.estimator.zero_velocity``).

The error models say what a prediction does to P (a :class:`Transition`, derived beside its
model) and what a new landmark's Jacobians are (:class:`NewLandmarks`); they never write P.
Landmark slot s owns rows ``layout.landmark_rows(core, s)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..errors import FilterError
from .covariance import augment, gather_landmarks, gather_symmetric, repair_if_indefinite
from .layout import POSE
from .offset import offset_columns_of_new_landmarks
from .state import FilterState
from .tracks import plan_removal
from .update import Innovation, select_and_update_inplace

__all__ = ["StateHelper", "Transition", "CoreTransition", "NewLandmarks", "UpdateResult"]

_NONE = np.zeros(0, dtype=bool)  # an empty mask: no track ended


class Transition(Protocol):
    """What one prediction does to P, in the structured form its error model derived."""

    def apply(self, P: np.ndarray) -> np.ndarray:
        """P <- F P F^T + G Q G^T: returns the new P (``P`` itself, changed in place, or a new array)."""


@dataclass
class CoreTransition:
    """A transition that moves only the core (pose, bias; the inertial core): F = blockdiag(Phi, I)
    and Q on the core, the rows after it static (landmarks of the body model, a window's clones),

        P_cc <- Phi P_cc Phi^T + Q,   P_c,l <- Phi P_c,l                  (B1, W2)

    ``Phi`` (c,c) for a core of c rows; ``q_var`` its noise: (c,) variances (Q diagonal) or (c,c)."""

    Phi: np.ndarray
    q_var: np.ndarray

    def apply(self, P: np.ndarray) -> np.ndarray:
        c = self.Phi.shape[0]
        P[:c, :] = self.Phi @ P[:c, :]
        P[:, :c] = P[:, :c] @ self.Phi.T
        P[c:, :c] = P[:c, c:].T  # exact symmetry of the cross blocks
        if self.q_var.ndim == 2:
            P[:c, :c] += self.q_var
        P[:c, :c] = 0.5 * (P[:c, :c] + P[:c, :c].T)
        if self.q_var.ndim == 1:
            P[np.arange(c), np.arange(c)] += self.q_var
        return P


@dataclass
class NewLandmarks:
    """New landmarks from their first stereo observations, as an error model makes them (I4, B4):
    parameters ``theta`` (n,3), ``anchors`` (n,4,4) or None, the Jacobians ``J_xi`` (3n,6) on the
    pose (zero with the poses held fixed) and ``J_z`` (n,3,4) on the pixels (A1)."""

    theta: np.ndarray
    anchors: np.ndarray | None
    J_xi: np.ndarray
    J_z: np.ndarray
    J_offset: np.ndarray | None = None  # (3n,) on the disparity offset (O3), where the state holds it


@dataclass
class UpdateResult:
    """What the joint update did: ``status`` (0, or the Cholesky's info when S was not positive
    definite and the prior was kept), the error-state correction ``dx`` (D,) and the observations
    ``used`` (k,) bool."""

    status: int
    dx: np.ndarray
    used: np.ndarray


class StateHelper:
    """The operations that change P (module docstring); the filter's only writer of the covariance."""

    @staticmethod
    def set_prior(state: FilterState, covariance: np.ndarray) -> None:
        """Start P as ``covariance`` (core, core) of the core states; no landmark may be in the state."""
        if state.num_landmarks:
            raise ValueError("set_prior: the state already holds landmarks")
        cov = np.array(covariance, dtype=float)
        if cov.shape != (state.core, state.core):
            raise ValueError(f"set_prior: covariance must be ({state.core},{state.core}), got {cov.shape}")
        state.P = 0.5 * (cov + cov.T)

    @staticmethod
    def propagate(state: FilterState, transition: Transition | None,
                  landmark_walk_var: float | np.ndarray = 0.0) -> None:
        """P by the model's ``transition`` (None: poses held fixed, P of the core unchanged), then
        the landmarks' random walk: ``landmark_walk_var`` (a number, or (n,) per landmark slot)
        added to each landmark row's variance."""
        if transition is not None:
            state.P = transition.apply(state.P)
        if state.num_landmarks and np.any(landmark_walk_var):
            diag = np.arange(state.core, state.P.shape[0])
            walk = np.asarray(landmark_walk_var, dtype=float)
            state.P[diag, diag] += np.repeat(walk, 3) if walk.ndim else walk

    @staticmethod
    def update(state: FilterState, inn: Innovation, slots: np.ndarray, gate: float, ransac_threshold_px: float,
               pixel_var: float, persistent_outlier_steps: int) -> UpdateResult:
        """The gate (U4), 1-point RANSAC (U5), the rescue (U3) and the joint update (U2) of P in one
        compiled call, with the prior innovation ``inn`` of landmarks ``slots``; the landmarks'
        RANSAC and gating runs are counted in the state's track rows. The mean is the caller's to
        correct by ``dx`` (the error model's retraction). Consider states (a disparity offset, O4; a
        lever arm, V2) keep their covariance block and mean."""
        held = state.considered_rows()
        if held.size:
            prior = state.P[np.ix_(held, held)]
        status, dx, used = select_and_update_inplace(
            state.P, inn.HP, inn.S, inn.residual, inn.off_row, inn.nis, inn.in_front, slots, gate,
            ransac_threshold_px, pixel_var, state.outlier_run, persistent_outlier_steps, state.gated_run)
        if held.size:
            state.P[np.ix_(held, held)] = prior
            dx[held] = 0.0
        return UpdateResult(int(status), dx, used)

    @staticmethod
    def augment(state: FilterState, ids: np.ndarray, new: NewLandmarks, pixel_var: float, counts: np.ndarray,
                limits: np.ndarray) -> None:
        """(A1) landmarks ``ids`` (n,) enter the state after the last slot, with the Jacobians of
        ``new`` and white pixel noise ``pixel_var``; their observation counts and limits (R1, R2);
        with the disparity offset in the state, its columns (O3)."""
        old = state.P.shape[0]
        state.P = augment(state.P, np.ascontiguousarray(new.J_xi), np.ascontiguousarray(new.J_z), pixel_var)
        if state.offset_row is not None:
            offset_columns_of_new_landmarks(state.P, old, new.J_offset, state.offset_row)
        state.append_landmarks(ids, new.theta, counts, limits, new.anchors)

    @staticmethod
    def marginalize(state: FilterState, mask: np.ndarray, ended: np.ndarray | None = None) -> np.ndarray:
        """(A2) the landmarks in ``mask`` leave the state (their rows and columns of P dropped);
        returns the new slot of each old one (-1: removed). The RANSAC rejection runs of tracks
        that may go on (not ``ended``; None: none ended) are kept by track id."""
        _, keep, remap, counted = plan_removal(mask, _NONE if ended is None else ended, state.outlier_run)
        state.stash_outlier_runs(counted)
        state.P = gather_landmarks(state.P, keep, state.core)  # C-ordered, one pass
        state.keep_landmarks(keep)
        return remap

    @staticmethod
    def clone(state: FilterState) -> None:
        """(W1) the pose joins the window as its newest clone: P's pose rows and columns copied after
        the last clone, the clone's covariance with the pose equal to the pose's own."""
        P = state.P
        D = P.shape[0]
        out = np.empty((D + 6, D + 6))
        out[:D, :D] = P
        out[D:, :D] = P[POSE, :]  # E P, E = [I_6 0]: the pose rows
        out[:D, D:] = out[D:, :D].T
        out[D:, D:] = P[POSE, POSE]
        state.P = out
        pose = state.mu[None].copy()
        state.clones = pose if state.clones is None else np.concatenate([state.clones, pose])

    @staticmethod
    def drop_oldest_clone(state: FilterState) -> None:
        """(W7) the oldest clone leaves the window: its rows and columns of P are dropped."""
        c = state.core
        state.P = gather_symmetric(state.P, np.r_[0:c, c + 6:state.P.shape[0]])
        state.clones = state.clones[1:]

    @staticmethod
    def update_window(state: FilterState, info: np.ndarray, pixel_var: float) -> np.ndarray:
        """(W6) the update by rows r = H xi_w + n over the clones' columns given by their information
        ``info`` = [Lambda g] (6w,6w+1), Lambda = H^T H, g = H^T r, n white of variance ``pixel_var``, in
        the clones' dimension whatever the rows: with the push-through identity
        H^T (sigma^2 I + H P H^T)^-1 = (sigma^2 I + Lambda P_ww)^-1 H^T,

            K_w = (sigma^2 I + Lambda P_ww)^-1 [Lambda, g],   dx = P_:,w K_w[:, -1],
            P <- P - P_:,w K_w[:, :6w] P_w,:

        (the Kalman update P - K S K^T with its m x m inverse never formed). Returns dx (D,)."""
        from scipy.linalg.lapack import dgesv  # a window's run only: a velocity run need not import scipy.linalg

        c = state.core
        w6 = info.shape[1] - 1
        P = state.P
        Pw = P[c:c + w6, :]  # (6w, D): H touches the clone rows only
        T = info[:, :w6] @ P[c:c + w6, c:c + w6]
        T[np.diag_indices_from(T)] += pixel_var
        _, _, K, status = dgesv(np.asfortranarray(T), np.asfortranarray(info), overwrite_a=1, overwrite_b=1)
        if status:
            raise FilterError(f"the window's update: sigma^2 I + Lambda P_ww is singular (getrf info {status})")
        dx = Pw.T @ K[:, w6]
        KP = K[:, :w6].T @ Pw  # K_w's first block is symmetric (push-through); its transpose is C-ordered
        P -= Pw.T @ KP
        state.P = 0.5 * (P + P.T)
        return dx

    @staticmethod
    def update_dense(state: FilterState, H_core: np.ndarray, residual: np.ndarray, S: np.ndarray) -> np.ndarray:
        """The Kalman update by m rows r = H dx + n whose Jacobian ``H_core`` (m,k) touches the first k
        rows of the state only, with ``S`` (m,m) = H P H^T + R the prior covariance of ``residual`` (m,):

            dx = P H^T S^-1 r,   P <- P - (P H^T) S^-1 (P H^T)^T   (symmetrized)

        (the Joseph form's equal for the optimal gain, O(D^2 m)). Returns dx (D,)."""
        k = H_core.shape[1]
        PHt = state.P[:, :k] @ H_core.T  # (D, m)
        L = np.linalg.cholesky(S)
        A = np.linalg.solve(L, PHt.T)  # L^-1 H P  (m, D)
        dx = A.T @ np.linalg.solve(L, residual)
        P = state.P
        P -= A.T @ A
        state.P = 0.5 * (P + P.T)
        return dx

    @staticmethod
    def repair(state: FilterState, estimated: np.ndarray) -> float | None:
        """(H2) P over the ``estimated`` states (bool (D,)) made positive definite if it is not;
        returns the smallest eigenvalue found then (else None)."""
        return repair_if_indefinite(state.P, estimated)
