"""backend.linalg: the dense kernels of the update, against plain numpy."""

from __future__ import annotations

import numpy as np
import pytest

from backend.kernels import mirror_lower_inplace
from backend.linalg import block_nis, cholesky_lower, solve_lower, submatrix, symmetric_downdate, take_rows, whiten_rows

RNG = np.random.default_rng(7)


def _spd(n: int) -> np.ndarray:
    B = RNG.normal(size=(n, n))
    P = B @ B.T + n * np.eye(n)
    mirror_lower_inplace(P)
    return P


@pytest.mark.parametrize("order", ["C", "F"])
def test_symmetric_downdate_is_exact_and_symmetric(order):
    P = _spd(40)
    A = np.asarray(RNG.normal(size=(25, 40)) * 0.3, order=order)
    expected = P - A.T @ A
    symmetric_downdate(P, A)
    assert np.array_equal(P, P.T)
    np.testing.assert_allclose(P, expected, rtol=0, atol=1e-12 * np.abs(expected).max())


def test_whitening_and_cholesky():
    S = _spd(30)
    B = RNG.normal(size=(30, 45))
    L = cholesky_lower(S)
    np.testing.assert_allclose(np.tril(L) @ np.tril(L).T, S, atol=1e-10)
    np.testing.assert_allclose(whiten_rows(L, B), np.linalg.solve(np.tril(L), B), atol=1e-12)
    np.testing.assert_allclose(solve_lower(L, B), np.linalg.solve(np.tril(L), B), atol=1e-12)
    with pytest.raises(np.linalg.LinAlgError):
        cholesky_lower(-S)


def test_row_selection_keeps_order():
    M = np.arange(20.0).reshape(5, 4)
    assert take_rows(M, np.arange(5)) is M  # every row in order: no copy
    np.testing.assert_array_equal(take_rows(M, np.array([3, 4, 0, 1, 2])), M[[3, 4, 0, 1, 2]])  # a permutation is applied
    S = _spd(6)
    rows = np.array([1, 4, 5])
    np.testing.assert_array_equal(submatrix(S, rows), S[np.ix_(rows, rows)])


def test_block_nis():
    blocks = np.stack([_spd(3) for _ in range(4)])
    r = RNG.normal(size=(4, 3))
    expected = [r[i] @ np.linalg.solve(blocks[i], r[i]) for i in range(4)]
    np.testing.assert_allclose(block_nis(blocks, r), expected, rtol=1e-12)
    blocks[2] = 0.0
    assert np.isinf(block_nis(blocks, r)[2]) and np.isfinite(block_nis(blocks, r)[[0, 1, 3]]).all()
