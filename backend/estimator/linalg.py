"""BLAS/LAPACK for the compiled kernels: potrf, trsm, syrk, gemm called from numba code, no Python between.

Each call through scipy's Python wrappers adds 5-20 us of argument checking plus the Python glue
around it, comparable to the routine itself at the filter's sizes. Here the same routines are scipy's own (``scipy.linalg.cython_blas`` /
``cython_lapack``, the BLAS numpy and scipy ship), declared to numba as external symbols, so a
kernel calls them directly and stays cacheable: the symbol names, not the process-specific
addresses, are compiled in, and :func:`_register` binds them in every process before a cached
kernel is loaded (importing this module does it).

Layout: the filter keeps matrices C-ordered. A C-ordered (m, n) array is the Fortran-ordered
(n, m) transpose, so every routine below is called on transposes with the triangles swapped;
each docstring says what it computes in C-order terms. Scalars reach Fortran by pointer, through
small work arrays.
"""

from __future__ import annotations

import ctypes
import importlib.machinery
import importlib.util
import os
import sys

import numpy as np
from llvmlite import binding as _llvm
from numba import types
from numba.extending import get_cython_function_address

from ..compiled import jit

_BLAS = ("dsyrk", "dtrsm", "dgemm")
_LAPACK = ("dpotrf",)


def _cython_module(name: str):
    """scipy's ``scipy.linalg.<name>`` (cython_blas, cython_lapack) loaded from its own file, without
    ``scipy.linalg``'s package (its import, scipy's array-API layer with it, took 0.15-0.2 s of a run's
    start-up that needs four function pointers); None where that file is not found."""
    module = sys.modules.get(f"scipy.linalg.{name}")
    if module is not None:
        return module
    import scipy

    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        path = os.path.join(scipy.__path__[0], "linalg", name + suffix)
        if os.path.exists(path):
            loader = importlib.machinery.ExtensionFileLoader(f"scipy.linalg.{name}", path)
            module = importlib.util.module_from_spec(importlib.util.spec_from_loader(loader.name, loader))
            loader.exec_module(module)
            sys.modules[loader.name] = module  # the module scipy.linalg would import: later imports take it
            return module
    return None


def _cython_address(module_name: str, name: str) -> int:
    """The address of the cython-exported function ``name`` of scipy's ``module_name`` (its capsule in
    ``__pyx_capi__``, as ``numba.extending.get_cython_function_address`` reads it)."""
    module = _cython_module(module_name)
    if module is None:
        return get_cython_function_address(f"scipy.linalg.{module_name}", name)
    capsule = module.__pyx_capi__[name]
    return _capsule_pointer(capsule, _capsule_name(capsule))


_capsule_name = ctypes.PYFUNCTYPE(ctypes.c_char_p, ctypes.py_object)(("PyCapsule_GetName", ctypes.pythonapi))
_capsule_pointer = ctypes.PYFUNCTYPE(ctypes.c_void_p, ctypes.py_object, ctypes.c_char_p)(
    ("PyCapsule_GetPointer", ctypes.pythonapi))


def _register() -> None:
    for name in _BLAS:
        _llvm.add_symbol("vislam_" + name, _cython_address("cython_blas", name))
    for name in _LAPACK:
        _llvm.add_symbol("vislam_" + name, _cython_address("cython_lapack", name))


_register()
_p = types.voidptr
# Fortran signatures, every argument by pointer (scipy's cython wrappers take no hidden string lengths)
_dsyrk = types.ExternalFunction("vislam_dsyrk", types.void(_p, _p, _p, _p, _p, _p, _p, _p, _p, _p))
_dtrsm = types.ExternalFunction("vislam_dtrsm", types.void(_p, _p, _p, _p, _p, _p, _p, _p, _p, _p, _p))
_dgemm = types.ExternalFunction("vislam_dgemm", types.void(_p, _p, _p, _p, _p, _p, _p, _p, _p, _p, _p, _p, _p))
_dpotrf = types.ExternalFunction("vislam_dpotrf", types.void(_p, _p, _p, _p, _p))

_U, _L, _N, _T, _R = ord("U"), ord("L"), ord("N"), ord("T"), ord("R")  # ord() in a kernel compiles unicode code


@jit
def cholesky_upper_inplace(S):
    """S <- U with S = U^T U, on the upper triangle of the C-ordered square S (the lower triangle
    is left as it was); U^T is the lower Cholesky factor L (S = L L^T). LAPACK potrf on the
    Fortran view, whose lower triangle is our upper one. Returns potrf's info: 0, or > 0 when S
    is not positive definite."""
    n = S.shape[0]
    if n == 0:
        return 0
    ch = np.array([_L], dtype=np.uint8)
    ints = np.array([n, n, 0], dtype=np.int32)
    _dpotrf(ch.ctypes, ints[0:].ctypes, S.ctypes, ints[1:].ctypes, ints[2:].ctypes)
    return ints[2]


@jit
def solve_lower_inplace(U, B):
    """B <- L^-1 B for L = U^T (U from :func:`cholesky_upper_inplace`) and a C-ordered (n, k) B:
    BLAS trsm on the right of the Fortran view, B^T <- B^T L^-T."""
    n, k = B.shape
    if n == 0 or k == 0:
        return
    # Fortran sees B as B^T and U's upper triangle as the lower triangle of L: B^T <- B^T L^-T
    ch = np.array([_R, _L, _T, _N], dtype=np.uint8)  # side, uplo, transa, diag
    ints = np.array([k, n, n, k], dtype=np.int32)  # m, n of B^T; lda; ldb
    one = np.array([1.0])
    _dtrsm(ch[0:].ctypes, ch[1:].ctypes, ch[2:].ctypes, ch[3:].ctypes, ints[0:].ctypes, ints[1:].ctypes,
           one.ctypes, U.ctypes, ints[2:].ctypes, B.ctypes, ints[3:].ctypes)


@jit
def downdate_lower(P, A):
    """P <- P - A^T A on the lower triangle of the C-ordered symmetric (D, D) P (the upper triangle is
    left as it was), for a C-ordered (m, D) A: BLAS syrk on the Fortran views (P^T's upper triangle
    is P's lower; A's view is A^T, so trans = 'N')."""
    D = P.shape[0]
    m = A.shape[0]
    if m == 0:
        return
    ch = np.array([_U, _N], dtype=np.uint8)
    ints = np.array([D, m, D, D], dtype=np.int32)  # n, k, lda, ldc
    alpha_beta = np.array([-1.0, 1.0])
    _dsyrk(ch[0:].ctypes, ch[1:].ctypes, ints[0:].ctypes, ints[1:].ctypes, alpha_beta[0:].ctypes, A.ctypes,
           ints[2:].ctypes, alpha_beta[1:].ctypes, P.ctypes, ints[3:].ctypes)


@jit
def add_product_lower(P, Z, X):
    """P <- P + Z X^T for C-ordered (D, D) P and (D, w) Z, X whose product is symmetric (the
    prediction's F P F^T + G Q G^T - P): BLAS gemm straight into P, no temporary; only the lower
    triangle is to be trusted for exact symmetry (mirror it). In Fortran terms P^T += X Z^T."""
    D, w = Z.shape
    if D == 0 or w == 0:
        return
    # Fortran sees X and Z as X^T, Z^T (w, D; leading dimension w): op(A) = X is transa 'T', op(B) = Z^T 'N'
    ch = np.array([_T, _N], dtype=np.uint8)
    ints = np.array([D, D, w, D], dtype=np.int32)  # m, n, k of the product; ldc
    ld = np.array([w, w], dtype=np.int32)
    alpha_beta = np.array([1.0, 1.0])
    _dgemm(ch[0:].ctypes, ch[1:].ctypes, ints[0:].ctypes, ints[1:].ctypes, ints[2:].ctypes, alpha_beta[0:].ctypes,
           X.ctypes, ld[0:].ctypes, Z.ctypes, ld[1:].ctypes, alpha_beta[1:].ctypes, P.ctypes, ints[3:].ctypes)


# No warm-up here: no run calls these kernels from Python. Each is compiled into the kernels that call
# it (their caches hold its machine code), and loading it on its own at start-up cost a run time
# for nothing (``backend.compiled``).


@jit
def inverse3(H, out):
    """out = H^-1 of a 3x3 (adjugate); False when singular."""
    a, b, c = H[0, 0], H[0, 1], H[0, 2]
    d, e, f = H[1, 0], H[1, 1], H[1, 2]
    g, h, i = H[2, 0], H[2, 1], H[2, 2]
    A = e * i - f * h
    B = -(d * i - f * g)
    C = d * h - e * g
    det = a * A + b * B + c * C
    if det == 0.0 or not np.isfinite(det):
        return False
    inv = 1.0 / det
    out[0, 0], out[0, 1], out[0, 2] = A * inv, -(b * i - c * h) * inv, (b * f - c * e) * inv
    out[1, 0], out[1, 1], out[1, 2] = B * inv, (a * i - c * g) * inv, -(a * f - c * d) * inv
    out[2, 0], out[2, 1], out[2, 2] = C * inv, -(a * h - b * g) * inv, (a * e - b * d) * inv
    return True


@jit
def solve_small(A, b):
    """x with A x = b for a small square A (Gaussian elimination, partial pivoting); ok False when singular."""
    n = A.shape[0]
    M = A.copy()
    x = b.copy()
    for c in range(n):
        piv = c
        best = abs(M[c, c])
        for r in range(c + 1, n):
            if abs(M[r, c]) > best:
                best = abs(M[r, c])
                piv = r
        if not best > 0.0:
            return x, False
        if piv != c:
            for k in range(n):
                M[c, k], M[piv, k] = M[piv, k], M[c, k]
            x[c], x[piv] = x[piv], x[c]
        for r in range(c + 1, n):
            f = M[r, c] / M[c, c]
            if f != 0.0:
                for k in range(c, n):
                    M[r, k] -= f * M[c, k]
                x[r] -= f * x[c]
    for c in range(n - 1, -1, -1):
        s = x[c]
        for k in range(c + 1, n):
            s -= M[c, k] * x[k]
        x[c] = s / M[c, c]
    return x, True


@jit
def kth_smallest(x, m):
    """The (m+1)-th smallest of ``x`` (n,), m < n (Hoare's selection; ``x`` is reordered)."""
    lo, hi = 0, x.size - 1
    while lo < hi:
        pivot = x[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while x[i] < pivot:
                i += 1
            while x[j] > pivot:
                j -= 1
            if i <= j:
                x[i], x[j] = x[j], x[i]
                i += 1
                j -= 1
        if m <= j:
            hi = j
        elif m >= i:
            lo = i
        else:
            break
    return x[m]


@jit
def median_inplace(x):
    """The median of ``x`` (n,), n >= 1 (numpy's: the mean of the middle two for an even n); ``x`` is
    reordered."""
    n = x.size
    upper = kth_smallest(x, n // 2)
    if n % 2:
        return upper
    lower = x[0]
    for i in range(1, n // 2):  # after the selection x[:n//2] holds the smaller half: its largest
        if x[i] > lower:
            lower = x[i]
    return 0.5 * (lower + upper)
