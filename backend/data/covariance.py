"""A run's pose covariance, ``pose_covariance.npz``: writer and reader.

Two arrays, nothing else:

* ``time_stamps`` (N,) float64, seconds: the trajectory's stamps (those of ``trajectory.txt``);
* ``covariance`` (N,6,6) float64: per step, the covariance of the right perturbation
  ``world_T_imu = mu exp(xi^)``, ``xi = [rho (translation, m); phi (rotation, rad)]`` in the body
  frame (``VisualInertialEKF.pose_covariance``).

:func:`read_pose_covariance` never loads with pickle and refuses, with one line
``<file>: key '<key>': <what is wrong>`` (:class:`~vislam.backend.errors.InputError`), a missing key,
an object or non-numeric array, NaN/inf, a wrong shape, stamps not strictly increasing, a matrix
that is not symmetric (beyond :data:`SYMMETRY_TOL` of its largest entry) or not positive
semi-definite (an eigenvalue below ``-PSD_TOL`` times its largest entry).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from .files import atomic_write
from .npz import open_npz
from .sequence import check_numeric, format_number, input_error

__all__ = ["read_pose_covariance", "write_pose_covariance", "POSE_COVARIANCE_FILE", "TRAJECTORY_FILE"]

#: The file name a run writes beside ``trajectory.txt``
POSE_COVARIANCE_FILE = "pose_covariance.npz"
#: The trajectory file of a run whose covariance that is
TRAJECTORY_FILE = "trajectory.txt"
#: Largest |C - C^T| accepted, relative to the largest |C_ij| of the matrix (the filter's are symmetric
#: to rounding, ~1e-16)
SYMMETRY_TOL = 1e-9
#: Smallest eigenvalue accepted, as a share of the largest |C_ij| of the matrix (times -1)
PSD_TOL = 1e-9

_KEYS = ("time_stamps", "covariance")


def _checked(time_stamps: Any, covariance: Any) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(time_stamps, dtype=np.float64)
    cov = np.asarray(covariance, dtype=np.float64)
    if t.ndim != 1:
        raise ValueError(f"time_stamps must have shape (N,), got {t.shape}")
    if cov.shape != (t.shape[0], 6, 6):
        raise ValueError(f"covariance must have shape ({t.shape[0]}, 6, 6), got {cov.shape}")
    if not (np.isfinite(t).all() and np.isfinite(cov).all()):
        bad = np.flatnonzero(~(np.isfinite(t) & np.isfinite(cov).all(axis=(1, 2))))
        raise ValueError(f"non-finite time stamp or covariance at index {int(bad[0])}")
    return t, cov


def write_pose_covariance(path: str | os.PathLike, time_stamps: Any, covariance: Any) -> None:
    """Save the pose covariance of every step (module docstring), atomically.

    Parameters
    ----------
    path : the .npz to write (the exact name: no ``.npz`` is appended)
    time_stamps : (N,) array, seconds
    covariance : (N, 6, 6) array, of xi = [rho; phi] (m, rad)
    """
    t, cov = _checked(time_stamps, covariance)
    with atomic_write(path) as tmp:
        # A file object: np.savez would otherwise append ".npz" to a name not ending in it.
        with open(tmp, "wb") as fh:
            np.savez(fh, time_stamps=t, covariance=cov)


def _check_stamps(src: str, t: np.ndarray) -> None:
    if t.ndim != 1:
        raise input_error(src, "time_stamps", f"expected shape (N,), got {t.shape}")
    if t.shape[0] == 0:
        raise input_error(src, "time_stamps", "no time stamp (N = 0)")
    with np.errstate(over="ignore", invalid="ignore"):
        steps = np.diff(t)
    bad = np.flatnonzero(~(steps > 0))
    if bad.size:
        i = int(bad[0]) + 1
        raise input_error(src, "time_stamps", f"not strictly increasing: [{i}] = {format_number(t[i])} <= "
                                              f"[{i - 1}] = {format_number(t[i - 1])}")


def _check_covariances(src: str, cov: np.ndarray) -> None:
    """Symmetric and positive semi-definite, each relative to its largest entry (no overflow)."""
    scale = np.abs(cov).max(axis=(1, 2))
    unit = cov / np.where(scale > 0, scale, 1.0)[:, None, None]  # entries in [-1, 1]
    asym = np.abs(unit - np.swapaxes(unit, 1, 2)).max(axis=(1, 2))
    bad = np.flatnonzero(asym > SYMMETRY_TOL)
    if bad.size:
        k = int(bad[0])
        raise input_error(src, "covariance", f"matrix {k} is not symmetric: max |C - C^T| = "
                                             f"{asym[k] * scale[k]:.3g} (largest entry {scale[k]:.3g})")
    lowest = np.linalg.eigvalsh(0.5 * (unit + np.swapaxes(unit, 1, 2)))[:, 0]
    bad = np.flatnonzero(lowest < -PSD_TOL)
    if bad.size:
        k = int(bad[0])
        raise input_error(src, "covariance", f"matrix {k} is not positive semi-definite: eigenvalue "
                                             f"{lowest[k] * scale[k]:.3g} (largest entry {scale[k]:.3g})")


def read_pose_covariance(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a ``pose_covariance.npz`` (module docstring).

    Returns
    -------
    time_stamps : (N,) float64 array, seconds, strictly increasing
    covariance : (N, 6, 6) float64 array, symmetric positive semi-definite

    Raises :class:`InputError` with one line naming the file (and the key) for anything unusable.
    """
    path = Path(path)
    src = str(path)
    npz = open_npz(path)
    with npz:
        keys = set(npz.files)
        arrays = {}
        for key in _KEYS:
            if key not in keys:
                raise input_error(src, key, f"missing (file has keys {sorted(keys)})")
            try:
                arrays[key] = npz[key]
            except Exception as e:  # object arrays (no pickle), bad .npy headers, damaged or encrypted members
                raise input_error(src, key, f"cannot read: {type(e).__name__}: {e}") from None
    t = check_numeric(src, "time_stamps", arrays["time_stamps"])
    _check_stamps(src, t)
    cov = check_numeric(src, "covariance", arrays["covariance"])
    if cov.shape != (t.shape[0], 6, 6):
        raise input_error(src, "covariance", f"expected shape ({t.shape[0]}, 6, 6) (N from 'time_stamps'), "
                                             f"got {cov.shape}")
    _check_covariances(src, cov)
    return np.ascontiguousarray(t), np.ascontiguousarray(cov)
