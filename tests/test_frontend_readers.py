"""Property tests of the front end's readers: whatever a file holds, the reader gives one clean
InputError (one line, naming the file) or a valid result (the right shapes, every number finite,
time stamps strictly increasing, a rigid extrinsic), never another exception and never NaN.

Readers: the KITTI-layout directory (``open_stereo_directory`` and the frames it reads),
``calib.txt`` (``read_calibration``), ``times.txt`` (``read_times``), the IMU CSV (``read_imu``)
and the ``--imu-T-cam`` extrinsic (``read_imu_T_cam``). Each is fed valid files damaged at random
(truncated lines and files, dropped, repeated and swapped lines, extra and missing columns, NaN,
inf, huge and tiny numbers, stray text, empty files, non-UTF-8 bytes, random binary) and, where the
answer is known exactly, files of drawn edge values checked against that answer.
"""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from vislam.backend.errors import InputError
from vislam.frontend.images import open_stereo_directory, read_calibration, read_times
from vislam.frontend.imu_input import read_imu, read_imu_T_cam

CALIB = (
    "P0: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 0.000000000000e+00 0.000000000000e+00 "
    "7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 "
    "1.000000000000e+00 0.000000000000e+00\n"
    "P1: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 -3.861448000000e+02 0.000000000000e+00 "
    "7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 "
    "1.000000000000e+00 0.000000000000e+00\n"
    "P2: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 4.538225000000e+01 0.000000000000e+00 "
    "7.188560000000e+02 1.852157000000e+02 -1.130887000000e-01 0.000000000000e+00 0.000000000000e+00 "
    "1.000000000000e+00 3.779761000000e-03\n"
    "Tr: 4.276802385584e-04 -9.999672484946e-01 -8.084491683471e-03 -1.198459927713e-02 "
    "-7.210626507497e-03 8.081198471645e-03 -9.999413164504e-01 -5.403984729748e-02 "
    "9.999738645903e-01 4.859485810390e-04 -7.206933692422e-03 -2.921968648686e-01\n"
)

#: Tokens that break a number or sit at its edges.
SPECIAL_TOKENS = [
    "nan", "-nan", "NaN", "inf", "-inf", "Infinity", "1e309", "-1e309", "1.7976931348623157e308", "-1e308",
    "1e-320", "5e-324", "0", "-0", "0.0", "", "x", "0x1p3", "1e", ".", "--1", "1.2.3", "\uff11", "\u0663",
    "9" * 400, "\x00", "\ufeff", "\u00e9", "1,", ",", "#", "P0:", "P1:",
]

TOKEN = st.one_of(
    st.sampled_from(SPECIAL_TOKENS),
    st.floats().map(repr),
    st.integers(-(10**30), 10**30).map(str),
    st.text(max_size=8),
)

_SEPARATORS = re.compile(r"([,\s]+)")


def _edit_token(line: str, draw, drop: bool) -> str:
    """Replace (or with ``drop`` remove) one token of a line (tokens split at commas and white space)."""
    parts = _SEPARATORS.split(line)
    k = 2 * draw(st.integers(0, (len(parts) - 1) // 2))
    if drop:
        del parts[k : k + 2]
    else:
        parts[k] = draw(TOKEN)
    return "".join(parts)


@st.composite
def damaged(draw, text: str, separator: str = " ") -> bytes:
    """``text`` with 1-4 random line edits, then possibly one edit of the bytes."""
    lines = text.split("\n")
    for _ in range(draw(st.integers(1, 4))):
        if not lines:
            lines = [""]
        i = draw(st.integers(0, len(lines) - 1))
        op = draw(st.sampled_from(["drop line", "repeat line", "swap lines", "truncate line", "extra column",
                                   "drop column", "replace token", "insert line", "blank or comment"]))
        if op == "drop line":
            del lines[i]
        elif op == "repeat line":
            lines.insert(i, lines[i])
        elif op == "swap lines":
            j = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
        elif op == "truncate line":
            lines[i] = lines[i][: draw(st.integers(0, len(lines[i])))]
        elif op == "extra column":
            lines[i] = lines[i] + separator + draw(TOKEN)
        elif op in ("drop column", "replace token"):
            lines[i] = _edit_token(lines[i], draw, drop=op == "drop column")
        elif op == "insert line":
            lines.insert(i, draw(st.text(max_size=40)))
        else:
            lines.insert(i, draw(st.sampled_from(["", "   ", "# comment", "#", "\t"])))
    data = "\n".join(lines).encode("utf-8")
    op = draw(st.sampled_from(["none", "none", "truncate", "bad bytes", "empty", "binary", "crlf"]))
    if op == "truncate":
        data = data[: draw(st.integers(0, len(data)))]
    elif op == "bad bytes":
        at = draw(st.integers(0, len(data)))
        data = data[:at] + draw(st.sampled_from([b"\xff", b"\xfe\xff", b"\x80", b"\xc3", b"\xed\xa0\x80"])) + data[at:]
    elif op == "empty":
        data = b""
    elif op == "binary":
        data = draw(st.binary(max_size=200))
    elif op == "crlf":
        data = data.replace(b"\n", b"\r\n")
    return data


def refused_or(call, path):
    """``call()``'s result, or None when it raised an InputError of one line naming ``path``; any
    other exception propagates (and fails the test)."""
    try:
        return call()
    except InputError as exc:
        message = str(exc)
        assert str(path) in message, message
        assert "\n" not in message and "\r" not in message and len(message.splitlines()) == 1, message
        return None


def _check_calibration(result) -> None:
    K, baseline = result
    assert K.shape == (3, 3) and np.isfinite(K).all()
    assert K[0, 0] > 0 and K[1, 1] > 0 and K[1, 0] == 0 and np.array_equal(K[2], [0.0, 0.0, 1.0])
    assert np.isfinite(baseline) and baseline > 0


def _check_times(t, n: int) -> None:
    assert t.shape == (n,) and np.isfinite(t).all() and np.all(np.diff(t) > 0)


def _check_rigid(T) -> None:
    """Rigid within the tolerance either extrinsic check may use (exact orthonormality is not asked)."""
    assert T.shape == (4, 4) and np.isfinite(T).all()
    assert np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0])
    R = T[:3, :3]
    assert np.abs(R.T @ R - np.eye(3)).max() <= 1e-3 and np.linalg.det(R) > 0


def _check_imu(imu, n: int) -> None:
    _check_times(imu.time_stamps, n)
    assert imu.linear_velocity.shape == (n, 3) and np.isfinite(imu.linear_velocity).all()
    assert imu.angular_velocity.shape == (n, 3) and np.isfinite(imu.angular_velocity).all()
    _check_rigid(imu.imu_T_cam)


def _write(folder: str, name: str, data: bytes) -> Path:
    path = Path(folder) / name
    path.write_bytes(data)
    return path


# ---------------------------------------------------------------------------------------------- calib.txt


def test_calibration_base_file_is_valid(tmp_path):
    K, baseline = read_calibration(_write(str(tmp_path), "calib.txt", CALIB.encode()))
    assert K[0, 0] == 718.856 and baseline == pytest.approx(386.1448 / 718.856, rel=1e-12)


def test_calibration_whose_baseline_overflows_is_refused(tmp_path):
    path = _write(str(tmp_path), "calib.txt", b"P0: 1e-300 0 0 0 0 1 0 0 0 0 1 0\nP1: 1e-300 0 0 -1e10 0 1 0 0 0 0 1 0\n")
    with pytest.raises(InputError, match=r"calib\.txt: baseline .* must be a finite number > 0"):
        read_calibration(path)


@settings(max_examples=100, deadline=None)
@given(data=damaged(CALIB))
def test_damaged_calibration_is_refused_or_valid(data):
    with tempfile.TemporaryDirectory() as folder:
        path = _write(folder, "calib.txt", data)
        result = refused_or(lambda: read_calibration(path), path)
        if result is not None:
            _check_calibration(result)


EDGE_FLOATS = st.one_of(
    st.floats(),
    st.sampled_from([0.0, -0.0, 1e308, -1e308, 1.7976931348623157e308, 5e-324, -5e-324, 1e-300, 1e300, 1.0, -1.0]),
)


@settings(max_examples=100, deadline=None)
@given(changes=st.lists(st.tuples(st.sampled_from(["P0", "P1", "both"]), st.integers(0, 11), EDGE_FLOATS),
                        min_size=1, max_size=4))
def test_calibration_edge_values_are_refused_or_valid(changes):
    """Edge values in P0, P1 or the same entry of both (K must agree between them)."""
    rows = {
        "P0": [718.856, 0, 607.1928, 0, 0, 718.856, 185.2157, 0, 0, 0, 1, 0],
        "P1": [718.856, 0, 607.1928, -386.1448, 0, 718.856, 185.2157, 0, 0, 0, 1, 0],
    }
    for key, index, value in changes:
        for row in (("P0", "P1") if key == "both" else (key,)):
            rows[row][index] = value
    text = "".join(f"{key}: " + " ".join(repr(float(x)) for x in values) + "\n" for key, values in rows.items())
    with tempfile.TemporaryDirectory() as folder:
        path = _write(folder, "calib.txt", text.encode())
        result = refused_or(lambda: read_calibration(path), path)
        if result is not None:
            _check_calibration(result)
            np.testing.assert_array_equal(result[0], np.array(rows["P0"]).reshape(3, 4)[:, :3])


# ---------------------------------------------------------------------------------------------- times.txt


@settings(max_examples=100, deadline=None)
@given(n=st.integers(1, 6), extra=st.integers(0, 3), st_data=st.data())
def test_damaged_times_are_refused_or_valid(n, extra, st_data):
    text = "".join(f"{0.1037595 * i:.6e}\n" for i in range(n + extra))
    data = st_data.draw(damaged(text))
    with tempfile.TemporaryDirectory() as folder:
        path = _write(folder, "times.txt", data)
        result = refused_or(lambda: read_times(path, n), path)
        if result is not None:
            _check_times(result, n)


@settings(max_examples=100, deadline=None)
@given(n=st.integers(1, 6), stamps=st.lists(st.one_of(st.floats(), st.floats(-1e3, 1e3)), max_size=9))
def test_times_accepted_exactly_when_the_first_n_are_finite_and_increasing(n, stamps):
    """``times.txt`` holds any number of stamps: accepted with its first ``n`` when it has at least
    ``n`` and those are finite and strictly increasing (lines after them are not read)."""
    with tempfile.TemporaryDirectory() as folder:
        path = _write(folder, "times.txt", "".join(f"{t!r}\n" for t in stamps).encode())
        result = refused_or(lambda: read_times(path, n), path)
        first = np.array(stamps[:n])
        good = len(stamps) >= n and np.isfinite(first).all() and np.all(np.diff(first) > 0)
        assert (result is not None) == bool(good), (stamps, n)
        if good:
            np.testing.assert_array_equal(result, first)


# ---------------------------------------------------------------------------------------------- IMU CSV


def _extrinsic(folder: str) -> Path:
    return _write(folder, "imu_T_cam.txt", b"0 0 1 1.08\n-1 0 0 -0.32\n0 -1 0 0.72\n0 0 0 1\n")


@settings(max_examples=100, deadline=None)
@given(n=st.integers(1, 5), extra=st.integers(0, 3), header=st.booleans(), comma=st.booleans(), st_data=st.data())
def test_damaged_imu_csv_is_refused_or_valid(n, extra, header, comma, st_data):
    sep = "," if comma else " "
    rows = [sep.join(repr(x) for x in (0.1 * i, 1.0 + i, 0.01, -0.02, 0.001, -0.002, 0.03)) for i in range(n + extra)]
    text = ("t,vx,vy,vz,wx,wy,wz\n" if header else "") + "\n".join(rows) + "\n"
    data = st_data.draw(damaged(text, sep))
    with tempfile.TemporaryDirectory() as folder:
        path = _write(folder, "imu.csv", data)
        result = refused_or(lambda: read_imu(path, n, _extrinsic(folder)), path)
        if result is not None:
            _check_imu(result, n)


@settings(max_examples=100, deadline=None)
@given(n=st.integers(1, 4), header=st.booleans(),
       rows=st.lists(st.lists(st.one_of(st.floats(), st.floats(-10, 10)), min_size=7, max_size=7), max_size=6))
def test_imu_csv_accepted_exactly_when_its_first_rows_are_finite_and_increasing(n, header, rows):
    """Rows of 7 numbers: accepted with the first ``n`` rows when there are that many, all finite,
    with strictly increasing times; those rows are returned exactly."""
    text = ("t,vx,vy,vz,wx,wy,wz\n" if header else "") + "".join(",".join(repr(x) for x in r) + "\n" for r in rows)
    with tempfile.TemporaryDirectory() as folder:
        path = _write(folder, "imu.csv", text.encode())
        result = refused_or(lambda: read_imu(path, n, _extrinsic(folder)), path)
        first = np.array(rows[:n], dtype=np.float64).reshape(-1, 7)
        good = len(rows) >= n and np.isfinite(first).all() and np.all(np.diff(first[:, 0]) > 0)
        assert (result is not None) == bool(good), (rows, n)
        if good:
            np.testing.assert_array_equal(result.time_stamps, first[:, 0])
            np.testing.assert_array_equal(result.linear_velocity, first[:, 1:4])
            np.testing.assert_array_equal(result.angular_velocity, first[:, 4:7])


def test_imu_csv_first_row_with_a_stray_word_is_not_taken_for_a_header(tmp_path):
    """Only a first line without any number is a header: a damaged first row is refused, so the
    rows never shift by one frame."""
    ext = _extrinsic(str(tmp_path))
    path = _write(str(tmp_path), "imu.csv", b"0.0,1,0,0,0,0,zero\n0.1,1,0,0,0,0,0\n0.2,1,0,0,0,0,0\n")
    with pytest.raises(InputError, match=r"imu\.csv: line 1: not 7 numbers"):
        read_imu(path, 2, ext)
    headed = _write(str(tmp_path), "headed.csv", b"time s, vx m/s, vy, vz, wx rad/s, wy, wz\n0,1,0,0,0,0,0\n0.1,2,0,0,0,0,0\n")
    np.testing.assert_array_equal(read_imu(headed, 2, ext).linear_velocity[:, 0], [1.0, 2.0])


# ---------------------------------------------------------------------------------------------- extrinsic


ROTATIONS = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1)


def _transform(quaternion, translation) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(np.asarray(quaternion) / np.linalg.norm(quaternion)).as_matrix()
    T[:3, 3] = translation
    return T


def _matrix_text(T: np.ndarray, comma: bool = False) -> bytes:
    sep = ", " if comma else " "
    return ("# imu_T_cam\n" + "".join(sep.join(repr(float(x)) for x in row) + "\n" for row in T)).encode()


@settings(max_examples=100, deadline=None)
@given(q=ROTATIONS, t=st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3), comma=st.booleans())
def test_clean_extrinsic_is_read_as_written(q, t, comma):
    T = _transform(q, t)
    with tempfile.TemporaryDirectory() as folder:
        path = _write(folder, "imu_T_cam.txt", _matrix_text(T, comma))
        np.testing.assert_allclose(read_imu_T_cam(path), T, rtol=0, atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(q=ROTATIONS, t=st.lists(st.floats(-10, 10), min_size=3, max_size=3),
       fault=st.sampled_from(["scale", "reflection", "shear", "last row", "non-finite"]),
       amount=st.floats(0.05, 10.0), index=st.integers(0, 15), st_data=st.data())
def test_grossly_wrong_extrinsic_is_refused(q, t, fault, amount, index, st_data):
    """Rotations off orthonormal by far more than any tolerance (>= 0.05), reflections, a wrong
    last row or a NaN/inf entry: refused, naming the file."""
    T = _transform(q, t)
    if fault == "scale":
        T[:3, :3] *= st_data.draw(st.sampled_from([1.0 + amount, 1.0 / (1.0 + amount)]))
    elif fault == "reflection":
        T[:3, :3] = T[:3, :3] @ np.diag([1.0, 1.0, -1.0])
    elif fault == "shear":
        i, j = divmod(index % 9, 3)
        T[i, j] += amount if T[i, j] < 0.5 else -amount
    elif fault == "last row":
        T[3, index % 4] += amount
    else:
        T[index // 4, index % 4] = st_data.draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    with tempfile.TemporaryDirectory() as folder:
        path = _write(folder, "imu_T_cam.txt", _matrix_text(T))
        assert refused_or(lambda: read_imu_T_cam(path), path) is None


@settings(max_examples=100, deadline=None)
@given(q=ROTATIONS, t=st.lists(st.floats(-10, 10), min_size=3, max_size=3), comma=st.booleans(), st_data=st.data())
def test_damaged_extrinsic_is_refused_or_rigid(q, t, comma, st_data):
    text = _matrix_text(_transform(q, t), comma).decode()
    data = st_data.draw(damaged(text, "," if comma else " "))
    with tempfile.TemporaryDirectory() as folder:
        path = _write(folder, "imu_T_cam.txt", data)
        result = refused_or(lambda: read_imu_T_cam(path), path)
        if result is not None:
            _check_rigid(result)


# ---------------------------------------------------------------------------------------------- the directory


def _png(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", image)
    assert ok
    return data.tobytes()


IMAGE_FAULTS = ["garbage", "truncated", "empty file", "16-bit", "colour", "alpha", "other size", "a directory",
                "removed", "extra frame", "renamed"]
DIRECTORY_FAULTS = ["calib", "times", "times longer", "folder is a file", "no calib", "no times", "stray files"]


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 4), size=st.tuples(st.integers(1, 24), st.integers(1, 24)), st_data=st.data(),
       faults=st.lists(st.one_of(st.tuples(st.just("image"), st.sampled_from(IMAGE_FAULTS), st.integers(0, 1), st.integers(0, 5)),
                                 st.tuples(st.just("directory"), st.sampled_from(DIRECTORY_FAULTS), st.integers(0, 1), st.integers(0, 5))),
                       max_size=3))
def test_damaged_directory_is_refused_or_read(n, size, faults, st_data):
    """A KITTI-layout directory with damaged images, folders, calib.txt or times.txt: opening it and
    reading every frame gives InputErrors naming a file under it, or grey images of one size."""
    w, h = size
    rng = np.random.default_rng(n * 1000 + w * 31 + h)
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder) / "seq"
        sides = [root / "image_0", root / "image_1"]
        for side in sides:
            side.mkdir(parents=True)
            for k in range(n):
                (side / f"{k:06d}.png").write_bytes(_png(rng.integers(0, 256, (h, w), dtype=np.uint8)))
        (root / "calib.txt").write_bytes(CALIB.encode())
        (root / "times.txt").write_text("".join(f"{0.1 * k:.6e}\n" for k in range(n)))
        for kind, fault, side_index, frame in faults:
            side = sides[side_index]
            if kind == "image":
                files = sorted(p for p in side.glob("*.png") if not p.name.startswith("."))
                if not files:
                    continue
                path = files[frame % len(files)]
                if path.is_dir():  # made a directory by an earlier fault
                    continue
                if fault == "garbage":
                    path.write_bytes(st_data.draw(st.binary(max_size=64)))
                elif fault == "truncated":
                    data = path.read_bytes()
                    path.write_bytes(data[: st_data.draw(st.integers(0, max(len(data) - 1, 0)))])
                elif fault == "empty file":
                    path.write_bytes(b"")
                elif fault == "16-bit":
                    path.write_bytes(_png(rng.integers(0, 2**16, (h, w), dtype=np.uint16)))
                elif fault == "colour":
                    path.write_bytes(_png(rng.integers(0, 256, (h, w, 3), dtype=np.uint8)))
                elif fault == "alpha":
                    path.write_bytes(_png(rng.integers(0, 256, (h, w, 4), dtype=np.uint8)))
                elif fault == "other size":
                    path.write_bytes(_png(rng.integers(0, 256, (h + 1, max(1, w - 1)), dtype=np.uint8)))
                elif fault == "a directory":
                    path.unlink()
                    path.mkdir()
                elif fault == "removed":
                    path.unlink()
                elif fault == "extra frame":
                    (side / "zzzzzz.png").write_bytes(_png(np.zeros((h, w), np.uint8)))
                else:
                    path.rename(side / f"x{path.name}")
            elif fault in ("calib", "times"):
                path = root / f"{fault}.txt"
                if path.is_file():
                    path.write_bytes(st_data.draw(damaged(path.read_bytes().decode("utf-8", "replace"))))
            elif fault == "times longer":
                with open(root / "times.txt", "a") as handle:
                    handle.write("".join(f"{100.0 + k}\n" for k in range(frame + 1)))
            elif fault == "folder is a file":
                if side.is_dir():
                    for p in side.iterdir():
                        p.rmdir() if p.is_dir() else p.unlink()
                    side.rmdir()
                    side.write_text("not a folder")
            elif fault == "no calib":
                (root / "calib.txt").unlink(missing_ok=True)
            elif fault == "no times":
                (root / "times.txt").unlink(missing_ok=True)
            else:
                if side.is_dir():
                    for name, content in (("notes.txt", b"not a frame"), (".hidden.png", b"junk")):
                        if not (side / name).exists():
                            (side / name).write_bytes(content)
        stereo = refused_or(lambda: open_stereo_directory(root), root)
        if stereo is None:
            return
        assert len(stereo) >= 1 and len(stereo.left_paths) == len(stereo.right_paths) == len(stereo)
        _check_times(stereo.times, len(stereo))
        _check_calibration((stereo.K, stereo.baseline))
        width, height = stereo.image_size  # that of the first left image
        assert cv2.imread(str(stereo.left_paths[0]), cv2.IMREAD_UNCHANGED).shape[:2] == (height, width)
        for k in range(len(stereo)):
            pair = refused_or(lambda k=k: stereo.read(k), root)
            if pair is not None:
                for image in pair:
                    assert image.dtype == np.uint8 and image.shape == (height, width)


# ------------------------------------------------------------------------------------------------
# frame order: names without padding (1.png ... 50.png) sort by their number, not as text


@settings(max_examples=40, deadline=None)
@given(numbers=st.lists(st.integers(0, 10**7), min_size=2, max_size=12, unique=True), pad=st.booleans(),
       order=st.randoms())
def test_frames_are_read_in_the_order_of_their_numbers_property(numbers, pad, order):
    """Whether a recorder pads its frame numbers (000002.png) or not (2.png), the pairs come in the
    order of the numbers: 2.png before 10.png, never the text order that puts 10 before 2."""
    from vislam.frontend.images import paired_frame_names

    width = len(str(max(numbers))) if pad else 0
    names = [f"{n:0{width}d}.png" for n in numbers]
    shuffled = list(names)
    order.shuffle(shuffled)
    image = np.zeros((4, 4), np.uint8)
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        for side in ("image_0", "image_1"):
            (root / side).mkdir()
            for name in shuffled:
                cv2.imwrite(str(root / side / name), image)
        got = paired_frame_names(root, "image_0", "image_1", "test layout")
    assert got == [f"{n:0{width}d}.png" for n in sorted(numbers)]


@settings(max_examples=25, deadline=None)
@given(width=st.integers(1, 64), height=st.integers(1, 64), channels=st.sampled_from([1, 3]))
def test_png_size_is_read_from_the_header_property(width, height, channels):
    """The header gives the size cv2 decodes; a PNG declaring 50000 x 50000 pixels is refused before
    its gigabytes are decoded, naming the file and the size."""
    import struct
    import zlib

    from vislam.frontend.images import png_size, read_grey

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "f.png"
        cv2.imwrite(str(path), np.zeros((height, width, channels) if channels == 3 else (height, width), np.uint8))
        assert png_size(path) == (width, height) and read_grey(path).shape == (height, width)

        def chunk(kind: bytes, data: bytes) -> bytes:
            return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

        huge = Path(d) / "huge.png"
        huge.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 50000, 50000, 8, 0, 0, 0, 0))
                         + chunk(b"IDAT", zlib.compress(b"\0" * 16)) + chunk(b"IEND", b""))
        with pytest.raises(InputError) as e:
            read_grey(huge)
        assert str(e.value).startswith(f"{huge}: declares 50000x50000 pixels") and "\n" not in str(e.value)
        (Path(d) / "text.png").write_text("not an image")
        assert png_size(Path(d) / "text.png") is None
