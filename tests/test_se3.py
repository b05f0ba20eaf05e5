"""Tests of vislam.backend.geometry.se3: SO(3)/SE(3) exponentials, logarithms, Jacobians and
adjoints against expm, finite differences and readable references, in Python and in compiled code."""

from __future__ import annotations

import numba
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import expm

from vislam.backend.geometry import se3
from helpers import numeric_jacobian

SETTINGS = settings(max_examples=60, deadline=None)

_coord = st.floats(-1.0, 1.0, allow_nan=False)
_direction = st.tuples(_coord, _coord, _coord).map(np.array).filter(lambda v: np.linalg.norm(v) > 0.1)


def _rotvec(max_angle: float, min_angle: float = 0.0):
    return st.builds(
        lambda d, a: a * d / np.linalg.norm(d), _direction, st.floats(min_angle, max_angle)
    )


def _twist(max_angle: float = 3.0, max_translation: float = 10.0):
    rho = st.tuples(*[st.floats(-max_translation, max_translation)] * 3).map(np.array)
    return st.builds(np.concatenate, st.tuples(rho, _rotvec(max_angle)))


def _pose():
    return _twist().map(se3.exp_se3)


# ---------------------------------------------------------------- readable references


def hat(xi: np.ndarray) -> np.ndarray:
    """Twist to se(3): [[theta^, rho], [0, 0]] (Barfoot eq. 7.28); (6,) -> (4, 4)."""
    X = np.zeros((4, 4))
    X[:3, :3] = se3.hat3(xi[3:])
    X[:3, 3] = xi[:3]
    return X


def vee(X: np.ndarray) -> np.ndarray:
    """Inverse of :func:`hat`; (4, 4) -> (6,) = [rho, theta]."""
    return np.concatenate([X[:3, 3], se3.vee3(X[:3, :3])])


def curly_hat(xi: np.ndarray) -> np.ndarray:
    """Adjoint of se(3), xi^curly = [[theta^, rho^], [0, theta^]] (Barfoot eq. 7.32)."""
    C = np.zeros((6, 6))
    C[:3, :3] = C[3:, 3:] = se3.hat3(xi[3:])
    C[:3, 3:] = se3.hat3(xi[:3])
    return C


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rodrigues' rotation exp(w^) (Barfoot eq. 7.14), the rotation half of the production pair."""
    return se3.exp_so3_and_left_jacobian(w)[0]


def right_jacobian_so3(w: np.ndarray) -> np.ndarray:
    """J_r(w) = J_l(-w) (Barfoot eq. 7.87)."""
    return se3.left_jacobian_so3(-np.asarray(w, dtype=float))


@SETTINGS
@given(_twist())
def test_hat_vee_are_inverse(xi):
    assert np.array_equal(vee(hat(xi)), xi)
    assert np.array_equal(se3.vee3(se3.hat3(xi[3:])), xi[3:])
    assert np.allclose(se3.hat3(xi[3:]) @ xi[:3], np.cross(xi[3:], xi[:3]))


def test_hat3_batched():
    w = np.arange(12.0).reshape(4, 3)
    W = se3.hat3(w)
    assert W.shape == (4, 3, 3)
    for i in range(4):
        assert np.array_equal(W[i], se3.hat3(w[i]))
        assert np.array_equal(W[i], -W[i].T)


@SETTINGS
@given(_twist())
def test_exp_se3_matches_expm(xi):
    assert np.allclose(se3.exp_se3(xi), expm(hat(xi)), atol=1e-10, rtol=0)


@SETTINGS
@given(_rotvec(3.0))
def test_exp_so3_and_left_jacobian_match_the_separate_forms(w):
    """The pair agrees with exp_se3's rotation block and left_jacobian_so3 (bit for bit), and
    R = I + w^ J_l(w) ties its two halves together."""
    R, J = se3.exp_so3_and_left_jacobian(w)
    assert np.array_equal(R, se3.exp_se3(np.r_[0.0, 0.0, 0.0, w])[:3, :3])
    assert np.array_equal(J, se3.left_jacobian_so3(w))
    assert np.allclose(R, np.eye(3) + se3.hat3(w) @ J, atol=1e-14, rtol=0)


@SETTINGS
@given(st.lists(_twist(), min_size=1, max_size=8), st.floats(0.0, 0.2))
def test_exp_se3_batch_matches_expm(twists, small):
    """Batch of twists, including rotations below and around the series switch (0.1 rad) and zero."""
    xis = np.array(twists + [np.r_[1.0, 2.0, 3.0, small, 0.0, 0.0], np.zeros(6)])
    batch = se3.exp_se3_batch(xis)
    for xi, T in zip(xis, batch):
        assert np.allclose(T, expm(hat(xi)), atol=1e-10, rtol=0)


@SETTINGS
@given(_twist(max_angle=np.pi - 0.1))
def test_log_exp_se3_roundtrip(xi):
    assert np.allclose(se3.log_se3(se3.exp_se3(xi)), xi, atol=1e-9, rtol=0)


@SETTINGS
@given(_pose())
def test_exp_log_se3_roundtrip(T):
    assert np.allclose(se3.exp_se3(se3.log_se3(T)), T, atol=1e-10, rtol=0)


@SETTINGS
@given(_rotvec(np.pi - 1e-3))
def test_exp_so3_matches_expm_and_log_roundtrip(w):
    R = exp_so3(w)
    assert np.allclose(R, expm(se3.hat3(w)), atol=1e-12, rtol=0)
    assert np.allclose(se3.log_so3(R), w, atol=1e-10, rtol=0)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-9, 1e-6, 1e-3, 0.0999, 0.1001, 1.0, np.pi - 0.0101,
                                   np.pi - 0.0099, np.pi - 1e-6, np.pi - 1e-9])
@pytest.mark.parametrize("axis", [[1, 0, 0], [0, 0, 1], [0.3, -0.5, 0.8], [-0.9, 0.1, -0.2]])
def test_so3_edge_angles(angle, axis):
    w = angle * np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    R = exp_so3(w)
    assert np.allclose(R, expm(se3.hat3(w)), atol=1e-14, rtol=0)
    assert se3.is_rigid(R_to_T(R), tol=1e-14)
    assert np.allclose(se3.log_so3(R), w, atol=1e-12, rtol=0)
    xi = np.concatenate([[1.0, -2.0, 0.5], w])
    assert np.allclose(se3.exp_se3(xi), expm(hat(xi)), atol=1e-13, rtol=0)
    # J_l^-1 grows like 1/(pi - angle) near pi, amplifying the rounding of p
    assert np.allclose(se3.log_se3(se3.exp_se3(xi)), xi, atol=1e-12 / (np.pi - angle), rtol=0)


@pytest.mark.parametrize("axis", [[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.3, -0.5, 0.8]])
def test_log_so3_at_pi(axis):
    w = np.pi * np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    R = exp_so3(w)
    w_back = se3.log_so3(R)
    assert np.isclose(np.linalg.norm(w_back), np.pi)
    assert np.allclose(np.abs(w_back), np.abs(w), atol=1e-7)
    assert np.allclose(exp_so3(w_back), R, atol=1e-12, rtol=0)


@pytest.mark.parametrize("angle", [0.05, 0.0999, 0.15])
def test_series_coefficients_match_closed_forms(angle, monkeypatch):
    monkeypatch.setattr(se3, "_SMALL_ANGLE", 1.0)
    series = se3._coefficients(angle)
    monkeypatch.setattr(se3, "_SMALL_ANGLE", 0.0)
    closed_form = se3._coefficients(angle)
    assert np.allclose(series, closed_form, rtol=1e-8, atol=0)


def R_to_T(R: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    return T


@SETTINGS
@given(_twist())
def test_adjoint_of_exp_matches_expm_of_curly_hat(xi):
    """exp(xi^curly) = Ad(exp(xi^)) (Barfoot eq. 7.50)."""
    A = se3.adjoint(se3.exp_se3(xi))
    assert np.allclose(A, expm(curly_hat(xi)), atol=1e-9, rtol=0)


@SETTINGS
@given(_pose(), _twist())
def test_adjoint_identity(T, xi):
    lhs = T @ se3.exp_se3(xi) @ se3.inverse(T)
    assert np.allclose(lhs, se3.exp_se3(se3.adjoint(T) @ xi), atol=1e-9, rtol=0)


@SETTINGS
@given(_twist(), st.tuples(*[st.floats(-50, 50)] * 3).map(np.array), st.floats(-2, 2))
def test_odot(xi, p, eta):
    s = np.append(p, 1.0)
    assert np.allclose(hat(xi) @ s, se3.odot(s) @ xi, atol=1e-12, rtol=0)
    assert np.array_equal(se3.odot(p), se3.odot(s))
    s_general = np.append(p, eta)
    assert np.allclose(hat(xi) @ s_general, se3.odot(s_general) @ xi, atol=1e-12, rtol=0)


def test_odot_batched():
    p = np.arange(15.0).reshape(5, 3)
    batched = se3.odot(p)
    assert batched.shape == (5, 4, 6)
    for i in range(5):
        assert np.array_equal(batched[i], se3.odot(p[i]))
    homogeneous = np.concatenate([p, np.ones((5, 1))], axis=1)
    assert np.array_equal(se3.odot(homogeneous), batched)


@SETTINGS
@given(_twist(), _twist())
def test_curly_hat_anticommutes(xi, eta):
    assert np.allclose(curly_hat(xi) @ eta, -curly_hat(eta) @ xi, atol=1e-12, rtol=0)
    # the curly hat is the Lie bracket: [xi^, eta^] = (xi^curly eta)^
    bracket = hat(xi) @ hat(eta) - hat(eta) @ hat(xi)
    assert np.allclose(bracket, hat(curly_hat(xi) @ eta), atol=1e-12, rtol=0)


@SETTINGS
@given(_twist(max_angle=3.0, max_translation=5.0))
def test_right_jacobian_se3_finite_differences(xi):
    T_inv = se3.inverse(se3.exp_se3(xi))
    numeric = numeric_jacobian(lambda x: se3.log_se3(T_inv @ se3.exp_se3(x)), xi)
    # log(exp(xi)^-1 exp(xi + d)) ~ J_r(xi) d
    assert np.allclose(se3.right_jacobian_se3(xi), numeric, atol=1e-6, rtol=0)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 0.0999, 0.1001, 0.5, 3.0])
def test_se3_jacobians_small_angles(angle):
    xi = np.array([0.4, -1.2, 2.0, *(angle * np.array([0.6, 0.0, -0.8]))])
    T_inv = se3.inverse(se3.exp_se3(xi))
    numeric = numeric_jacobian(lambda x: se3.log_se3(T_inv @ se3.exp_se3(x)), xi)
    assert np.allclose(se3.right_jacobian_se3(xi), numeric, atol=1e-8, rtol=0)
    numeric_left = numeric_jacobian(lambda x: se3.log_se3(se3.exp_se3(x) @ T_inv), xi)
    assert np.allclose(se3.left_jacobian_se3(xi), numeric_left, atol=1e-8, rtol=0)


@SETTINGS
@given(_rotvec(3.0))
def test_so3_jacobians_finite_differences(w):
    R_t = exp_so3(w).T
    right = numeric_jacobian(lambda x: se3.log_so3(R_t @ exp_so3(x)), w)
    left = numeric_jacobian(lambda x: se3.log_so3(exp_so3(x) @ R_t), w)
    assert np.allclose(right_jacobian_so3(w), right, atol=1e-7, rtol=0)
    assert np.allclose(se3.left_jacobian_so3(w), left, atol=1e-7, rtol=0)
    assert np.allclose(right_jacobian_so3(w), se3.left_jacobian_so3(w).T, atol=1e-14, rtol=0)


@SETTINGS
@given(_pose())
def test_inverse(T):
    assert np.allclose(se3.inverse(T) @ T, np.eye(4), atol=1e-12, rtol=0)
    assert np.allclose(se3.inverse(T), np.linalg.inv(T), atol=1e-10, rtol=0)


@SETTINGS
@given(st.lists(_pose(), min_size=1, max_size=5).map(np.stack))
def test_inverse_batched(Ts):
    inv = se3.inverse(Ts)
    assert inv.shape == Ts.shape
    assert np.allclose(inv @ Ts, np.eye(4), atol=1e-12, rtol=0)


@SETTINGS
@given(_pose())
def test_is_rigid(T):
    assert se3.is_rigid(T)
    scaled = T.copy()
    scaled[:3, :3] *= 1.01
    assert not se3.is_rigid(scaled)
    bad_row = T.copy()
    bad_row[3, 0] = 0.5
    assert not se3.is_rigid(bad_row)
    reflection = T.copy()
    reflection[:3, :3] = -reflection[:3, :3]
    assert not se3.is_rigid(reflection)
    nan = T.copy()
    nan[1, 3] = np.nan
    assert not se3.is_rigid(nan)
    assert not se3.is_rigid(T[:3])


@given(_rotvec(np.pi))
@settings(max_examples=200, deadline=None)
def test_quaternion_round_trip_and_against_scipy(w):
    """Shepperd's method (any angle up to pi, where qw -> 0) against scipy's Rotation, and back."""
    from scipy.spatial.transform import Rotation

    R = exp_so3(w)
    q = se3.quaternion_from_rotation(R)
    expected = Rotation.from_matrix(R).as_quat()
    expected *= 1.0 if expected[3] >= 0 else -1.0
    assert abs(np.linalg.norm(q) - 1.0) < 1e-12 and q[3] >= 0.0
    if q[3] > 1e-6:  # at qw = 0 both signs are the same rotation
        np.testing.assert_allclose(q, expected, atol=1e-12)
    np.testing.assert_allclose(se3.rotation_from_quaternion(q), R, atol=1e-12)


def test_quaternion_of_half_turns_and_batches():
    Rs = np.stack([np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])])
    q = se3.quaternion_from_rotation(Rs)
    np.testing.assert_allclose(np.abs(q), np.eye(4)[[3, 0, 1, 2]], atol=1e-15)
    np.testing.assert_allclose(se3.rotation_from_quaternion(q), Rs, atol=1e-15)
    assert se3.quaternion_from_rotation(Rs.reshape(2, 2, 3, 3)).shape == (2, 2, 4)


# ---------------------------------------------------------------- the jitable functions in compiled code


@numba.njit
def _hat3_jit(w):
    return se3.hat3(w)


@numba.njit
def _inverse_jit(T):
    return se3.inverse(T)


@numba.njit
def _adjoint_jit(T):
    return se3.adjoint(T)


@numba.njit
def _exp_se3_jit(xi):
    return se3.exp_se3(xi)


@numba.njit
def _exp_se3_and_left_jacobian_jit(xi):
    return se3.exp_se3_and_left_jacobian(xi)


@numba.njit
def _exp_se3_and_right_jacobian_jit(xi):
    return se3.exp_se3_and_right_jacobian(xi)


@numba.njit
def _left_jacobian_se3_jit(xi):
    return se3.left_jacobian_se3(xi)


@numba.njit
def _right_jacobian_se3_jit(xi):
    return se3.right_jacobian_se3(xi)


def _twist_at(angle: float) -> np.ndarray:
    return np.array([0.4, -1.2, 2.0, *(angle * np.array([0.6, 0.0, -0.8]))])


@pytest.mark.parametrize("angle", [1e-9, 0.05, 0.5, 3.1])  # below and above the series switch (0.1)
def test_jitable_functions_match_in_compiled_code(angle):
    """hat3, inverse, adjoint, exp_se3, exp_se3_and_left_jacobian, left_jacobian_se3 and
    right_jacobian_se3 give the same values called from numba-compiled code as from Python."""
    xi = _twist_at(angle)
    T = se3.exp_se3(xi)

    def same(compiled, python):
        assert compiled.shape == python.shape
        assert np.allclose(compiled, python, atol=1e-12, rtol=0)

    same(_hat3_jit(xi[3:]), se3.hat3(xi[3:]))
    same(_inverse_jit(T), se3.inverse(T))
    same(_adjoint_jit(T), se3.adjoint(T))
    same(_exp_se3_jit(xi), T)
    T_jit, J_jit = _exp_se3_and_left_jacobian_jit(xi)
    T_py, J_py = se3.exp_se3_and_left_jacobian(xi)
    same(T_jit, T_py)
    same(J_jit, J_py)
    same(_left_jacobian_se3_jit(xi), se3.left_jacobian_se3(xi))
    same(_right_jacobian_se3_jit(xi), se3.right_jacobian_se3(xi))
    T_jit, Jr_jit = _exp_se3_and_right_jacobian_jit(xi)
    same(T_jit, T)
    same(Jr_jit, se3.right_jacobian_se3(xi))


def test_compiled_loops_match_numpy_on_random_twists():
    """The scalar loops compiled code gets (hat3, inverse, adjoint, exp_se3, exp_se3_and_left_jacobian,
    exp_se3_and_right_jacobian, left/right_jacobian_se3) agree with the numpy versions Python runs to
    1e-12 on random twists, angles from 0 and 1e-12 (the series) through the switch at 0.1 to near pi."""
    rng = np.random.default_rng(25)
    angles = np.concatenate([[0.0, 1e-12, 1e-6, 0.0999999, 0.1, 0.1000001, 3.14], rng.uniform(0.0, 3.1, 40),
                             10.0 ** rng.uniform(-9, -1, 20)])
    for angle in angles:
        axis = rng.normal(size=3)
        xi = np.concatenate([rng.normal(scale=5.0, size=3), angle * axis / np.linalg.norm(axis)])
        T = se3.exp_se3(xi)
        T[:3, 3] += rng.normal(size=3)

        def same(compiled, python):
            assert compiled.shape == python.shape
            np.testing.assert_allclose(compiled, python, rtol=0, atol=1e-12)

        same(_hat3_jit(xi[3:]), se3.hat3(xi[3:]))
        same(_inverse_jit(T), se3.inverse(T))
        same(_adjoint_jit(T), se3.adjoint(T))
        same(_exp_se3_jit(xi), se3.exp_se3(xi))
        for compiled, python in zip(_exp_se3_and_left_jacobian_jit(xi), se3.exp_se3_and_left_jacobian(xi)):
            same(compiled, python)
        for compiled, python in zip(_exp_se3_and_right_jacobian_jit(xi), se3.exp_se3_and_right_jacobian(xi)):
            same(compiled, python)
        same(_left_jacobian_se3_jit(xi), se3.left_jacobian_se3(xi))
        same(_right_jacobian_se3_jit(xi), se3.right_jacobian_se3(xi))
        same(_right_jacobian_se3_jit(xi), se3.left_jacobian_se3(-xi))


def test_hat3_and_inverse_on_batches():
    """hat3 maps (..., 3) -> (..., 3, 3) and inverse (..., 4, 4) -> (..., 4, 4) element by element,
    from Python and from compiled code."""
    rng = np.random.default_rng(3)
    w = rng.normal(size=(2, 3, 3))
    W = se3.hat3(w)
    assert W.shape == (2, 3, 3, 3)
    for idx in np.ndindex(2, 3):
        assert np.array_equal(W[idx], se3.hat3(w[idx]))
        assert np.allclose(W[idx] @ np.array([1.0, -2.0, 0.5]), np.cross(w[idx], [1.0, -2.0, 0.5]),
                           atol=1e-14, rtol=0)
    assert np.allclose(_hat3_jit(w), W, atol=1e-12, rtol=0)
    assert np.allclose(_hat3_jit(w[0]), W[0], atol=1e-12, rtol=0)

    Ts = se3.exp_se3_batch(rng.normal(size=(6, 6))).reshape(2, 3, 4, 4)
    inv = se3.inverse(Ts)
    assert inv.shape == (2, 3, 4, 4)
    for idx in np.ndindex(2, 3):
        assert np.array_equal(inv[idx], se3.inverse(Ts[idx]))
        assert np.allclose(inv[idx] @ Ts[idx], np.eye(4), atol=1e-12, rtol=0)
    assert np.allclose(_inverse_jit(Ts), inv, atol=1e-12, rtol=0)
    assert np.allclose(_inverse_jit(Ts[0]), inv[0], atol=1e-12, rtol=0)
