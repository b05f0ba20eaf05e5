"""backend.estimator.linalg: BLAS/LAPACK called from compiled code, the small solver and the
selection, against plain numpy; and the block NIS of the landmark NEES (backend.evaluation.consistency) against per-block solves."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from vislam.backend.estimator.linalg import (add_product_lower, cholesky_upper_inplace, downdate_lower, kth_smallest,
                                              median_inplace, solve_lower_inplace, solve_small)
from vislam.backend.evaluation.consistency import landmark_nees

RNG = np.random.default_rng(7)


def _spd(n: int) -> np.ndarray:
    B = RNG.normal(size=(n, n))
    P = B @ B.T + n * np.eye(n)
    return 0.5 * (P + P.T)


def test_downdate_lower_triangle():
    P = _spd(40)
    upper = np.triu(P, 1).copy()
    A = RNG.normal(size=(25, 40)) * 0.3
    expected = P - A.T @ A
    downdate_lower(P, A)
    np.testing.assert_allclose(np.tril(P), np.tril(expected), rtol=0, atol=1e-12 * np.abs(expected).max())
    assert np.array_equal(np.triu(P, 1), upper)  # the upper triangle is not touched


def test_cholesky_and_triangular_solve():
    S = _spd(30)
    U = S.copy()
    assert cholesky_upper_inplace(U) == 0
    L = np.triu(U).T
    np.testing.assert_allclose(L @ L.T, S, atol=1e-10)
    np.testing.assert_allclose(np.tril(U, -1), np.tril(S, -1))  # the lower triangle is left as it was
    B = RNG.normal(size=(30, 45))
    X = B.copy()
    solve_lower_inplace(U, X)
    np.testing.assert_allclose(X, np.linalg.solve(L, B), atol=1e-12)
    bad = -S
    assert cholesky_upper_inplace(bad) > 0


def block_nis(blocks: np.ndarray, residual: np.ndarray) -> np.ndarray:
    """Reference: r_i^T B_i^-1 r_i for (k,d,d) blocks and (k,d) residuals, one solve per block; inf
    where a block is singular."""
    out = np.full(residual.shape[0], np.inf)
    for i in range(residual.shape[0]):
        try:
            out[i] = residual[i] @ np.linalg.solve(blocks[i], residual[i])
        except np.linalg.LinAlgError:
            pass
    return out


def test_block_nis():
    """landmark_nees(positions, covariances, truth) is the block NIS of the errors positions - truth."""
    blocks = np.stack([_spd(3) for _ in range(4)])
    r = RNG.normal(size=(4, 3))
    truth = RNG.normal(0.0, 10.0, size=(4, 3))
    expected = [r[i] @ np.linalg.solve(blocks[i], r[i]) for i in range(4)]
    np.testing.assert_allclose(block_nis(blocks, r), expected, rtol=1e-12)
    np.testing.assert_allclose(landmark_nees(r, blocks, np.zeros((4, 3))), expected, rtol=1e-12)
    np.testing.assert_allclose(landmark_nees(truth + r, blocks, truth), block_nis(blocks, (truth + r) - truth),
                               rtol=1e-12)
    blocks[2] = 0.0
    assert np.isinf(block_nis(blocks, r)[2]) and np.isfinite(block_nis(blocks, r)[[0, 1, 3]]).all()
    nees = landmark_nees(r, blocks, np.zeros((4, 3)))
    assert np.isinf(nees[2]) and np.isfinite(nees[[0, 1, 3]]).all()
    np.testing.assert_allclose(nees[[0, 1, 3]], np.array(expected)[[0, 1, 3]], rtol=1e-12)
    assert landmark_nees(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3))).shape == (0,)


def test_add_product_lower():
    P = _spd(20)
    Z, X = RNG.normal(size=(20, 6)), RNG.normal(size=(20, 6))
    expected = P + Z @ X.T
    add_product_lower(P, Z, X)
    np.testing.assert_allclose(P, expected, rtol=0, atol=1e-12 * np.abs(expected).max())


@settings(max_examples=200, deadline=None)
@given(st.lists(st.sampled_from([-2.5, -1.0, 0.0, 0.5, 0.5, 3.0]) | st.floats(-1e6, 1e6), min_size=1, max_size=40),
       st.data())
def test_selection_and_median_are_numpys(values, data):
    """kth_smallest is the sorted array's element m, median_inplace numpy's median (the mean of the middle
    two for an even count), ties and one element included."""
    x = np.array(values)
    m = data.draw(st.integers(0, x.size - 1))
    assert kth_smallest(x.copy(), m) == np.sort(x)[m]
    assert median_inplace(x.copy()) == np.median(x)


def test_solve_small_against_numpy_and_singular():
    """Gaussian elimination with partial pivoting solves a small system as numpy does; a singular one says so."""
    A = RNG.normal(size=(7, 7))
    b = RNG.normal(size=7)
    x, ok = solve_small(A, b)
    assert ok
    np.testing.assert_allclose(x, np.linalg.solve(A, b), rtol=1e-10, atol=1e-12)
    A[3] = 2.0 * A[1]
    assert not solve_small(A, b)[1]
