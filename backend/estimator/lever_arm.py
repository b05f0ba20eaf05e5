"""The residual lever arm of the IMU's velocities and the rotation of its samples' frame in the filter (V1-V4).

A velocity sensor measures the velocity of its own point, not of the frame the extrinsic defines:
with that point at r in the IMU frame, v_imu = v_m - omega x r (N3 of ``backend.run.noise``, which
removes the r it measures from the tracks). What is left, delta_r = r - r_hat, is a constant of the
rig, the same at every step: a turn of angle alpha moves the pose by about alpha |delta_r| whatever
the velocities' white noise says. On ece276a2019_0042 the ground truth is the pose of a point about
2.5 m from the OXTS unit whose velocities the file holds, and its 3.5 tracks a step cannot measure
r: 2.3 m of lateral error in the first 4 s against a reported 0.11 m, position NEES 224.

Prediction. The step's twist error gains delta_u = [-omega x delta_r; 0] tau, so with the error
models' map G of a twist error into the error state (Ad(mu_next) J_r of I2, J_r of B1), the
lever arm's column block of F is G E_r with

    E_r = -[(tau omega)^ ; 0]   (6,3)                                                          (V1)

(as the gyro bias's is G E_b, E_b = -tau [0; I]); at a frozen step (I8) its rows are scaled by the
IMU's share of the fused linear velocity, and every landmark's translation rows follow the pose's.
The lever arm takes no process noise. Estimated (``estimator.estimate_lever_arm``), it is three
more states: F gains those columns, the update moves its mean r_hat_s, and every step's twist is
taken as v - omega x r_hat_s.

Considered (the default). Vision sees r only through the poses, and estimating it lets the
linearization and unmodelled errors pull it (0042: the estimate ends at (-0.2, -0.5, -3.8) +- (0.1,
0.3, 1.0) m against the (-1.1, 1.5, -1.9) m the ground truth's body velocities give, ATE 0.97 ->
1.03 m). A Schmidt consider state (the full update's gain, its covariance held, as O4 does for the
disparity offset) leaves the mean alone but not the gain, and the gain then trusts the few tracks
more (0042: ATE 0.97 -> 1.86 m). So the filter runs as if r_hat were exact and its covariance
carries what r's error does to it (consider covariance analysis; Bierman, "Factorization Methods
for Discrete Sequential Estimation", 1977, ch. VII): the error of that estimate is e = e_0 + S
delta_r, e_0 with the filter's own covariance P_0 and S = d e / d delta_r its sensitivity (D,3).
P's lever arm rows hold P_rr (the prior) and its columns S P_rr, P's other rows P_0, and

    prediction     P_0 as without r (F without the columns of V1),   S <- F S + G E_r
    augmentation   S_new = J_xi S_xi  (A1 as it is: r is not in the pixels)
    update         S <- (I - K H) S,  K = P_0 H^T S_0^-1 (the gain without r; dx_r = 0, P_rr held)
    covariance     Cov(e) = P_0 + S P_rr S^T = P_0 + P_.r P_rr^-1 P_r.                          (V2)

The estimate is the one without the lever arm, to rounding; the covariance a run reports (the
poses', the map's) holds its share. P is not a covariance over the lever arm's rows (P_0 - S P_rr
S^T need not be positive semi-definite): the positive-definiteness repair (H2) leaves them out.
On the default invariant filter S is the estimate's own derivative to first order (central
differences of the filter without r: to 1e-6 without vision, 4 % with it, where the gains and
Jacobians also move with the estimate; ``tests/test_lever_arm.py``).

The prior (V3, ``Decisions.lever_covariance``), the second moment of what N3 leaves: where N3
applied its correction, its covariance; where N3 measured r and the velocities stay as given, that
plus r_hat r_hat^T; where the tracks could not measure it, N3's own prior ``LEVER_PRIOR_M`` per axis.
A component the motion does not excite (a street's height, for its yaw) keeps about N3's prior and
moves no pose. ``noise.lever_arm_sigma`` sets sigma^2 I instead (0: no such state).

The samples' frame (V4). Where the samples are given in a frame turned from the IMU frame by a
small rotation theta (N6 of ``backend.run.noise``: a mounting, or the level frame of KITTI's OXTS
that the 2019 course files keep: on ece276a2019_0042 the rates differ from the ground truth's body
rates by 0.011 / 0.006 rad/s RMS in roll / pitch during turns, 0.005 / 0.003 as level-frame rates
with the world tilted 0.7 and 2.9 deg), the body's twist is Ad(exp(theta^)) u = u + theta x u, so
the step's twist error gains

    E_theta = -[(tau v)^ ; (tau omega)^]   (6,3)                                               (V4)

the same error for both halves. It is considered as the lever arm is (V2): the considered block is
then 6 rows, [delta_r; theta], its prior block-diagonal, P_rr^-1 its pseudo-inverse (a block set
to 0 carries nothing). Its prior is N6's theta theta^T plus its covariance where the tracks measured
it significant (none where not), ``ROTATION_PRIOR_RAD`` per axis where they could not; ``noise.imu_rotation_sigma`` (deg) sets it
(0: none). An estimated lever arm carries no rotation.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..geometry import se3
from .layout import LEVER_ROWS

__all__ = ["LeverArmEstimate", "SensitivityTransition", "carried_prior", "consider_information", "twist_columns"]


@dataclass(frozen=True)
class LeverArmEstimate:
    """The residual lever arm in the filter (V1): its mean and per-axis sigma now (m) and its prior's sigma."""

    residual_m: list  # (3,) delta_r_hat, IMU frame; zeros for a considered one
    sigma_m: list  # (3,) sqrt of the diagonal of P_rr
    prior_sigma_m: list  # (3,) sqrt of the diagonal of its prior
    estimated: bool  # False: considered (V2), its mean 0 and its prior held
    rotation_prior_sigma_deg: list | None = None  # (3,) the samples' frame rotation considered with it (V4); None: not carried

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def twist_columns(twist: np.ndarray, imu_weight: np.ndarray | None = None, rotation: bool = False) -> np.ndarray:
    """(V1) E_r (6,3): d(twist error) / d(delta_r) for the step's twist ``twist`` (6,) = tau [v; omega];
    with ``rotation``, [E_r, E_theta] (6,6), E_theta = d(twist error) / d(theta) of (V4).
    ``imu_weight`` (6,): the IMU's share of each axis of the twist where it fuses another
    prediction (I8), else 1."""
    u = np.asarray(twist, dtype=float)
    E = np.zeros((6, 6 if rotation else 3))
    E[0:3, 0:3] = -se3.hat3(u[3:6])
    if rotation:
        E[0:3, 3:6] = -se3.hat3(u[0:3])
        E[3:6, 3:6] = -se3.hat3(u[3:6])
    if imu_weight is not None:
        E *= np.asarray(imu_weight, dtype=float)[:, None]
    return E


def carried_prior(prior: np.ndarray, estimated: bool) -> np.ndarray:
    """(V4) the block a filter carries of a prior (3,3), or (6,6) with the samples' frame rotation:
    an estimated lever arm carries no rotation, so there its (3,3)."""
    prior = np.asarray(prior, dtype=float)
    return prior[:LEVER_ROWS, :LEVER_ROWS] if estimated else prior


def consider_information(prior: np.ndarray) -> np.ndarray:
    """(V2, V4) P_rr^-1 (k,k) of a considered block's prior (k,k); its pseudo-inverse where a part is
    0 (a lever arm configured away, its rotation kept)."""
    prior = np.asarray(prior, dtype=float)
    if np.all(np.diag(prior) > 0):
        return np.linalg.inv(prior)
    return np.linalg.pinv(prior, hermitian=True)


@dataclass
class SensitivityTransition:
    """(V2) a prediction whose error also moves by g delta_r, delta_r a considered parameter (rows
    ``row`` .. + k - 1, k = 3, or 6 with the rotation of V4) that P holds as sensitivity columns S
    P_rr: P by ``inner`` (the prediction without delta_r), then S <- F S + g, i.e. P[x, r] += g P_rr
    on the pose rows (``g`` (6,k)) and,
    with ``core`` given (a frozen step, I8: every landmark's translation rows follow the pose's), on
    each landmark's rows by g[0:3]."""

    inner: object
    row: int
    g: np.ndarray
    core: int | None = None

    def apply(self, P: np.ndarray) -> np.ndarray:
        P = self.inner.apply(P)
        r = slice(self.row, self.row + self.g.shape[1])
        add = self.g @ P[r, r]
        P[0:6, r] += add
        if self.core is not None and P.shape[0] > self.core:
            K = (P.shape[0] - self.core) // 3
            P[self.core:, r] += np.tile(add[0:3], (K, 1))
        P[r, :] = P[:, r].T
        return P
