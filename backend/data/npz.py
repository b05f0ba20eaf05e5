"""The course .npz file format: streaming reader and writer of :class:`~vislam.backend.data.sequence.Sequence`.

Two course layouts exist (see ``shared/data/SOURCES.md``); both hold ``time_stamps`` (1,N),
``features`` (4,M,N) pixels ``uL vL uR vR`` with all four = -1 where landmark j is not seen at
step k, ``linear_velocity`` (3,N), ``K`` (3,3), ``b`` (baseline, metres) and

* 2022/23 layout: ``angular_velocity`` (3,N) and ``imu_T_cam`` (camera -> IMU),
* 2019/20 layout: ``rotational_velocity`` (3,N) and ``cam_T_imu`` (IMU -> camera).

The *inertial* layout has a real IMU's samples instead of the velocities: the frame keys
(``time_stamps``, ``features``, ``K``, ``b``, ``imu_T_cam`` or ``cam_T_imu``) plus
``imu_time_stamps`` (1,L) s, ``imu_linear_acceleration`` (3,L) m/s^2 (specific force in the IMU frame)
and ``imu_angular_velocity`` (3,L) rad/s, and optionally the four noise scalars named as in Kalibr
(``accelerometer_noise_density``, ``accelerometer_random_walk``, ``gyroscope_noise_density``,
``gyroscope_random_walk``; all four or none). A file with both the velocity keys and the inertial
keys is refused unless ``imu="velocity"`` or ``imu="inertial"`` picks one.

:func:`load_sequence` streams the ``features.npy`` member out of the zip in chunks of a few MB
(works for ``np.savez`` and ``np.savez_compressed``) and keeps the observations per step, so a
165 MB features array of 66k observations costs a few MB beyond the observations themselves.

Every unusable input raises :class:`~vislam.backend.errors.InputError` with one line naming the
file, the key and what is wrong. Bad *observations* are not fatal: they are dropped and counted in
``Sequence.dropped``:

* ``outside_image``: any of uL, vL, uR, vR is < 0 or >= the image size, including a partially
  -1 observation (some channels -1, not all). Takes precedence over the disparity test.
* ``nonpositive_disparity``: uL - uR <= 0 (a point at or beyond infinity, or a mismatch).

The optional key ``tracker`` (one string) names what made the tracks (``Sequence.tracker``).
The files carry no image size. Unless ``image_size=(width, height)`` is given it is inferred
from K as ``width = 2 cx * 1.25``, ``height = 2 cy * 1.25``; the 25 % margin is needed because the
principal point need not be centred (real files have observations beyond 2 cx).
"""

from __future__ import annotations

import os
import queue
import stat
import threading
import zipfile
import zlib
from pathlib import Path

import numpy as np
from numpy.lib import format as npformat

try:  # ISA-L's inflate and CRC-32 (a dependency; zlib's, 1.6x / 3x slower, where it is missing)
    from isal import isal_zlib as _inflate_lib
except ImportError:  # pragma: no cover - isal is installed with vislam
    _inflate_lib = zlib
_INFLATE_ERRORS = (zlib.error, _inflate_lib.error)
_READ_ERRORS = (zipfile.BadZipFile, *_INFLATE_ERRORS, EOFError, OSError)  # a damaged member of the zip

from ..errors import InputError
from ..geometry.se3 import inverse
from ..reading import describe_mode
from .files import atomic_write, check_output_file
from .inertial import KALIBR_KEYS, check_imu_samples, check_noise_densities
from .sequence import (LAYOUTS, ORTHO_ACCEPT, Sequence, check_baseline, check_camera_matrix, check_numeric, check_rigid,
                       check_shape, check_time_stamps, format_number, input_error, nearest_rigid, validate_sequence)

__all__ = ["load_sequence", "save_sequence", "IMAGE_MARGIN", "INERTIAL_KEYS", "IMU_INPUTS"]

#: Factor applied to 2*cx, 2*cy to infer the image size when none is given.
IMAGE_MARGIN = 1.25

#: Bytes of ``features`` data decoded at a time while streaming (tests shrink it).
_CHUNK_BYTES = 1 << 20

_COMMON_KEYS = ("time_stamps", "features", "linear_velocity", "K", "b")
#: The real IMU's samples of the inertial layout
INERTIAL_KEYS = ("imu_time_stamps", "imu_linear_acceleration", "imu_angular_velocity")
#: load_sequence's ``imu``: which IMU input of a file to read
IMU_INPUTS = ("auto", "velocity", "inertial")
#: The sparse layout of the observations, instead of ``features``: per step, CSR
_SPARSE_KEYS = ("obs_ptr", "obs_ids", "obs_pixels", "num_features")
#: The most feature tracks a file may declare (num_features of the sparse layout)
MAX_FEATURES = 2**31 - 1
#: save_sequence writes the sparse layout when the dense features array would exceed this
DENSE_LIMIT_BYTES = 256 * 2**20


# ----------------------------------------------------------------------------------------------
# loading


def _image_bounds(src: str, K: np.ndarray, image_size) -> tuple[float, float]:
    if image_size is None:
        cx, cy = float(K[0, 2]), float(K[1, 2])
        if not (cx > 0 and cy > 0):
            raise input_error(src, "K", f"cannot infer the image size from cx = {format_number(cx)}, cy = "
                                        f"{format_number(cy)}; set input.image_width and input.image_height")
        return 2.0 * cx * IMAGE_MARGIN, 2.0 * cy * IMAGE_MARGIN
    try:
        w, h = (float(x) for x in image_size)
    except (TypeError, ValueError):
        raise InputError(f"{src}: image_size must be (width, height), got {image_size!r}") from None
    if not (np.isfinite(w) and np.isfinite(h) and w > 0 and h > 0):
        raise InputError(f"{src}: image_size must be positive (width, height), got {image_size!r}")
    return w, h


def _read_exact(f, nbytes: int, src: str) -> bytes:
    buf = f.read(nbytes)
    if len(buf) != nbytes:
        raise input_error(src, "features", f"data truncated: expected {nbytes} more bytes, got {len(buf)}")
    return buf


def _first_nonfinite(src: str, a: np.ndarray, to_index) -> None:
    """Raise naming the first NaN/inf of the chunk ``a`` (flat); ``to_index(i)`` -> (c, j, k)."""
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        i = int(np.flatnonzero(~np.isfinite(a))[0])
        c, j, k = to_index(i)
        raise input_error(src, "features", f"non-finite value {a[i]} at [channel, feature, step] = [{c}, {j}, {k}]")


def _popcount(bits: np.ndarray) -> int:
    table = np.array([bin(i).count("1") for i in range(256)], dtype=np.int64)
    return int(table[bits].sum())


def _stream_c_order(f, src: str, dtype: np.dtype, m: int, n: int):
    """features (4,M,N) C-ordered: channel by channel, chunks of the flattened (M*N) plane.

    Returns (flat j*N+k positions with uL != -1 in increasing order, pixels (L,4), number of
    partial observations whose uL is -1 but another channel is not).
    """
    mn = m * n
    chunk = max(8, (_CHUNK_BYTES // dtype.itemsize) // 8 * 8)  # multiple of 8: packbits aligns
    starts = list(range(0, mn, chunk))
    pos_parts, val0_parts = [], []
    for s in starts:
        cnt = min(chunk, mn - s)
        a = np.frombuffer(_read_exact(f, cnt * dtype.itemsize, src), dtype=dtype)
        _first_nonfinite(src, a, lambda i, s=s: (0, (s + i) // n, (s + i) % n))
        nz = np.flatnonzero(a != -1)
        pos_parts.append(nz + s)
        val0_parts.append(a[nz].astype(np.float64))
    pos = np.concatenate(pos_parts) if pos_parts else np.zeros(0, np.int64)
    bounds = np.zeros(len(starts) + 1, dtype=np.int64)
    np.cumsum([len(p) for p in pos_parts], out=bounds[1:])
    del pos_parts
    pixels = np.empty((pos.shape[0], 4), dtype=np.float64)
    pixels[:, 0] = np.concatenate(val0_parts) if val0_parts else 0.0
    del val0_parts
    extra = np.zeros((mn + 7) // 8, dtype=np.uint8)  # partial: uL == -1, some other channel not
    for c in (1, 2, 3):
        for i, s in enumerate(starts):
            cnt = min(chunk, mn - s)
            a = np.frombuffer(_read_exact(f, cnt * dtype.itemsize, src), dtype=dtype)
            _first_nonfinite(src, a, lambda q, s=s, c=c: (c, (s + q) // n, (s + q) % n))
            local = pos[bounds[i]:bounds[i + 1]] - s
            pixels[bounds[i]:bounds[i + 1], c] = a[local]
            seen = a != -1
            seen[local] = False
            if seen.any():
                extra[s // 8: s // 8 + (cnt + 7) // 8] |= np.packbits(seen)
    return pos, pixels, _popcount(extra)


def _stream_f_order(f, src: str, dtype: np.dtype, m: int, n: int):
    """features (4,M,N) Fortran-ordered = (N,M,4) C-ordered: whole steps at a time.

    Returns (steps, ids, pixels (L,4)) of every (j,k) with any channel != -1, already step-major
    with ids increasing; partial observations are included (they fail the bounds test later).
    """
    row = m * 4
    per = max(1, _CHUNK_BYTES // max(1, row * dtype.itemsize))
    ks, js, px = [], [], []
    for k0 in range(0, n if m else 0, per):
        nk = min(per, n - k0)
        a = np.frombuffer(_read_exact(f, nk * row * dtype.itemsize, src), dtype=dtype)
        _first_nonfinite(src, a, lambda i, k0=k0: (i % 4, (i // 4) % m, k0 + i // row))
        a = a.reshape(nk, m, 4)
        kk, jj = np.nonzero((a != -1).any(axis=2))
        ks.append(kk + k0)
        js.append(jj)
        px.append(a[kk, jj].astype(np.float64))
    if not ks:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 4))
    return (np.concatenate(ks).astype(np.int64), np.concatenate(js).astype(np.int64),
            np.concatenate(px))


def _open_member(zf: zipfile.ZipFile, src: str, key: str, path: Path | None = None):
    """The member ``key`` (.npy) as a file object: with ``path``, a deflated member is inflated
    ahead by a second thread (:class:`_InflateAhead`); otherwise zipfile's own stream."""
    names = set(zf.namelist())
    for name in (key + ".npy", key):
        if name in names:
            info = zf.getinfo(name)
            if path is not None and info.compress_type == zipfile.ZIP_DEFLATED and not info.flag_bits & 0x1:
                return _InflateAhead(path, info)
            return zf.open(name)
    raise input_error(src, key, "missing")


class _InflateAhead:
    """A deflated zip member read as a file (``read(n)``), inflated by a background thread while the
    caller parses the previous chunk: zlib releases the GIL, so on two cores loading a course file
    takes the inflate time instead of inflate + CRC + parsing. The reader checks the member's CRC-32
    at its end (as zipfile does); at most ``_AHEAD`` chunks of ``_CHUNK_BYTES`` wait in memory. Inflate
    and CRC-32 are ISA-L's (``isal``) where installed (faster than zlib's; zlib is the fallback)."""

    _AHEAD = 4

    def __init__(self, path: Path, info: zipfile.ZipInfo) -> None:
        self._info = info
        self._queue: queue.Queue = queue.Queue(self._AHEAD)
        self._stop = threading.Event()
        self._pieces: list[bytes] = []
        self._have = 0
        self._crc = 0
        self._done = False
        self._thread = threading.Thread(target=self._inflate, args=(path,), daemon=True)
        self._thread.start()

    def _put(self, item) -> bool:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _inflate(self, path: Path) -> None:
        info = self._info
        try:
            with open(path, "rb") as fh:
                fh.seek(info.header_offset)
                header = fh.read(30)
                if len(header) != 30 or header[:4] != b"PK\x03\x04":
                    raise zipfile.BadZipFile(f"bad local header of member {info.filename!r}")
                fh.seek(int.from_bytes(header[26:28], "little") + int.from_bytes(header[28:30], "little"), os.SEEK_CUR)
                inflater = _inflate_lib.decompressobj(-15)
                left = info.compress_size
                while left or inflater.unconsumed_tail:
                    data = inflater.unconsumed_tail
                    if not data:
                        data = fh.read(min(left, 1 << 16))
                        if not data:
                            raise EOFError(f"member {info.filename!r} truncated")
                        left -= len(data)
                    out = inflater.decompress(data, _CHUNK_BYTES)
                    if out and not self._put(out):
                        return
                tail = inflater.flush()
                if tail and not self._put(tail):
                    return
        except Exception as exc:  # handed to the reader, which raises it
            self._put(exc)
            return
        self._put(None)

    def _next(self) -> bool:
        item = self._queue.get()
        if isinstance(item, Exception):
            self._done = True
            raise item
        if item is None:
            self._done = True
            if self._crc != self._info.CRC:
                raise zipfile.BadZipFile(f"Bad CRC-32 for file {self._info.filename!r}")
            return False
        self._crc = _inflate_lib.crc32(item, self._crc)
        self._pieces.append(item)
        self._have += len(item)
        return True

    def read(self, n: int = -1) -> bytes:
        while (n < 0 or self._have < n) and not self._done and self._next():
            pass
        data = b"".join(self._pieces)
        n = len(data) if n < 0 else min(n, len(data))
        rest = data[n:]
        self._pieces = [rest] if rest else []
        self._have = len(rest)
        return data[:n]

    def close(self) -> None:
        self._stop.set()
        self._thread.join()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _read_features(path: Path, src: str, n: int, image_wh: tuple[float, float]):
    """Stream 'features' into (steps, ids, pixels) kept, and the drop counts."""
    try:
        with zipfile.ZipFile(path) as zf, _open_member(zf, src, "features", path) as f:
            try:
                version = npformat.read_magic(f)
                if version == (1, 0):
                    shape, fortran, dtype = npformat.read_array_header_1_0(f)
                elif version in ((2, 0), (3, 0)):  # 3.0 = 2.0 with a UTF-8 header: the same for numeric dtypes
                    shape, fortran, dtype = npformat.read_array_header_2_0(f)
                else:
                    raise ValueError(f"unsupported .npy format version {version}")
            except Exception as e:  # numpy's header parser raises ValueError, TokenError, SyntaxError...
                raise input_error(src, "features", f"not a valid .npy member: {type(e).__name__}: {e}") from None
            if dtype.hasobject:
                raise input_error(src, "features", "object dtype is not allowed")
            if dtype.kind not in "iuf":
                raise input_error(src, "features", f"expected a numeric (int or float) array, got dtype {dtype}")
            if len(shape) != 3 or shape[0] != 4 or shape[2] != n:
                raise input_error(src, "features", f"expected shape (4, M, {n}) (N from 'time_stamps'), got {tuple(shape)}")
            m = int(shape[1])
            if fortran:
                steps, ids, pixels = _stream_f_order(f, src, dtype, m, n)
                partial_extra = 0
            else:
                pos, pixels, partial_extra = _stream_c_order(f, src, dtype, m, n)
                ids, steps = np.divmod(pos, n)
                order = np.argsort(steps, kind="stable")  # step-major, ids stay increasing
                steps, ids, pixels = steps[order], ids[order], pixels[order]
            if f.read(1):  # also makes zipfile check the CRC at the end of the member
                raise input_error(src, "features", "trailing data after the array")
    except _READ_ERRORS as e:
        raise input_error(src, "features", f"cannot read the member: {type(e).__name__}: {e}") from None

    keep, dropped = _keep_in_image(pixels, image_wh)
    dropped["outside_image"] += partial_extra
    return m, steps[keep], ids[keep], np.ascontiguousarray(pixels[keep]), dropped


def _keep_in_image(pixels: np.ndarray, image_wh: tuple[float, float]) -> tuple[np.ndarray, dict[str, int]]:
    """Observations inside the image with positive disparity, and the counts of the others."""
    w, h = image_wh
    u, v = pixels[:, 0::2], pixels[:, 1::2]
    outside = ((u < 0) | (u >= w) | (v < 0) | (v >= h)).any(axis=1)
    nonpos = ~outside & (pixels[:, 0] - pixels[:, 2] <= 0)
    return ~(outside | nonpos), {"nonpositive_disparity": int(nonpos.sum()), "outside_image": int(outside.sum())}


def open_npz(path: Path) -> "np.lib.npyio.NpzFile":
    """``np.load(path, allow_pickle=False)`` of a user's file, or an InputError naming it: missing,
    not a regular file, unreadable, not a zip archive, or a zip numpy cannot read."""
    src = str(path)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        dangling = " (a symbolic link to nothing)" if path.is_symlink() else ""
        raise InputError(f"{src}: file does not exist{dangling}") from None
    except OSError as exc:  # a loop of symbolic links, a permission on the way
        raise InputError(f"{src}: cannot read: {exc.strerror}") from None
    if not stat.S_ISREG(mode):
        raise InputError(f"{src}: not a regular file (is {describe_mode(mode)})")
    try:
        with open(path, "rb"):
            pass
    except OSError as exc:
        raise InputError(f"{src}: cannot read: {exc.strerror}") from None
    if not zipfile.is_zipfile(path):
        raise InputError(f"{src}: not an .npz (zip) file")
    try:
        return np.load(path, allow_pickle=False)
    except Exception as e:  # zipfile's and numpy's parsers raise many kinds (BadZipFile, ValueError, ...)
        raise InputError(f"{src}: cannot open as .npz: {e}".replace("\n", " ")) from None


def _imu_input(src: str, keys: set, imu: str) -> bool:
    """True when the file is read as inertial (module docstring): its keys and the caller's ``imu``."""
    if imu not in IMU_INPUTS:
        raise ValueError(f"imu must be one of {IMU_INPUTS}, got {imu!r}")
    inertial = bool(set(INERTIAL_KEYS) & keys)
    velocity = "linear_velocity" in keys or any(pair[0] in keys for pair in LAYOUTS.values())
    if imu == "auto" and inertial and velocity:
        raise input_error(src, INERTIAL_KEYS[0], "the file has both IMU velocities ('linear_velocity') and a real "
                                                 "IMU's samples: pick one (vislam run --imu velocity|inertial)")
    return imu == "inertial" or (imu == "auto" and inertial)


def load_sequence(path, *, image_size: tuple[float, float] | None = None, imu: str = "auto") -> Sequence:
    """Load a course .npz (either layout, velocities or a real IMU's samples) without materializing
    the dense features array.

    ``image_size=(width, height)`` bounds the pixels; if None it is inferred from K (see the
    module docstring). ``imu``: "velocity" or "inertial" reads that IMU input of a file that has
    both ("auto" refuses such a file). Raises InputError (one line: file, key, problem) for
    unusable input.
    """
    path = Path(path)
    src = str(path)
    npz = open_npz(path)
    with npz:
        keys = set(npz.files)
        have = sorted(keys)
        inertial = _imu_input(src, keys, imu)
        sparse = "features" not in keys and bool(set(_SPARSE_KEYS) & keys)  # then every sparse key is needed
        common = tuple(k for k in _COMMON_KEYS if k != "linear_velocity") + INERTIAL_KEYS if inertial else _COMMON_KEYS
        for key in common + (_SPARSE_KEYS if sparse else ()):
            if key not in keys and not (key == "features" and sparse):
                layout_of = " of the sparse layout" if key in _SPARSE_KEYS else ""
                raise input_error(src, key, f"missing{layout_of} (file has keys {have})")
        if inertial:
            complete = [lay for lay, pair in LAYOUTS.items() if pair[1] in keys]
            need = "need the extrinsic 'imu_T_cam' or 'cam_T_imu'"
        else:
            complete = [lay for lay, pair in LAYOUTS.items() if set(pair) <= keys]
            need = ("need 'angular_velocity'+'imu_T_cam' (2022/23 layout) "
                    "or 'rotational_velocity'+'cam_T_imu' (2019/20 layout)")
        if not complete:
            partial = [lay for lay, pair in LAYOUTS.items() if set(pair) & keys]
            lay = partial[0] if len(partial) == 1 else "2022"
            missing = LAYOUTS[lay][1] if inertial else [k for k in LAYOUTS[lay] if k not in keys][0]
            raise input_error(src, missing, f"missing; {need}; file has keys {have}")
        layout = complete[0]
        ang_key, ext_key = LAYOUTS[layout]
        notes: list[str] = []

        def get(key: str) -> np.ndarray:
            try:
                return check_numeric(src, key, npz[key])
            except (ValueError, *_READ_ERRORS) as e:  # object arrays refused by allow_pickle=False, bad headers
                raise input_error(src, key, f"cannot read: {type(e).__name__}: {e}") from None

        if len(complete) == 2:  # both layouts' keys: usable when they say the same
            _check_layouts_agree(src, get, velocities=not inertial)
            notes.append(f"{src}: both layouts' keys present and in agreement; read as the 2022/23 layout")

        t = get("time_stamps")
        if t.ndim == 2 and t.shape[0] == 1:
            t = t[0]
        if t.ndim != 1:
            raise input_error(src, "time_stamps", f"expected shape (N,) or (1, N), got {t.shape}")
        check_time_stamps(src, "time_stamps", t)
        n = t.shape[0]
        vel = {"linear_velocity": None, ang_key: None}
        samples = _read_imu_samples(src, get, keys) if inertial else None
        for key in () if inertial else ("linear_velocity", ang_key):
            a = get(key)
            check_shape(src, key, a, (3, n), f"(3, {n}) (N from 'time_stamps')")
            vel[key] = np.ascontiguousarray(a.T)
        K = get("K")
        check_camera_matrix(src, "K", K)
        b = get("b")
        if b.size != 1:
            raise input_error(src, "b", f"expected a scalar baseline, got shape {b.shape}")
        baseline = float(b.reshape(()))
        check_baseline(src, "b", baseline)
        ext, note = nearest_rigid(src, ext_key, get(ext_key))
        notes += [note] if note else []
        with np.errstate(over="ignore", invalid="ignore"):
            imu_T_cam = inverse(ext) if layout == "2019" else np.ascontiguousarray(ext)
        if not np.isfinite(imu_T_cam).all():
            raise input_error(src, ext_key, "translation too large: the inverse transform overflows")
        wh = _image_bounds(src, K, image_size)
        tracker = _read_tracker(src, npz) if "tracker" in keys else ""
        if sparse:
            m, steps, ids, pixels, dropped = _read_sparse(src, get, n, wh)

    if not sparse:
        m, steps, ids, pixels, dropped = _read_features(path, src, n, wh)
    ptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(steps, minlength=n), out=ptr[1:])

    cam_T_imu_file = np.ascontiguousarray(ext) if layout == "2019" else None
    seq = Sequence(
        time_stamps=np.ascontiguousarray(t),
        linear_velocity=vel["linear_velocity"],
        angular_velocity=vel[ang_key],
        K=np.ascontiguousarray(K),
        baseline=baseline,
        imu_T_cam=imu_T_cam,
        obs_ptr=ptr,
        obs_ids=ids.astype(np.int64, copy=False),
        obs_pixels=pixels,
        num_features=m,
        source=src,
        layout=layout,
        dropped=dropped,
        tracker=tracker,
        notes=notes,
        imu=samples,
        _cam_T_imu_file=cam_T_imu_file,
    )
    validate_sequence(seq)
    return seq


def _read_imu_samples(src: str, get, keys: set):
    """The inertial layout's IMU samples and, when all four Kalibr scalars are there, their noise."""
    noise = None
    present = [k for k in KALIBR_KEYS if k in keys]
    if present:
        noise = check_noise_densities(src, {k: get(k) for k in present})
    return check_imu_samples(src, *(get(k) for k in INERTIAL_KEYS), noise)


def _check_layouts_agree(src: str, get, velocities: bool = True) -> None:
    """A file with both layouts' keys is read when they agree (the same angular rates unless
    ``velocities`` is False, extrinsics that are each other's inverse); InputError naming the keys
    otherwise."""
    need = "keep one layout's keys ('angular_velocity'+'imu_T_cam' or 'rotational_velocity'+'cam_T_imu')"
    if velocities:
        a, r = get("angular_velocity"), get("rotational_velocity")
        if a.shape != r.shape or not np.allclose(a, r, rtol=0.0, atol=1e-9):
            raise input_error(src, "rotational_velocity", f"both layouts' keys present and 'angular_velocity' differs; "
                                                          f"{need}")
    imu_T_cam, cam_T_imu = get("imu_T_cam"), get("cam_T_imu")
    check_rigid(src, "imu_T_cam", imu_T_cam, ORTHO_ACCEPT)
    check_rigid(src, "cam_T_imu", cam_T_imu, ORTHO_ACCEPT)
    gap = float(np.abs(imu_T_cam @ cam_T_imu - np.eye(4)).max())
    if gap > 1e-6:
        raise input_error(src, "cam_T_imu", f"both layouts' keys present and the extrinsics are not each other's "
                                            f"inverse (max |imu_T_cam cam_T_imu - I| = {gap:.3g}); {need}")


def _read_sparse(src: str, get, n: int, image_wh: tuple[float, float]):
    """The observations of the sparse layout (``obs_ptr`` (N+1,), ``obs_ids`` (L,), ``obs_pixels``
    (L,4), ``num_features``), with the same drop counts as the dense one."""
    ptr, ids, pixels, m = (get(key) for key in _SPARSE_KEYS)  # float64, finite (check_numeric)
    if m.size != 1 or not (0 <= m.reshape(()) <= MAX_FEATURES) or m.reshape(()) != np.round(m.reshape(())):
        raise input_error(src, "num_features", f"expected one integer in [0, {MAX_FEATURES}], got "
                                               f"{m.reshape(-1)[:3].tolist()}")
    m = int(m.reshape(()))
    if ids.ndim != 1:
        raise input_error(src, "obs_ids", f"expected shape (L,), got {ids.shape}")
    if ids.size and not (np.array_equal(ids, np.round(ids)) and ids.min() >= 0 and ids.max() < m):
        raise input_error(src, "obs_ids", f"ids must be integers in [0, num_features = {m})")
    if ptr.shape != (n + 1,) or not np.array_equal(ptr, np.round(ptr)):
        raise input_error(src, "obs_ptr", f"expected ({n + 1},) integers (N from 'time_stamps'), got {ptr.shape}")
    if ptr[0] != 0 or ptr[-1] != ids.size or ptr.min() < 0 or ptr.max() > ids.size:  # bounded: no int64 wrap below
        raise input_error(src, "obs_ptr", f"not a CSR pointer from 0 to L = {ids.size}")
    counts = np.diff(ptr.astype(np.int64))
    if (counts < 0).any():
        raise input_error(src, "obs_ptr", "not non-decreasing")
    check_shape(src, "obs_pixels", pixels, (ids.size, 4), f"({ids.size}, 4)")
    steps = np.repeat(np.arange(n), counts)
    keep, dropped = _keep_in_image(pixels, image_wh)
    return m, steps[keep], ids.astype(np.int64)[keep], np.ascontiguousarray(pixels[keep], dtype=np.float64), dropped


def _read_tracker(src: str, npz) -> str:
    """The optional ``tracker`` key: one string."""
    try:
        a = npz["tracker"]
    except (ValueError, *_READ_ERRORS) as e:  # an object array, refused by allow_pickle=False; a damaged member
        raise input_error(src, "tracker", f"cannot read: {type(e).__name__}: {e}") from None
    if a.dtype.kind != "U" or a.size != 1:
        raise input_error(src, "tracker", f"expected one string, got dtype {a.dtype} and shape {a.shape}")
    return str(a.reshape(()))


# ----------------------------------------------------------------------------------------------
# saving


def save_sequence(seq: Sequence, path, *, layout: str | None = None, dense: bool | None = None) -> None:
    """Write ``seq`` in the course layout (features with -1 where not seen, ``b`` 0-d).

    ``layout`` "2022" writes ``angular_velocity`` + ``imu_T_cam``, "2019" writes
    ``rotational_velocity`` + ``cam_T_imu``; default: ``seq.layout``. The observations go in the
    course's dense (4,M,N) ``features`` array, or with ``dense`` False in the sparse layout
    (``obs_ptr``, ``obs_ids``, ``obs_pixels``, ``num_features``: per step, as in memory), which
    :func:`load_sequence` reads too; by default dense unless that array would exceed
    DENSE_LIMIT_BYTES (a long synthetic drive would need tens of GB). Written with
    ``np.savez_compressed`` to a temporary file in the target's directory, then moved onto
    ``path``: the target is either the old file or the complete new one (KeyboardInterrupt
    included). The exact name ``path`` is used (no ``.npz`` is appended). Dropped observations
    are not written. An inertial sequence writes the inertial layout (its IMU samples and noise
    instead of the velocities; ``layout`` then names only the extrinsic's key).
    """
    layout = seq.layout if layout is None else layout
    if layout not in LAYOUTS:
        raise InputError(f"{path}: layout must be '2022' or '2019', got {layout!r}")
    check_output_file(path)
    validate_sequence(seq)
    ang_key, ext_key = LAYOUTS[layout]
    n, m = seq.num_steps, int(seq.num_features)
    if dense is None:
        dense = 4 * m * n * 8 <= DENSE_LIMIT_BYTES
    if dense:
        features = np.full((4, m, n), -1.0, dtype=np.float64)
        steps = np.repeat(np.arange(n), np.diff(seq.obs_ptr))
        features[:, seq.obs_ids, steps] = np.asarray(seq.obs_pixels, dtype=np.float64).T
        observations = {"features": features}
    else:
        observations = {"obs_ptr": np.asarray(seq.obs_ptr, dtype=np.int64), "obs_ids": np.asarray(seq.obs_ids, np.int64),
                        "obs_pixels": np.asarray(seq.obs_pixels, dtype=np.float64),
                        "num_features": np.asarray(m, dtype=np.int64)}
    if seq.imu is not None:
        imu = seq.imu
        motion = {"imu_time_stamps": np.asarray(imu.time_stamps, dtype=np.float64).reshape(1, -1),
                  "imu_linear_acceleration": np.asarray(imu.linear_acceleration, dtype=np.float64).T,
                  "imu_angular_velocity": np.asarray(imu.angular_velocity, dtype=np.float64).T}
        if imu.noise is not None:
            motion.update({k: np.asarray(float(getattr(imu.noise, k))) for k in KALIBR_KEYS})
    else:
        motion = {"linear_velocity": np.asarray(seq.linear_velocity, dtype=np.float64).T,
                  ang_key: np.asarray(seq.angular_velocity, dtype=np.float64).T}
    arrays = {
        "time_stamps": np.asarray(seq.time_stamps, dtype=np.float64).reshape(1, n),
        **observations,
        **motion,
        "K": np.asarray(seq.K, dtype=np.float64),
        "b": np.asarray(float(seq.baseline), dtype=np.float64),
        ext_key: seq.cam_T_imu if layout == "2019" else np.asarray(seq.imu_T_cam, dtype=np.float64),
    }
    if seq.tracker:
        arrays["tracker"] = np.asarray(seq.tracker)

    with atomic_write(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)  # a file object: np.savez would append ".npz" to the name
