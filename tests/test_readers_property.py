"""Property-based tests (hypothesis) of the backend's readers: random corruptions and edge values end
either in a clean one-line error naming the file (and the key at fault) or in a valid result, never
in an uncaught exception or a NaN/inf in the output.

Readers: the course .npz loader (``backend.data.npz.load_sequence``, dense and sparse layouts), the
TUM trajectory reader (``backend.data.tum.read_tum``), a run's pose covariances
(``backend.data.covariance.read_pose_covariance``), TOML configuration files
(``backend.config.Config.load`` / ``Config.from_values``) and ``--set TABLE.KEY=VALUE`` assignments
(``backend.options.parse_assignment``, ``tools.options.filter_config``).

Bugs the properties found are kept as plain regression tests at the end of each section.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import enum
import functools
import itertools
import math
import string
import subprocess
import sys
import tempfile
import tomllib
import typing
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.spatial.transform import Rotation

from helpers import assert_clean_input_error, named_key
from vislam.backend.config import Config
from vislam.backend.data.covariance import read_pose_covariance
from vislam.backend.data.npz import load_sequence, save_sequence
from vislam.backend.data.sequence import validate_sequence
from vislam.backend.data.tum import read_tum
from vislam.backend.errors import ConfigError, InputError
from vislam.backend.options import parse_assignment
from vislam.tools.options import filter_config

SETTINGS = {"deadline": None, "suppress_health_check": [HealthCheck.too_slow, HealthCheck.data_too_large]}


# ==============================================================================================
# .npz sequences
# ==============================================================================================

K_SYN = np.array([[500.0, 0.0, 320.0], [0.0, 510.0, 240.0], [0.0, 0.0, 1.0]])  # inferred image 800 x 600
W_SYN, H_SYN = 2 * 320 * 1.25, 2 * 240 * 1.25
LAYOUT_KEYS = {"2022": ("angular_velocity", "imu_T_cam"), "2019": ("rotational_velocity", "cam_T_imu")}
SPARSE_KEYS = ("obs_ptr", "obs_ids", "obs_pixels", "num_features")
KNOWN_KEYS = ("time_stamps", "features", "linear_velocity", "angular_velocity", "rotational_velocity", "K", "b",
              "imu_T_cam", "cam_T_imu", *SPARSE_KEYS, "tracker")
N_DEPENDENT = {"features", "linear_velocity", "angular_velocity", "rotational_velocity", "obs_ptr"}
EXTRINSIC_AND_RATES = {"angular_velocity", "imu_T_cam", "rotational_velocity", "cam_T_imu"}


def _rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    x = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * x + (1 - np.cos(angle)) * x @ x


def _rigid(R, p):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T


IMU_T_CAM = _rigid(_rot([1, 2, 3], 2.0), [1.5, 0.01, -0.65])
CAM_T_IMU = _rigid(IMU_T_CAM[:3, :3].T, -IMU_T_CAM[:3, :3].T @ IMU_T_CAM[:3, 3])


@functools.cache
def _base_arrays(layout: str, sparse: bool, n: int, m: int = 5) -> dict[str, np.ndarray]:
    """A valid course file's arrays: every observation inside the 800 x 600 image with disparity >= 1."""
    rng = np.random.default_rng(7 + n)
    seen = rng.random((m, n)) < 0.6
    uL, v, d = rng.uniform(100, 700, (m, n)), rng.uniform(10, 500, (m, n)), rng.uniform(1, 60, (m, n))
    F = np.full((4, m, n), -1.0)
    for c, val in enumerate((uL, v, uL - d, v)):
        F[c][seen] = val[seen]
    ang_key, ext_key = LAYOUT_KEYS[layout]
    arrays = {
        "time_stamps": (1.3e9 + 0.1 * np.arange(n) + rng.uniform(0, 0.01, n)).reshape(1, n),
        "linear_velocity": rng.normal(size=(3, n)),
        ang_key: rng.normal(scale=0.1, size=(3, n)),
        "K": K_SYN.copy(),
        "b": np.array(0.54),
        ext_key: IMU_T_CAM.copy() if layout == "2022" else CAM_T_IMU.copy(),
    }
    if sparse:
        ids = [np.flatnonzero(seen[:, k]) for k in range(n)]
        ptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum([i.size for i in ids], out=ptr[1:])
        arrays["obs_ptr"] = ptr
        arrays["obs_ids"] = np.concatenate(ids).astype(np.int64) if n else np.zeros(0, np.int64)
        arrays["obs_pixels"] = (np.concatenate([F[:, i, k].T for k, i in enumerate(ids)]) if n
                                else np.zeros((0, 4)))
        arrays["num_features"] = np.asarray(m, dtype=np.int64)
    else:
        arrays["features"] = F
    return arrays


def course_arrays(layout="2022", sparse=False, n=6):
    """A fresh copy of the base arrays (the cache keeps the originals)."""
    return {k: v.copy() for k, v in _base_arrays(layout, sparse, n).items()}


def _write(path: Path, arrays: dict, compressed: bool = True) -> Path:
    with open(path, "wb") as fh:  # a file object: np.savez would append ".npz" to other names
        (np.savez_compressed if compressed else np.savez)(fh, **arrays)
    return path


def assert_valid_sequence(seq, workdir: Path) -> None:
    """What a loaded sequence must be: valid, finite, and savable and loadable again unchanged."""
    validate_sequence(seq)
    for name in ("time_stamps", "linear_velocity", "angular_velocity", "K", "imu_T_cam", "obs_pixels"):
        a = getattr(seq, name)
        assert a.dtype == np.float64 and np.isfinite(a).all(), name
    assert math.isfinite(seq.baseline) and seq.baseline > 0
    assert seq.obs_ptr.dtype == np.int64 and seq.obs_ids.dtype == np.int64
    R = seq.imu_T_cam[:3, :3]
    assert np.abs(R.T @ R - np.eye(3)).max() <= 1e-5 and np.linalg.det(R) > 0
    again_path = workdir / "round-trip.npz"
    save_sequence(seq, again_path, dense=False)
    again = load_sequence(again_path)
    for name in ("time_stamps", "linear_velocity", "angular_velocity", "K", "obs_ptr", "obs_ids", "obs_pixels"):
        assert np.array_equal(getattr(again, name), getattr(seq, name)), name
    assert again.baseline == seq.baseline and again.num_features == seq.num_features
    np.testing.assert_allclose(again.imu_T_cam, seq.imu_T_cam, rtol=1e-12, atol=1e-12)


def allowed_keys(mutated: set[str], written: dict) -> set[str]:
    """Keys an error may name when ``mutated`` were changed: those, and the keys checked against them."""
    allowed = set(mutated)
    if "time_stamps" in mutated:
        allowed |= N_DEPENDENT
    if "obs_ids" in mutated:
        allowed |= {"obs_ptr", "obs_pixels"}
    if mutated & {"obs_ptr", "num_features"}:
        allowed |= {"obs_ids"}
    if mutated & EXTRINSIC_AND_RATES and EXTRINSIC_AND_RATES <= set(written):  # both layouts: checked together
        allowed |= EXTRINSIC_AND_RATES
    return allowed


def load_outcome(path: Path, mutated: set[str] | None, written: dict, image_size=None):
    """Load ``path``: (sequence, None) after checking it is valid, or (None, message) after checking the
    InputError is one line, names the file and, with ``mutated``, a key at fault. Any other exception
    propagates and fails the test."""
    try:
        seq = load_sequence(path, image_size=image_size)
    except InputError as e:
        msg = assert_clean_input_error(e, path)
        if mutated is not None:
            key = named_key(msg, path)
            if key in written:
                assert key in allowed_keys(mutated, written), f"names {key!r} after changing {sorted(mutated)}: {msg}"
            else:  # a key the file lacks: only as missing
                assert "missing" in msg, msg
        return None, msg
    assert_valid_sequence(seq, path.parent)
    return seq, None


# -- random arrays ---------------------------------------------------------------------------------

NATIVE_DTYPES = ["int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64", "float16", "float32",
                 "float64", "bool", "complex64", "complex128", "<U4", "|S4"]
FLOAT_SPECIALS = [np.nan, np.inf, -np.inf, 1e308, -1e308, 1e300, -1e300, -1.0, 0.0, -0.0, 5e-324, 1e-300, 0.5,
                  2.0**63, -(2.0**63), 1.7e18, 9007199254740993.0]


def _int_specials(arrays):
    L = arrays["obs_ids"].size if "obs_ids" in arrays else 0
    return [-1, 0, 1, -2**63, 2**63 - 1, 10**18, -10**18, 5, 6, L, L + 1]


@st.composite
def random_arrays(draw, shape=None):
    """A numeric, bool or string array (what np.savez stores without pickle) of a random or given shape,
    native or big-endian."""
    dtype = np.dtype(draw(st.sampled_from(NATIVE_DTYPES)))
    if shape is None:
        shape = draw(hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=6))
    a = draw(hnp.arrays(dtype, shape))
    if dtype.kind in "iufc" and dtype.itemsize > 1 and draw(st.booleans()):
        a = a.astype(dtype.newbyteorder(">"))
    return a


def _mutate(data, arrays: dict, key: str, op: str) -> None:
    """One damage ``op`` to ``arrays[key]``: drop, replace (any shape, or the same shape), astype to
    another native dtype, reshape, or NaN/inf/huge/negative values ("specials")."""
    x = arrays[key]
    if op == "drop":
        del arrays[key]
    elif op == "replace":
        arrays[key] = data.draw(random_arrays(), label="value")
    elif op == "replace-same-shape":
        arrays[key] = data.draw(random_arrays(shape=x.shape), label="value")
    elif op == "astype":
        dtype = data.draw(st.sampled_from(NATIVE_DTYPES), label="dtype")
        if np.iscomplexobj(x) and not np.issubdtype(np.dtype(dtype), np.complexfloating):
            x = x.real  # what the cast keeps, without numpy's ComplexWarning
        with np.errstate(all="ignore"):
            arrays[key] = x.astype(dtype)
    elif op == "reshape":
        arrays[key] = _reshaped(data.draw, x)
    else:
        arrays[key] = _with_specials(data.draw, x, arrays)


def _reshaped(draw, x: np.ndarray) -> np.ndarray:
    how = draw(st.sampled_from(["T", "add-axis", "flatten", "drop-last", "append", "swap-axes-0-last"]))
    if how == "T":
        return np.ascontiguousarray(x.T)
    if how == "add-axis":
        return x[None]
    if how == "flatten":
        return x.reshape(-1)
    if x.ndim == 0:
        return x.reshape(1)
    if how == "drop-last":
        return x[..., :-1]
    if how == "append":
        return np.concatenate([x, x[..., -1:]], axis=-1)
    return np.ascontiguousarray(np.moveaxis(x, 0, -1))


def _with_specials(draw, x: np.ndarray, arrays) -> np.ndarray:
    """``x`` with special values at 1-4 random positions: floats (NaN, inf, huge, negative, subnormal...)
    after a conversion to float64, or, for an integer array, integers out of range."""
    if x.dtype.kind in "iu" and draw(st.booleans()):
        y = x.astype(np.int64)
        values = st.sampled_from(_int_specials(arrays))
    else:
        with np.errstate(all="ignore"):
            y = np.array(x.real if np.iscomplexobj(x) else x, dtype=np.float64)
        values = st.sampled_from(FLOAT_SPECIALS)
    if y.size:
        for pos in draw(st.lists(st.integers(0, y.size - 1), min_size=1, max_size=4)):
            y.flat[pos] = draw(values)
    return y


# -- structural corruption -------------------------------------------------------------------------

@settings(max_examples=150, **SETTINGS)
@given(data=st.data(), layout=st.sampled_from(["2022", "2019"]), sparse=st.booleans(), compressed=st.booleans())
def test_npz_structural_corruption_property(data, layout, sparse, compressed):
    """1-3 random changes of the arrays dict before saving (drop a key, add an unknown or a known key,
    replace a key's value by a random array of any shape and dtype, convert its dtype, reshape it, put
    NaN/inf/huge/negative values into it): the loader gives a valid, finite, savable sequence or a
    one-line InputError naming the file and a key at fault (a changed one, one checked against it, or
    one missing)."""
    arrays = course_arrays(layout, sparse)
    mutated: set[str] = set()
    for _ in range(data.draw(st.integers(1, 3), label="changes")):
        op = data.draw(st.sampled_from(["drop", "add-unknown", "add-known", "replace", "replace-same-shape",
                                        "astype", "reshape", "specials"]), label="op")
        if op == "add-unknown":
            name = data.draw(st.from_regex(r"[a-z][a-z0-9_]{0,10}", fullmatch=True)
                             .filter(lambda s: s not in KNOWN_KEYS), label="new key")
            arrays[name] = data.draw(random_arrays(), label="value")
            continue
        if op == "add-known":
            absent = [k for k in KNOWN_KEYS if k not in arrays]
            key = data.draw(st.sampled_from(absent), label="key")
            arrays[key] = data.draw(random_arrays(), label="value")
            mutated.add(key)
            continue
        if not arrays:
            continue
        key = data.draw(st.sampled_from(sorted(arrays)), label="key")
        mutated.add(key)
        x = arrays[key]
        if x.dtype.kind in "US" and op in ("astype", "specials"):  # strings (an earlier change) hold no numbers
            op = "replace"
        _mutate(data, arrays, key, op)
    with tempfile.TemporaryDirectory() as d:
        path = _write(Path(d) / "corrupt.npz", arrays, compressed)
        load_outcome(path, mutated, arrays)


@settings(max_examples=80, **SETTINGS)
@given(data=st.data(), layout=st.sampled_from(["2022", "2019"]), sparse=st.booleans())
def test_npz_special_values_in_one_key_property(data, layout, sparse):
    """NaN/inf/huge/negative/subnormal values (or out-of-range integers) at random positions of one key:
    a NaN or inf in any key the layout reads is refused naming that key; finite values give a valid
    sequence or a one-line InputError naming that key or one checked against it."""
    arrays = course_arrays(layout, sparse)
    key = data.draw(st.sampled_from(sorted(arrays)), label="key")
    arrays[key] = _with_specials(data.draw, arrays[key], arrays)
    nonfinite = arrays[key].dtype.kind == "f" and not np.isfinite(arrays[key]).all()
    with tempfile.TemporaryDirectory() as d:
        path = _write(Path(d) / "specials.npz", arrays)
        seq, msg = load_outcome(path, {key}, arrays)
    if nonfinite:
        assert seq is None and named_key(msg, path) == key, msg


@settings(max_examples=60, **SETTINGS)
@given(layout=st.sampled_from(["2022", "2019"]), sparse=st.booleans(),
       extra=st.dictionaries(st.from_regex(r"[a-z][a-z0-9_]{0,10}", fullmatch=True)
                             .filter(lambda s: s not in KNOWN_KEYS), random_arrays(), min_size=1, max_size=3))
def test_npz_unknown_keys_are_ignored_property(layout, sparse, extra):
    """Keys the loader does not know, of any shape and dtype, change nothing: the same sequence as
    without them."""
    arrays = course_arrays(layout, sparse)
    with tempfile.TemporaryDirectory() as d:
        plain = load_sequence(_write(Path(d) / "plain.npz", arrays))
        seq, msg = load_outcome(_write(Path(d) / "extra.npz", {**arrays, **extra}), set(), arrays)
    assert msg is None, msg
    for name in ("time_stamps", "linear_velocity", "angular_velocity", "K", "imu_T_cam", "obs_ptr", "obs_ids",
                 "obs_pixels"):
        assert np.array_equal(getattr(seq, name), getattr(plain, name)), name
    assert seq.num_features == plain.num_features and seq.dropped == plain.dropped and seq.layout == layout


@settings(max_examples=40, **SETTINGS)
@given(layout=st.sampled_from(["2022", "2019"]), sparse=st.booleans(), data=st.data())
def test_npz_missing_key_is_named_property(layout, sparse, data):
    """Dropping one key the layout needs: a one-line InputError saying it is missing and naming it."""
    arrays = course_arrays(layout, sparse)
    key = data.draw(st.sampled_from(sorted(arrays)), label="key")
    del arrays[key]
    with tempfile.TemporaryDirectory() as d:
        path = _write(Path(d) / "missing.npz", arrays)
        with pytest.raises(InputError) as e:
            load_sequence(path)
    msg = assert_clean_input_error(e.value, path)
    assert "missing" in msg and named_key(msg, path) == key, msg


# -- time stamps -----------------------------------------------------------------------------------

@st.composite
def time_stamp_arrays(draw, n):
    """Time stamps in seconds, nanoseconds or microseconds, with random (also zero, negative, huge)
    steps, of a random dtype and of shape (1, N) or (N,)."""
    unit = draw(st.sampled_from(["s", "ns", "us"]))
    if unit == "s":
        start = draw(st.sampled_from([0.0, 1.3e9, 1.7e9, -100.0, 1e-3, 1e15]))
        steps = draw(st.lists(st.one_of(
            st.floats(-1, 100), st.sampled_from([0.0, 1e-9, 1e-6, 0.1, 10.0, 10.000001, 59.999, 60.0, 60.000001,
                                                 1e5, -0.1])), min_size=max(n - 1, 0), max_size=max(n - 1, 0)))
        t = start + np.concatenate([[0.0], np.cumsum(steps)])[:n]
    else:
        start = 1_700_000_000_000_000_000 if unit == "ns" else 1_700_000_000_000_000
        scale = 10**9 if unit == "ns" else 10**6
        steps = draw(st.lists(st.one_of(st.integers(-scale, 100 * scale),
                                        st.sampled_from([0, 1, scale // 10, scale // 30, -scale // 10])),
                              min_size=max(n - 1, 0), max_size=max(n - 1, 0)))
        t = start + np.concatenate([[0], np.cumsum(steps, dtype=np.int64)])[:n].astype(np.int64)
    dtype = draw(st.sampled_from(["float64", "float32", "int64", "uint64", "int32", "float16"]))
    with np.errstate(all="ignore"):
        t = np.asarray(t).astype(dtype)
    return t.reshape(1, n) if draw(st.booleans()) else t


@settings(max_examples=120, **SETTINGS)
@given(n=st.integers(0, 8), layout=st.sampled_from(["2022", "2019"]), sparse=st.booleans(), data=st.data())
def test_npz_time_stamps_property(n, layout, sparse, data):
    """Random time stamps (non-increasing, equal, nanosecond integers ~1.7e18, big gaps, any dtype): read
    exactly (as float64) iff there are >= 2, all finite and strictly increasing, the median step is <= 10 s
    and no step exceeds 60 s; otherwise refused with one line naming 'time_stamps'."""
    arrays = course_arrays(layout, sparse, n)
    arrays["time_stamps"] = t = data.draw(time_stamp_arrays(n), label="time_stamps")
    s = t.astype(np.float64).reshape(-1)
    with np.errstate(invalid="ignore", over="ignore"):  # inf - inf in the oracle: such stamps are refused
        steps = np.diff(s)
    ok = (s.size >= 2 and np.isfinite(s).all() and (steps > 0).all() and np.median(steps) <= 10.0
          and steps.max() <= 60.0)
    with tempfile.TemporaryDirectory() as d:
        path = _write(Path(d) / "stamps.npz", arrays)
        seq, msg = load_outcome(path, {"time_stamps"}, arrays)
    if ok:
        assert msg is None, msg
        assert np.array_equal(seq.time_stamps, s)
    else:
        assert seq is None and named_key(msg, path) == "time_stamps", msg


# -- rotations -------------------------------------------------------------------------------------

@settings(max_examples=120, **SETTINGS)
@given(layout=st.sampled_from(["2022", "2019"]), log_eps=st.floats(-14, 0),
       E=hnp.arrays(np.float64, (3, 3), elements=st.floats(-1, 1)),
       p=hnp.arrays(np.float64, 3, elements=st.floats(-1e3, 1e3)))
def test_npz_perturbed_rotation_property(layout, log_eps, E, p):
    """The extrinsic's rotation perturbed by eps * E (|E| <= 1, eps 1e-14 .. 1): with max |R^T R - I| <= 1e-3
    (and det > 0) it is read and its rotation is orthonormal, no entry moved by more than 2x the deviation,
    the translation kept, and (beyond 1e-5) a note in seq.notes names the key; beyond 1e-3 it is refused
    with one line naming the key."""
    arrays = course_arrays(layout)
    ext_key = LAYOUT_KEYS[layout][1]
    T = arrays[ext_key]
    T[:3, :3] += 10.0**log_eps * E
    T[:3, 3] = p
    R = T[:3, :3]
    dev = float(np.abs(R.T @ R - np.eye(3)).max())
    assume(abs(dev - 1e-3) > 1e-9)  # the same test, computed the same way; no rounding tie at the bound
    ok = dev <= 1e-3 and np.linalg.det(R) > 0
    with tempfile.TemporaryDirectory() as d:
        path = _write(Path(d) / "rot.npz", arrays)
        seq, msg = load_outcome(path, {ext_key}, arrays)
    if not ok:
        assert seq is None and named_key(msg, path) == ext_key, msg
        return
    assert msg is None, msg
    out = seq.imu_T_cam if layout == "2022" else seq.cam_T_imu
    Ro = out[:3, :3]
    assert np.abs(Ro.T @ Ro - np.eye(3)).max() <= 1e-12 and abs(np.linalg.det(Ro) - 1) <= 1e-12
    assert np.abs(Ro - R).max() <= 2 * dev + 1e-15
    np.testing.assert_allclose(out[:3, 3], p, rtol=1e-12, atol=1e-9)
    if dev > 1e-5:
        assert any(f"key '{ext_key}'" in note for note in seq.notes), seq.notes


# -- the sparse layout -----------------------------------------------------------------------------

#: a reader may refuse a num_features above this (no feature file has more columns)
SANE_FEATURES = 2**31 - 1


def _csr_problems(arrays, n) -> tuple[set[str], set[str]]:
    """(keys the sparse layout's rules say are broken, keys a reader may refuse though not broken) for these
    arrays. Rules: obs_ptr (N+1,) integers from 0 to L, non-decreasing; obs_ids (L,) integers in [0, M),
    strictly increasing within a step; obs_pixels (L, 4); num_features one integer >= 0 (above
    SANE_FEATURES: may be refused). All base pixels are inside the image, so every row is kept."""
    ptr, ids, m, pix = (np.asarray(arrays[k]) for k in ("obs_ptr", "obs_ids", "num_features", "obs_pixels"))

    def numbers(a):
        return a.dtype.kind in "iuf" and np.isfinite(a.astype(np.float64)).all()

    broken, optional = set(), set()
    p = [float(x) for x in ptr.reshape(-1)] if numbers(ptr) else None
    if (p is None or ptr.shape != (n + 1,) or any(x != round(x) for x in p) or p[0] != 0 or p[-1] != ids.size
            or any(b < a for a, b in itertools.pairwise(p))):
        broken.add("obs_ptr")
    mv = float(m.reshape(())) if m.size == 1 and numbers(m) else None
    if mv is None or mv < 0 or mv != round(mv):
        broken.add("num_features")
    elif mv > SANE_FEATURES:
        optional.add("num_features")
    iv = [float(x) for x in ids.reshape(-1)] if numbers(ids) else None
    if iv is None or ids.ndim != 1 or any(x != round(x) or x < 0 or (mv is not None and x >= mv) for x in iv):
        broken.add("obs_ids")
    if pix.shape != (ids.size, 4):
        broken.add("obs_pixels")
    if not broken & {"obs_ptr", "obs_ids"}:
        for k in range(n):
            step = iv[int(p[k]):int(p[k + 1])]
            if any(b <= a for a, b in itertools.pairwise(step)):
                broken.add("obs_ids")
    return broken, optional


@settings(max_examples=150, **SETTINGS)
@given(data=st.data(), layout=st.sampled_from(["2022", "2019"]),
       target=st.sampled_from(["obs_ptr", "obs_ids", "num_features", "obs_pixels"]))
def test_npz_sparse_layout_corruption_property(data, layout, target):
    """One corrupted array of the sparse layout: obs_ptr / obs_ids / num_features changed at random
    (negative, >= num_features, huge, non-integer, out of order, another dtype or shape) are accepted
    exactly when the CSR rules hold (_csr_problems), else refused naming a key they say is broken;
    obs_pixels with NaN/inf are refused naming it, with negative disparities or pixels outside the image
    those observations are dropped and counted."""
    arrays = course_arrays(layout, sparse=True)
    n, L, m = arrays["time_stamps"].shape[1], arrays["obs_ids"].size, int(arrays["num_features"])
    x = arrays[target]
    how = data.draw(st.sampled_from(["set", "set-float", "astype", "swap", "reshape"] if target != "obs_pixels"
                                    else ["specials", "disparity", "outside", "reshape"]), label="how")
    if how == "set":
        y = x.astype(np.int64).copy()
        for pos in data.draw(st.lists(st.integers(0, max(y.size - 1, 0)), min_size=1, max_size=3), label="pos"):
            if y.size:
                y.flat[pos] = data.draw(st.sampled_from([-1, 0, 1, m - 1, m, m + 7, L, L + 1, -2**63, 2**63 - 1]))
    elif how == "set-float":
        y = x.astype(np.float64).copy()
        for pos in data.draw(st.lists(st.integers(0, max(y.size - 1, 0)), min_size=1, max_size=3), label="pos"):
            if y.size:
                y.flat[pos] = data.draw(st.sampled_from([0.5, y.flat[pos] + 0.25, -0.0, -3.0, 1e-300, 1e15, 1e20,
                                                         2.0**63, 1e300]))
    elif how == "astype":
        with np.errstate(all="ignore"):
            y = x.astype(data.draw(st.sampled_from(["int8", "uint8", "float16", "float32", "uint64", "bool",
                                                    "complex128", "<U3"]), label="dtype"))
    elif how == "swap":
        y = x.copy()
        if y.size >= 2:
            i = data.draw(st.integers(0, y.size - 2), label="i")
            y[i], y[i + 1] = y[i + 1], y[i]
    elif how == "reshape":
        y = _reshaped(data.draw, x)
    elif how == "specials":
        y = x.copy()
        for pos in data.draw(st.lists(st.integers(0, y.size - 1), min_size=1, max_size=3), label="pos"):
            y.flat[pos] = data.draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    else:  # negative disparity / outside the image at a few rows
        y = x.copy()
        rows = data.draw(st.lists(st.integers(0, L - 1), min_size=1, max_size=3, unique=True), label="rows")
        for r in rows:
            if how == "disparity":
                y[r, 2] = y[r, 0] + data.draw(st.sampled_from([0.0, 1e-9, 3.0, 500.0]))
            else:
                c = data.draw(st.integers(0, 3))
                y[r, c] = data.draw(st.sampled_from([-1e-9, -1.0, -1e308, W_SYN if c % 2 == 0 else H_SYN, 1e308]))
    arrays[target] = y
    with tempfile.TemporaryDirectory() as d:
        path = _write(Path(d) / "sparse.npz", arrays)
        seq, msg = load_outcome(path, {target}, arrays)
    if target == "obs_pixels":
        if how == "specials" or y.shape != (L, 4):
            assert seq is None and named_key(msg, path) == "obs_pixels", msg
            return
        assert msg is None, msg
        u, v = y[:, 0::2], y[:, 1::2]
        outside = ((u < 0) | (u >= W_SYN) | (v < 0) | (v >= H_SYN)).any(axis=1)
        nonpos = ~outside & (y[:, 0] - y[:, 2] <= 0)
        assert seq.dropped == {"nonpositive_disparity": int(nonpos.sum()), "outside_image": int(outside.sum())}
        assert np.array_equal(seq.obs_pixels, y[~(outside | nonpos)])
        return
    broken, optional = _csr_problems(arrays, n)
    if broken:
        assert seq is None, f"accepted, though {sorted(broken)} break the format"
    if seq is None:
        assert named_key(msg, path) in broken | optional, msg
    else:
        assert np.array_equal(seq.obs_ids, arrays["obs_ids"].astype(np.int64).reshape(-1))
        assert seq.num_features == int(np.asarray(arrays["num_features"]).reshape(()))


# -- npz regressions (bugs the properties found) ---------------------------------------------------

@pytest.mark.parametrize("shape", ["scalar", "row"])
def test_sparse_0d_obs_ids_regression(tmp_path, shape):
    """Found by the properties (fixed since): npz._read_sparse's `ids.astype(np.int64)[keep]` indexed an
    obs_ids that is not 1-d (0-d: one observation stored as a scalar; (1, L): a row) with the 1-d mask of
    the L observations: IndexError. Now: a valid sequence or a one-line InputError naming obs_ids."""
    arrays = course_arrays(sparse=True)
    n = arrays["time_stamps"].shape[1]
    if shape == "scalar":
        arrays.update(obs_ptr=np.array([0] + [1] * n), obs_ids=np.array(2), obs_pixels=np.array([[300.0, 50, 280, 50]]))
    else:
        arrays["obs_ids"] = arrays["obs_ids"][None]
    path = _write(tmp_path / f"{shape}_ids.npz", arrays)
    seq, msg = load_outcome(path, {"obs_ids", "obs_ptr", "obs_pixels"}, arrays)
    assert seq is not None or named_key(msg, path) == "obs_ids"


def test_sparse_obs_ptr_wraparound_regression(tmp_path):
    """Found by the properties (fixed since): npz._read_sparse checked obs_ptr's order on int64 differences,
    which wrap around: [0, 2**62 + 2**61, -2**62, 0, 0, 0, L] passed (every wrapped count >= 0, summing to L
    mod 2**64) and np.repeat(np.arange(n), counts) crashed the interpreter (segmentation fault). Run in a
    child process: refused with one line naming obs_ptr."""
    arrays = course_arrays(sparse=True)
    L = arrays["obs_ids"].size
    arrays["obs_ptr"] = np.array([0, 2**62 + 2**61, -2**62, 0, 0, 0, L], dtype=np.int64)
    path = _write(tmp_path / "wrap.npz", arrays)
    code = ("import sys\nfrom vislam.backend.data.npz import load_sequence\n"
            "try:\n    load_sequence(sys.argv[1])\nexcept Exception as e:\n    print(type(e).__name__, e)\n")
    run = subprocess.run([sys.executable, "-c", code, str(path)], check=False, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, f"the loader's process died (return code {run.returncode})"  # segfault: -11
    assert run.stdout.startswith("InputError") and "key 'obs_ptr'" in run.stdout, run.stdout


def test_sparse_num_features_beyond_int64_regression(tmp_path):
    """Found by the properties (fixed since): npz._read_sparse accepted any integer-valued num_features
    (1e300, or 2**63 as float/uint64): Sequence.num_features became an int beyond int64 and save_sequence
    raised OverflowError. Now: refused naming num_features, or a sequence that saves and loads again."""
    arrays = course_arrays(sparse=True)
    arrays["num_features"] = np.array(1e300)
    path = _write(tmp_path / "huge_m.npz", arrays)
    load_outcome(path, {"num_features"}, arrays)


def test_2019_extrinsic_overflowing_inverse_regression(tmp_path):
    """A 2019-layout cam_T_imu whose rigid inverse overflows: read, or refused naming 'cam_T_imu' (the file's key)."""
    arrays = course_arrays("2019")
    arrays["cam_T_imu"] = _rigid(_rot([0, 0, 1], np.pi / 4), [1.5e308, 1.5e308, 0.0])
    path = _write(tmp_path / "far.npz", arrays)
    with np.errstate(all="ignore"):
        seq, msg = load_outcome(path, {"cam_T_imu"}, arrays)
    assert seq is not None or named_key(msg, path) == "cam_T_imu", msg


@pytest.mark.parametrize("key", ["obs_ids", "obs_ptr"])
def test_sparse_missing_key_named_regression(tmp_path, key):
    """Found by the properties (fixed since): a sparse-layout file missing 'obs_ids' (or another sparse key)
    was refused as "key 'features': missing", naming a key the layout never had."""
    arrays = course_arrays(sparse=True)
    del arrays[key]
    path = _write(tmp_path / "sparse_missing.npz", arrays)
    with pytest.raises(InputError) as e:
        load_sequence(path)
    assert named_key(assert_clean_input_error(e.value, path), path) == key


def test_npz_not_a_file_is_refused(tmp_path):
    """A directory or a missing path given as the .npz: a one-line InputError naming it."""
    for path in (tmp_path, tmp_path / "nope.npz"):
        with pytest.raises(InputError) as e:
            load_sequence(path)
        assert_clean_input_error(e.value, path)


# ==============================================================================================
# TUM trajectories
# ==============================================================================================

JUNK_TOKENS = ["abc", "nan", "NaN", "-nan", "inf", "-Infinity", "1e999", "-1e400", "0x10", "1,5", "1.5.2", "--1",
               "1e", "+", "e5", "\x00", "1_0", "\u0661\u0662", "\ufeff1", "1e-400", "0e0", "-0.0", "1e150", "'1'",
               "1e200", "-1e308", "5e-324"]
QUAT_SCALES = [0.0, 1e-300, 1e-200, 1e-160, 1e-13, 1e-6, 1e-3, 1.0, 7.5, 1e6, 1e100, 1e150, 1e200, 1e300]
RAW_BYTES = [b"\xff", b"\xc3(", b"\xef\xbb\xbf", b"\r", b"\n", b"\r\n", b"\x00", b"\x0b", b"\x0c", b"\x1c", b"\xc2\x85",
             b"\xe2\x80\xa8", b"\xc2\xa0", b"\t", b"#", b" ", b"\x80\x80", b"\xed\xa0\x80"]


@st.composite
def tum_lines(draw):
    """A valid TUM file as lines of tokens (str lines are verbatim)."""
    n = draw(st.integers(1, 6))
    t0 = draw(st.sampled_from([0.0, 1.3e9, -5.0, 1.7e18, 1e-3]))
    dts = draw(st.lists(st.sampled_from([1e-3, 0.1, 1.0, 1e6]), min_size=n, max_size=n))
    lines = []
    t = t0
    for i in range(n):
        trans = draw(st.lists(st.floats(-1e6, 1e6), min_size=3, max_size=3))
        q = draw(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: sum(x * x for x in q) > 1e-6))
        fmt = draw(st.sampled_from([repr, lambda x: f"{x:.6f}", lambda x: f"{x:.9e}"]))
        lines.append([repr(t)] + [fmt(x) for x in trans + q])
        t = max(t + dts[i], float(np.nextafter(t, np.inf)))
    return lines


def _corrupt_tum(draw, lines):
    """0-3 random changes of single lines (tokens, quaternions, stamps) or of the lines (blank, comment,
    dropped, duplicated), in place."""
    for _ in range(draw(st.integers(0, 3), label="line changes")):
        i = draw(st.integers(0, len(lines) - 1), label="line")
        line = lines[i]
        op = draw(st.sampled_from(["drop-token", "dup-token", "swap-tokens", "junk-token", "zero-quat", "scale-quat",
                                   "equal-time", "earlier-time", "blank", "comment", "drop-line", "dup-line"]))
        if op in ("blank", "comment"):
            lines.insert(i, draw(st.sampled_from(["", "   ", "\t", "#", "# t tx ty tz qx qy qz qw", "  # 1 2 3",
                                                  "#1 2 3 4 5 6 7 8"])))
            continue
        if op == "drop-line":
            del lines[i]
            if not lines:
                lines.append("# nothing")
            continue
        if op == "dup-line":
            lines.insert(i, line if isinstance(line, str) else list(line))
            continue
        if isinstance(line, str):
            continue
        if op == "drop-token" and line:
            del line[draw(st.integers(0, len(line) - 1))]
        elif op == "dup-token" and line:
            j = draw(st.integers(0, len(line) - 1))
            line.insert(j, line[j])
        elif op == "swap-tokens" and len(line) >= 2:
            j, k = draw(st.integers(0, len(line) - 1)), draw(st.integers(0, len(line) - 1))
            line[j], line[k] = line[k], line[j]
        elif op == "junk-token" and line:
            line[draw(st.integers(0, len(line) - 1))] = draw(st.sampled_from(JUNK_TOKENS))
        elif op == "zero-quat" and len(line) == 8:
            line[4:8] = [draw(st.sampled_from(["0", "-0.0", "0e0", "0.000"])) for _ in range(4)]
        elif op == "scale-quat" and len(line) == 8:
            s = draw(st.sampled_from(QUAT_SCALES))
            try:
                line[4:8] = [repr(float(x) * s) for x in line[4:8]]
            except ValueError:
                pass
        elif op in ("equal-time", "earlier-time") and line:
            prev = next((p for p in reversed(lines[:i]) if not isinstance(p, str) and p), None)
            if prev is not None and op == "equal-time":
                line[0] = prev[0]
            elif prev is not None and _is_float(prev[0]):
                line[0] = repr(float(prev[0]) - 1.0)


def _is_float(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


@st.composite
def tum_files(draw):
    """The bytes of a TUM file: valid lines corrupted at random, random separators and line endings, an
    optional BOM and random bytes (invalid UTF-8, NUL, other line breaks) put in."""
    lines = draw(tum_lines())
    _corrupt_tum(draw, lines)
    sep = st.sampled_from([" ", "  ", "\t", " \t "])
    texts = [line if isinstance(line, str) else draw(sep).join(line) + draw(st.sampled_from(["", " ", "\t"]))
             for line in lines]
    eol = draw(st.sampled_from(["\n", "\r\n", "\r", "mixed"]))
    out = ""
    for text in texts:
        out += text + (draw(st.sampled_from(["\n", "\r\n", "\r"])) if eol == "mixed" else eol)
    if not draw(st.booleans()):
        out = out.rstrip("\r\n")
    raw = out.encode("utf-8")
    if draw(st.booleans()):
        raw = b"\xef\xbb\xbf" + raw
    for _ in range(draw(st.integers(0, 2), label="raw insertions")):
        pos = draw(st.integers(0, len(raw)), label="pos")
        raw = raw[:pos] + draw(st.sampled_from(RAW_BYTES) | st.binary(min_size=1, max_size=3)) + raw[pos:]
    return raw


def _robust_rotation(q):
    q = np.asarray(q, dtype=float)
    q = q / np.abs(q).max()
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _tum_oracle(raw: bytes):
    """What the documented format says of ``raw``: (("ok", times, translations, rotations) or ("refuse",
    line number or None), the first line whose quaternion is not zero but below 1e-12 in norm, where a
    reader may also stop as at a zero quaternion, or None)."""
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        return ("refuse", None), None
    times, trans, rots, tiny = [], [], [], None
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        tokens = s.split()
        if len(tokens) != 8:
            return ("refuse", lineno), tiny
        if any("_" in x for x in tokens):  # Python's digit separator (float("0.7_5") == 0.75) is no number in a data file
            return ("refuse", lineno), tiny
        try:
            values = [float(x) for x in tokens]
        except ValueError:
            return ("refuse", lineno), tiny
        if not all(math.isfinite(v) for v in values):
            return ("refuse", lineno), tiny
        q = values[4:]
        big = max(abs(v) for v in q)
        if big == 0:
            return ("refuse", lineno), tiny
        if big * math.sqrt(sum((v / big) ** 2 for v in q)) < 1e-12 and tiny is None:
            tiny = lineno
        if times and values[0] <= times[-1]:
            return ("refuse", lineno), tiny
        times.append(values[0])
        trans.append(values[1:4])
        rots.append(_robust_rotation(q))
    if not times:
        return ("refuse", None), tiny
    return ("ok", np.array(times), np.array(trans), np.array(rots)), tiny


def check_tum(path: Path):
    """read_tum's outcome against the oracle: the same poses, or a one-line InputError naming the file and
    the first bad line."""
    expected, tiny = _tum_oracle(path.read_bytes())
    try:
        t, poses = read_tum(str(path))
    except InputError as e:
        msg = str(e)
        assert "\n" not in msg and "\r" not in msg, msg
        lines = {expected[1]} if expected[0] == "refuse" else set()
        lines |= {tiny} if tiny is not None else set()
        assert lines, f"refused a valid file: {msg}"
        assert any(msg.startswith(f"{path}:{line}: " if line is not None else f"{path}: ") for line in lines), msg
        return None
    assert expected[0] == "ok", f"accepted, expected a refusal at line {expected[1]}"
    _, times, trans, rots = expected
    assert t.dtype == np.float64 and poses.dtype == np.float64
    assert t.shape == times.shape and poses.shape == (len(times), 4, 4)
    assert np.isfinite(t).all() and np.isfinite(poses).all()
    assert (np.diff(t) > 0).all()
    assert np.array_equal(t, times) and np.array_equal(poses[:, :3, 3], trans)
    assert np.array_equal(poses[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (len(t), 1)))
    R = poses[:, :3, :3]
    assert np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max() <= 1e-9
    assert np.abs(np.linalg.det(R) - 1).max() <= 1e-9
    assert np.abs(R - rots).max() <= 1e-9
    return t, poses


@settings(max_examples=150, **SETTINGS)
@given(raw=tum_files())
def test_tum_random_corruption_property(raw):
    """Random line corruptions of a TUM file (tokens dropped, duplicated, swapped or replaced by junk,
    nan/inf, zero or unnormalized quaternions, equal or earlier stamps, blank and comment lines, CRLF/CR,
    a BOM, random bytes incl. invalid UTF-8): read_tum returns exactly the poses the format defines
    (finite, strictly increasing times, orthonormal rotations of the normalized quaternions) or a
    one-line InputError naming the file and the first bad line."""
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "traj.txt"
        path.write_bytes(raw)
        check_tum(path)


@settings(max_examples=60, **SETTINGS)
@given(lines=tum_lines(), crlf=st.booleans(), bom=st.booleans(), comments=st.booleans())
def test_tum_valid_files_are_read_property(lines, crlf, bom, comments):
    """Valid TUM files (quaternions of any norm from 1e-3 to 2), with CRLF line ends, a BOM and comment
    lines or not, are read back exactly."""
    texts = [" ".join(line) for line in lines]
    if comments:
        texts = ["# timestamp tx ty tz qx qy qz qw", *texts[:1], "", "  # between", *texts[1:]]
    raw = (("\r\n" if crlf else "\n").join(texts) + "\n").encode()
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "good.txt"
        path.write_bytes(b"\xef\xbb\xbf" + raw if bom else raw)
        assert check_tum(path) is not None


def test_tum_not_a_file_is_refused(tmp_path):
    """A directory or a missing path given as the trajectory: a one-line InputError naming it."""
    for path in (tmp_path, tmp_path / "nope.txt"):
        with pytest.raises(InputError) as e:
            read_tum(path)
        msg = str(e.value)
        assert "\n" not in msg and msg.startswith(f"{path}:"), msg


def test_tum_huge_quaternion_regression(tmp_path):
    """Found by the properties (fixed since): a quaternion with components beyond ~1e154 passed read_tum's
    norm check (its Python norm overflowed to inf, not < 1e-12), then np.linalg.norm was inf and q / norm
    gave NaN: the rotation was NaN instead of that of the normalized quaternion."""
    path = tmp_path / "huge_q.txt"
    path.write_text("0 0 0 0 1e200 0 0 1\n1 0 0 0 0 0 0 1\n")
    with np.errstate(all="ignore"):
        result = check_tum(path)  # a 180 deg turn about x (or a clean refusal)
    assert result is None or np.allclose(result[1][0, :3, :3], np.diag([1.0, -1.0, -1.0]))


# ==============================================================================================
# pose covariances (pose_covariance.npz)
# ==============================================================================================

COV_KEYS = ("time_stamps", "covariance")


@functools.cache
def _base_covariance(n: int = 5) -> dict[str, np.ndarray]:
    """A valid file's arrays: the world frame's 1e-12 I, then random SPD matrices."""
    rng = np.random.default_rng(11)
    A = rng.standard_normal((n, 6, 6))
    cov = 0.01 * A @ np.swapaxes(A, 1, 2)
    cov[0] = 1e-12 * np.eye(6)
    return {"time_stamps": 1.3e9 + 0.1 * np.arange(n), "covariance": cov}


def covariance_arrays(n: int = 5) -> dict[str, np.ndarray]:
    return {k: v.copy() for k, v in _base_covariance(n).items()}


def assert_valid_covariance(t: np.ndarray, cov: np.ndarray) -> None:
    """What read_pose_covariance returns: float64 stamps (N >= 1, strictly increasing) and (N,6,6)
    finite, symmetric and positive semi-definite matrices (to 1e-9 of each one's largest entry)."""
    assert t.dtype == cov.dtype == np.float64
    assert t.ndim == 1 and t.size >= 1 and cov.shape == (t.size, 6, 6)
    assert np.isfinite(t).all() and np.isfinite(cov).all()
    assert (np.diff(t) > 0).all()
    scale = np.abs(cov).max(axis=(1, 2))
    unit = cov / np.where(scale > 0, scale, 1.0)[:, None, None]
    assert (np.abs(unit - np.swapaxes(unit, 1, 2)) <= 1e-9).all()
    assert (np.linalg.eigvalsh(0.5 * (unit + np.swapaxes(unit, 1, 2)))[:, 0] >= -1e-9).all()


def covariance_outcome(path: Path, mutated: set[str] | None):
    """Read ``path``: ((t, cov), None) after checking them, or (None, message) after checking the InputError
    is one line naming the file and, with ``mutated``, a key at fault (the stamps give N: changing them may
    blame the covariance's shape). Any other exception propagates and fails the test."""
    try:
        t, cov = read_pose_covariance(path)
    except InputError as e:
        msg = assert_clean_input_error(e, path)
        if mutated is not None:
            allowed = set(mutated) | ({"covariance"} if "time_stamps" in mutated else set())
            assert named_key(msg, path) in allowed, f"names another key after changing {sorted(mutated)}: {msg}"
        return None, msg
    assert_valid_covariance(t, cov)
    return (t, cov), None


def _asymmetric(draw, x: np.ndarray) -> np.ndarray:
    y = np.array(x, dtype=np.float64)
    if y.ndim == 3 and y.shape[1:] == (6, 6) and y.shape[0]:
        k, i, j = draw(st.integers(0, y.shape[0] - 1)), draw(st.integers(0, 5)), draw(st.integers(0, 5))
        amount = draw(st.sampled_from([1e-15, 1e-10, 1e-6, 1e-3, 1.0, -1.0, 1e300]))
        y[k, i, j] += amount * max(np.abs(y[k]).max(), 1e-300)
    return y


def _indefinite(draw, x: np.ndarray) -> np.ndarray:
    y = np.array(x, dtype=np.float64)
    if y.ndim == 3 and y.shape[1:] == (6, 6) and y.shape[0]:
        k, i = draw(st.integers(0, y.shape[0] - 1)), draw(st.integers(0, 5))
        amount = draw(st.sampled_from([1e-14, 1e-6, 1.0, 1e6]))
        y[k, i, i] -= amount * np.abs(y[k]).max()
    return y


@settings(max_examples=150, **SETTINGS)
@given(data=st.data(), compressed=st.booleans())
def test_pose_covariance_corruption_property(data, compressed):
    """1-3 random changes of the two arrays before saving (drop one, add an unknown key, replace one by a
    random array of any shape and dtype, convert its dtype, reshape it, put NaN/inf/huge/negative values
    into it, make a matrix asymmetric or indefinite by a random amount): read_pose_covariance gives
    finite, increasing stamps and symmetric PSD (N,6,6) matrices, or a one-line InputError naming the
    file and a key at fault; never another exception. Unknown keys alone change nothing."""
    arrays = covariance_arrays()
    mutated: set[str] = set()
    for _ in range(data.draw(st.integers(1, 3), label="changes")):
        op = data.draw(st.sampled_from(["drop", "add-unknown", "replace", "replace-same-shape", "astype", "reshape",
                                        "specials", "asymmetric", "indefinite"]), label="op")
        if op == "add-unknown":
            name = data.draw(st.from_regex(r"[a-z][a-z0-9_]{0,10}", fullmatch=True)
                             .filter(lambda s: s not in COV_KEYS), label="new key")
            arrays[name] = data.draw(random_arrays(), label="value")
            continue
        present = [k for k in COV_KEYS if k in arrays]
        if not present:
            continue
        key = data.draw(st.sampled_from(present), label="key")
        mutated.add(key)
        x = arrays[key]
        if x.dtype.kind in "USbc" and op in ("astype", "specials", "asymmetric", "indefinite"):
            op = "replace"
        if op == "asymmetric":
            with np.errstate(all="ignore"):
                arrays[key] = _asymmetric(data.draw, x)
        elif op == "indefinite":
            with np.errstate(all="ignore"):
                arrays[key] = _indefinite(data.draw, x)
        else:
            _mutate(data, arrays, key, op)
    with tempfile.TemporaryDirectory() as d:
        path = _write(Path(d) / "pose_covariance.npz", arrays, compressed)
        read, msg = covariance_outcome(path, mutated)
    if not mutated:
        assert msg is None, msg
        base = _base_covariance()
        assert np.array_equal(read[0], base["time_stamps"]) and np.array_equal(read[1], base["covariance"])


@settings(max_examples=60, **SETTINGS)
@given(data=st.data(), key=st.sampled_from(COV_KEYS))
def test_pose_covariance_special_values_property(data, key):
    """NaN/inf/huge/negative/subnormal values at random positions of one key: NaN or inf is refused naming
    that key; finite values are read (as written) or refused naming that key or, for the stamps, the
    covariance checked against them."""
    arrays = covariance_arrays()
    arrays[key] = _with_specials(data.draw, arrays[key], arrays)
    nonfinite = not np.isfinite(arrays[key]).all()
    with tempfile.TemporaryDirectory() as d:
        path = _write(Path(d) / "specials.npz", arrays)
        read, msg = covariance_outcome(path, {key})
    if nonfinite:
        assert read is None and named_key(msg, path) == key, msg
    elif read is not None:
        assert np.array_equal(read[0], arrays["time_stamps"]) and np.array_equal(read[1], arrays["covariance"])


def _object_array() -> np.ndarray:
    a = np.empty(5, dtype=object)
    a[:] = [1.0, "x", None, [1], 2.0]
    return a


def _changed(arrays: dict, **changes) -> dict:
    out = {**arrays, **changes}
    return {k: v for k, v in out.items() if v is not None}


@pytest.mark.parametrize("key, change, fragment", [
    ("time_stamps", dict(time_stamps=None), "missing"),
    ("covariance", dict(covariance=None), "missing"),
    ("time_stamps", dict(time_stamps=np.zeros((1, 5)) + np.arange(5)), "expected shape (N,)"),
    ("time_stamps", dict(time_stamps=np.zeros(0), covariance=np.zeros((0, 6, 6))), "no time stamp"),
    ("time_stamps", dict(time_stamps=np.array([0.0, 0.1, 0.1, 0.3, 0.4])), "not strictly increasing: [2]"),
    ("time_stamps", dict(time_stamps=np.array([0.0, 0.1, np.nan, 0.3, 0.4])), "non-finite value nan at index [2]"),
    ("time_stamps", dict(time_stamps=_object_array()), "cannot read"),
    ("time_stamps", dict(time_stamps=np.array(["a", "b", "c", "d", "e"])), "expected a numeric"),
    ("covariance", dict(covariance=np.zeros((5, 6, 5))), "expected shape (5, 6, 6)"),
    ("covariance", dict(covariance=np.zeros((4, 6, 6))), "expected shape (5, 6, 6)"),
    ("covariance", dict(covariance=np.full((5, 6, 6), np.inf)), "non-finite value inf at index [0, 0, 0]"),
    ("covariance", dict(covariance=np.zeros((5, 6, 6), dtype=complex)), "expected a numeric"),
    ("covariance", dict(covariance=_object_array()), "cannot read"),
    ("covariance", "asymmetric", "matrix 3 is not symmetric"),
    ("covariance", "indefinite", "matrix 2 is not positive semi-definite"),
])
def test_pose_covariance_damage_is_one_line(tmp_path, key, change, fragment):
    arrays = covariance_arrays()
    if change == "asymmetric":
        arrays["covariance"][3, 0, 5] += 1e-6 * np.abs(arrays["covariance"][3]).max()
        change = {}
    elif change == "indefinite":
        arrays["covariance"][2] = 0.01 * np.diag([1.0, 1.0, -1.0, 1.0, 1.0, 1.0])  # eigenvalue -0.01
        change = {}
    path = tmp_path / "pose_covariance.npz"
    with open(path, "wb") as fh:
        np.savez(fh, **_changed(arrays, **change))  # object arrays are pickled by savez: the reader never unpickles
    with pytest.raises(InputError) as e:
        read_pose_covariance(path)
    msg = assert_clean_input_error(e.value, path)
    assert named_key(msg, path) == key and fragment in msg, msg


def test_pose_covariance_unusable_files_are_one_line(tmp_path):
    (tmp_path / "text.npz").write_text("not a zip")
    (tmp_path / "dir.npz").mkdir()
    for path, fragment in ((tmp_path / "text.npz", "not an .npz"), (tmp_path / "dir.npz", "not a regular file"),
                           (tmp_path / "nope.npz", "does not exist")):
        with pytest.raises(InputError) as e:
            read_pose_covariance(path)
        assert fragment in assert_clean_input_error(e.value, path)


def test_pose_covariance_rounding_and_semi_definite_are_accepted(tmp_path):
    """The filter's matrices: symmetric to rounding, zero (a pose held fixed), singular but PSD; int stamps."""
    arrays = covariance_arrays()
    cov = arrays["covariance"]
    cov[1, 0, 1] *= 1 + 1e-14
    cov[2] = 0.0
    v = np.arange(1.0, 7.0)
    cov[3] = np.outer(v, v)  # rank 1
    arrays["time_stamps"] = np.arange(5, dtype=np.int64)
    path = _write(tmp_path / "ok.npz", arrays)
    (t, read), msg = covariance_outcome(path, None)
    assert msg is None and np.array_equal(t, np.arange(5.0)) and np.array_equal(read, cov)


# ==============================================================================================
# TOML configuration
# ==============================================================================================

def _config_fields():
    """(table, key) -> (value type, optional, default) of every option of Config."""
    out = {}
    for table, cls in Config.table_types().items():
        hints = typing.get_type_hints(cls)
        defaults = cls()
        for f in dataclasses.fields(cls):
            kind, optional = hints[f.name], False
            args = typing.get_args(kind)
            if type(None) in args:
                kind, optional = next(a for a in args if a is not type(None)), True
            out[(table, f.name)] = (kind, optional, getattr(defaults, f.name))
    return out


FIELDS = _config_fields()
TABLES = sorted(Config.table_types())
#: (table, key) pairs a cross-table rule joins: an error may name either of its keys
RULE_KEYS = {("estimator", "error_model"): "estimator.error_model",
             ("landmarks", "parametrization"): "estimator.error_model",
             ("input", "image_width"): "input.image_width", ("input", "image_height"): "input.image_width"}
#: keys the per-table check() limits beyond "> 0" / ">= 0" / ">= 1"
VALID_FLOATS = {("update", "gate_probability"): st.floats(0.501, 0.9999),
                ("update", "huber_probability"): st.just(0) | st.floats(0.501, 0.9999),  # 0: off
                ("drift", "track_test_probability"): st.just(0) | st.floats(1e-9, 0.499),  # 0: off
                ("health", "nis_warn_factor"): st.floats(1.001, 1e6)}
#: integer options whose valid values are not 1 .. 10^6
VALID_INTS = {("estimator", "window"): st.just(0) | st.integers(2, 10**6)}  # 0: off, else at least 2 clones


def _is_enum(kind):
    return isinstance(kind, type) and issubclass(kind, enum.Enum)


def valid_value(table, key):
    """A value the option takes, as TOML gives it (an int for a float option too; "none" for unset)."""
    kind, optional, _ = FIELDS[(table, key)]
    if kind is bool:
        s = st.booleans()
    elif _is_enum(kind):
        s = st.sampled_from([m.value for m in kind])
    elif kind is int:
        s = VALID_INTS.get((table, key), st.integers(1, 10**6))
    else:
        s = VALID_FLOATS.get((table, key), st.floats(1e-9, 1e9) | st.integers(1, 1000))
    return s | st.just("none") if optional else s


toml_scalars = st.one_of(
    st.booleans(),
    st.integers(-2**70, 2**70),
    st.sampled_from([0, 1, -1, 2, 2**63 - 1, 2**63, -2**63 - 1, 10**30, -(10**300), 10**300, 10**400, -(10**400)]),
    st.floats(),
    st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -1e308, 5e-324, -0.0, 0.5, 1e-300]),
    st.text(max_size=12),
    st.sampled_from(["none", "None", "auto", "null", "", "slam", "body", "inverse-depth", "xyz", "yes", "no", "on",
                     "true", "1", "0", "1.5", " 2 ", "nan", "inf", "-inf", "1e999", "-1", "0x10", "1_000"]),
    st.dates(),
    st.times(),
)
toml_values = st.recursive(toml_scalars, lambda inner: st.lists(inner, max_size=3) | st.dictionaries(
    st.text(string.ascii_letters + "_", min_size=1, max_size=6), inner, max_size=3), max_leaves=6)
junk_names = st.text(string.ascii_letters + string.digits + "_-. '\n\t\u00e9\u00a0", min_size=1, max_size=10)
# unknown table names (top-level keys: not "table.key", which from_values takes as --set does)
junk_tables = junk_names.filter(lambda s: s.partition(".")[0] not in TABLES)


def mentions(msg: str, name: str) -> bool:
    """``name`` is in the message, as it is or with line breaks and other control characters escaped."""
    return name in msg or repr(name)[1:-1] in msg


def toml_str(s: str) -> str:
    out = []
    for c in s:
        if c in '\\"':
            out.append("\\" + c)
        elif ord(c) < 0x20 or ord(c) == 0x7F:
            out.append(f"\\u{ord(c):04x}")
        else:
            out.append(c)
    return '"' + "".join(out) + '"'


def toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return toml_str(v)
    if isinstance(v, (datetime.date, datetime.time)):
        return v.isoformat()
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    return "{" + ", ".join(f"{toml_str(k)} = {toml_value(x)}" for k, x in v.items()) + "}"


def toml_document(top: dict, tables: dict) -> str:
    lines = [f"{toml_str(k)} = {toml_value(v)}" for k, v in top.items()]
    for name, entries in tables.items():
        lines.append(f"[{toml_str(name)}]")
        lines += [f"{toml_str(k)} = {toml_value(v)}" for k, v in entries.items()]
    return "\n".join(lines) + "\n"


def expected_option(kind, optional, v):
    """The value an accepted option must hold when TOML gave ``v`` (not a string)."""
    if kind is float:
        return float(v)
    if kind is bool:
        return bool(v)
    return v


def check_option_type(kind, optional, got):
    if got is None:
        assert optional
    elif kind is float:
        assert type(got) is float and math.isfinite(got)
    elif kind is int:
        assert type(got) is int
    elif kind is bool:
        assert type(got) is bool
    else:
        assert isinstance(got, kind)


def assert_clean_config_error(err: BaseException, *needles: str) -> str:
    """A one-line ConfigError containing every needle (the file, ...); returns the message."""
    assert isinstance(err, ConfigError), repr(err)
    msg = str(err)
    assert "\n" not in msg and "\r" not in msg, msg
    for needle in needles:
        assert needle in msg, f"{needle!r} not in: {msg}"
    return msg


def assert_valid_config(cfg: Config) -> None:
    """A config is valid: validate() passes again, every option has its type, floats are finite."""
    assert isinstance(cfg, Config)
    cfg.validate()
    for (table, key), (kind, optional, _) in FIELDS.items():
        check_option_type(kind, optional, getattr(getattr(cfg, table), key))


def rules_broken(cfg_values: dict) -> set[str]:
    """The keys the broken cross-table rules name for these (table, key) -> value (TOML values)."""
    def get(t, k):
        v = cfg_values.get((t, k), FIELDS[(t, k)][2])
        return None if v == "none" else v
    broken = set()
    if get("estimator", "error_model") == "invariant" and get("landmarks", "parametrization") != "xyz":
        broken.add("estimator.error_model")
    if (get("input", "image_width") is None) != (get("input", "image_height") is None):
        broken.add("input.image_width")
    return broken


@st.composite
def valid_documents(draw):
    """{(table, key): value} of valid values for a random subset of the options."""
    keys = draw(st.lists(st.sampled_from(sorted(FIELDS)), unique=True, max_size=12))
    return {tk: draw(valid_value(*tk), label=".".join(tk)) for tk in keys}


def _tables_of(values: dict) -> dict:
    tables: dict = {}
    for (t, k), v in values.items():
        tables.setdefault(t, {})[k] = v
    return tables


def load_config_outcome(path: Path, text: str):
    """Config.load(path) and Config.from_values(the parsed TOML): both give the same valid Config, or
    both a one-line ConfigError (the one of load naming the file)."""
    try:
        cfg = Config.load(path)
    except ConfigError as e:
        msg = assert_clean_config_error(e, str(path))
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError:
            return None, msg
        with pytest.raises(ConfigError) as e2:
            Config.from_values(data)
        assert_clean_config_error(e2.value)
        return None, msg
    assert_valid_config(cfg)
    assert Config.from_values(tomllib.loads(text)).as_dict() == cfg.as_dict()
    return cfg, None


@settings(max_examples=100, **SETTINGS)
@given(values=valid_documents())
def test_config_valid_documents_are_read_property(values):
    """TOML files of valid values for random options (ints for float options, "none" for unset ones) are
    read with exactly those values; only a broken cross-table rule (invariant error model with
    inverse-depth landmarks, one of image_width / image_height set) is refused, naming its key."""
    text = toml_document({}, _tables_of(values))
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "valid.toml"
        path.write_text(text, encoding="utf-8")
        cfg, msg = load_config_outcome(path, text)
    rules = rules_broken(values)
    if rules:
        assert cfg is None and any(f"'{r}'" in msg for r in rules), msg
        return
    assert msg is None, f"refused a valid file: {msg}\n{text}"
    for (t, k), v in values.items():
        kind, optional, _ = FIELDS[(t, k)]
        got = getattr(getattr(cfg, t), k)
        assert got == (None if v == "none" else expected_option(kind, optional, v)), (t, k, v, got)


@settings(max_examples=150, **SETTINGS)
@given(data=st.data())
def test_config_random_documents_property(data):
    """Random TOML documents: the real tables and keys, unknown tables and keys, top-level keys, and values
    of any TOML type (ints, floats incl. nan/inf/huge/negative, bools, strings, dates, arrays, inline
    tables): a one-line ConfigError naming the file and something at fault, or a valid Config holding
    what the file says."""
    draw = data.draw
    top = draw(st.dictionaries(junk_tables | st.sampled_from(TABLES),
                               toml_scalars, max_size=1), label="top-level")
    names = draw(st.lists(st.sampled_from(TABLES) | junk_tables,
                          unique=True, max_size=4).map(lambda ns: [n for n in ns if n not in top]), label="tables")
    tables, culprits, values, random_keys = {}, [f"'{k}'" for k in top], {}, set()
    for name in names:
        entries = {}
        if name not in TABLES:
            culprits.append(name)
            for k in draw(st.lists(junk_names | st.sampled_from([k for _, k in FIELDS]), unique=True, max_size=2)):
                entries[k] = draw(toml_values)
        else:
            known = [k for t, k in FIELDS if t == name]
            for k in draw(st.lists(st.sampled_from(known) | junk_names, unique=True, max_size=4)):
                if k in known and draw(st.booleans()):
                    entries[k] = values[(name, k)] = draw(valid_value(name, k))
                else:
                    entries[k] = draw(toml_values)
                    culprits.append(f"'{name}.{k}'")
                    if k in known:
                        random_keys.add((name, k))
                        values[(name, k)] = entries[k]
        tables[name] = entries
    for tk, rule_key in RULE_KEYS.items():
        if tk in values:
            culprits.append(f"'{rule_key}'")
    text = toml_document(top, tables)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "random.toml"
        path.write_text(text, encoding="utf-8")
        cfg, msg = load_config_outcome(path, text)
    junk = bool(top) or any(n not in TABLES for n in names) or any(
        k not in [kk for t, kk in FIELDS if t == n] for n in names if n in TABLES for k in tables[n])
    if msg is not None:
        assert any(mentions(msg, c) for c in culprits), f"names none of {culprits}: {msg}"
        assert junk or random_keys or rules_broken(values), f"refused a valid file: {msg}"
        return
    assert not junk, f"accepted unknown keys or tables:\n{text}"
    for (t, k), v in values.items():
        kind, optional, _ = FIELDS[(t, k)]
        got = getattr(getattr(cfg, t), k)
        if isinstance(v, str):
            continue  # strings are parsed as on the command line (" 2 ", "yes", "none", ...): the type is checked
        assert got == expected_option(kind, optional, v), (t, k, v, got)


@settings(max_examples=120, **SETTINGS)
@given(base=valid_documents(), data=st.data())
def test_config_one_bad_entry_is_named_property(base, data):
    """A valid document with one entry changed (a random value of any type for one option, an unknown
    key in a real table, or an unknown table): refused with one line naming the file and exactly that
    key or table (or the cross-table rule it takes part in), or read with that value."""
    assume(not rules_broken(base))
    tables = _tables_of(base)
    what = data.draw(st.sampled_from(["value", "unknown-key", "unknown-table"]), label="what")
    if what == "value":
        t, k = data.draw(st.sampled_from(sorted(FIELDS)), label="option")
        v = data.draw(toml_values, label="value")
        tables.setdefault(t, {})[k] = v
        needles = [f"'{t}.{k}'"] + ([f"'{RULE_KEYS[(t, k)]}'"] if (t, k) in RULE_KEYS else [])
    elif what == "unknown-key":
        t = data.draw(st.sampled_from(TABLES), label="table")
        k = data.draw(junk_names.filter(lambda s: (t, s) not in FIELDS), label="key")
        tables.setdefault(t, {})[k] = data.draw(toml_values, label="value")
        needles = [f"'{t}.{k}'"]
    else:
        t = data.draw(junk_tables, label="table")
        tables[t] = {"x": 1}
        needles = [t]
    text = toml_document({}, tables)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "one_bad.toml"
        path.write_text(text, encoding="utf-8")
        cfg, msg = load_config_outcome(path, text)
    if what != "value":
        assert msg is not None, f"accepted:\n{text}"
    if msg is not None:
        assert any(mentions(msg, n) for n in needles), f"names none of {needles}: {msg}"
    elif not isinstance(v, str):
        kind, optional, _ = FIELDS[(t, k)]
        assert getattr(getattr(cfg, t), k) == expected_option(kind, optional, v)


@settings(max_examples=100, **SETTINGS)
@given(raw=st.one_of(st.binary(max_size=200), st.text(max_size=200).map(lambda s: s.encode("utf-8")),
                     st.builds(lambda doc, pos, junk: doc[:pos % (len(doc) + 1)] + junk + doc[pos % (len(doc) + 1):],
                               st.just(Config().to_toml().encode()), st.integers(0, 10**6),
                               st.sampled_from([b"\xff", b"\xef\xbb\xbf", b"\x00", b"[", b"]", b"=", b'"', b"\n[[x]]\n",
                                                b"\r", b"\\", b"\xc3(", b"#"]) | st.binary(min_size=1, max_size=4))))
def test_config_random_bytes_property(raw):
    """Random bytes, random text and the default config.toml with random bytes put in (invalid TOML,
    invalid UTF-8, a BOM, NUL): a one-line ConfigError naming the file, or a valid Config."""
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "bytes.toml"
        path.write_bytes(raw)
        try:
            cfg = Config.load(path)
        except ConfigError as e:
            assert_clean_config_error(e, str(path))
            return
    assert_valid_config(cfg)


def test_config_not_a_file_is_refused(tmp_path):
    """A directory or a missing path given as the config file: a one-line ConfigError naming it."""
    for path in (tmp_path, tmp_path / "nope.toml"):
        with pytest.raises(ConfigError) as e:
            Config.load(path)
        assert_clean_config_error(e.value, str(path))


@pytest.mark.parametrize("how", ["toml-float-option", "toml-int-option", "set-int-option"])
def test_config_huge_integer_regression(tmp_path, how):
    """Found by the properties (fixed since): an integer beyond ~1.8e308 (TOML and --set allow any) raised
    OverflowError: in _coerce's float(value) for a float option, in OptionTable.require_at_least's
    math.isfinite(value) for an int option."""
    huge = "1" + "0" * 400
    path = tmp_path / "huge.toml"
    try:
        if how == "set-int-option":
            Config.from_values(dict([parse_assignment(f"health.nis_window={huge}")]))
        else:
            key = "noise.pixel_sigma" if how == "toml-float-option" else "health.nis_window"
            table, _, leaf = key.partition(".")
            path.write_text(f"[{table}]\n{leaf} = {huge}\n")
            Config.load(path)
    except ConfigError as e:  # the right outcome (or a valid config)
        assert_clean_config_error(e)


@pytest.mark.parametrize("how", ["toml-key", "toml-table", "set"])
def test_config_key_with_line_break_regression(tmp_path, how):
    """Found by the properties (fixed since): a key or table name holding a line break (a TOML quoted key
    "a\\nb", --set $'a\\nb=1') went into the message as it was (OptionSet._refuse / _grouped,
    OptionTable.from_values): a multi-line ConfigError."""
    path = tmp_path / "nl.toml"
    with pytest.raises(ConfigError) as e:
        if how == "set":
            Config.from_values(dict([parse_assignment("noise.a\nb=1")]))
        else:
            path.write_text('[noise]\n"a\\nb" = 1\n' if how == "toml-key" else '["a\\nb"]\nx = 1\n')
            Config.load(path)
    assert_clean_config_error(e.value)


@pytest.mark.parametrize("name", ["noise.", "x."])
def test_config_table_name_ending_in_dot_regression(tmp_path, name):
    """Found by the properties (fixed since): OptionSet._grouped split a TOML table name at its first '.',
    as for --set's TABLE.KEY: the quoted table ["noise."] was read as [noise] (accepted), and ["x."] was
    refused as 'unknown table [x]', a name the file does not have."""
    path = tmp_path / "dot.toml"
    path.write_text(f'["{name}"]\npixel_sigma = 2.0\n')
    with pytest.raises(ConfigError) as e:
        Config.load(path)
    assert_clean_config_error(e.value, str(path), f"[{name}]")


def test_config_bom_regression(tmp_path):
    """Found by the properties (fixed since): a config file starting with a UTF-8 byte-order mark (as some
    Windows editors write) was refused as 'not valid TOML: Invalid statement (at line 1, column 1)', though
    textio.read_lines skips a BOM for every other text input."""
    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf[noise]\npixel_sigma = 2.0\n")
    assert Config.load(path).noise.pixel_sigma == 2.0


def test_config_top_level_dotted_key_regression(tmp_path):
    """A top-level "noise.pixel_sigma" in a TOML file: read, or refused without naming the key as its own new place."""
    path = tmp_path / "dotted.toml"
    path.write_text('"noise.pixel_sigma" = 2.0\n')
    try:
        cfg = Config.load(path)
    except ConfigError as e:
        assert "is now 'noise.pixel_sigma'" not in assert_clean_config_error(e, str(path), "noise.pixel_sigma")
    else:
        assert cfg.noise.pixel_sigma == 2.0


# ==============================================================================================
# --set TABLE.KEY=VALUE
# ==============================================================================================

def _option_text(tk, draw):
    """A valid value of the option ``tk`` as command-line text."""
    kind = FIELDS[tk][0]
    if kind is bool:
        return draw(st.sampled_from(["true", "false", "1", "0", "yes", "no", "on", "off", "True", " TRUE "]))
    if _is_enum(kind):
        return draw(st.sampled_from([m.value for m in kind])) + draw(st.sampled_from(["", " "]))
    if kind is int:
        return str(draw(VALID_INTS.get(tk, st.integers(1, 10**6))))
    x = draw(VALID_FLOATS.get(tk, st.floats(1e-6, 1e6)))
    return draw(st.sampled_from([repr, lambda x: f" {x:.6e}", lambda x: f"{x:.17g}"]))(x)


def expected_from_text(kind, optional, text):
    """The value of an accepted ``--set`` text (what options._coerce documents)."""
    s = text.strip()
    if optional and s.lower() in ("none", "null", "auto", ""):
        return None
    if kind is bool:
        return s.lower() in ("1", "true", "yes", "on")
    if kind is int:
        return int(s)
    if kind is float:
        return float(s)
    return s


value_texts = st.one_of(
    st.sampled_from(["nan", "NaN", "inf", "-inf", "1e999", "-1e999", "", " ", "0", "1", "-1", "2", "0.5", "1e-300",
                     "true", "false", "yes", "None", "none", "null", "auto", "slam", "body", "inverse-depth", "xyz",
                     "3.0", "1_000", "0x10", "\u0663", "\u00bd", "\u2162", "1" * 300, "1" + "0" * 400, "9" * 5000, "=",
                     "a=b", "\n",
                     "1\n", "'1'", "\"2\""]),
    st.text(max_size=10),
    st.integers(-10**30, 10**30).map(str),
    st.floats().map(repr),
)
key_texts = st.one_of(
    st.sampled_from([f"{t}.{k}" for t, k in FIELDS]),
    st.sampled_from([f"{t}.{k}".replace("_", "-") for t, k in FIELDS]),
    st.sampled_from([f" {t}.{k} " for t, k in FIELDS]),
    st.sampled_from([k for _, k in FIELDS] + TABLES + ["landmark_parametrization", "convention_horizon",
                                                        "tracker.target_tracks", "target_tracks", "tracker",
                                                        "NOISE.PIXEL_SIGMA", "noise.", ".pixel_sigma", "", ".",
                                                        "noise..pixel_sigma", "noise.pixel_sigma.x"]),
    st.text(string.ascii_letters + string.digits + "._- '\"\u00e9\n\r\t\u2028", max_size=14),
)


@st.composite
def assignments(draw):
    """(item, its key as parse_assignment reads it, (table, key) of the real option it names or None,
    True if the value is a valid text for that option)."""
    key = draw(key_texts, label="key")
    tk = key.strip().replace("-", "_")
    tk = tuple(tk.split(".", 1)) if tk.count(".") == 1 else None
    tk = tk if tk in FIELDS else None
    valid = tk is not None and draw(st.booleans())
    value = _option_text(tk, draw) if valid else draw(value_texts, label="value")
    item = f"{key}={value}" if draw(st.integers(0, 9)) else key + value  # now and then no '='
    keypart = item.split("=", 1)[0]
    norm = keypart.strip().replace("-", "_")
    if keypart != key:  # no '=' between key and value
        tk, valid = None, False
    return item, norm, tk, valid


@settings(max_examples=150, **SETTINGS)
@given(a=assignments())
def test_set_assignment_property(a):
    """One ``--set TABLE.KEY=VALUE`` (real keys, with dashes, spaces or upper case, moved and tracker keys,
    junk; values such as nan, inf, 1e999, "", 0, 1, true, None, unicode digits): parse_assignment then
    Config.from_values give a one-line ConfigError naming the key (or the item), or a valid Config holding
    the value the text says; a valid value of a real option is always taken (but for a cross-table rule)."""
    item, norm, tk, valid = a
    try:
        key, value = parse_assignment(item)
        cfg = Config.from_values({key: value})
    except ConfigError as e:
        msg = assert_clean_config_error(e)
        if "=" not in item:
            assert repr(item) in msg, msg
        else:
            assert mentions(msg, norm), msg
            if valid:  # only a cross-table rule may refuse it
                assert tk in RULE_KEYS and f"'{RULE_KEYS[tk]}'" in msg, msg
        return
    assert_valid_config(cfg)
    assert tk is not None and "=" in item, f"accepted {item!r}"
    kind, optional, _ = FIELDS[tk]
    assert getattr(getattr(cfg, tk[0]), tk[1]) == expected_from_text(kind, optional, value)


@settings(max_examples=80, **SETTINGS)
@given(items=st.lists(assignments(), max_size=3), config=st.none() | valid_documents(),
       mode=st.sampled_from([None, "slam", "mapping", "dead-reckoning"]), full_state=st.booleans(),
       imu_flip=st.sampled_from([None, "auto", "yes", "no"]),
       velocity_index=st.sampled_from([None, "auto", "this", "next"]))
def test_filter_config_property(items, config, mode, full_state, imu_flip, velocity_index):
    """The command line's path (tools.options.filter_config): an optional --config file, the dedicated
    flags and up to three --set items: a one-line ConfigError, or a valid Config in which the last --set of
    each real option wins and the flags hold where no --set overrides them; tracker.* items are skipped."""
    with tempfile.TemporaryDirectory() as d:
        path = None
        if config is not None:
            path = Path(d) / "run.toml"
            path.write_text(toml_document({}, _tables_of(config)), encoding="utf-8")
        args = argparse.Namespace(config=str(path) if path else None, set=[i for i, *_ in items], mode=mode,
                                  full_state=full_state, imu_flip=imu_flip, velocity_index=velocity_index)
        try:
            cfg = filter_config(args)
        except ConfigError as e:
            msg = assert_clean_config_error(e)
            culprits = [repr(i) for i, *_ in items] + [n for _, n, *_ in items] + ([str(path)] if path else [])
            culprits += ["estimator.error_model", "input.image_width"]  # the cross-table rules
            assert any(mentions(msg, c) for c in culprits), f"names none of {culprits}: {msg}"
            return
    assert_valid_config(cfg)
    for item, norm, tk, _ in items:
        # a tracker.KEY item is the tracker's (skipped here)
        assert "=" in item and (tk is not None or norm.startswith("tracker.")), f"accepted {item!r}"
    last = {tk: item.split("=", 1)[1] for item, _, tk, _ in items if tk is not None}
    for tk, text in last.items():
        assert getattr(getattr(cfg, tk[0]), tk[1]) == expected_from_text(*FIELDS[tk][:2], text)
    flags = {("estimator", "mode"): mode, ("conventions", "imu_flip"): imu_flip,
             ("conventions", "velocity_index"): velocity_index, ("estimator", "full_state"): full_state or None}
    for tk, flag in flags.items():
        if flag is not None and tk not in last:
            assert getattr(getattr(cfg, tk[0]), tk[1]) == flag, tk


@pytest.mark.parametrize("item", ["tracker=5", "tracker.=5"])
def test_set_bare_tracker_table_regression(item):
    """'--set tracker=5' names no option: refused (one line naming 'tracker'), as '--set noise=5' is."""
    args = argparse.Namespace(config=None, set=[item], mode=None, full_state=False, imu_flip=None, velocity_index=None)
    with pytest.raises(ConfigError) as e:
        filter_config(args)
    assert_clean_config_error(e.value, "tracker")


# ------------------------------------------------------------------------------------------------
# Python's digit separators are no number in a data file: '1_3.17' is never read as 13.17


def _with_separator(draw, value: float) -> str:
    """``value`` as text with an underscore between two of its digits."""
    text = repr(value)
    spots = [i for i in range(1, len(text)) if text[i - 1].isdigit() and text[i].isdigit()]
    assume(spots)
    i = draw(st.sampled_from(spots))
    return text[:i] + "_" + text[i:]


@st.composite
def tum_line_with_separator(draw):
    values = [draw(st.floats(1.0, 1e6)), *draw(st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3)),
              0.0, 0.0, 0.0, 1.0]
    column = draw(st.integers(0, 3))
    tokens = [repr(v) for v in values]
    tokens[column] = _with_separator(draw, values[column])
    return " ".join(tokens), column


@given(tum_line_with_separator())
@settings(max_examples=60, deadline=None)
def test_tum_digit_separators_are_refused_property(case):
    line, _ = case
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "t.txt"
        path.write_text(f"0 0 0 0 0 0 0 1\n{line}\n")
        with pytest.raises(InputError) as e:
            read_tum(str(path))
        msg = assert_clean_input_error(e.value, str(path))
        assert ":2" in msg and "not a number" in msg, msg


@given(st.lists(st.floats(-50, 50), min_size=7, max_size=7), st.integers(0, 6), st.data())
@settings(max_examples=60, deadline=None)
def test_imu_csv_digit_separators_are_refused_property(values, column, data):
    from vislam.frontend.imu_input import read_imu_csv

    values[0] = abs(values[0]) + 1.0  # the second row's stamp after the first's 0
    tokens = [repr(v) for v in values]
    tokens[column] = _with_separator(data.draw, values[column])
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "imu.csv"
        path.write_text("t,vx,vy,vz,wx,wy,wz\n0,0,0,0,0,0,0\n" + ",".join(tokens) + "\n")
        with pytest.raises(InputError) as e:
            read_imu_csv(path, 2)
        assert "line 3" in assert_clean_input_error(e.value, str(path))


@given(st.floats(allow_nan=False, allow_infinity=False))
@settings(max_examples=200, deadline=None)
def test_text_float_reads_every_float_repr_property(value):
    from vislam.backend.data.textio import text_float

    assert text_float(repr(value)) == value and text_float(f"{value:.17e}") == value


# ------------------------------------------------------------------------------------------------
# KITTI pose files (backend.data.tum.read_kitti_poses, read_trajectory)


def _rotation(rotvec) -> np.ndarray:
    from vislam.backend.geometry import se3

    return se3.exp_so3_and_left_jacobian(np.asarray(rotvec, dtype=float))[0]


def _refused_at_line(reader, name: str, lines: list[str], k: int, damaged: str) -> None:
    """``reader`` of a file ``name`` whose line k+1 is ``damaged``: a one-line InputError naming the
    file and that line."""
    lines = list(lines)
    lines[k] = damaged
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / name
        path.write_text("\n".join(lines) + "\n")
        with pytest.raises(InputError) as e:
            reader(path)
        msg = assert_clean_input_error(e.value, str(path))
        assert msg.startswith(f"{path}:{k + 1}:"), msg


@st.composite
def kitti_pose_lines(draw):
    """(text lines, poses (N,4,4)) of a valid KITTI pose file printed with 9 or 6 significant digits."""
    n = draw(st.integers(1, 8))
    digits = draw(st.sampled_from([9, 6]))
    rotvecs = draw(hnp.arrays(np.float64, (n, 3), elements=st.floats(-3, 3)))
    trans = draw(hnp.arrays(np.float64, (n, 3), elements=st.floats(-1e4, 1e4)))
    poses = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        poses[k, :3, :3] = _rotation(rotvecs[k])
        poses[k, :3, 3] = trans[k]
    lines = [" ".join(f"{v:.{digits - 1}e}" for v in P[:3].ravel()) for P in poses]
    return lines, poses, digits


@settings(max_examples=80, **SETTINGS)
@given(case=kitti_pose_lines(), blank=st.booleans(), crlf=st.booleans())
def test_kitti_valid_files_are_read_property(case, blank, crlf):
    """A KITTI pose file printed to 6 or 9 digits reads back as its poses (rotations made exactly
    orthonormal, within the printing's rounding), and read_trajectory calls it KITTI, by index."""
    from vislam.backend.data.tum import read_kitti_poses, read_trajectory

    lines, poses, digits = case
    text = ("\r\n" if crlf else "\n").join(lines + ([""] if blank else [])) + "\n"
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "poses.txt"
        path.write_text(text)
        read = read_kitti_poses(path)
        traj = read_trajectory(path)
    tol = 10.0 ** (1 - digits)
    R = read[:, :3, :3]
    assert np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max() <= 1e-12
    assert np.abs(R - poses[:, :3, :3]).max() <= 4 * tol
    assert np.allclose(read[:, :3, 3], poses[:, :3, 3], rtol=tol, atol=tol)
    assert traj.format == "kitti" and traj.by_index and np.array_equal(traj.time_stamps, np.arange(len(poses)))


@settings(max_examples=120, **SETTINGS)
@given(case=kitti_pose_lines(), data=st.data())
def test_kitti_damaged_lines_are_one_line_errors_property(case, data):
    """A pose line with a token dropped or added, junk, nan, a digit separator, a rotation scaled
    beyond rounding or a reflection: one-line InputError naming the file and that line."""
    from vislam.backend.data.tum import read_kitti_poses

    lines, poses, _ = case
    k = data.draw(st.integers(0, len(lines) - 1))
    tokens = lines[k].split()
    damage = data.draw(st.sampled_from(["drop", "add", "junk", "nan", "separator", "scale", "reflect"]))
    if damage == "drop":
        tokens.pop(data.draw(st.integers(0, 11)))
    elif damage == "add":
        tokens.append("1.0")
    elif damage == "junk":
        tokens[data.draw(st.integers(0, 11))] = "x1"
    elif damage == "nan":
        tokens[data.draw(st.integers(0, 11))] = "nan"
    elif damage == "separator":
        i = data.draw(st.integers(0, 11))
        tokens[i] = "1_" + tokens[i].lstrip("-")
    else:
        P = poses[k][:3].copy()
        if damage == "scale":
            P[:, :3] *= 1.01
        else:
            P[:, 0] *= -1
        tokens = [f"{v:.9e}" for v in P.ravel()]
    _refused_at_line(read_kitti_poses, "poses.txt", lines, k, " ".join(tokens))


def test_trajectory_files_of_neither_format_are_refused(tmp_path):
    from vislam.backend.data.tum import read_trajectory

    path = tmp_path / "t.txt"
    path.write_text("# comment\n1 2 3 4 5\n")
    with pytest.raises(InputError) as e:
        read_trajectory(path)
    msg = assert_clean_input_error(e.value, str(path))
    assert ":2:" in msg and "8 columns" in msg and "12" in msg


# ------------------------------------------------------------------------------------------------
# EuRoC pose csv (backend.data.tum.read_euroc_csv, read_trajectory)


@st.composite
def euroc_pose_rows(draw):
    """(text lines with a header, stamps in ns, poses (N,4,4)) of a valid EuRoC pose csv, with 0 or 9
    extra columns (velocity and biases, as state_groundtruth_estimate0/data.csv)."""
    n = draw(st.integers(1, 8))
    start = draw(st.integers(0, 2 * 10**18))
    steps = draw(st.lists(st.integers(1, 10**10), min_size=n, max_size=n))
    ns = [start + sum(steps[:k + 1]) for k in range(n)]
    rotvecs = draw(hnp.arrays(np.float64, (n, 3), elements=st.floats(-3, 3)))
    trans = draw(hnp.arrays(np.float64, (n, 3), elements=st.floats(-1e4, 1e4)))
    extra = draw(st.sampled_from([0, 9]))
    poses = np.tile(np.eye(4), (n, 1, 1))
    lines = ["#timestamp [ns],p_x [m],p_y [m],p_z [m],q_w [],q_x [],q_y [],q_z []" + ",v" * extra]
    for k in range(n):
        poses[k, :3, :3] = _rotation(rotvecs[k])
        poses[k, :3, 3] = trans[k]
        q = Rotation.from_matrix(poses[k, :3, :3]).as_quat()  # x y z w
        values = list(trans[k]) + [q[3], q[0], q[1], q[2]] + [0.5] * extra
        lines.append(",".join([str(ns[k])] + [repr(float(v)) for v in values]))
    return lines, np.array(ns, dtype=object), poses


@settings(max_examples=80, **SETTINGS)
@given(case=euroc_pose_rows(), bare_header=st.booleans(), crlf=st.booleans())
def test_euroc_valid_files_are_read_property(case, bare_header, crlf):
    """An EuRoC pose csv (header with or without '#', 8 or 17 columns) reads back as its poses, its
    nanosecond stamps as seconds to float64's spacing, and read_trajectory calls it EuRoC (by time)."""
    from vislam.backend.data.tum import read_euroc_csv, read_trajectory

    lines, ns, poses = case
    if bare_header:
        lines = [lines[0].lstrip("#")] + lines[1:]
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "data.csv"
        path.write_text(("\r\n" if crlf else "\n").join(lines) + "\n")
        t, read = read_euroc_csv(path)
        traj = read_trajectory(path)
    expected = np.array([float(n) / 1e9 for n in ns])
    assert np.all(np.abs(t - expected) <= 4 * np.spacing(expected))
    assert np.all(np.diff(t) >= 0)
    assert np.abs(read - poses).max() <= 1e-9 * max(1.0, np.abs(poses).max())
    assert traj.format == "euroc" and not traj.by_index and np.array_equal(traj.time_stamps, t)


@settings(max_examples=120, **SETTINGS)
@given(case=euroc_pose_rows(), data=st.data())
def test_euroc_damaged_lines_are_one_line_errors_property(case, data):
    """A row with too few columns, junk, nan, a fractional or negative stamp, a stamp not after the
    previous one or a zero quaternion: one-line InputError naming the file and that line."""
    from vislam.backend.data.tum import read_euroc_csv

    lines, ns, _ = case
    k = data.draw(st.integers(1, len(lines) - 1))
    tokens = lines[k].split(",")
    damage = data.draw(st.sampled_from(["short", "junk", "nan", "fraction", "negative", "order", "zero"]))
    if damage == "order" and k == 1:
        damage = "fraction"
    if damage == "short":
        tokens = tokens[:data.draw(st.integers(1, 7))]
    elif damage == "junk":
        tokens[data.draw(st.integers(1, 7))] = "x1"
    elif damage == "nan":
        tokens[data.draw(st.integers(1, 7))] = "nan"
    elif damage == "fraction":
        tokens[0] = tokens[0] + ".5"
    elif damage == "negative":
        tokens[0] = "-" + tokens[0]
    elif damage == "order":
        tokens[0] = str(ns[k - 2])
    else:
        tokens[4:8] = ["0", "0", "0", "0"]
    _refused_at_line(read_euroc_csv, "data.csv", lines, k, ",".join(tokens))


# ------------------------------------------------------------------------------------------------
# symbolic links: a chain reads as its target, a loop or a dangling link is one line saying which


@settings(max_examples=20, **SETTINGS)
@given(links=st.integers(1, 6), kind=st.sampled_from(["npz", "tum"]))
def test_readers_follow_a_chain_of_links_and_name_a_loop_property(links, kind):
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        if kind == "npz":
            target = _write(root / "data.npz", course_arrays())
            read = load_sequence
        else:
            target = root / "t.txt"
            target.write_text("0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n")
            read = read_tum
        chain = target
        for i in range(links):
            link = root / f"link{i}.{kind}"
            link.symlink_to(chain)
            chain = link
        direct, through = read(target), read(chain)
        if kind == "npz":
            assert np.array_equal(direct.obs_pixels, through.obs_pixels)
            assert np.array_equal(direct.time_stamps, through.time_stamps)
        else:
            assert all(np.array_equal(a, b) for a, b in zip(direct, through))
        loop_a, loop_b = root / f"a.{kind}", root / f"b.{kind}"
        loop_a.symlink_to(loop_b)
        loop_b.symlink_to(loop_a)
        dangling = root / f"gone.{kind}"
        dangling.symlink_to(root / "nothing")
        gone = "not found" if kind == "tum" else "does not exist (a symbolic link to nothing)"
        for path, needle in ((loop_a, "Too many levels of symbolic links"), (dangling, gone)):
            with pytest.raises(InputError) as e:
                read(path)
            msg = assert_clean_input_error(e.value, str(path))
            assert needle in msg, msg
