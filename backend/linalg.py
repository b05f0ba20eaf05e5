"""Dense kernels of the EKF update (pure functions on numpy arrays, one BLAS thread assumed).

Layout matters at the ~200x200 sizes of the filter as much as the flop count: the covariance P
is kept C-ordered and exactly symmetric, so its transpose is an F-ordered view of the same
matrix that BLAS/LAPACK take without a copy. Measured on the development machine at D ~ 190,
m ~ 180: potrf 0.15 ms, trsm 0.23 ms, syrk 0.2 ms; a copy of P costs ~0.05 ms.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import get_blas_funcs, get_lapack_funcs

from backend import kernels

_potrf = get_lapack_funcs("potrf", dtype=np.float64)
_syrk = get_blas_funcs("syrk", dtype=np.float64)
_trsm = get_blas_funcs("trsm", dtype=np.float64)
_trtrs = get_lapack_funcs("trtrs", dtype=np.float64)


def whiten_rows(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """L^-1 B for lower-triangular L and a C-ordered B (m,D), as (B^T L^-T)^T by BLAS trsm on the
    right: B^T is the F-ordered view of B, so nothing is copied; the result is C-ordered."""
    return _trsm(1.0, L, B.T, side=1, lower=1, trans_a=1).T


def solve_lower(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """L^-1 B for lower-triangular L (LAPACK trtrs, no input checks: this is the hot path)."""
    X, info = _trtrs(L, B, lower=True)
    if info != 0:
        raise np.linalg.LinAlgError(f"singular triangular factor (trtrs info {info})")
    return X


def block_nis(blocks: np.ndarray, residual: np.ndarray) -> np.ndarray:
    """r_i^T B_i^-1 r_i for (k,d,d) blocks and (k,d) residuals; inf where a block is singular."""
    try:
        return np.einsum("ki,ki->k", residual, np.linalg.solve(blocks, residual[:, :, None])[:, :, 0])
    except np.linalg.LinAlgError:
        out = np.full(residual.shape[0], np.inf)
        for i in range(residual.shape[0]):
            try:
                out[i] = residual[i] @ np.linalg.solve(blocks[i], residual[i])
            except np.linalg.LinAlgError:
                pass
        return out


def submatrix(M: np.ndarray, rows: np.ndarray, cols: np.ndarray | None = None) -> np.ndarray:
    """M[rows][:, cols] (cols defaults to rows; both increasing), without a copy when both select everything."""
    cols = rows if cols is None else cols
    if rows.size == M.shape[0] and cols.size == M.shape[1]:
        return M
    return M[rows][:, cols]  # two gathers: faster than M[np.ix_(rows, cols)]


def take_rows(M: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """M[rows], without a copy when ``rows`` is every row in order."""
    if rows.size == M.shape[0] and (rows.size == 0 or (rows[0] == 0 and rows[-1] == rows.size - 1 and np.all(rows[1:] > rows[:-1]))):
        return M
    return M[rows]


def symmetric_downdate(P: np.ndarray, A: np.ndarray) -> None:
    """P <- P - A^T A in place for a symmetric C-ordered P: BLAS syrk on one triangle, then mirrored.

    P.T is the Fortran-ordered view of the same (symmetric) matrix, so syrk updates it in place.
    """
    if A.flags.f_contiguous:  # A^T A from A itself (trans=1), else from A^T (trans=0): no copy either way
        out = _syrk(-1.0, A, beta=1.0, c=P.T, trans=1, lower=0, overwrite_c=1)
    else:
        out = _syrk(-1.0, A.T, beta=1.0, c=P.T, trans=0, lower=0, overwrite_c=1)
    if not np.shares_memory(out, P):  # not updated in place (P not C-contiguous): copy back
        P[...] = out.T
    kernels.mirror_lower_inplace(P)  # syrk wrote the upper triangle of P.T, i.e. the lower triangle of P


def cholesky_lower(S: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor L of the symmetric positive definite S (S = L L^T). The upper triangle
    of the result is left as it was: only triangular solves with the lower triangle read it. An
    F-ordered S is factored without a copy. Raises LinAlgError when S is not positive definite."""
    L, info = _potrf(S, lower=True, clean=False)
    if info != 0:
        raise np.linalg.LinAlgError(f"innovation covariance not positive definite (potrf info {info})")
    return L
