"""Closed-form SO(3)/SE(3) Lie-group maths (pure functions, float64).

Conventions (Barfoot, "State Estimation for Robotics", 2017, ch. 7):
a twist is ``xi = [rho, theta]`` (translation first, rotation second) and
``hat(xi) = [[theta^, rho], [0, 0]]``. Poses are 4x4 homogeneous matrices named
``a_T_b`` (maps points in frame b to frame a).

Every closed form switches to its Taylor series (to t^8) for rotation angles below
``_SMALL_ANGLE`` = 0.1: there the series is exact to ~1e-16 relative, and above it the
closed-form coefficients are accurate to ~1e-11 relative or better (the least accurate
ones multiply O(t^4) terms, so the matrices stay at machine precision).

The functions marked *jitable* are written in the subset of numpy that numba compiles
(``numba.extending.register_jitable``): Python calls them as they are, and the filter's compiled
kernels call the very same functions, so each operation is stated once. The others that compiled
kernels call (:func:`hat3`, :func:`inverse`, :func:`exp_se3`, :func:`exp_se3_and_left_jacobian`,
:func:`exp_se3_and_right_jacobian`, :func:`adjoint`, :func:`left_jacobian_se3`,
:func:`right_jacobian_se3`, the products) state the maths in numpy for Python and get scalar loops
in compiled code (``numba.extending.overload``), with the same operations in the same order
(tests/test_se3.py compares the two): numba compiles every array expression, slice assignment and
small helper again into each kernel calling it, which took predict_step's chain of helpers about
4.5 s of CPU to compile against about 2 s for the loops.
"""

from __future__ import annotations

import math

import numpy as np
from numba import types
from numba.extending import overload, register_jitable

_SMALL_ANGLE = 0.1
_NEAR_PI = 1e-2  # log_so3 reads the axis from the symmetric part when pi - angle < this
_I3 = np.eye(3)
_I3.setflags(write=False)


@register_jitable
def _coefficients(angle: float) -> tuple[float, float, float, float, float, float]:
    """Scalar coefficients (jitable) of the SO(3)/SE(3) series at rotation angle ``angle``.

    Returns (a, b, c, d, e, f):
      a = sin t / t,  b = (1 - cos t) / t^2,  c = (t - sin t) / t^3   (eqs. 7.14, 7.37)
      d = 1/t^2 - (1 + cos t) / (2 t sin t)                             (inverse J, 7.45)
      e = (t^2 + 2 cos t - 2) / (2 t^4),  f = (2t - 3 sin t + t cos t) / (2 t^5)  (Q, 7.86)
    """
    t = angle
    t2 = t * t
    if t < _SMALL_ANGLE:
        t4 = t2 * t2
        t6 = t4 * t2
        t8 = t4 * t4
        return (
            1.0 - t2 / 6.0 + t4 / 120.0 - t6 / 5040.0 + t8 / 362880.0,
            0.5 - t2 / 24.0 + t4 / 720.0 - t6 / 40320.0 + t8 / 3628800.0,
            1.0 / 6.0 - t2 / 120.0 + t4 / 5040.0 - t6 / 362880.0 + t8 / 39916800.0,
            1.0 / 12.0 + t2 / 720.0 + t4 / 30240.0 + t6 / 1209600.0 + t8 / 47900160.0,
            1.0 / 24.0 - t2 / 720.0 + t4 / 40320.0 - t6 / 3628800.0 + t8 / 479001600.0,
            1.0 / 120.0 - t2 / 2520.0 + t4 / 120960.0 - t6 / 9979200.0 + t8 / 1245404160.0,
        )
    s, c = math.sin(t), math.cos(t)
    return (
        s / t,
        (1.0 - c) / t2,
        (t - s) / (t2 * t),
        1.0 / t2 - 1.0 / (2.0 * t * math.tan(0.5 * t)),
        (t2 + 2.0 * c - 2.0) / (2.0 * t2 * t2),
        (2.0 * t - 3.0 * s + t * c) / (2.0 * t2 * t2 * t),
    )


# ---------------------------------------------------------------- small products


def small_matmul(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A @ B for the small matrices here (3x3, 6x6; B may be a vector). Python calls numpy's
    product; compiled code gets the loop nest below instead of a BLAS call per 3x3 product."""
    return A @ B


def small_matmul_into(A: np.ndarray, B: np.ndarray, out: np.ndarray) -> np.ndarray:
    """out = A @ B for small matrices (m,k) @ (k,n), in place (no allocation in a kernel's inner loop);
    returns ``out``. Python uses numpy's product; compiled code the loop nest of :func:`small_matmul`."""
    np.matmul(A, B, out=out)
    return out


def put_block(out: np.ndarray, row: int, col: int, block: np.ndarray) -> None:
    """out[row:row + m, col:col + n] = block (m,n), in place. Python uses numpy's slice assignment;
    compiled code gets a loop nest instead (numba's first 2-d slice assignment in a process costs
    about 3 s of compiling: measured on numba 0.60)."""
    out[row:row + block.shape[0], col:col + block.shape[1]] = block


@overload(put_block)
def _put_block_compiled(out, row, col, block):
    def put(out, row, col, block):
        for i in range(block.shape[0]):
            for j in range(block.shape[1]):
                out[row + i, col + j] = block[i, j]
    return put


@overload(small_matmul_into)
def _small_matmul_into_compiled(A, B, out):
    def product(A, B, out):
        for i in range(A.shape[0]):
            for j in range(B.shape[1]):
                out[i, j] = 0.0
            for k in range(A.shape[1]):
                a = A[i, k]
                for j in range(B.shape[1]):
                    out[i, j] += a * B[k, j]
        return out
    return product


@overload(small_matmul)
def _small_matmul_compiled(A, B):
    if B.ndim == 1:
        def product(A, B):
            out = np.zeros(A.shape[0])
            for i in range(A.shape[0]):
                for k in range(A.shape[1]):
                    out[i] += A[i, k] * B[k]
            return out
    else:
        def product(A, B):
            return small_matmul_into(A, B, np.empty((A.shape[0], B.shape[1])))
    return product


# ---------------------------------------------------------------- skew matrices


@register_jitable
def _norm3(w: np.ndarray) -> float:
    """Euclidean length of a 3-vector (jitable)."""
    return np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])


@register_jitable
def _hat3_any(w):
    """:func:`hat3` of any shape (..., 3) (jitable)."""
    w = np.asarray(w, dtype=np.float64)
    W = np.zeros(w.shape[:-1] + (3, 3))
    W[..., 0, 1] = -w[..., 2]
    W[..., 0, 2] = w[..., 1]
    W[..., 1, 0] = w[..., 2]
    W[..., 1, 2] = -w[..., 0]
    W[..., 2, 0] = -w[..., 1]
    W[..., 2, 1] = w[..., 0]
    return W


def hat3(w: np.ndarray) -> np.ndarray:
    """Skew matrix w^ with w^ v = w x v (Barfoot eq. 7.7); (..., 3) -> (..., 3, 3). Compiled code
    gets element assignments for one 3-vector (the ellipsis-indexed assignments of :func:`_hat3_any`
    compile numba's broadcasting machinery)."""
    return _hat3_any(w)


def _by_shape(arg, ndim: int, one, general):
    """An overload's implementation: ``one`` (element loops) for an array argument of ``ndim``
    dimensions, else ``general`` (the jitable any-shape version). numba takes either as the
    implementation only with the overloaded function's argument names, unannotated."""
    return one if isinstance(arg, types.Array) and arg.ndim == ndim else general


def _hat3_one(w):
    """:func:`hat3` of one 3-vector by element assignments (compiled code's)."""
    W = np.zeros((3, 3))
    W[0, 1] = -w[2]
    W[0, 2] = w[1]
    W[1, 0] = w[2]
    W[1, 2] = -w[0]
    W[2, 0] = -w[1]
    W[2, 1] = w[0]
    return W


@overload(hat3)
def _hat3_compiled(w):
    return _by_shape(w, 1, _hat3_one, _hat3_any)


def vee3(W: np.ndarray) -> np.ndarray:
    """Inverse of :func:`hat3`; (..., 3, 3) -> (..., 3)."""
    W = np.asarray(W, dtype=float)
    return np.stack([W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]], axis=-1)


# ---------------------------------------------------------------- SO(3)


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector of R, angle in [0, pi] (inverse of Barfoot eq. 7.14).

    The angle is atan2(|vee(R - R^T)|/2, (tr R - 1)/2), accurate over the whole range.
    Near pi the axis comes from the symmetric part (R + R^T)/2 - cos t I = (1 - cos t) a a^T,
    its sign from the skew part.
    """
    R = np.asarray(R, dtype=float)
    skew = vee3(R - R.T)  # = 2 sin(t) a
    s = 0.5 * float(np.linalg.norm(skew))
    c = 0.5 * (float(np.trace(R)) - 1.0)
    angle = float(np.arctan2(s, c))
    if np.pi - angle >= _NEAR_PI:
        a, *_ = _coefficients(angle)  # sin t / t
        return skew / (2.0 * a)
    B = 0.5 * (R + R.T) - c * np.eye(3)
    i = int(np.argmax(np.diag(B)))
    axis = B[:, i] / np.sqrt(B[i, i] * (1.0 - c))
    if axis @ skew < 0.0:
        axis = -axis
    return angle * axis


@register_jitable
def left_jacobian_so3(w: np.ndarray) -> np.ndarray:
    """J_l(w) = I + ((1-cos t)/t^2) w^ + ((t - sin t)/t^3) w^ w^ (Barfoot eq. 7.37) (jitable)."""
    return exp_so3_and_left_jacobian(w)[1]


def _inv_left_jacobian_so3(w: np.ndarray) -> np.ndarray:
    """J_l(w)^-1 = I - w^/2 + (1/t^2 - (1+cos t)/(2 t sin t)) w^ w^ (Barfoot eq. 7.45)."""
    _, _, _, d, *_ = _coefficients(_norm3(w))
    W = hat3(w)
    return _I3 - 0.5 * W + d * (W @ W)


# ---------------------------------------------------------------- SE(3)


def exp_so3_and_left_jacobian(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(exp(w^), J_l(w)) from one set of coefficients (Barfoot eqs. 7.14, 7.37). Python uses numpy's
    products; compiled code gets the scalar loop below (the array expressions took 4 s to compile in
    a kernel, the loop 0.5 s)."""
    w = np.asarray(w, dtype=np.float64)
    a, b, c, _, _, _ = _coefficients(_norm3(w))
    W = hat3(w)
    WW = W @ W
    return _I3 + a * W + b * WW, _I3 + b * W + c * WW


@overload(exp_so3_and_left_jacobian)
def _exp_so3_and_left_jacobian_compiled(w):
    def exp_and_jacobian(w):
        w0, w1, w2 = float(w[0]), float(w[1]), float(w[2])
        t2 = w0 * w0 + w1 * w1 + w2 * w2
        a, b, c, _, _, _ = _coefficients(np.sqrt(t2))
        wv = (w0, w1, w2)
        W = ((0.0, -w2, w1), (w2, 0.0, -w0), (-w1, w0, 0.0))
        E = np.empty((3, 3))
        J = np.empty((3, 3))
        for i in range(3):
            for j in range(3):
                ww = wv[i] * wv[j] - (t2 if i == j else 0.0)  # (w^)^2 = w w^T - |w|^2 I
                d = 1.0 if i == j else 0.0
                E[i, j] = d + a * W[i][j] + b * ww
                J[i, j] = d + b * W[i][j] + c * ww
        return E, J
    return exp_and_jacobian


def exp_se3_and_left_jacobian(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(exp(xi^), J_l(theta)): exp(xi^) = [[exp(theta^), J_l(theta) rho], [0, 1]] (Barfoot eq. 7.39)
    and the SO(3) left Jacobian it was built with; xi (6,) -> ((4,4), (3,3)). Compiled code gets
    :func:`_exp_se3_fill`."""
    xi = np.asarray(xi, dtype=np.float64)
    R, J = exp_so3_and_left_jacobian(xi[3:])
    T = np.eye(4)
    put_block(T, 0, 0, R)
    t = small_matmul(J, np.ascontiguousarray(xi[:3]))
    T[0, 3], T[1, 3], T[2, 3] = t[0], t[1], t[2]
    return T, J


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """exp(xi^) = [[exp(theta^), J_l(theta) rho], [0, 1]] (Barfoot eq. 7.39); xi (6,) -> (4,4).
    Compiled code gets :func:`_exp_se3_fill`."""
    return exp_se3_and_left_jacobian(xi)[0]


def exp_se3_and_right_jacobian(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(exp(xi^) (4,4), J_r(xi) (6,6)) of a twist xi (6,) (Barfoot eqs. 7.39, 7.87), from one set of
    coefficients in compiled code."""
    return exp_se3(xi), right_jacobian_se3(xi)


@register_jitable
def _exp_se3_fill(T: np.ndarray, J: np.ndarray, r0: float, r1: float, r2: float, w0: float, w1: float, w2: float,
                  t2: float, a: float, b: float, c: float) -> None:
    """T (4,4) <- exp(xi^) and J (3,3) <- J_l(theta) of xi = (r0, r1, r2, w0, w1, w2) by scalar loops
    (jitable), t2 = |theta|^2 and a, b, c of :func:`_coefficients`: exp(theta^) = I + a W + b W^2,
    J_l(theta) = I + b W + c W^2 (Barfoot eqs. 7.14, 7.37; W = theta^, W^2 = theta theta^T - t2 I),
    translation J_l(theta) rho (7.39)."""
    wv = (w0, w1, w2)
    W = ((0.0, -w2, w1), (w2, 0.0, -w0), (-w1, w0, 0.0))
    for i in range(3):
        for j in range(3):
            ww = wv[i] * wv[j] - (t2 if i == j else 0.0)
            d = 1.0 if i == j else 0.0
            T[i, j] = d + a * W[i][j] + b * ww
            J[i, j] = d + b * W[i][j] + c * ww
    for i in range(3):
        T[i, 3] = J[i, 0] * r0 + J[i, 1] * r1 + J[i, 2] * r2
        T[3, i] = 0.0
    T[3, 3] = 1.0


@register_jitable
def _exp_se3_pair(xi):
    """(exp(xi^) (4,4), J_l(phi) (3,3)) of a twist xi (6,) as scalar loops (:func:`_exp_se3_fill`)."""
    w0, w1, w2 = float(xi[3]), float(xi[4]), float(xi[5])
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    a, b, c, _, _, _ = _coefficients(np.sqrt(t2))
    T, J = np.empty((4, 4)), np.empty((3, 3))
    _exp_se3_fill(T, J, float(xi[0]), float(xi[1]), float(xi[2]), w0, w1, w2, t2, a, b, c)
    return T, J


@overload(exp_se3_and_left_jacobian)
def _exp_se3_and_left_jacobian_compiled(xi):
    return lambda xi: _exp_se3_pair(xi)


@overload(exp_se3)
def _exp_se3_compiled(xi):
    return lambda xi: _exp_se3_pair(xi)[0]


@overload(exp_se3_and_right_jacobian)
def _exp_se3_and_right_jacobian_compiled(xi):
    def exp_and_right(xi):
        r0, r1, r2 = float(xi[0]), float(xi[1]), float(xi[2])
        w0, w1, w2 = float(xi[3]), float(xi[4]), float(xi[5])
        t2 = w0 * w0 + w1 * w1 + w2 * w2
        a, b, c, _, e, f = _coefficients(np.sqrt(t2))
        T, Jl = np.empty((4, 4)), np.empty((3, 3))
        _exp_se3_fill(T, Jl, r0, r1, r2, w0, w1, w2, t2, a, b, c)
        J = np.zeros((6, 6))
        _left_jacobian_se3_into(J, -r0, -r1, -r2, -w0, -w1, -w2, t2, b, c, e, f)  # J_r(xi) = J_l(-xi)
        return T, J
    return exp_and_right


def exp_se3_batch(xi: np.ndarray) -> np.ndarray:
    """:func:`exp_se3` of many twists at once (Barfoot eqs. 7.14, 7.37, 7.39); (n, 6) -> (n, 4, 4).

    The coefficients a = sin t/t, b = (1-cos t)/t^2, c = (t-sin t)/t^3 use the same Taylor series
    below ``_SMALL_ANGLE`` as :func:`_coefficients`.
    """
    xi = np.asarray(xi, dtype=float).reshape(-1, 6)
    t = np.linalg.norm(xi[:, 3:], axis=1)
    t2 = t * t
    t4, t6, t8 = t2 * t2, t2 * t2 * t2, t2 * t2 * t2 * t2
    small = t < _SMALL_ANGLE
    ts = np.where(small, 1.0, t)  # no division by zero in the branch not taken
    s, co = np.sin(ts), np.cos(ts)
    a = np.where(small, 1.0 - t2 / 6.0 + t4 / 120.0 - t6 / 5040.0 + t8 / 362880.0, s / ts)
    b = np.where(small, 0.5 - t2 / 24.0 + t4 / 720.0 - t6 / 40320.0 + t8 / 3628800.0, (1.0 - co) / (ts * ts))
    c = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t4 / 5040.0 - t6 / 362880.0 + t8 / 39916800.0,
                 (ts - s) / (ts * ts * ts))
    W = hat3(xi[:, 3:])
    WW = W @ W
    eye = np.eye(3)
    out = np.zeros((xi.shape[0], 4, 4))
    out[:, :3, :3] = eye + a[:, None, None] * W + b[:, None, None] * WW
    J = eye + b[:, None, None] * W + c[:, None, None] * WW
    out[:, :3, 3] = np.einsum("nij,nj->ni", J, xi[:, :3])
    out[:, 3, 3] = 1.0
    return out


def log_se3(T: np.ndarray) -> np.ndarray:
    """[J_l(theta)^-1 p, theta] with theta = log_so3(R) (inverse of Barfoot eq. 7.39)."""
    T = np.asarray(T, dtype=float)
    theta = log_so3(T[:3, :3])
    return np.concatenate([_inv_left_jacobian_so3(theta) @ T[:3, 3], theta])


def adjoint(T: np.ndarray) -> np.ndarray:
    """Ad(T) = [[R, p^ R], [0, R]] (Barfoot eq. 7.48); (4,4) -> (6,6). Compiled code gets the
    scalar loop of :func:`_adjoint_compiled`."""
    T = np.asarray(T, dtype=np.float64)
    R = np.ascontiguousarray(T[:3, :3])
    A = np.zeros((6, 6))
    put_block(A, 0, 0, R)
    put_block(A, 3, 3, R)
    put_block(A, 0, 3, small_matmul(hat3(T[:3, 3]), R))
    return A


@overload(adjoint)
def _adjoint_compiled(T):
    def ad(T):
        p0, p1, p2 = float(T[0, 3]), float(T[1, 3]), float(T[2, 3])
        H = ((0.0, -p2, p1), (p2, 0.0, -p0), (-p1, p0, 0.0))  # p^
        A = np.zeros((6, 6))
        for i in range(3):
            for j in range(3):
                A[i, j] = T[i, j]
                A[3 + i, 3 + j] = T[i, j]
                A[i, 3 + j] = H[i][0] * T[0, j] + H[i][1] * T[1, j] + H[i][2] * T[2, j]
        return A
    return ad


def _q_matrix(xi: np.ndarray) -> np.ndarray:
    """Q(rho, theta), the upper-right block of the SE(3) left Jacobian (Barfoot eq. 7.86); (6,) -> (3,3)."""
    P, W = hat3(xi[:3]), hat3(xi[3:])
    _, _, c, _, e, f = _coefficients(_norm3(xi[3:]))
    WP, PW, WW = small_matmul(W, P), small_matmul(P, W), small_matmul(W, W)
    WPW = small_matmul(WP, W)
    return (
        0.5 * P
        + c * (WP + PW + WPW)
        + e * (small_matmul(WW, P) + small_matmul(PW, W) - 3.0 * WPW)
        + f * (small_matmul(WPW, W) + small_matmul(WW, PW))
    )


def left_jacobian_se3(xi: np.ndarray) -> np.ndarray:
    """J_l(xi) = [[J_l(theta), Q], [0, J_l(theta)]] (Barfoot eq. 7.85); (6,) -> (6,6). Compiled code
    gets :func:`_left_jacobian_se3_into`."""
    xi = np.asarray(xi, dtype=np.float64)
    J = np.zeros((6, 6))
    Jl = left_jacobian_so3(xi[3:])
    put_block(J, 0, 0, Jl)
    put_block(J, 3, 3, Jl)
    put_block(J, 0, 3, _q_matrix(xi))
    return J


def right_jacobian_se3(xi: np.ndarray) -> np.ndarray:
    """J_r(xi) = J_l(-xi), so exp((xi + d)^) ~ exp(xi^) exp((J_r(xi) d)^) (Barfoot eq. 7.87);
    (6,) -> (6,6). Compiled code gets :func:`_left_jacobian_se3_into` of -xi."""
    return left_jacobian_se3(-np.asarray(xi, dtype=np.float64))


@register_jitable
def _left_jacobian_se3_into(J: np.ndarray, r0: float, r1: float, r2: float, w0: float, w1: float, w2: float,
                            t2: float, b: float, c: float, e: float, f: float) -> None:
    """J (6,6) <- J_l(xi) of xi = (r0, r1, r2, w0, w1, w2), t2 = |theta|^2 and the coefficients b, c,
    e, f of :func:`_coefficients`, by loops over 3x3 blocks (jitable): J_l(theta) = I + b W + c W^2
    (Barfoot eq. 7.37) on the diagonal, Q = P/2 + c (WP + PW + WPW) + e (W^2 P + PW^2 - 3 WPW)
    + f (WPW^2 + W^2 PW) (7.86) above it, P = rho^, W = theta^; the lower-left block is left as is."""
    wv = (w0, w1, w2)
    Wt = ((0.0, -w2, w1), (w2, 0.0, -w0), (-w1, w0, 0.0))
    Pt = ((0.0, -r2, r1), (r2, 0.0, -r0), (-r1, r0, 0.0))
    M = np.empty((10, 3, 3))  # WP, PW, WW, WPW, WWP, PWW, WPWW, WWPW, P, W
    for i in range(3):
        for j in range(3):
            ww = wv[i] * wv[j] - (t2 if i == j else 0.0)
            d = 1.0 if i == j else 0.0
            v = d + b * Wt[i][j] + c * ww
            J[i, j] = v
            J[3 + i, 3 + j] = v
            M[8, i, j] = Pt[i][j]
            M[9, i, j] = Wt[i][j]
    left = (9, 8, 9, 0, 2, 1, 3, 2)
    right = (8, 9, 9, 9, 8, 9, 9, 1)
    for n in range(8):
        for i in range(3):
            for j in range(3):
                s = 0.0
                for k in range(3):
                    s += M[left[n], i, k] * M[right[n], k, j]
                M[n, i, j] = s
    for i in range(3):
        for j in range(3):
            J[i, 3 + j] = (0.5 * M[8, i, j] + c * (M[0, i, j] + M[1, i, j] + M[3, i, j])
                           + e * (M[4, i, j] + M[5, i, j] - 3.0 * M[3, i, j]) + f * (M[6, i, j] + M[7, i, j]))


@overload(left_jacobian_se3)
def _left_jacobian_se3_compiled(xi):
    def left(xi):
        w0, w1, w2 = float(xi[3]), float(xi[4]), float(xi[5])
        t2 = w0 * w0 + w1 * w1 + w2 * w2
        _, b, c, _, e, f = _coefficients(np.sqrt(t2))
        J = np.zeros((6, 6))
        _left_jacobian_se3_into(J, float(xi[0]), float(xi[1]), float(xi[2]), w0, w1, w2, t2, b, c, e, f)
        return J
    return left


@overload(right_jacobian_se3)
def _right_jacobian_se3_compiled(xi):
    def right(xi):
        w0, w1, w2 = -float(xi[3]), -float(xi[4]), -float(xi[5])
        t2 = w0 * w0 + w1 * w1 + w2 * w2
        _, b, c, _, e, f = _coefficients(np.sqrt(t2))
        J = np.zeros((6, 6))
        _left_jacobian_se3_into(J, -float(xi[0]), -float(xi[1]), -float(xi[2]), w0, w1, w2, t2, b, c, e, f)
        return J
    return right


@register_jitable
def _inverse_any(T):
    """:func:`inverse` of any shape (..., 4, 4) (jitable)."""
    T = np.asarray(T, dtype=np.float64)
    out = np.zeros(T.shape)
    for i in range(3):
        for j in range(3):
            out[..., i, j] = T[..., j, i]
        out[..., i, 3] = -(T[..., 0, i] * T[..., 0, 3] + T[..., 1, i] * T[..., 1, 3] + T[..., 2, i] * T[..., 2, 3])
    out[..., 3, 3] = 1.0
    return out


def inverse(T: np.ndarray) -> np.ndarray:
    """Rigid inverse [[R^T, -R^T p], [0, 1]]; (..., 4, 4) -> (..., 4, 4). Compiled code gets element
    assignments for one (4,4) pose."""
    return _inverse_any(T)


def _inverse_one(T):
    """:func:`inverse` of one (4,4) pose by element assignments (compiled code's)."""
    out = np.zeros((4, 4))
    for i in range(3):
        for j in range(3):
            out[i, j] = T[j, i]
        out[i, 3] = -(T[0, i] * T[0, 3] + T[1, i] * T[1, 3] + T[2, i] * T[2, 3])
    out[3, 3] = 1.0
    return out


@overload(inverse)
def _inverse_compiled(T):
    return _by_shape(T, 2, _inverse_one, _inverse_any)


def odot(s: np.ndarray) -> np.ndarray:
    """s^odot = [[eta I, -eps^], [0, 0]] for s = [eps; eta] (Barfoot eq. 7.42).

    ``hat(xi) @ s == odot(s) @ xi``. Accepts (..., 3) points (eta = 1) or (..., 4)
    homogeneous points; returns (..., 4, 6).
    """
    s = np.asarray(s, dtype=float)
    eps = s[..., :3]
    eta = s[..., 3] if s.shape[-1] == 4 else np.ones(s.shape[:-1])
    out = np.zeros(s.shape[:-1] + (4, 6))
    out[..., :3, :3] = eta[..., None, None] * np.eye(3)
    out[..., :3, 3:] = -hat3(eps)
    return out


def quaternion_from_rotation(R: np.ndarray) -> np.ndarray:
    """Unit quaternion [qx, qy, qz, qw] (scalar last, qw >= 0) of rotation matrices (..., 3, 3) ->
    (..., 4), by Shepperd's method: the largest of 4 qw^2, 4 qx^2, 4 qy^2, 4 qz^2 (from the trace and
    the diagonal) is taken directly and the others from the off-diagonal sums and differences, so
    no division is by a small number (Shepperd, J. Guidance and Control 1978)."""
    R = np.asarray(R, dtype=float)
    r = R.reshape(-1, 3, 3)
    d0, d1, d2 = r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]
    cand = np.stack([1.0 + d0 + d1 + d2, 1.0 + d0 - d1 - d2, 1.0 - d0 + d1 - d2, 1.0 - d0 - d1 + d2], axis=1)
    k = np.argmax(cand, axis=1)
    s = 2.0 * np.sqrt(np.maximum(cand[np.arange(r.shape[0]), k], 1e-300))  # 4 |q_k|
    a = (r[:, 2, 1] - r[:, 1, 2]) / s  # 4 qw qx / (4 |q_k|), and so on
    b = (r[:, 0, 2] - r[:, 2, 0]) / s
    c = (r[:, 1, 0] - r[:, 0, 1]) / s
    xy, xz, yz = (r[:, 0, 1] + r[:, 1, 0]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s, (r[:, 1, 2] + r[:, 2, 1]) / s
    big = 0.25 * s
    table = np.stack([
        np.stack([a, b, c, big], axis=1),  # k = 0: qw largest
        np.stack([big, xy, xz, a], axis=1),  # k = 1: qx largest
        np.stack([xy, big, yz, b], axis=1),  # k = 2: qy largest
        np.stack([xz, yz, big, c], axis=1),  # k = 3: qz largest
    ])
    q = table[k, np.arange(r.shape[0])]  # x, y, z, w
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1.0
    return q.reshape(R.shape[:-2] + (4,))


def rotation_from_quaternion(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of quaternions [qx, qy, qz, qw] (..., 4), normalized first."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    R[..., 0, 1] = 2.0 * (x * y - z * w)
    R[..., 0, 2] = 2.0 * (x * z + y * w)
    R[..., 1, 0] = 2.0 * (x * y + z * w)
    R[..., 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    R[..., 1, 2] = 2.0 * (y * z - x * w)
    R[..., 2, 0] = 2.0 * (x * z - y * w)
    R[..., 2, 1] = 2.0 * (y * z + x * w)
    R[..., 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return R


def is_rigid(T: np.ndarray, tol: float = 1e-5) -> bool:
    """True iff T is a finite 4x4 with last row [0,0,0,1], R^T R = I (to tol), det R > 0."""
    T = np.asarray(T)
    if T.shape != (4, 4) or not np.issubdtype(T.dtype, np.number) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3].astype(float)
    return bool(
        np.all(T[3] == [0.0, 0.0, 0.0, 1.0])
        and np.max(np.abs(R.T @ R - np.eye(3))) <= tol
        and np.linalg.det(R) > 0.0
    )
