"""Shared test helpers (imported by the test modules; pytest puts tests/ on sys.path)."""

from __future__ import annotations

import numpy as np


def numeric_jacobian(f, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Central finite differences of f at x: (..., x.size), one column per coordinate of x."""
    cols = []
    for i in range(x.size):
        dx = np.zeros_like(x, dtype=float)
        dx[i] = eps
        cols.append((f(x + dx) - f(x - dx)) / (2 * eps))
    return np.stack(cols, axis=-1)


# (U1) of backend.ekf: the orthogonal change of the 4 pixel rows [uL, vL, uR, vR] into the
# 3 rows the filter keeps, [uL, (vL + vR)/sqrt 2, uR], and the fourth, (vL - vR)/sqrt 2
_S = np.sqrt(0.5)
THREE_ROWS = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, _S, 0.0, _S], [0.0, 0.0, 1.0, 0.0]])
OFF_ROW = np.array([0.0, _S, 0.0, -_S])


def four_rows(three: np.ndarray, off: np.ndarray | float = 0.0) -> np.ndarray:
    """Back from the 3-row form (..., 3, n) with the fourth row's values ``off`` to the 4 pixel rows."""
    return THREE_ROWS.T @ three + OFF_ROW[:, None] * np.asarray(off)[..., None, None]
