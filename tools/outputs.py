"""Writing the files a vislam run produces (the trajectories' TUM text is ``backend.data.tum``, the pose
covariances' ``pose_covariance.npz`` ``backend.data.covariance``, beside its reader).

Every writer goes through :func:`~vislam.backend.data.files.atomic_write`: the data is written to a temporary file in
the target's directory and moved over the target only once it is complete, so an
interrupted or failed run never leaves a half-written file behind.

open3d is imported lazily (inside the PLY writers, :func:`import_open3d`) because importing it
takes over a second, and without its web viewer's dependencies, which vislam never uses.
"""

from __future__ import annotations

import json
import math
import os
import sys
import types
from dataclasses import asdict, is_dataclass
from typing import Any

import numpy as np

from ..backend.data.files import atomic_write
from ..backend.errors import VislamError

__all__ = [
    "write_map_npz",
    "write_map_ply",
    "uncertainty_colors",
    "write_trajectory_ply",
    "write_json",
]

# open3d's plotly/dash viewer (open3d.visualization.draw_plotly) imports these when open3d is imported
_WEB_VIEWER_MODULES = ("dash", "plotly", "plotly.graph_objects")


class _Unavailable:
    """Stands in for an object of a module vislam did not import; using it says so."""

    def __init__(self, name: str) -> None:
        self._name = name

    def __getattr__(self, attr: str) -> "_Unavailable":
        if attr.startswith("__"):
            raise AttributeError(attr)
        return _Unavailable(f"{self._name}.{attr}")

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        raise ImportError(f"{self._name}: not imported (vislam imports open3d without its plotly/dash web viewer)")


class _Placeholder(types.ModuleType):
    def __getattr__(self, attr: str) -> _Unavailable:
        if attr.startswith("__"):
            raise AttributeError(attr)
        return _Unavailable(f"{self.__name__}.{attr}")


def import_open3d() -> types.ModuleType:
    """``import open3d``, without importing dash and plotly.

    open3d (0.19, 0.20) imports its plotly/dash web viewer whenever it is imported; with dash 4
    that costs ~0.4 s and ~45 MB a process, for a viewer vislam never opens. While
    open3d is first imported, placeholders stand in for those modules (unless they are imported
    already), and they are removed from ``sys.modules`` right after, so a later ``import dash``
    gets the real package; only ``open3d.visualization.draw_plotly`` cannot be used in this process.
    """
    if "open3d" in sys.modules:
        return sys.modules["open3d"]
    placeholders = {name: _Placeholder(name) for name in _WEB_VIEWER_MODULES if name not in sys.modules}
    sys.modules.update(placeholders)
    try:
        import open3d
    finally:
        for name, module in placeholders.items():
            if sys.modules.get(name) is module:
                del sys.modules[name]
    return open3d


MAP_COLORMAP = "viridis"
TRAJECTORY_COLORMAP = "plasma"


# --------------------------------------------------------------------------------------
# landmark map
# --------------------------------------------------------------------------------------


def _check_map(positions: Any, covariances: Any) -> tuple[np.ndarray, np.ndarray]:
    pos = np.asarray(positions, dtype=float)
    cov = np.asarray(covariances, dtype=float)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"positions must have shape (K, 3), got {pos.shape}")
    if cov.shape != (pos.shape[0], 3, 3):
        raise ValueError(f"covariances must have shape ({pos.shape[0]}, 3, 3), got {cov.shape}")
    return pos, cov


def write_map_npz(path: str | os.PathLike, ids: Any, positions: Any, covariances: Any) -> None:
    """Save the landmark map as ``.npz`` with the keys ``ids`` (K,), ``positions`` (K, 3)
    and ``covariances`` (K, 3, 3) (world frame, metres / square metres)."""
    pos, cov = _check_map(positions, covariances)
    ids_arr = np.asarray(ids)
    if ids_arr.shape != (pos.shape[0],):
        raise ValueError(f"ids must have shape ({pos.shape[0]},), got {ids_arr.shape}")
    with atomic_write(path) as tmp:
        # A file object: np.savez would otherwise append ".npz" to a name not ending in it.
        with open(tmp, "wb") as fh:
            np.savez(fh, ids=ids_arr, positions=pos, covariances=cov)


def write_imu_states(path: str | os.PathLike, time_stamps: Any, velocity: Any, gyro_bias: Any, accel_bias: Any) -> None:
    """A real IMU's run: one line per step, ``t vx vy vz bgx bgy bgz bax bay baz`` (world velocity m/s,
    gyro bias rad/s, accelerometer bias m/s^2), with a header line; written atomically."""
    rows = np.column_stack([np.asarray(time_stamps, dtype=float), np.asarray(velocity, dtype=float),
                            np.asarray(gyro_bias, dtype=float), np.asarray(accel_bias, dtype=float)])
    with atomic_write(path) as tmp:
        np.savetxt(tmp, rows, fmt="%.9f", header="t vx vy vz bgx bgy bgz bax bay baz")


def uncertainty_colors(covariances: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Colours of landmarks by position uncertainty: returns ``(rgb (K,3), sigma (K,), u (K,))``.

    * ``sigma = sqrt(largest eigenvalue of the 3x3 position covariance)``: the standard
      deviation (metres) along the least certain direction.
    * ``u = clip((log10 sigma - log10 s5) / (log10 s95 - log10 s5), 0, 1)`` where ``s5`` and
      ``s95`` are the 5th and 95th percentiles of sigma over the map (``u = 0.5`` for all
      points when they are equal), so a few outliers do not wash out the scale.
    * ``rgb = viridis(u)``: dark blue/purple = most certain, green = middle, yellow = least
      certain. Viridis' green channel (and its brightness) increases monotonically with ``u``.
    """
    import matplotlib

    cov = np.asarray(covariances, dtype=float)
    if cov.ndim != 3 or cov.shape[1:] != (3, 3):
        raise ValueError(f"covariances must have shape (K, 3, 3), got {cov.shape}")
    if cov.shape[0] == 0:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0)
    sym = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    sigma = np.sqrt(np.clip(np.linalg.eigvalsh(sym)[:, -1], 0.0, None))
    log_s = np.log10(np.maximum(sigma, 1e-12))
    finite = np.isfinite(log_s)
    if finite.any():
        lo, hi = np.percentile(log_s[finite], [5.0, 95.0])
    else:
        lo = hi = 0.0
    if hi - lo > 1e-12:
        u = np.clip((log_s - lo) / (hi - lo), 0.0, 1.0)
    else:
        u = np.full(sigma.shape, 0.5)
    u = np.where(finite, u, 1.0)  # non-finite covariance: as uncertain as it gets
    rgb = matplotlib.colormaps[MAP_COLORMAP](u)[:, :3]
    return rgb, sigma, u


def write_map_ply(path: str | os.PathLike, positions: Any, covariances: Any) -> bool:
    """Save the landmark positions as a binary PLY point cloud coloured by uncertainty (open3d);
    returns False, writing nothing, for an empty map (a PLY cloud needs a point).

    The colour mapping is the one of :func:`uncertainty_colors`: sigma = square root of the
    largest covariance eigenvalue, on a log scale clipped to its 5th..95th percentile,
    through matplotlib's ``viridis`` (dark blue/purple = certain, yellow = uncertain).
    ``path`` should end in ``.ply`` (open3d picks the format by extension).
    """
    pos, cov = _check_map(positions, covariances)
    if len(pos) == 0:
        return False
    rgb, _, _ = uncertainty_colors(cov)
    with atomic_write(path) as tmp:
        o3d = import_open3d()

        cloud = o3d.geometry.PointCloud()
        cloud.points = o3d.utility.Vector3dVector(pos)
        cloud.colors = o3d.utility.Vector3dVector(rgb)
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            ok = o3d.io.write_point_cloud(str(tmp), cloud, write_ascii=False)
        if not ok:
            raise VislamError(f"{path}: open3d could not write the point cloud")
    return True


def write_trajectory_ply(
    path: str | os.PathLike, world_T_imu: Any, time_stamps: Any | None = None
) -> None:
    """Save the trajectory as a PLY line set (open3d ``LineSet``: the positions as vertices,
    consecutive ones joined by edges), coloured by time through matplotlib's ``plasma``:
    dark blue = start, yellow = end. Without ``time_stamps`` the pose index stands for time.
    With one pose (no line) the file holds just its vertex (a point cloud).
    ``world_T_imu`` is ``(N, 4, 4)`` (or ``(N, 3)`` positions), N >= 1.
    """
    import matplotlib

    arr = np.asarray(world_T_imu, dtype=float)
    if arr.ndim == 3 and arr.shape[1:] == (4, 4):
        pts = arr[:, :3, 3].copy()
    elif arr.ndim == 2 and arr.shape[1] == 3:
        pts = arr.copy()
    else:
        raise ValueError(f"world_T_imu must have shape (N, 4, 4) or (N, 3), got {arr.shape}")
    n = len(pts)
    if n == 0:
        raise ValueError("world_T_imu: no poses to write")
    if time_stamps is None:
        tt = np.arange(n, dtype=float)
    else:
        tt = np.asarray(time_stamps, dtype=float)
        if tt.shape != (n,):
            raise ValueError(f"time_stamps must have shape ({n},), got {tt.shape}")
    span = float(tt[-1] - tt[0])
    frac = (tt - tt[0]) / span if span > 0 else np.zeros(n)
    point_rgb = matplotlib.colormaps[TRAJECTORY_COLORMAP](np.clip(frac, 0, 1))[:, :3]
    edges = np.column_stack([np.arange(n - 1), np.arange(1, n)]) if n > 1 else np.zeros((0, 2))
    edge_rgb = 0.5 * (point_rgb[:-1] + point_rgb[1:]) if n > 1 else np.zeros((0, 3))

    o3d = import_open3d()
    with atomic_write(path) as tmp, o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        if n == 1:  # open3d writes no line set without lines: the vertex as a point cloud
            cloud = o3d.geometry.PointCloud()
            cloud.points = o3d.utility.Vector3dVector(pts)
            cloud.colors = o3d.utility.Vector3dVector(point_rgb)
            if not o3d.io.write_point_cloud(str(tmp), cloud, write_ascii=False):
                raise VislamError(f"{path}: open3d could not write the trajectory's vertex")
            return
        lines = o3d.geometry.LineSet()
        lines.points = o3d.utility.Vector3dVector(pts)
        lines.lines = o3d.utility.Vector2iVector(edges.astype(np.int32))
        lines.colors = o3d.utility.Vector3dVector(edge_rgb)
        ok = o3d.io.write_line_set(str(tmp), lines, write_ascii=False)
        if not ok:
            raise VislamError(f"{path}: open3d could not write the trajectory line set")


# --------------------------------------------------------------------------------------
# JSON
# --------------------------------------------------------------------------------------


def _jsonable(obj: Any) -> Any:
    """Plain-Python copy of ``obj``: numpy scalars/arrays -> numbers/lists, NaN/inf -> None."""
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, np.generic):
        obj = obj.item()
        if not isinstance(obj, (bool, int, float, str)):
            return str(obj)
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, int):
        return obj
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, dict):
        out = {}
        for key, value in obj.items():
            if isinstance(key, np.generic):
                key = key.item()
            if not isinstance(key, (str, int, float, bool)) and key is not None:
                key = str(key)
            out[key] = _jsonable(value)
        return out
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if hasattr(obj, "as_dict"):
        return _jsonable(obj.as_dict())
    if is_dataclass(obj) and not isinstance(obj, type):
        return _jsonable(asdict(obj))
    raise TypeError(f"cannot write an object of type {type(obj).__name__} as JSON")


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as JSON (indent 2, trailing newline). numpy scalars and arrays become
    plain numbers and lists, paths strings, objects with ``as_dict()`` and dataclasses
    dicts; NaN and +-inf become ``null`` (so the file is strict JSON)."""
    text = json.dumps(_jsonable(obj), indent=2, allow_nan=False) + "\n"
    with atomic_write(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
