"""The compiled operations on the filter's covariance P as a whole: symmetry, augmentation,
marginalization, and the positive-definiteness check (``StateHelper`` of
``backend.estimator.state_helper`` applies them to the state).

New landmarks theta = g(z, mu) from a stereo observation z (pixel noise sigma^2 I) seen from the
pose mu with error xi, with Jacobians J_xi = dg/dxi (3n,6) and J_z = dg/dz (n,3,4), augment the
state (EKF-SLAM state augmentation):

    P_m,x = J_xi P_xi,x,    P_mm = J_xi P_xixi J_xi^T + blockdiag(sigma^2 J_z J_z^T)          (A1)

Marginalizing landmarks drops their rows and columns of P (exact for a Gaussian):           (A2)

    P <- P[keep][:, keep]

P is kept exactly symmetric: every kernel writes one triangle and mirrors it.
"""

from __future__ import annotations

import numpy as np

from ..compiled import jit, warms_up
from ..geometry.se3 import put_block
from .layout import CORE, landmark_row


@jit
def mirror_lower_inplace(P):
    """Copy the lower triangle of the square C-ordered P onto its upper triangle (exact symmetry)."""
    n = P.shape[0]
    for i in range(n):
        for j in range(i):
            P[j, i] = P[i, j]


@jit
def gather_symmetric(P, keep):
    """(A2) P[keep][:, keep] as a new C-ordered matrix, in one pass."""
    n = keep.size
    out = np.empty((n, n))
    for i in range(n):
        row = P[keep[i]]
        for j in range(n):
            out[i, j] = row[keep[j]]
    return out


@jit
def gather_landmarks(P, keep, core=CORE):
    """(A2) P over the first ``core`` rows (pose, bias; velocity and accelerometer bias in the inertial
    state) and the landmark slots ``keep`` (the others marginalized)."""
    idx = np.empty(landmark_row(core, keep.size), dtype=np.int64)
    for i in range(core):
        idx[i] = i
    for i in range(keep.size):
        new, old = landmark_row(core, i), landmark_row(core, keep[i])
        for a in range(3):
            idx[new + a] = old + a
    return gather_symmetric(P, idx)


@jit
def augment(P, J_xi, J_z, pixel_var):
    """(A1) for n new landmarks, the pose Jacobian J_xi (3n,6) and the pixel Jacobians J_z (n,3,4):
    returns [[P, P_m,x^T], [P_m,x, P_mm]] as a new C-ordered matrix, exactly symmetric."""
    D = P.shape[0]
    n3 = J_xi.shape[0]
    out = np.empty((D + n3, D + n3))
    put_block(out, 0, 0, P)
    cross = np.zeros((n3, D))
    for i in range(n3):
        for j in range(6):
            h = J_xi[i, j]
            if h != 0.0:
                row = P[j]
                for c in range(D):
                    cross[i, c] += h * row[c]
    for i in range(n3):
        for j in range(D):
            out[D + i, j] = cross[i, j]
            out[j, D + i] = cross[i, j]
    for i in range(n3):
        for j in range(i + 1):
            s = 0.0
            for t in range(6):
                s += cross[i, t] * J_xi[j, t]
            if i // 3 == j // 3:  # the pixel part, block diagonal
                lm = i // 3
                a, b = i - 3 * lm, j - 3 * lm
                for t in range(4):
                    s += pixel_var * J_z[lm, a, t] * J_z[lm, b, t]
            out[D + i, D + j] = s
            out[D + j, D + i] = s
    return out


def repair_if_indefinite(P: np.ndarray, estimated: np.ndarray) -> float | None:
    """Check that P over the ``estimated`` states (bool mask) is positive definite; if it is not,
    clip its eigenvalues to 1e-12 in place and return the smallest eigenvalue found (else None).

    A Cholesky factor proves definiteness in the common case (~10x cheaper than ``eigh``);
    eigenvalues down to -1e-9 of the largest count as rounding."""
    sub = P[np.ix_(estimated, estimated)]
    if sub.size == 0:
        return None
    try:
        np.linalg.cholesky(sub)
        return None
    except np.linalg.LinAlgError:
        pass
    eigval, eigvec = np.linalg.eigh(sub)
    if eigval.min() > -1e-9 * max(eigval.max(), 1e-30):
        return None
    repaired = (eigvec * np.maximum(eigval, 1e-12)) @ eigvec.T
    P[np.ix_(estimated, estimated)] = 0.5 * (repaired + repaired.T)
    return float(eigval.min())


@warms_up(only="landmarks")
def _warm_up() -> None:
    """The kernels a run calls from Python (``backend.compiled``: the others are compiled into their callers)."""
    P = np.eye(CORE + 6)
    gather_landmarks(P, np.arange(2, dtype=np.int64), CORE)  # core given, as StateHelper.marginalize passes it
    augment(P, np.zeros((3, 6)), np.ones((1, 3, 4)), 1.0)


@warms_up(only="inertial")
def _warm_up_clones() -> None:
    """A real IMU's run also calls :func:`gather_symmetric` from Python (a clone leaves: ``StateHelper.drop_oldest_clone``)."""
    gather_symmetric(np.eye(CORE + 12), np.r_[0:CORE, CORE + 6:CORE + 12])
