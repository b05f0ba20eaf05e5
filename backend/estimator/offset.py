"""The stereo pair's residual disparity offset as a state of the filter (O1-O3).

The run removes the disparity offset it identified from the tracks (D1 of
``backend.run.stereo_offset``: the right column moved by beta_hat), but that estimate carries a
standard error, and an offset not found significant is not removed at all. What is left,
delta_beta, is one number for the whole run that scales every landmark's depth (z = fx b / d) and
through them the translation vision measures: taken as exact, a tenth of a pixel on disparities of
10 px is a 1 % scale error the covariance does not hold. The filter therefore estimates it, a
constant with the prior N(0, sigma_beta^2) the decision gives (``Decisions.offset_sigma``):

    uR = uR_true - delta_beta,   h_uR(x, delta_beta) = pi_R(x) - delta_beta                        (O1)

so every observation's right column enters corrected by the current mean, uR + delta_beta_hat. In
the update's 3-row form (U1) the offset touches only the uR row, H_beta = -e_uR, so with u = H P e_b
(the innovation's existing column of H P at the offset's row b):

    r' = r + delta_beta_hat e_uR,   H P' = H P - e_uR P[b, :],
    S' = S - u e_uR^T - e_uR u^T + P_bb e_uR e_uR^T                                                 (O2)

(the sum over the observations' uR rows). A new landmark is triangulated from the corrected
pixels, theta = g(x, z + delta_beta_hat e_uR), so its Jacobian on the offset is the uR column of its
pixel Jacobian, j = d g / d uR (3 per landmark); with the augment's cross block C = J_xi P (A1) and
c = C[:, b] = J_xi P e_b before the offset's column is added:

    C' = C + j P[b, :],   P_mm' = P_mm + c j^T + j c^T + P_bb j j^T                                 (O3)

The offset takes no process noise (a constant of the rig). Velocity-model runs only: a real IMU's
run keeps its offset as decided.

By default it is a consider state (Schmidt): the update leaves the offset's mean and variance as
they were and updates everything else with the gain of the full update, so the poses and
landmarks carry the offset's uncertainty without the filter moving it:                           (O4)

    dx_b = 0,   P_bb+ = P_bb   (the other blocks of P - (H P)^T S^-1 H P unchanged)

Estimated instead (``estimator.estimate_stereo_offset``), it finds an offset nobody removed (a
synthetic street's -0.3 px to 0.01-0.03 px), but the EKF's linearization pulls it: on drift-free
synthetic streets without an offset it ends at +0.002, +0.007, +0.016 and +0.050 px (1.2, 1.7, 2.2
and 4.3 sigma) for pixel noise of 0.1, 0.25, 0.5 and 1 px, and on real tracks with unmodelled
errors far more. Where the decided offset's error is within its standard error the two are alike
(synthetic streets with -1 px planted, seeds 5-12: ATE 0.055 and 0.056 m, position NEES 3.5 and
3.5, against 0.090 m and 15.7 with the decided offset taken as exact).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .update import Innovation, block_nis

__all__ = ["OffsetEstimate", "offset_innovation", "offset_columns_of_new_landmarks", "corrected_pixels"]


@dataclass(frozen=True)
class OffsetEstimate:
    """The residual disparity offset in the filter (O1): its mean and sigma now and its prior's sigma, px."""

    residual_px: float  # delta_beta_hat, added to every uR on top of the decided correction
    sigma_px: float
    prior_sigma_px: float
    estimated: bool  # False: a consider state (O4), its mean and variance held

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def corrected_pixels(pixels: np.ndarray, offset: float) -> np.ndarray:
    """(O1) ``pixels`` (n,4) = [uL vL uR vR] with uR + ``offset`` (a copy)."""
    out = np.array(pixels, dtype=float, copy=True)
    out[:, 2] += offset
    return out


def offset_innovation(inn: Innovation, P: np.ndarray, row: int, pixel_var: float) -> Innovation:
    """(O2) the innovation ``inn``, formed by the error model from the corrected pixels (O1: its
    residual is r') without the offset's column in H, with that column for the offset at row ``row``
    of ``P`` (D,D); the NIS recomputed (U4). Returns a new Innovation."""
    HP = inn.HP.copy()
    u = HP[:, row].copy()  # (3k,) H P e_b
    HP[2::3] -= P[row][None, :]
    S = inn.S.copy()
    S[:, 2::3] -= u[:, None]
    S[2::3, :] -= u[None, :]
    S[2::3, 2::3] += P[row, row]
    return Innovation(inn.residual, inn.off_row, inn.H_x, inn.H_m, HP, S,
                      block_nis(S, inn.residual, inn.off_row, pixel_var), inn.in_front, inn.variance)


def offset_columns_of_new_landmarks(P: np.ndarray, old: int, j: np.ndarray, row: int) -> None:
    """(O3) in place: ``P`` (D+3n, D+3n) just augmented by n landmarks after its first ``old`` = D
    rows from their pose Jacobians alone, given their Jacobian ``j`` (3n,) on the offset at ``row``."""
    c = P[old:, row].copy()  # J_xi P e_b
    pb = P[row, :old].copy()
    P[old:, :old] += j[:, None] * pb[None, :]
    P[:old, old:] = P[old:, :old].T
    new = P[old:, old:]
    new += c[:, None] * j[None, :] + j[:, None] * c[None, :] + P[row, row] * (j[:, None] * j[None, :])
    P[old:, old:] = 0.5 * (new + new.T)
