"""The in-memory stereo-feature + IMU-velocity sequence, and its validation.

A :class:`Sequence` always holds ``imu_T_cam`` (camera -> IMU) and keeps the observations per step
in CSR form (``obs_ptr``/``obs_ids``/``obs_pixels``), never the dense (4,M,N) array of the file
format (``backend.data.npz`` reads and writes that). :func:`validate_sequence` and the ``check_*``
validators raise :class:`~vislam.backend.errors.InputError` with one line naming the source, the
key and what is wrong.

An optional ``tracker`` names what made the tracks: ``vislam track`` writes ``"vislam"``
(:data:`VISLAM_TRACKER`), ``vislam synth`` ``"synthetic"`` (:data:`SYNTHETIC_TRACKER`); course files
have none.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..errors import InputError
from ..geometry.se3 import inverse

if TYPE_CHECKING:
    from .inertial import ImuSamples

__all__ = [
    "Sequence",
    "validate_sequence",
    "LAYOUTS",
    "VISLAM_TRACKER",
    "SYNTHETIC_TRACKER",
]

#: Tolerance of max |R^T R - I| for the extrinsic of a Sequence made in memory (validate_sequence).
ORTHO_TOL = 1e-5
#: A rotation read from a file (nearest_rigid) off by more than ORTHO_EXACT is replaced by the
#: nearest rotation; with a note when off by more than ORTHO_SILENT (the rounding of single
#: precision; the real course files are off by 1e-8 .. 2e-7); refused beyond ORTHO_ACCEPT (a matrix
#: typed to 3-5 decimals, as calibration sheets print it, is off by 1e-5 .. 1e-3).
ORTHO_EXACT = 1e-12
ORTHO_SILENT = 1e-6
ORTHO_ACCEPT = 1e-3
#: Time stamps: a median step above this many seconds is not in seconds (nanoseconds, microseconds)
MAX_MEDIAN_STEP = 10.0
#: ... and no single step may span more (dead reckoning cannot bridge it).
MAX_STEP = 60.0

#: The two course layouts: (angular rate key, extrinsic key) of each
LAYOUTS = {
    "2022": ("angular_velocity", "imu_T_cam"),
    "2019": ("rotational_velocity", "cam_T_imu"),
}
#: ``tracker`` key of files written by vislam's own front end (frontend/) and by synth/
VISLAM_TRACKER = "vislam"
SYNTHETIC_TRACKER = "synthetic"


# ----------------------------------------------------------------------------------------------
# small helpers


def input_error(src: str, key: str, what: str) -> InputError:
    """An InputError with the one-line message ``<file>: key '<key>': <what>``."""
    msg = f"{src}: key '{key}': {what}"
    return InputError(" ".join(msg.split("\n")))


def format_number(x: float) -> str:
    return np.format_float_positional(float(x), precision=10, trim="-") if np.isfinite(x) else str(x)



def check_numeric(src: str, key: str, a: np.ndarray) -> np.ndarray:
    """``a`` as float64 after refusing object / non-numeric dtypes and NaN/inf."""
    a = np.asarray(a)
    if a.dtype.hasobject:
        raise input_error(src, key, "object dtype is not allowed")
    if a.dtype.kind not in "iuf":
        raise input_error(src, key, f"expected a numeric (int or float) array, got dtype {a.dtype}")
    a = a.astype(np.float64, copy=False)
    if a.size and not np.isfinite(a).all():
        idx = np.unravel_index(int(np.flatnonzero(~np.isfinite(a))[0]), a.shape)
        where = "[" + ", ".join(str(int(i)) for i in idx) + "]"
        raise input_error(src, key, f"non-finite value {a[idx]} at index {where}")
    return a


def check_shape(src: str, key: str, a: np.ndarray, expected: tuple, desc: str | None = None) -> None:
    if a.shape != expected:
        raise input_error(src, key, f"expected shape {desc or expected}, got {a.shape}")


def check_time_stamps(src: str, key: str, t: np.ndarray) -> None:
    """At least 2 stamps, strictly increasing, in seconds (median step <= MAX_MEDIAN_STEP), no step
    longer than MAX_STEP."""
    if t.shape[0] == 0:
        raise input_error(src, key, "empty sequence (N = 0 steps)")
    if t.shape[0] < 2:
        raise input_error(src, key, f"need at least 2 steps (one motion to estimate), got {t.shape[0]}")
    with np.errstate(over="ignore", invalid="ignore"):
        steps = np.diff(t)
    if not np.isfinite(steps).all():
        raise input_error(src, key, "time stamps of magnitudes near 1e308: their differences overflow")
    bad = np.flatnonzero(steps <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise input_error(
            src, key,
            f"time stamps not strictly increasing: [{i}] = {format_number(t[i])} <= [{i - 1}] = {format_number(t[i - 1])}",
        )
    median = float(np.median(steps))
    if median > MAX_MEDIAN_STEP:
        raise input_error(src, key, f"the median step is {median:.6g} s: not seconds (stamps in nanoseconds or "
                                    "microseconds? divide them by 1e9 or 1e6)")
    if steps.max() > MAX_STEP:
        i = int(np.argmax(steps)) + 1
        raise input_error(src, key, f"a gap of {steps[i - 1]:.6g} s between steps {i - 1} and {i}: dead reckoning "
                                    f"cannot bridge more than {MAX_STEP:g} s; split the sequence there")


def check_camera_matrix(src: str, key: str, K: np.ndarray) -> None:
    check_shape(src, key, K, (3, 3))
    if not np.isfinite(K).all():
        raise input_error(src, key, "K has non-finite entries")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise input_error(src, key, f"not a camera matrix: fx = {format_number(K[0, 0])}, fy = {format_number(K[1, 1])} must be > 0")
    if not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        raise input_error(src, key, f"not a camera matrix: last row must be [0, 0, 1], got {K[2].tolist()}")
    if K[1, 0] != 0:
        raise input_error(src, key, f"not a camera matrix: K[1,0] must be 0, got {format_number(K[1, 0])}")
    if abs(K[0, 1]) > 1e-6 * K[0, 0]:  # below, a thousandth of a pixel at the image edge: rounding
        raise input_error(src, key, f"skew K[0,1] = {format_number(K[0, 1])}: a rectified stereo pair has none "
                                    "(the stereo model has no skew term)")


def check_baseline(src: str, key: str, b: float) -> None:
    if not np.isfinite(b):
        raise input_error(src, key, f"baseline is not finite: {b}")
    if not b > 0:
        raise input_error(src, key, f"baseline must be > 0, got {format_number(b)}")


def check_rigid(src: str, key: str, T: np.ndarray, tol: float = ORTHO_TOL) -> float:
    """Refuse ``T`` unless it is a 4x4 rigid transform whose rotation is orthonormal to ``tol``;
    returns max |R^T R - I|."""
    check_shape(src, key, T, (4, 4))
    if not np.isfinite(T).all():
        raise input_error(src, key, "extrinsic has non-finite entries")
    if not np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise input_error(src, key, f"not a rigid transform: last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    R = T[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: inf or NaN, refused below
        det = float(np.linalg.det(R))
        dev = float(np.abs(R.T @ R - np.eye(3)).max())
    if not det > 0:
        raise input_error(src, key, f"not a rigid transform: det(R) = {det:.6g} (a reflection)")
    if not dev <= tol:
        raise input_error(src, key, f"not a rigid transform: max |R^T R - I| = {dev:.3g} > {tol:g}")
    return dev


def nearest_rigid(src: str, key: str, T: np.ndarray) -> tuple[np.ndarray, str | None]:
    """``T`` as read from a file, and a note or None: used as it is when its rotation is orthonormal
    to ORTHO_EXACT; up to ORTHO_ACCEPT replaced by the nearest rotation (R = U V^T of R's SVD), with
    a note saying so beyond ORTHO_SILENT; InputError with the deviation beyond ORTHO_ACCEPT."""
    dev = check_rigid(src, key, T, ORTHO_ACCEPT)
    if dev <= ORTHO_EXACT:
        return T, None
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = np.array(T, dtype=np.float64)
    out[:3, :3] = U @ Vt  # det > 0 was checked, so no reflection
    moved = float(np.abs(out[:3, :3] - T[:3, :3]).max())
    if dev <= ORTHO_SILENT:  # the rounding of a number stored in single precision: not worth a note
        return out, None
    return out, (f"{src}: key '{key}': rotation re-orthonormalized (max |R^T R - I| = {dev:.3g}; "
                 f"the nearest rotation moves no entry by more than {moved:.3g})")



# ----------------------------------------------------------------------------------------------
# the sequence


@dataclass(eq=False, repr=False)
class Sequence:
    """A stereo-feature + IMU sequence, observations stored per step (CSR), never dense M x N.

    The IMU is either body velocities per step (``linear_velocity``, ``angular_velocity``) or a
    real IMU's samples at their own rate (``imu``, :class:`~vislam.backend.data.inertial.ImuSamples`;
    the velocities are then None): an *inertial* sequence."""

    time_stamps: np.ndarray  # (N,) float64 seconds, strictly increasing
    linear_velocity: np.ndarray | None  # (N,3) m/s in the IMU frame; None in an inertial sequence
    angular_velocity: np.ndarray | None  # (N,3) rad/s in the IMU frame; None in an inertial sequence
    K: np.ndarray  # (3,3)
    baseline: float
    imu_T_cam: np.ndarray  # (4,4) maps camera-frame points into the IMU frame
    obs_ptr: np.ndarray  # (N+1,) int64; observations of step k are rows obs_ptr[k]:obs_ptr[k+1]
    obs_ids: np.ndarray  # (L,) int64 feature column j (landmark id), increasing within a step
    obs_pixels: np.ndarray  # (L,4) float64 uL vL uR vR
    num_features: int  # M of the file
    source: str = ""  # file path, for messages
    layout: str = "2022"  # "2022" (angular_velocity/imu_T_cam) or "2019" (rotational_velocity/cam_T_imu)
    dropped: dict[str, int] = field(default_factory=dict)  # {"nonpositive_disparity": n, "outside_image": n}
    tracker: str = ""  # the front end that made the tracks (optional key 'tracker'; "" unknown)
    imu: "ImuSamples | None" = None  # a real IMU's samples (an inertial sequence), else None
    notes: list[str] = field(default_factory=list, compare=False)  # what the reader corrected and how
    # The cam_T_imu read from a 2019-layout file, kept so that saving in that layout writes it back
    # bit for bit. Used only while rigid_inverse(it) still equals imu_T_cam exactly.
    _cam_T_imu_file: np.ndarray | None = field(default=None, repr=False, compare=False)

    # -- sizes ---------------------------------------------------------------------------------
    @property
    def inertial(self) -> bool:
        """A real IMU's samples (``imu``), not body velocities."""
        return self.imu is not None

    @property
    def num_steps(self) -> int:
        return int(self.time_stamps.shape[0])

    @property
    def num_observations(self) -> int:
        return int(self.obs_ids.shape[0])

    @property
    def cam_T_imu(self) -> np.ndarray:
        """(4,4) maps IMU-frame points into the camera frame (rigid inverse of ``imu_T_cam``)."""
        c = self._cam_T_imu_file
        if c is not None and np.array_equal(inverse(c), self.imu_T_cam):
            return c.copy()
        return inverse(np.asarray(self.imu_T_cam, dtype=np.float64))

    @classmethod
    def from_steps(cls, time_stamps, linear_velocity, angular_velocity, ids: list, pixels: list, K, baseline: float,
                   imu_T_cam, num_features: int | None = None, source: str = "", layout: str = "2022",
                   tracker: str = "", imu: "ImuSamples | None" = None) -> "Sequence":
        """A validated sequence from per-step lists of ids (n_k,) and pixels (n_k,4), and per-step
        time stamps and velocities (N,), (N,3), (N,3) (None for both with a real IMU's samples
        ``imu``); ``num_features`` defaults to the largest id + 1. Arrays of other shapes, or ids that
        are not integers, are refused (InputError)."""
        src = source or "<sequence>"
        if len(pixels) != len(ids):
            raise input_error(src, "obs_pixels", f"{len(pixels)} steps of pixels for {len(ids)} steps of ids")
        step_ids, step_pixels = [], []
        for k, (i, z) in enumerate(zip(ids, pixels)):
            i, z = np.asarray(i), np.asarray(z)
            if i.size == 0 and z.size == 0:  # a step without observations, in any empty shape
                i, z = np.zeros(0, np.int64), np.zeros((0, 4))
            if i.ndim != 1 or (i.size and i.dtype.kind not in "iu"):
                raise input_error(src, "obs_ids", f"step {k}: expected integer ids of shape (n,), got {i.dtype} {i.shape}")
            if z.shape != (i.size, 4):
                raise input_error(src, "obs_pixels", f"step {k}: expected shape ({i.size}, 4), got {z.shape}")
            step_ids.append(i.astype(np.int64))
            step_pixels.append(check_numeric(src, "obs_pixels", z))
        n = len(step_ids)
        ptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum([i.size for i in step_ids], out=ptr[1:])
        obs_ids = np.concatenate(step_ids) if n else np.zeros(0, np.int64)
        if num_features is None:
            num_features = int(obs_ids.max()) + 1 if obs_ids.size else 0
        seq = cls(
            time_stamps=np.array(time_stamps, dtype=np.float64),
            linear_velocity=None if linear_velocity is None else np.array(linear_velocity, dtype=np.float64),
            angular_velocity=None if angular_velocity is None else np.array(angular_velocity, dtype=np.float64),
            K=np.array(K, dtype=np.float64),
            baseline=float(baseline),
            imu_T_cam=np.array(imu_T_cam, dtype=np.float64),
            obs_ptr=ptr,
            obs_ids=obs_ids,
            obs_pixels=np.concatenate(step_pixels) if n else np.zeros((0, 4)),
            num_features=int(num_features),
            source=source,
            layout=layout,
            tracker=tracker,
            imu=imu,
        )
        validate_sequence(seq)
        return seq

    def steps(self):
        """(t, linear velocity (3,), angular velocity (3,), ids (n,), pixels (n,4)) of each step, in order
        (the velocities None in an inertial sequence)."""
        for k in range(self.num_steps):
            if self.imu is not None:
                yield (self.time_stamps[k], None, None, *self.observations(k))
            else:
                yield (self.time_stamps[k], self.linear_velocity[k], self.angular_velocity[k], *self.observations(k))

    # -- access --------------------------------------------------------------------------------
    def observations(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(ids (n,), pixels (n,4)) seen at step k: views into the CSR arrays, do not modify."""
        n = self.num_steps
        if not -n <= k < n:
            raise IndexError(f"step {k} out of range for a sequence of {n} steps")
        k = int(k) % n
        a, b = int(self.obs_ptr[k]), int(self.obs_ptr[k + 1])
        return self.obs_ids[a:b], self.obs_pixels[a:b]

    def subset(self, steps: slice | int) -> Sequence:
        """The steps selected by a slice (positive stride), or the first ``steps`` steps for an int."""
        src = self.source or "<sequence>"
        sl = slice(0, steps) if isinstance(steps, (int, np.integer)) else steps
        if not isinstance(sl, slice):
            raise TypeError(f"subset expects an int or a slice, got {type(steps).__name__}")
        if sl.step is not None and sl.step <= 0:
            raise input_error(src, "time_stamps", f"subset needs a positive stride, got {sl.step}")
        idx = np.arange(self.num_steps)[sl]
        if idx.size == 0:
            raise input_error(src, "time_stamps", f"subset {steps!r} selects no step of {self.num_steps}")
        starts = self.obs_ptr[idx]
        counts = self.obs_ptr[idx + 1] - starts
        ptr = np.zeros(idx.size + 1, dtype=np.int64)
        np.cumsum(counts, out=ptr[1:])
        rows = np.repeat(starts - ptr[:-1], counts) + np.arange(ptr[-1], dtype=np.int64)
        return dataclasses.replace(
            self,
            time_stamps=self.time_stamps[idx].copy(),
            linear_velocity=None if self.linear_velocity is None else self.linear_velocity[idx].copy(),
            angular_velocity=None if self.angular_velocity is None else self.angular_velocity[idx].copy(),
            obs_ptr=ptr,
            obs_ids=self.obs_ids[rows],
            obs_pixels=self.obs_pixels[rows],
            dropped=dict(self.dropped),
        )

    def dropped_text(self) -> str:
        """What the reader left out, in words: 'dropped 120 observations with a non-positive disparity
        (uL <= uR)'; '' when nothing was."""
        parts = [f"{n} observation{'s' * (n != 1)} {_DROPPED_WHY.get(key, key.replace('_', ' '))}"
                 for key, n in self.dropped.items() if n]
        return "dropped " + "; ".join(parts) if parts else ""

    def __repr__(self) -> str:
        imu = f", imu={self.imu.num_samples} samples" if self.imu is not None else ""
        return (
            f"Sequence(source={self.source!r}, layout={self.layout!r}, steps={self.num_steps}{imu}, "
            f"features={self.num_features}, observations={self.num_observations}, "
            f"dropped={self.dropped})"
        )


#: Why the reader drops an observation, by the key of ``Sequence.dropped``
_DROPPED_WHY = {"nonpositive_disparity": "with a non-positive disparity (uL <= uR: a point at or behind infinity)",
                "outside_image": "outside the image"}


def check_inertial(src: str, seq: Sequence, t: np.ndarray) -> None:
    """An inertial sequence: no velocities, valid IMU samples whose record covers the frames (to one
    sample interval at each end)."""
    from .inertial import check_imu_samples

    for key in ("linear_velocity", "angular_velocity"):
        if getattr(seq, key) is not None:
            raise input_error(src, key, "given with a real IMU's samples: keep one of the two IMU inputs")
    imu = seq.imu
    checked = check_imu_samples(src, imu.time_stamps, imu.linear_acceleration, imu.angular_velocity, imu.noise)
    for key, given, valid in (("imu_time_stamps", imu.time_stamps, checked.time_stamps),
                              ("imu_linear_acceleration", imu.linear_acceleration, checked.linear_acceleration),
                              ("imu_angular_velocity", imu.angular_velocity, checked.angular_velocity)):
        if not (isinstance(given, np.ndarray) and given.dtype == np.float64 and given.shape == valid.shape):
            raise input_error(src, key, f"an ImuSamples in memory holds float64 arrays of shape {valid.shape}, got "
                                        f"{type(given).__name__} {getattr(given, 'dtype', '')} {np.shape(given)} "
                                        "(vislam.backend.data.inertial.check_imu_samples makes them)")
    ti = imu.time_stamps
    step = float(np.median(np.diff(ti)))
    if ti[0] > t[0] + step or ti[-1] < t[-1] - step:
        raise input_error(src, "imu_time_stamps", f"the IMU record [{format_number(ti[0])}, {format_number(ti[-1])}] s "
                                                  f"does not cover the frames [{format_number(t[0])}, "
                                                  f"{format_number(t[-1])}] s: IMU and frame stamps must share a clock")


def validate_sequence(seq: Sequence) -> None:
    """Raise InputError (one line: source, field, problem) unless ``seq`` is consistent.

    Checks shapes, dtypes, finiteness, strictly increasing time, the camera matrix, a positive
    baseline, a rigid ``imu_T_cam`` and the CSR structure (``obs_ptr`` from 0 to L,
    non-decreasing; ids in [0, M) and strictly increasing within a step). Observation quality
    (disparity, image bounds) is *not* checked: :func:`load_sequence` filters that.
    """
    src = seq.source or "<sequence>"
    if seq.layout not in LAYOUTS:
        raise input_error(src, "layout", f"unknown layout {seq.layout!r}, expected '2022' or '2019'")
    t = check_numeric(src, "time_stamps", seq.time_stamps)
    if t.ndim != 1:
        raise input_error(src, "time_stamps", f"expected shape (N,), got {t.shape}")
    check_time_stamps(src, "time_stamps", t)
    n = t.shape[0]
    if seq.imu is None:
        for key in ("linear_velocity", "angular_velocity"):
            if getattr(seq, key) is None:
                raise input_error(src, key, "missing: a sequence needs IMU velocities or a real IMU's samples")
            check_shape(src, key, check_numeric(src, key, getattr(seq, key)), (n, 3), f"({n}, 3)")
    else:
        check_inertial(src, seq, t)
    check_camera_matrix(src, "K", check_numeric(src, "K", seq.K))
    check_baseline(src, "baseline", float(seq.baseline))
    check_rigid(src, "imu_T_cam", check_numeric(src, "imu_T_cam", seq.imu_T_cam))

    m = int(seq.num_features)
    if m < 0:
        raise input_error(src, "num_features", f"must be >= 0, got {m}")
    ptr, ids, pix = (np.asarray(a) for a in (seq.obs_ptr, seq.obs_ids, seq.obs_pixels))
    for key, a in (("obs_ptr", ptr), ("obs_ids", ids)):
        if a.dtype.kind not in "iu":
            raise input_error(src, key, f"expected an integer array, got dtype {a.dtype}")
    if ptr.shape != (n + 1,):
        raise input_error(src, "obs_ptr", f"expected shape ({n + 1},), got {ptr.shape}")
    if ids.ndim != 1:
        raise input_error(src, "obs_ids", f"expected shape (L,), got {ids.shape}")
    L = ids.shape[0]
    if ptr[0] != 0 or ptr[-1] != L or (np.diff(ptr) < 0).any():
        raise input_error(src, "obs_ptr", f"not a CSR pointer from 0 to L = {L}, non-decreasing")
    check_shape(src, "obs_pixels", check_numeric(src, "obs_pixels", pix), (L, 4), f"({L}, 4)")
    if L:
        if ids.min() < 0 or ids.max() >= m:
            raise input_error(src, "obs_ids", f"ids must lie in [0, {m}), got [{ids.min()}, {ids.max()}]")
        step_of = np.repeat(np.arange(n), np.diff(ptr))
        bad = np.flatnonzero((np.diff(ids) <= 0) & (step_of[1:] == step_of[:-1]))
        if bad.size:
            k = int(step_of[bad[0]])
            raise input_error(src, "obs_ids", f"ids not strictly increasing within step {k}")
