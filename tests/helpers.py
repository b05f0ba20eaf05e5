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
