"""Tests of vislam.backend.data.sequence (the Sequence, its CSR access, construction from per-step
observations and validation) and vislam.backend.data.npz (streaming .npz loading and atomic saving)."""

from __future__ import annotations

import dataclasses
import io
import os
import tempfile
import time
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.lib import format as npformat

from vislam.backend.data import npz as npz_mod
from vislam.backend.data.npz import load_sequence, save_sequence
from vislam.backend.data.sequence import VISLAM_TRACKER, Sequence, validate_sequence
from vislam.backend.errors import InputError, OutputError, VislamError

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
REAL = {  # file: (layout, N, M) as documented in shared/data/SOURCES.md
    "ece276a_03.npz": ("2022", 1010, 5105),
    "ece276a_0027.npz": ("2019", 1106, 3950),
    "ece276a2019_0042.npz": ("2019", 500, 104),
}
LAYOUT_KEYS = {"2022": ("angular_velocity", "imu_T_cam"), "2019": ("rotational_velocity", "cam_T_imu")}

# synthetic camera: cx = 320, cy = 240 -> inferred image 800 x 600
K_SYN = np.array([[500.0, 0.0, 320.0], [0.0, 510.0, 240.0], [0.0, 0.0, 1.0]])
W_SYN, H_SYN = 2 * 320 * 1.25, 2 * 240 * 1.25


# ----------------------------------------------------------------------------------------------
# helpers


def rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    x = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * x + (1 - np.cos(angle)) * x @ x


def rigid(R, p):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T


IMU_T_CAM = rigid(rot([1, 2, 3], 2.0), [1.5, 0.01, -0.65])


def reference_csr(F, width, height):
    """Direct dense computation of the expected kept observations and drop counts."""
    present = (F != -1).any(axis=0)
    ptr, ids, pix = [0], [], []
    nonpos = outside_n = 0
    for k in range(F.shape[2]):
        js = np.flatnonzero(present[:, k])
        P = F[:, js, k].T.astype(np.float64)
        partial = (P == -1).any(axis=1)
        u, v = P[:, [0, 2]], P[:, [1, 3]]
        inside = (u >= 0).all(1) & (u < width).all(1) & (v >= 0).all(1) & (v < height).all(1)
        outside = partial | ~inside
        bad_disp = ~outside & (P[:, 0] - P[:, 2] <= 0)
        keep = ~outside & ~bad_disp
        nonpos += int(bad_disp.sum())
        outside_n += int(outside.sum())
        ids.append(js[keep])
        pix.append(P[keep])
        ptr.append(ptr[-1] + int(keep.sum()))
    return (np.array(ptr), np.concatenate(ids) if ids else np.zeros(0, int),
            np.concatenate(pix) if pix else np.zeros((0, 4)),
            {"nonpositive_disparity": nonpos, "outside_image": outside_n})


def synthetic_features(n=7, m=6):
    """(4,M,N) with a known mix of good, bad-disparity, outside and partial observations.

    Hand count: nonpositive_disparity = 2, outside_image = 6.
    """
    rng = np.random.default_rng(1)
    F = np.full((4, m, n), -1.0)
    for j in range(m):
        for k in range(n):
            if (j + 2 * k) % 3:
                uL = rng.uniform(60, 700)
                v = rng.uniform(5, 500)
                F[:, j, k] = [uL, v, uL - rng.uniform(0.5, 40), v + rng.uniform(-0.9, 0.9)]
    F[:, 0, 1] = [100, 50, 100, 50]  # disparity 0
    F[:, 1, 3] = [100, 50, 120, 50]  # negative disparity
    F[:, 2, 0] = [W_SYN, 50, 700, 50]  # uL == width: outside
    F[:, 3, 6] = [300, -0.5, 280, 3]  # vL < 0 (not the -1 sentinel): outside
    F[:, 4, 2] = [300, H_SYN + 1, 280, 3]  # vL beyond height, and negative-disparity-free
    F[:, 5, 5] = [-1, 50, 80, 50]  # partial, uL == -1
    F[:, 5, 4] = [90, 50, -1, -1]  # partial, uR vR == -1
    F[:, 1, 0] = [50, 60, 70, -1]  # partial and negative disparity: counts as outside only
    F[:, 0, 6] = [W_SYN - 1e-6, H_SYN - 1e-6, W_SYN - 2, H_SYN - 1e-6]  # just inside: kept
    return F


def course_arrays(layout="2022", n=7, m=6, features=None):
    rng = np.random.default_rng(2)
    ang_key, ext_key = LAYOUT_KEYS[layout]
    arrays = {
        "time_stamps": (1.3e9 + 0.1 * np.arange(n) + rng.uniform(0, 0.01, n)).reshape(1, n),
        "features": synthetic_features(n, m) if features is None else features,
        "linear_velocity": np.asfortranarray(rng.normal(size=(3, n))),
        ang_key: rng.normal(scale=0.1, size=(3, n)),
        "K": K_SYN.copy(),
        "b": np.array(0.54),
        ext_key: IMU_T_CAM if layout == "2022" else np.linalg.inv(IMU_T_CAM),
    }
    return arrays


def write_npz(path, arrays, compressed=True):
    (np.savez_compressed if compressed else np.savez)(path, **arrays)
    return path


def assert_one_line_error(excinfo, fname, key=None):
    msg = str(excinfo.value)
    assert isinstance(excinfo.value, InputError) and isinstance(excinfo.value, VislamError)
    assert "\n" not in msg, msg
    assert fname in msg, msg
    if key is not None:
        assert f"key '{key}'" in msg, msg
    return msg


def assert_same(seq_a: Sequence, seq_b: Sequence, exact_extrinsic=True, atol=1e-14):
    for name in ("time_stamps", "linear_velocity", "angular_velocity", "K", "obs_ptr", "obs_ids", "obs_pixels"):
        a, b = getattr(seq_a, name), getattr(seq_b, name)
        assert a.shape == b.shape and a.dtype == b.dtype, name
        assert np.array_equal(a, b), name
    assert seq_a.baseline == seq_b.baseline
    assert seq_a.num_features == seq_b.num_features
    if exact_extrinsic:
        assert np.array_equal(seq_a.imu_T_cam, seq_b.imu_T_cam)
    else:
        assert np.array_equal(seq_a.imu_T_cam[:3, :3], seq_b.imu_T_cam[:3, :3])
        np.testing.assert_allclose(seq_a.imu_T_cam, seq_b.imu_T_cam, rtol=0, atol=atol)


def steps_of(seq):
    return np.repeat(np.arange(seq.num_steps), np.diff(seq.obs_ptr))


def ids_increasing_within_steps(seq):
    s = steps_of(seq)
    same = s[1:] == s[:-1]
    return bool((np.diff(seq.obs_ids)[same] > 0).all())


# ----------------------------------------------------------------------------------------------
# loading synthetic files


@pytest.mark.parametrize("layout", ["2022", "2019"])
@pytest.mark.parametrize("compressed", [True, False])
@pytest.mark.parametrize("order", ["C", "F"])
@pytest.mark.parametrize("chunk_bytes", [None, 64, 72])
def test_load_matches_dense_reference(tmp_path, monkeypatch, layout, compressed, order, chunk_bytes):
    if chunk_bytes is not None:  # tiny chunks: many chunk boundaries inside channels and steps
        monkeypatch.setattr(npz_mod, "_CHUNK_BYTES", chunk_bytes)
    arrays = course_arrays(layout)
    F = arrays["features"]
    arrays["features"] = np.asfortranarray(F) if order == "F" else F
    path = write_npz(tmp_path / "syn.npz", arrays, compressed)
    if order == "F":  # the file really is Fortran-ordered
        with zipfile.ZipFile(path) as zf, zf.open("features.npy") as f:
            npformat.read_magic(f)
            assert npformat.read_array_header_1_0(f)[1] is True

    seq = load_sequence(path)
    ptr, ids, pix, dropped = reference_csr(F, W_SYN, H_SYN)
    assert seq.dropped == dropped == {"nonpositive_disparity": 2, "outside_image": 6}
    assert np.array_equal(seq.obs_ptr, ptr) and seq.obs_ptr.dtype == np.int64
    assert np.array_equal(seq.obs_ids, ids) and seq.obs_ids.dtype == np.int64
    assert np.array_equal(seq.obs_pixels, pix) and seq.obs_pixels.dtype == np.float64
    assert ids_increasing_within_steps(seq)
    assert seq.layout == layout and seq.num_features == 6 and seq.num_steps == 7
    assert seq.source == str(path)
    ang_key, ext_key = LAYOUT_KEYS[layout]
    assert np.array_equal(seq.time_stamps, arrays["time_stamps"][0]) and seq.time_stamps.shape == (7,)
    assert np.array_equal(seq.linear_velocity, arrays["linear_velocity"].T)
    assert np.array_equal(seq.angular_velocity, arrays[ang_key].T)
    assert seq.linear_velocity.flags.c_contiguous and seq.angular_velocity.shape == (7, 3)
    assert np.array_equal(seq.K, K_SYN) and seq.baseline == 0.54
    if layout == "2022":
        assert np.array_equal(seq.imu_T_cam, IMU_T_CAM)
    else:
        np.testing.assert_allclose(seq.imu_T_cam, IMU_T_CAM, atol=1e-14)
        np.testing.assert_allclose(seq.imu_T_cam @ arrays["cam_T_imu"], np.eye(4), atol=1e-14)
        assert np.array_equal(seq.cam_T_imu, arrays["cam_T_imu"])  # the file's own, bit for bit


@pytest.mark.parametrize("dtype", ["<f4", ">f8", "<i4", "<i8", ">i2"])
def test_load_other_numeric_dtypes(tmp_path, dtype):
    F = np.round(synthetic_features()) if dtype[1] == "i" else synthetic_features()
    F[:, 0, 6] = [700, 500, 600, 500]  # the just-inside sample is not integral
    Fd = F.astype(dtype)
    seq = load_sequence(write_npz(tmp_path / "d.npz", course_arrays(features=Fd)))
    ptr, ids, pix, dropped = reference_csr(Fd.astype(np.float64), W_SYN, H_SYN)
    assert seq.dropped == dropped
    assert np.array_equal(seq.obs_ptr, ptr) and np.array_equal(seq.obs_ids, ids)
    assert seq.obs_pixels.dtype == np.float64 and np.array_equal(seq.obs_pixels, pix)


def test_time_stamps_may_be_1d(tmp_path):
    arrays = course_arrays()
    arrays["time_stamps"] = arrays["time_stamps"][0]
    seq = load_sequence(write_npz(tmp_path / "t.npz", arrays))
    assert np.array_equal(seq.time_stamps, arrays["time_stamps"])
    arrays["b"] = np.array([0.54])  # size-1 baseline
    assert load_sequence(write_npz(tmp_path / "t2.npz", arrays)).baseline == 0.54


def test_image_bounds_inferred_from_K_and_explicit(tmp_path):
    n, m = 2, 3
    F = np.full((4, m, n), -1.0)
    F[:, 0, 0] = [W_SYN - 1e-9, 10, W_SYN - 5, 10]  # inside the inferred 800 x 600
    F[:, 1, 0] = [W_SYN, 10, W_SYN - 5, 10]  # u == width: outside
    F[:, 2, 1] = [700, H_SYN, 650, 10]  # v == height: outside
    F[:, 0, 1] = [650, 470, 600, 470]  # inside 800 x 600, outside 640 x 480 (650 >= 640)
    path = write_npz(tmp_path / "b.npz", course_arrays(n=n, m=m, features=F))
    seq = load_sequence(path)
    assert seq.dropped == {"nonpositive_disparity": 0, "outside_image": 2}
    assert seq.observations(0)[0].tolist() == [0] and seq.observations(1)[0].tolist() == [0]
    seq2 = load_sequence(path, image_size=(640, 480))
    assert seq2.dropped == {"nonpositive_disparity": 0, "outside_image": 4}
    assert seq2.num_observations == 0
    seq3 = load_sequence(path, image_size=(2000.0, 2000.0))
    assert seq3.dropped["outside_image"] == 0 and seq3.num_observations == 4
    with pytest.raises(InputError, match="image_size"):
        load_sequence(path, image_size=(0, 480))


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(2, 9),
    m=st.integers(0, 9),
    seed=st.integers(0, 2**32 - 1),
    chunk=st.sampled_from([8, 16, 24, 40, 1 << 20]),
    order=st.sampled_from("CF"),
)
def test_streaming_equals_dense_reference_property(n, m, seed, chunk, order):
    """Random sentinel patterns (incl. partial -1s) and random chunk sizes: streaming == dense."""
    rng = np.random.default_rng(seed)
    F = rng.uniform(-50, 900, size=(4, m, n)).round(rng.integers(0, 3))
    F[:, rng.random((m, n)) < 0.5] = -1.0
    F[rng.random((4, m, n)) < 0.1] = -1.0  # partial observations
    arrays = course_arrays(n=n, m=m, features=np.asfortranarray(F) if order == "F" else F)
    default_chunk = npz_mod._CHUNK_BYTES
    npz_mod._CHUNK_BYTES = chunk
    try:
        with tempfile.TemporaryDirectory() as d:
            seq = load_sequence(write_npz(Path(d) / "p.npz", arrays, compressed=bool(seed % 2)))
    finally:
        npz_mod._CHUNK_BYTES = default_chunk
    ptr, ids, pix, dropped = reference_csr(F, W_SYN, H_SYN)
    assert seq.dropped == dropped
    assert np.array_equal(seq.obs_ptr, ptr)
    assert np.array_equal(seq.obs_ids, ids)
    assert np.array_equal(seq.obs_pixels, pix)
    validate_sequence(seq)


# ----------------------------------------------------------------------------------------------
# refusing bad files


def _set(key, value):
    def mutate(a):
        a[key] = value(a) if callable(value) else value
    return mutate


def _drop(*keys):
    def mutate(a):
        for k in keys:
            del a[k]
    return mutate


def _nan_at(key, idx, val=np.nan):
    def mutate(a):
        x = np.array(a[key], dtype=np.float64)
        x[idx] = val
        a[key] = x
    return mutate


def _K(**entries):
    def mutate(a):
        K = K_SYN.copy()
        for name, v in entries.items():
            K[tuple(int(c) for c in name[1:])] = v
        a["K"] = K
    return mutate


def _ext(fn):
    def mutate(a):
        a["imu_T_cam"] = fn(IMU_T_CAM.copy())
    return mutate


def _scaled(T):
    T[:3, :3] *= 1.001
    return T


def _reflected(T):
    T[:3, 0] *= -1
    return T


def _last_row(T):
    T[3, 0] = 1e-3
    return T


def _time(fn):
    def mutate(a):
        t = a["time_stamps"].copy()
        fn(t[0])
        a["time_stamps"] = t
    return mutate


def _repeat_t3(t):
    t[3] = t[2]


def _decrease_t5(t):
    t[5] = t[4] - 1


BAD_FILES = {
    # id: (mutation of course_arrays("2022"), key named, message fragment)
    "missing-common-key": (_drop("K"), "K", "missing"),
    "missing-features": (_drop("features"), "features", "missing"),
    "missing-extrinsic": (_drop("imu_T_cam"), "imu_T_cam", "rotational_velocity'+'cam_T_imu"),
    "missing-angular": (_drop("angular_velocity"), "angular_velocity", "angular_velocity'+'imu_T_cam"),
    "mixed-layouts": (
        lambda a: a.update(cam_T_imu=a.pop("imu_T_cam")), "imu_T_cam", "rotational_velocity'+'cam_T_imu"),
    "both-layouts-disagree": (
        lambda a: a.update(cam_T_imu=np.linalg.inv(IMU_T_CAM), rotational_velocity=a["angular_velocity"] + 0.1),
        "rotational_velocity", "'angular_velocity' differs"),
    "both-layouts-extrinsics-disagree": (
        lambda a: a.update(cam_T_imu=IMU_T_CAM, rotational_velocity=a["angular_velocity"]),
        "cam_T_imu", "not each other's inverse"),
    "features-3-channels": (_set("features", lambda a: a["features"][:3]), "features",
                            "expected shape (4, M, 7) (N from 'time_stamps'), got (3, 6, 7)"),
    "features-wrong-N": (_set("features", lambda a: a["features"][:, :, :5]), "features", "got (4, 6, 5)"),
    "features-2d": (_set("features", lambda a: a["features"][0]), "features", "got (6, 7)"),
    "features-nan": (_nan_at("features", (2, 3, 4)), "features", "[2, 3, 4]"),
    "features-inf-ch0": (_nan_at("features", (0, 5, 6), np.inf), "features", "[0, 5, 6]"),
    "features-nan-unseen": (_nan_at("features", (3, 0, 0)), "features", "non-finite"),
    "features-object": (_set("features", lambda a: a["features"].astype(object)), "features", "object"),
    "features-bool": (_set("features", lambda a: a["features"] > 0), "features", "dtype bool"),
    "features-complex": (_set("features", lambda a: a["features"].astype(complex)), "features", "complex"),
    "time-2-rows": (_set("time_stamps", lambda a: np.vstack([a["time_stamps"]] * 2)), "time_stamps",
                    "expected shape (N,) or (1, N), got (2, 7)"),
    "time-empty": (lambda a: a.update(time_stamps=np.zeros((1, 0)), features=np.zeros((4, 6, 0)),
                                      linear_velocity=np.zeros((3, 0)), angular_velocity=np.zeros((3, 0))),
                   "time_stamps", "empty sequence"),
    "time-nan": (_nan_at("time_stamps", (0, 2)), "time_stamps", "non-finite"),
    "time-repeated": (_time(_repeat_t3), "time_stamps", "not strictly increasing: [3]"),
    "time-decreasing": (_time(_decrease_t5), "time_stamps", "not strictly increasing: [5]"),
    "time-object": (_set("time_stamps", lambda a: a["time_stamps"].astype(object)), "time_stamps", "cannot read"),
    "time-string": (_set("time_stamps", np.array([["a"] * 7])), "time_stamps", "dtype <U1"),
    "linvel-transposed": (_set("linear_velocity", lambda a: a["linear_velocity"].T), "linear_velocity",
                          "expected shape (3, 7) (N from 'time_stamps'), got (7, 3)"),
    "angvel-short": (_set("angular_velocity", lambda a: a["angular_velocity"][:, :6]), "angular_velocity",
                     "got (3, 6)"),
    "linvel-inf": (_nan_at("linear_velocity", (1, 1), -np.inf), "linear_velocity", "non-finite value -inf"),
    "K-shape": (_set("K", np.eye(3, 4)), "K", "expected shape (3, 3), got (3, 4)"),
    "K-fx-zero": (_K(k00=0.0), "K", "fx = 0"),
    "K-fy-negative": (_K(k11=-5.0), "K", "fy = -5"),
    "K-last-row": (_K(k21=1.0), "K", "last row"),
    "K-skew-row": (_K(k10=0.1), "K", "K[1,0]"),
    "K-nan": (_nan_at("K", (0, 2)), "K", "non-finite"),
    "b-zero": (_set("b", np.array(0.0)), "b", "must be > 0"),
    "b-negative": (_set("b", np.array(-0.5)), "b", "must be > 0"),
    "b-vector": (_set("b", np.array([0.5, 0.5])), "b", "scalar"),
    "b-nan": (_set("b", np.array(np.nan)), "b", "non-finite"),
    "ext-shape": (_set("imu_T_cam", np.eye(3, 4)), "imu_T_cam", "expected shape (4, 4)"),
    "ext-last-row": (_ext(_last_row), "imu_T_cam", "last row"),
    "ext-scaled": (_ext(_scaled), "imu_T_cam", "R^T R - I"),
    "ext-reflection": (_ext(_reflected), "imu_T_cam", "det(R)"),
    "ext-nan": (_nan_at("imu_T_cam", (0, 3)), "imu_T_cam", "non-finite"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_file_is_refused_with_one_line(tmp_path, case):
    mutate, key, fragment = BAD_FILES[case]
    arrays = course_arrays("2022")
    mutate(arrays)
    path = write_npz(tmp_path / f"bad_{case}.npz", arrays)
    with pytest.raises(InputError) as excinfo:
        load_sequence(path)
    msg = assert_one_line_error(excinfo, f"bad_{case}.npz", key)
    assert fragment in msg


def test_bad_2019_extrinsic_is_named_by_its_key(tmp_path):
    arrays = course_arrays("2019")
    arrays["cam_T_imu"] = _reflected(arrays["cam_T_imu"].copy())
    with pytest.raises(InputError) as excinfo:
        load_sequence(write_npz(tmp_path / "r.npz", arrays))
    assert "det(R)" in assert_one_line_error(excinfo, "r.npz", "cam_T_imu")


def test_missing_or_not_npz(tmp_path):
    with pytest.raises(InputError) as e:
        load_sequence(tmp_path / "nope.npz")
    assert "does not exist" in assert_one_line_error(e, "nope.npz")
    with pytest.raises(InputError) as e:
        load_sequence(tmp_path)
    assert "not a regular file" in assert_one_line_error(e, str(tmp_path))
    (tmp_path / "text.npz").write_text("time_stamps,features\n1,2\n")
    with pytest.raises(InputError) as e:
        load_sequence(tmp_path / "text.npz")
    assert "not an .npz (zip)" in assert_one_line_error(e, "text.npz")
    np.save(tmp_path / "plain.npy", np.zeros(3))
    with pytest.raises(InputError) as e:
        load_sequence(tmp_path / "plain.npy")
    assert "not an .npz (zip)" in assert_one_line_error(e, "plain.npy")


def _zip_with_features_member(path, member_bytes, arrays):
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for k, v in arrays.items():
            if k != "features":
                buf = io.BytesIO()
                np.save(buf, v)
                zf.writestr(k + ".npy", buf.getvalue())
        zf.writestr("features.npy", member_bytes)
    return path


@pytest.mark.parametrize("defect", ["truncated", "trailing", "bad-header"])
def test_corrupt_features_member(tmp_path, defect):
    arrays = course_arrays()
    F = arrays["features"]
    buf = io.BytesIO()
    np.save(buf, F)
    raw = buf.getvalue()
    if defect == "truncated":
        raw = raw[:-8]
    elif defect == "trailing":
        raw = raw + b"\0" * 8
    else:
        raw = raw[:6] + b"\x01\x00" + b"\x10\x00" + b"{'descr': <f8, garbage"
    path = _zip_with_features_member(tmp_path / f"{defect}.npz", raw, arrays)
    with pytest.raises(InputError) as e:
        load_sequence(path)
    assert_one_line_error(e, f"{defect}.npz", "features")


def test_corrupt_compressed_stream_is_refused(tmp_path):
    path = write_npz(tmp_path / "c.npz", course_arrays())
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo("features.npy")
    # flip bytes in the middle of the compressed features data (after the local header)
    start = info.header_offset + 30 + len(info.filename) + len(info.extra)
    mid = start + info.compress_size // 2
    data[mid:mid + 4] = bytes(b ^ 0xFF for b in data[mid:mid + 4])
    path.write_bytes(bytes(data))
    with pytest.raises(InputError) as e:
        load_sequence(path)
    assert_one_line_error(e, "c.npz", "features")


def test_zlib_fallback_reads_and_refuses_the_same(tmp_path, monkeypatch):
    """Without ISA-L (``isal``) the loader inflates with zlib: the same observations, and a corrupt
    stream is refused in the same way."""
    import zlib

    monkeypatch.setattr(npz_mod, "_CHUNK_BYTES", 256)
    path = write_npz(tmp_path / "z.npz", course_arrays(n=30, m=20))
    with_isal = load_sequence(path)
    monkeypatch.setattr(npz_mod, "_inflate_lib", zlib)
    with_zlib = load_sequence(path)
    for key in ("obs_ptr", "obs_ids", "obs_pixels"):
        np.testing.assert_array_equal(getattr(with_zlib, key), getattr(with_isal, key))
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo("features.npy")
    mid = info.header_offset + 30 + len(info.filename) + len(info.extra) + info.compress_size // 2
    data[mid:mid + 4] = bytes(b ^ 0xFF for b in data[mid:mid + 4])
    path.write_bytes(bytes(data))
    with pytest.raises(InputError) as e:
        load_sequence(path)
    assert_one_line_error(e, "z.npz", "features")


def test_features_crc_mismatch_is_refused(tmp_path):
    """A valid deflate stream whose CRC-32 does not match the zip directory: refused (the inflating
    thread's reader checks it, as zipfile does)."""
    path = write_npz(tmp_path / "crc.npz", course_arrays())
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo("features.npy")
    wrong = ((info.CRC ^ 0x5A5A5A5A) & 0xFFFFFFFF).to_bytes(4, "little")
    data[info.header_offset + 14:info.header_offset + 18] = wrong  # local header
    central = data.find(b"PK\x01\x02")
    while central >= 0:  # the central directory entry of features.npy
        name_len = int.from_bytes(data[central + 28:central + 30], "little")
        if bytes(data[central + 46:central + 46 + name_len]) == b"features.npy":
            data[central + 16:central + 20] = wrong
            break
        central = data.find(b"PK\x01\x02", central + 4)
    path.write_bytes(bytes(data))
    with pytest.raises(InputError) as e:
        load_sequence(path)
    assert "CRC" in assert_one_line_error(e, "crc.npz", "features")


@settings(max_examples=60, deadline=None)
@given(data=st.data(), layout=st.sampled_from(["2022", "2019"]), compressed=st.booleans())
def test_random_features_corruption_is_refused_or_harmless_property(data, layout, compressed):
    """Random bytes written into the stored 'features' member (the one the loader streams itself):
    either a one-line InputError naming 'features', or a sequence that passes validation."""
    with tempfile.TemporaryDirectory() as d:
        path = write_npz(Path(d) / "x.npz", course_arrays(layout, n=20, m=15), compressed=compressed)
        raw = bytearray(path.read_bytes())
        with zipfile.ZipFile(path) as zf:
            info = zf.getinfo("features.npy")
        start = info.header_offset + 30 + len(info.filename) + len(info.extra)
        for _ in range(data.draw(st.integers(1, 8), label="bytes changed")):
            i = data.draw(st.integers(start, start + info.compress_size - 1), label="offset")
            raw[i] = data.draw(st.integers(0, 255), label="value")
        path.write_bytes(bytes(raw))
        try:
            seq = load_sequence(path)
        except InputError as e:
            msg = str(e)
            assert "\n" not in msg and "x.npz" in msg and "key 'features'" in msg, msg
            return
        validate_sequence(seq)


def test_an_early_error_stops_the_inflating_thread(tmp_path, monkeypatch):
    """A NaN found in the first chunk ends the load at once, and no reading thread is left behind."""
    import threading

    monkeypatch.setattr(npz_mod, "_CHUNK_BYTES", 64)
    arrays = course_arrays(n=40, m=30, features=np.full((4, 30, 40), -1.0))
    arrays["features"][0, 0, 0] = np.nan
    path = write_npz(tmp_path / "nan.npz", arrays)
    before = threading.active_count()
    with pytest.raises(InputError) as e:
        load_sequence(path)
    assert "non-finite" in assert_one_line_error(e, "nan.npz", "features")
    assert threading.active_count() == before


# ----------------------------------------------------------------------------------------------
# the Sequence object


@pytest.fixture
def syn_seq(tmp_path):
    return load_sequence(write_npz(tmp_path / "s.npz", course_arrays("2022")))


def test_observations_are_views_of_the_csr(syn_seq):
    seq = syn_seq
    F = synthetic_features()
    assert seq.num_steps == 7
    assert seq.num_observations == int((F != -1).any(axis=0).sum()) - 8  # 2 + 6 dropped by hand count
    total = 0
    for k in range(seq.num_steps):
        ids, px = seq.observations(k)
        assert ids.base is not None and px.base is not None  # views, not copies
        assert px.shape == (ids.shape[0], 4)
        for j, p in zip(ids, px):
            assert np.array_equal(p, F[:, j, k])
        total += ids.shape[0]
    assert total == seq.num_observations
    ids_last, _ = seq.observations(-1)
    assert np.array_equal(ids_last, seq.observations(6)[0])
    with pytest.raises(IndexError):
        seq.observations(7)


def test_cam_T_imu_is_the_rigid_inverse(syn_seq):
    T = syn_seq.cam_T_imu
    np.testing.assert_allclose(T @ syn_seq.imu_T_cam, np.eye(4), atol=1e-14)
    np.testing.assert_allclose(T, np.linalg.inv(IMU_T_CAM), atol=1e-14)
    assert np.array_equal(T[:3, :3], IMU_T_CAM[:3, :3].T)


def test_replaced_extrinsic(syn_seq):
    """A copy with another imu_T_cam (dataclasses.replace) shares the observations, has the matching
    cam_T_imu and leaves the original alone; a non-rigid replacement fails validation."""
    flip = np.diag([1.0, -1.0, -1.0, 1.0]) @ syn_seq.imu_T_cam
    other = dataclasses.replace(syn_seq, imu_T_cam=flip, _cam_T_imu_file=None)
    validate_sequence(other)
    assert np.array_equal(other.imu_T_cam, flip)
    assert np.array_equal(syn_seq.imu_T_cam, IMU_T_CAM)  # original untouched
    np.testing.assert_allclose(other.cam_T_imu @ flip, np.eye(4), atol=1e-14)
    assert other.obs_ids is syn_seq.obs_ids and other.num_observations == syn_seq.num_observations
    assert other.dropped == syn_seq.dropped
    with pytest.raises(InputError) as e:
        validate_sequence(dataclasses.replace(syn_seq, imu_T_cam=np.diag([1.0, 1.0, -1.0, 1.0])))
    assert "det(R)" in assert_one_line_error(e, "s.npz", "imu_T_cam")


def test_replaced_extrinsic_ignores_the_2019_file_extrinsic(tmp_path):
    """cam_T_imu of a 2019 file is the file's own matrix only while it still inverts imu_T_cam."""
    seq = load_sequence(write_npz(tmp_path / "o.npz", course_arrays("2019")))
    flip = np.diag([1.0, -1.0, -1.0, 1.0]) @ seq.imu_T_cam
    other = dataclasses.replace(seq, imu_T_cam=flip, _cam_T_imu_file=None)
    np.testing.assert_allclose(other.cam_T_imu @ flip, np.eye(4), atol=1e-14)
    kept = dataclasses.replace(seq, imu_T_cam=flip)  # the stale file extrinsic is still attached
    np.testing.assert_allclose(kept.cam_T_imu @ flip, np.eye(4), atol=1e-14)
    seq.imu_T_cam = flip  # stale cached file extrinsic must not be used either
    np.testing.assert_allclose(seq.cam_T_imu @ flip, np.eye(4), atol=1e-14)


@pytest.mark.parametrize("arg", [3, 7, 100, slice(2, 5), slice(1, None, 2), slice(None, None, 3), slice(-2, None)])
def test_subset(syn_seq, arg):
    sub = syn_seq.subset(arg)
    steps = np.arange(7)[slice(0, arg) if isinstance(arg, int) else arg]
    assert sub.num_steps == steps.size
    assert np.array_equal(sub.time_stamps, syn_seq.time_stamps[steps])
    assert np.array_equal(sub.linear_velocity, syn_seq.linear_velocity[steps])
    assert np.array_equal(sub.angular_velocity, syn_seq.angular_velocity[steps])
    for i, k in enumerate(steps):
        a, b = sub.observations(i), syn_seq.observations(int(k))
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert sub.num_features == syn_seq.num_features
    validate_sequence(sub)


@pytest.mark.parametrize("arg", [0, slice(3, 3), slice(None, None, -1)])
def test_subset_refuses_empty_or_reversed(syn_seq, arg):
    with pytest.raises(InputError):
        syn_seq.subset(arg)


def test_steps_yields_each_step_in_order(syn_seq):
    seq = syn_seq
    steps = list(seq.steps())
    assert len(steps) == seq.num_steps == 7
    for k, (t, v, w, ids, px) in enumerate(steps):
        assert t == seq.time_stamps[k]
        assert v.shape == (3,) and np.array_equal(v, seq.linear_velocity[k])
        assert w.shape == (3,) and np.array_equal(w, seq.angular_velocity[k])
        ids_k, px_k = seq.observations(k)
        assert np.array_equal(ids, ids_k) and np.array_equal(px, px_k)
        assert ids.dtype == np.int64 and px.shape == (ids.shape[0], 4)
    assert sum(step[3].shape[0] for step in steps) == seq.num_observations


def _from_own_steps(seq, **overrides):
    t, v, w, ids, px = zip(*seq.steps())
    kwargs = dict(num_features=seq.num_features, source=seq.source, layout=seq.layout, tracker=seq.tracker)
    kwargs.update(overrides)
    return Sequence.from_steps(t, v, w, list(ids), list(px), seq.K, seq.baseline, seq.imu_T_cam, **kwargs)


@pytest.mark.parametrize("layout", ["2022", "2019"])
def test_from_steps_round_trip(tmp_path, layout):
    """from_steps of a sequence's own per-step ids and pixels is that sequence."""
    seq = dataclasses.replace(load_sequence(write_npz(tmp_path / "r.npz", course_arrays(layout))),
                              tracker=VISLAM_TRACKER)
    back = _from_own_steps(seq)
    assert_same(seq, back)
    assert (back.source, back.layout, back.tracker) == (seq.source, layout, VISLAM_TRACKER)
    np.testing.assert_allclose(back.cam_T_imu @ back.imu_T_cam, np.eye(4), atol=1e-14)
    # the subset of a sequence round-trips too, including steps without observations
    sub = seq.subset(slice(1, None, 2))
    assert_same(sub, _from_own_steps(sub))


def test_from_steps_num_features_defaults_to_the_largest_id_plus_one(syn_seq):
    seq = _from_own_steps(syn_seq, num_features=None)
    assert seq.num_features == int(syn_seq.obs_ids.max()) + 1
    first_two = max(int(syn_seq.observations(k)[0].max()) for k in (0, 1))
    assert _from_own_steps(syn_seq.subset(2), num_features=None).num_features == first_two + 1
    empty = Sequence.from_steps([0.0, 0.5], np.zeros((2, 3)), np.zeros((2, 3)), [np.zeros(0, int)] * 2,
                                [np.zeros((0, 4))] * 2, K_SYN, 0.5, np.eye(4))
    assert empty.num_features == 0 and empty.num_observations == 0
    assert np.array_equal(empty.obs_ptr, [0, 0, 0]) and empty.obs_ptr.dtype == np.int64
    assert empty.obs_ids.dtype == np.int64 and empty.obs_pixels.shape == (0, 4)
    validate_sequence(empty)
    hand = Sequence.from_steps([0.0, 1.0], [[1.0, 0, 0], [0, 1, 0]], [[0, 0, 1.0], [0, 0, 0]],
                               [[4, 9], [2]], [[[10.0, 20, 5, 20], [30, 40, 20, 40]], [[50, 60, 45, 60]]],
                               K_SYN, 0.3, np.eye(4))
    assert hand.num_features == 10
    assert np.array_equal(hand.obs_ptr, [0, 2, 3]) and np.array_equal(hand.obs_ids, [4, 9, 2])
    assert hand.obs_ids.dtype == np.int64 and hand.obs_pixels.dtype == np.float64


def _swap_first_step_ids(ids):
    k = next(i for i, a in enumerate(ids) if len(a) >= 2)
    ids[k] = ids[k][::-1].copy()


def _nan_pixel(px):
    k = next(i for i, a in enumerate(px) if len(a))
    px[k] = px[k].copy()
    px[k][0, 1] = np.nan


BAD_STEPS = {
    # id: (mutation of the from_steps arguments, key named, message fragment)
    "ids-not-increasing": (lambda a: _swap_first_step_ids(a["ids"]), "obs_ids", "strictly increasing"),
    "ids-negative": (lambda a: a["ids"].__setitem__(0, np.r_[-1, a["ids"][0][1:]]), "obs_ids", "[0,"),
    "num-features-too-small": (lambda a: a.update(num_features=int(max(map(np.max, filter(len, a["ids"]))))),
                               "obs_ids", "ids must lie in"),
    "num-features-negative": (lambda a: a.update(num_features=-1), "num_features", ">= 0"),
    "fewer-steps-of-ids": (lambda a: (a["ids"].pop(), a["pixels"].pop()), "obs_ptr", "shape"),
    "fewer-pixels": (lambda a: a["pixels"].__setitem__(0, a["pixels"][0][:-1]), "obs_pixels", "shape"),
    "pixels-nan": (lambda a: _nan_pixel(a["pixels"]), "obs_pixels", "non-finite"),
    "time-repeated": (lambda a: a["t"].__setitem__(3, a["t"][2]), "time_stamps", "not strictly increasing"),
    "time-empty": (lambda a: a.update(t=[], v=np.zeros((0, 3)), w=np.zeros((0, 3)), ids=[], pixels=[],
                                      num_features=0), "time_stamps", "empty sequence"),
    "velocity-short": (lambda a: a.update(v=a["v"][:-1]), "linear_velocity", "shape"),
    "angular-nan": (lambda a: a.update(w=np.where(np.arange(3) == 1, np.nan, a["w"])), "angular_velocity",
                    "non-finite"),
    "K": (lambda a: a.update(K=K_SYN.T), "K", "camera matrix"),
    "baseline": (lambda a: a.update(b=-0.5), "baseline", "> 0"),
    "extrinsic": (lambda a: a.update(ext=2 * IMU_T_CAM), "imu_T_cam", "rigid"),
    "layout": (lambda a: a.update(layout="2020"), "layout", "unknown layout"),
    "pixels-three-columns": (lambda a: a["pixels"].__setitem__(1, a["pixels"][1][:, :3]), "obs_pixels", "shape"),
    "pixels-for-fewer-steps": (lambda a: a["pixels"].pop(), "obs_pixels", "steps of pixels"),
    "ids-not-integer": (lambda a: a["ids"].__setitem__(0, a["ids"][0] + 0.5), "obs_ids", "integer"),
    "velocity-transposed": (lambda a: a.update(v=a["v"].T.copy()), "linear_velocity", "shape"),
}


@pytest.mark.parametrize("case", sorted(BAD_STEPS))
def test_from_steps_refuses_invalid_input(syn_seq, case):
    mutate, key, fragment = BAD_STEPS[case]
    t, v, w, ids, px = zip(*syn_seq.steps())
    args = dict(t=list(t), v=np.array(v), w=np.array(w), ids=list(ids), pixels=list(px), K=K_SYN, b=0.54,
                ext=IMU_T_CAM, num_features=syn_seq.num_features, layout="2022")
    mutate(args)
    with pytest.raises(InputError) as e:
        Sequence.from_steps(args["t"], args["v"], args["w"], args["ids"], args["pixels"], args["K"], args["b"],
                            args["ext"], num_features=args["num_features"], source="steps.npz",
                            layout=args["layout"])
    assert fragment in assert_one_line_error(e, "steps.npz", key)


def test_repr_is_short(syn_seq):
    r = repr(syn_seq)
    assert "steps=7" in r and "\n" not in r and len(r) < 300


def _broken(attr, fn):
    def make(seq):
        import dataclasses
        return dataclasses.replace(seq, **{attr: fn(seq)})
    return make


def _swap_first_two_ids(seq):
    ids = seq.obs_ids.copy()
    k = int(np.flatnonzero(np.diff(seq.obs_ptr) >= 2)[0])
    a = seq.obs_ptr[k]
    ids[a], ids[a + 1] = ids[a + 1], ids[a]
    return ids


BROKEN = {
    "ids-not-increasing": (_broken("obs_ids", _swap_first_two_ids), "obs_ids", "strictly increasing"),
    "ids-out-of-range": (_broken("num_features", lambda s: int(s.obs_ids.max())), "obs_ids", "[0,"),
    "ptr-short": (_broken("obs_ptr", lambda s: s.obs_ptr[:-1]), "obs_ptr", "shape"),
    "ptr-end": (_broken("obs_ptr", lambda s: np.r_[s.obs_ptr[:-1], s.obs_ptr[-1] - 1]), "obs_ptr", "CSR"),
    "ptr-float": (_broken("obs_ptr", lambda s: s.obs_ptr.astype(float)), "obs_ptr", "integer"),
    "pixels-shape": (_broken("obs_pixels", lambda s: s.obs_pixels[:, :3]), "obs_pixels", "shape"),
    "pixels-nan": (_broken("obs_pixels", lambda s: np.where(s.obs_pixels > 600, np.nan, s.obs_pixels)),
                   "obs_pixels", "non-finite"),
    "velocity-shape": (_broken("angular_velocity", lambda s: s.angular_velocity.T), "angular_velocity", "shape"),
    "time-2d": (_broken("time_stamps", lambda s: s.time_stamps[None]), "time_stamps", "shape"),
    "time-order": (_broken("time_stamps", lambda s: s.time_stamps[::-1].copy()), "time_stamps", "increasing"),
    "baseline": (_broken("baseline", lambda s: 0.0), "baseline", "> 0"),
    "layout": (_broken("layout", lambda s: "2020"), "layout", "unknown layout"),
    "extrinsic": (_broken("imu_T_cam", lambda s: 2 * s.imu_T_cam), "imu_T_cam", "rigid"),
    "K": (_broken("K", lambda s: s.K.T), "K", "camera matrix"),
}


@pytest.mark.parametrize("case", sorted(BROKEN))
def test_validate_sequence_catches(syn_seq, case):
    make, key, fragment = BROKEN[case]
    validate_sequence(syn_seq)
    with pytest.raises(InputError) as e:
        validate_sequence(make(syn_seq))
    assert fragment in assert_one_line_error(e, "s.npz", key)


# ----------------------------------------------------------------------------------------------
# saving


@pytest.mark.parametrize("src_layout", ["2022", "2019"])
@pytest.mark.parametrize("dst_layout", [None, "2022", "2019"])
def test_save_load_round_trip(tmp_path, src_layout, dst_layout):
    seq = load_sequence(write_npz(tmp_path / "in.npz", course_arrays(src_layout)))
    out = tmp_path / "out.npz"
    save_sequence(seq, out, layout=dst_layout)
    written = dst_layout or src_layout
    with np.load(out, allow_pickle=False) as z:
        assert set(z.files) == {"time_stamps", "features", "linear_velocity", "K", "b", *LAYOUT_KEYS[written]}
        assert z["b"].shape == () and z["time_stamps"].shape == (1, 7)
        assert z["features"].shape == (4, 6, 7) and z["linear_velocity"].shape == (3, 7)
        F = z["features"]
        # the drops are gone, everything else is exactly the dense input
        ptr, ids, pix, _ = reference_csr(synthetic_features(), W_SYN, H_SYN)
        expected = np.full_like(F, -1.0)
        expected[:, ids, np.repeat(np.arange(7), np.diff(ptr))] = pix.T
        assert np.array_equal(F, expected)
        if written == "2019":
            np.testing.assert_allclose(z["cam_T_imu"] @ seq.imu_T_cam, np.eye(4), atol=1e-14)
    back = load_sequence(out)
    assert back.layout == written
    assert back.dropped == {"nonpositive_disparity": 0, "outside_image": 0}
    # writing a 2022 sequence as 2019 inverts the extrinsic once: translation may move by an ulp
    assert_same(seq, back, exact_extrinsic=not (src_layout == "2022" and written == "2019"))
    # a second round trip in the same layout is exact in every array
    save_sequence(back, tmp_path / "again.npz")
    assert_same(back, load_sequence(tmp_path / "again.npz"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.npz", "in.npz", "out.npz"]


def test_save_hand_built_sequence_and_overwrite(tmp_path):
    seq = Sequence(
        time_stamps=np.array([0.0, 0.5, 1.0]),
        linear_velocity=np.ones((3, 3)),
        angular_velocity=np.zeros((3, 3)),
        K=K_SYN,
        baseline=0.3,
        imu_T_cam=np.eye(4),
        obs_ptr=np.array([0, 2, 2, 3]),
        obs_ids=np.array([1, 3, 0]),
        obs_pixels=np.array([[10.0, 20, 5, 20], [30, 40, 20, 40], [50, 60, 45, 60]]),
        num_features=5,
    )
    target = tmp_path / "hand.npz"
    target.write_bytes(b"old content")
    save_sequence(seq, target)
    back = load_sequence(target)
    assert_same(seq, back)
    assert back.num_features == 5 and back.observations(1)[0].size == 0
    mode = target.stat().st_mode & 0o777
    umask = os.umask(0)
    os.umask(umask)
    assert mode == 0o666 & ~umask  # not mkstemp's 0600
    with pytest.raises(InputError, match="layout"):
        save_sequence(seq, tmp_path / "x.npz", layout="2020")
    assert not (tmp_path / "x.npz").exists()


@pytest.mark.parametrize("exc", [KeyboardInterrupt, OSError])
@pytest.mark.parametrize("existing", [False, True])
def test_interrupted_save_leaves_no_file(tmp_path, monkeypatch, syn_seq, exc, existing):
    d = tmp_path / "out"
    d.mkdir()
    target = d / "seq.npz"
    if existing:
        target.write_bytes(b"previous")
    calls = []

    def half_write(file, **arrays):  # writes a partial zip, then dies
        calls.append(sorted(arrays))
        file.write(b"PK\x03\x04 half a zip")
        raise exc("interrupted")

    monkeypatch.setattr(np, "savez_compressed", half_write)
    with pytest.raises(OutputError if exc is OSError else exc):  # an OSError (a full disk): one line naming the file
        save_sequence(syn_seq, target)
    assert calls, "save_sequence must write through np.savez_compressed"
    assert sorted(p.name for p in d.iterdir()) == (["seq.npz"] if existing else [])
    if existing:
        assert target.read_bytes() == b"previous"


# ----------------------------------------------------------------------------------------------
# real data


def real_path(name):
    p = DATA / name
    if not p.exists():
        pytest.skip(f"real data {p} not present (see shared/data/SOURCES.md)")
    return p


@pytest.mark.parametrize("name", sorted(REAL))
def test_real_file_matches_dense_array(name):
    path = real_path(name)
    layout, n, m = REAL[name]
    seq = load_sequence(path)
    with np.load(path, allow_pickle=False) as z:  # one-off dense read, fine in a test
        F = z["features"]
        ext = z[LAYOUT_KEYS[layout][1]]
        t = z["time_stamps"]
        ang = z[LAYOUT_KEYS[layout][0]]
        lin = z["linear_velocity"]
        K = z["K"]
    assert seq.layout == layout and seq.num_steps == n and seq.num_features == m
    assert np.array_equal(seq.time_stamps, t[0]) and (np.diff(seq.time_stamps) > 0).all()
    assert np.array_equal(seq.linear_velocity, lin.T) and np.array_equal(seq.angular_velocity, ang.T)
    assert np.array_equal(seq.K, K)

    width, height = 2 * K[0, 2] * 1.25, 2 * K[1, 2] * 1.25
    ptr, ids, pix, dropped = reference_csr(F, width, height)
    assert np.array_equal(seq.obs_ptr, ptr)
    assert np.array_equal(seq.obs_ids, ids)
    assert np.array_equal(seq.obs_pixels, pix)
    # drops counted directly on the dense array
    seen = F[0] != -1
    assert seq.dropped["nonpositive_disparity"] == int(((F[0] - F[2] <= 0) & seen).sum()) > 0
    assert seq.dropped["outside_image"] == 0  # with the 1.25 margin nothing real falls outside
    assert not ((F != -1).any(0) & (F == -1).any(0)).any()  # the real files have no partial -1s
    assert seq.num_observations == int(seen.sum()) - sum(seq.dropped.values())
    assert ids_increasing_within_steps(seq)

    # the files' rotations are orthonormal only to 1e-8 .. 2e-7: the loader uses the nearest
    # rotation (U V^T of the SVD), without a note at that level (float rounding), and keeps the translation
    R, p = ext[:3, :3], ext[:3, 3]
    assert 1e-12 < np.abs(R.T @ R - np.eye(3)).max() < 1e-6
    U, _, Vt = np.linalg.svd(R)
    file_imu_T_cam = ext if layout == "2022" else seq.imu_T_cam
    R_read = seq.imu_T_cam[:3, :3] if layout == "2022" else seq.cam_T_imu[:3, :3]
    np.testing.assert_allclose(R_read, U @ Vt, rtol=0, atol=1e-15)
    np.testing.assert_allclose(R_read.T @ R_read, np.eye(3), rtol=0, atol=1e-12)
    np.testing.assert_allclose(R_read, R, rtol=0, atol=1e-6)
    assert not seq.notes
    if layout == "2019":
        np.testing.assert_array_equal(seq.cam_T_imu[:3, 3], p)
        np.testing.assert_allclose(seq.imu_T_cam @ ext, np.eye(4), rtol=0, atol=1e-6)
        np.testing.assert_allclose(seq.imu_T_cam @ seq.cam_T_imu, np.eye(4), rtol=0, atol=1e-14)
        assert np.array_equal(seq.imu_T_cam[3], [0, 0, 0, 1])
    else:
        np.testing.assert_array_equal(file_imu_T_cam[:3, 3], seq.imu_T_cam[:3, 3])


def test_real_kitti360_uL_exceeds_2cx():
    """Documents why the image-size margin exists: uL reaches 1405 while 2 cx = 1364."""
    path = real_path("ece276a_03.npz")
    seq = load_sequence(path)
    assert seq.obs_pixels[:, 0].max() > 2 * seq.K[0, 2]
    tight = load_sequence(path, image_size=(2 * seq.K[0, 2], 2 * seq.K[1, 2]))
    assert tight.dropped["outside_image"] > 0


def test_real_load_memory_stays_small():
    path = real_path("ece276a_03.npz")
    dense_bytes = 4 * 5105 * 1010 * 8  # 165 MB
    tracemalloc.start()
    try:
        t0 = time.perf_counter()
        seq = load_sequence(path)
        elapsed = time.perf_counter() - t0
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    obs_bytes = seq.obs_pixels.nbytes + seq.obs_ids.nbytes + seq.obs_ptr.nbytes
    assert peak < obs_bytes + 16 * 2**20, f"peak {peak / 2**20:.1f} MiB"
    assert peak < dense_bytes / 8
    assert elapsed < 30


@pytest.mark.parametrize("name", sorted(REAL))
@pytest.mark.parametrize("dst_layout", ["2022", "2019"])
def test_real_round_trip(tmp_path, name, dst_layout):
    if name != "ece276a2019_0042.npz" and os.environ.get("VISLAM_FAST_TESTS"):
        pytest.skip("VISLAM_FAST_TESTS set: big real round trips skipped")
    seq = load_sequence(real_path(name))
    out = tmp_path / "rt.npz"
    save_sequence(seq, out, layout=dst_layout)
    back = load_sequence(out)
    assert back.layout == dst_layout
    assert back.dropped == {"nonpositive_disparity": 0, "outside_image": 0}
    # 2022 -> 2019 inverts the extrinsic once; reading inverts it back. With R orthonormal only
    # to ~1e-8 (ece276a_03) the translation comes back as R R^T p, off by ~1e-8 m.
    assert_same(seq, back, exact_extrinsic=not (seq.layout == "2022" and dst_layout == "2019"), atol=1e-7)
    assert [p.name for p in tmp_path.iterdir()] == ["rt.npz"]


def test_tracker_key_round_trip_and_checked(tmp_path):
    """The optional 'tracker' key (who made the tracks) is read, written back, and checked."""
    seq = load_sequence(write_npz(tmp_path / "in.npz", course_arrays("2022")))
    assert seq.tracker == ""  # course files have none
    save_sequence(seq, tmp_path / "plain.npz")
    with np.load(tmp_path / "plain.npz", allow_pickle=False) as z:
        assert "tracker" not in z.files
    tagged = dataclasses.replace(seq, tracker=VISLAM_TRACKER)
    save_sequence(tagged, tmp_path / "tagged.npz")
    assert load_sequence(tmp_path / "tagged.npz").tracker == VISLAM_TRACKER
    for bad in (np.array([1.0, 2.0]), np.array(["a", "b"])):
        path = write_npz(tmp_path / "bad.npz", {**course_arrays("2022"), "tracker": bad})
        with pytest.raises(InputError) as e:
            load_sequence(path)
        assert "expected one string" in assert_one_line_error(e, "bad.npz", "tracker")


@pytest.mark.parametrize("member", ["time_stamps", "linear_velocity", "K"])
def test_damaged_member_besides_features_is_refused_naming_it(tmp_path, syn_seq, member):
    """A member whose deflated bytes are damaged gives a one-line InputError naming its key, not a
    zipfile or zlib exception."""
    import zipfile

    path = tmp_path / "damaged.npz"
    save_sequence(syn_seq, path)
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo(member + ".npy")
    raw = bytearray(path.read_bytes())
    start = info.header_offset + 30 + len(info.filename) + len(info.extra)
    for i in range(start, start + min(info.compress_size, 24)):
        raw[i] ^= 0x5A
    path.write_bytes(bytes(raw))
    with pytest.raises(InputError) as e:
        load_sequence(path)
    assert_one_line_error(e, str(path), member)


def test_what_the_reader_dropped_is_said_in_words():
    import dataclasses

    from vislam.synth.scene import SceneConfig, make_scene

    seq = make_scene(SceneConfig(steps=5)).sequence
    assert dataclasses.replace(seq, dropped={"nonpositive_disparity": 0, "outside_image": 0}).dropped_text() == ""
    text = dataclasses.replace(seq, dropped={"nonpositive_disparity": 120, "outside_image": 1}).dropped_text()
    assert text == ("dropped 120 observations with a non-positive disparity (uL <= uR: a point at or behind "
                    "infinity); 1 observation outside the image")
    assert "{" not in text and "_" not in text
