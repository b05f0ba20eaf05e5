"""EuRoC MAV sequences in the ASL layout as input (frontend.euroc).

(1) The shared slice of V1_01_easy (40 stereo pairs, the whole IMU record, ground truth; skipped
with a reason without it): counts, rates, the noise and the first rows against the files read by
hand, the rectification against values derived from the two sensor.yaml independently, the vertical
disparity of tracked corners before and after rectification, the extrinsic's rotation and gravity in
the rectified camera, and the ground truth standing still over the 40 pairs.
(2) Property-based: random valid sensor.yaml / data.csv files are read back exactly; damaged ones (a
missing key, a wrong number of T_BS entries, a value that is no number, stamps not increasing, a
quaternion of norm 0, a truncated line) end in a one-line InputError naming the file.
(3) Plain cases: layouts, headers, unsupported models, rotations, swapped cameras.
"""

from __future__ import annotations

import math
import re
import tempfile
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from helpers import assert_clean_input_error, named_key
from vislam.backend.errors import InputError
from vislam.frontend.euroc import (
    CAMERA_COLUMNS, GROUND_TRUTH_COLUMNS, IMU_COLUMNS, StereoRectification, find_mav0, ns_to_seconds,
    read_camera_yaml, read_euroc, read_frames, read_ground_truth, read_imu,
)

EUROC = Path(__file__).resolve().parents[1].parent / "shared" / "euroc"
SLICE = EUROC / "V1_01_easy_first40"
MAV0 = SLICE / "mav0"
needs_euroc = pytest.mark.skipif(not (MAV0 / "cam0" / "data.csv").is_file(),
                                 reason=f"EuRoC slice V1_01_easy_first40 not found at {MAV0} (../shared/euroc)")
SETTINGS = {"deadline": None, "suppress_health_check": [HealthCheck.too_slow]}


# ---------------------------------------------------------------------------------------------- helpers


def seconds(ns: int) -> float:
    """ns / 1e9 rounded once (the exact value's nearest float64)."""
    return float(Fraction(int(ns), 10**9))


def yaml_list(text: str, key: str) -> list[float]:
    """The numbers of ``key: [a, b, ...]`` (possibly over several lines), read by a regular expression."""
    m = re.search(rf"^\s*{key}:\s*\[([^\]]*)\]", text, re.M)
    assert m, key
    return [float(x) for x in m.group(1).replace("\n", " ").split(",") if x.strip()]


def yaml_number(text: str, key: str) -> float:
    m = re.search(rf"^{key}:\s*([-+0-9.eE]+)", text, re.M)
    assert m, key
    return float(m.group(1))


def quat_wxyz(q) -> np.ndarray:
    """The rotation of a unit quaternion (w, x, y, z), Hamilton convention, written out."""
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def rigid(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def vertical_disparity(left: np.ndarray, right: np.ndarray) -> tuple[int, float]:
    """(matches, median |v_left - v_right| px) of corners of ``left`` tracked into ``right`` by
    pyramidal Lucas-Kanade, kept when tracking back lands within 0.5 px."""
    p = cv2.goodFeaturesToTrack(left, 400, 0.01, 10)
    q, st1, _ = cv2.calcOpticalFlowPyrLK(left, right, p, None, winSize=(21, 21), maxLevel=3)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(right, left, q, None, winSize=(21, 21), maxLevel=3)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(back - p, axis=2).ravel() < 0.5)
    return int(ok.sum()), float(np.median(np.abs(p[ok, 0, 1] - q[ok, 0, 1])))


# ---------------------------------------------------------------------------------------------- (1) the shared slice


@pytest.fixture(scope="module")
def euroc():
    return read_euroc(MAV0)


@needs_euroc
def test_slice_counts_and_first_rows(euroc):
    """40 pairs (none unmatched), 29,120 IMU samples at 200 Hz with the yaml's noise, the first IMU and
    ground-truth rows as the files give them."""
    frames, imu, gt = euroc.frames, euroc.imu, euroc.ground_truth
    assert len(frames) == 40 and frames.unmatched == 0
    assert frames.left_paths[0] == MAV0 / "cam0" / "data" / "1403715273262142976.png"
    assert frames.right_paths[-1].parent == MAV0 / "cam1" / "data"
    assert frames.stamps_ns[0] == 1403715273262142976
    assert abs(frames.times[0] - seconds(1403715273262142976)) <= np.spacing(frames.times[0])
    assert np.allclose(np.diff(frames.times), 0.05, atol=1e-6)

    s = imu.samples
    assert s.num_samples == 29120 and abs(s.rate_hz - 200.0) < 0.1
    assert np.array_equal(imu.body_T_imu, np.eye(4)) and imu.rate_hz == 200
    text = (MAV0 / "imu0" / "sensor.yaml").read_text()
    for key in ("gyroscope_noise_density", "gyroscope_random_walk", "accelerometer_noise_density",
                "accelerometer_random_walk"):
        assert getattr(s.noise, key) == yaml_number(text, key), key
    first = [line for line in (MAV0 / "imu0" / "data.csv").read_text().splitlines() if not line.startswith("#")][0]
    values = first.split(",")
    assert s.time_stamps[0] == pytest.approx(seconds(int(values[0])), abs=1e-12 * s.time_stamps[0])
    assert s.angular_velocity[0].tolist() == [float(x) for x in values[1:4]]  # rate first in the file
    assert s.linear_acceleration[0].tolist() == [float(x) for x in values[4:7]]
    assert 9.0 < np.linalg.norm(s.linear_acceleration[:400], axis=1).mean() < 10.6  # specific force at rest

    first = [line for line in (MAV0 / "state_groundtruth_estimate0" / "data.csv").read_text().splitlines()
             if not line.startswith("#")][0]
    v = [float(x) for x in first.split(",")[1:]]
    assert len(gt) == 2895 and gt.times[0] == frames.times[0]
    assert gt.world_T_imu[0, :3, 3].tolist() == v[0:3]
    np.testing.assert_allclose(gt.world_T_imu[0, :3, :3], quat_wxyz(v[3:7]), rtol=0, atol=1e-12)
    assert gt.velocity[0].tolist() == v[7:10]
    assert gt.gyro_bias[0].tolist() == v[10:13] and gt.accel_bias[0].tolist() == v[13:16]


@needs_euroc
def test_slice_rectification_against_the_yaml(euroc):
    """The rectified baseline is |t| of cam1_T_cam0 from the two T_BS read by hand (1e-9 relative), the
    rectified K is shared by both cameras (fx = fy ~ 436 px), R_right R R_left^T = I and the right
    camera lies on the rectified left camera's +x axis."""
    T = {}
    for cam in ("cam0", "cam1"):
        text = (MAV0 / cam / "sensor.yaml").read_text()
        T[cam] = np.array(yaml_list(text, "data")).reshape(4, 4)
    cam1_T_cam0 = np.linalg.inv(T["cam1"]) @ T["cam0"]
    r = euroc.rectification
    assert r.baseline == pytest.approx(np.linalg.norm(cam1_T_cam0[:3, 3]), rel=1e-9)
    assert 0.109 < r.baseline < 0.111
    K = r.K
    assert K[0, 0] == K[1, 1] and 430 < K[0, 0] < 442, K
    assert 0 < K[0, 2] < 752 and 0 < K[1, 2] < 480 and K[0, 1] == 0
    assert np.array_equal(r.P_right[:, :3], K) and np.array_equal(r.P_left[:, :3], K)
    assert r.P_right[0, 3] == pytest.approx(-K[0, 0] * r.baseline, rel=1e-12)
    R = cam1_T_cam0[:3, :3]
    np.testing.assert_allclose(r.R_right @ R @ r.R_left.T, np.eye(3), atol=1e-9)
    c1 = r.R_left @ (-R.T @ cam1_T_cam0[:3, 3])  # cam1's centre in the rectified left frame
    np.testing.assert_allclose(c1, [r.baseline, 0, 0], atol=1e-9)
    assert r.size == (752, 480) and r.map_left_x.shape == (480, 752)
    assert euroc.K is r.K and euroc.baseline == r.baseline


@needs_euroc
def test_slice_rectified_rows_agree(euroc):
    """Corners tracked from left to right lie on the same row after rectification (median |dv| < 0.5 px)
    and not before it (> 5 px: the raw principal points differ by 7 px)."""
    raw_left, raw_right = euroc.read_pair(20, rectified=False)
    assert raw_left.shape == (480, 752) and raw_left.dtype == np.uint8
    n_raw, dv_raw = vertical_disparity(raw_left, raw_right)
    left, right = euroc.read_pair(20)
    n, dv = vertical_disparity(left, right)
    assert n_raw >= 50 and n >= 50, (n_raw, n)
    assert dv < 0.5, dv
    assert dv_raw > 5.0, dv_raw


@needs_euroc
def test_slice_imu_T_cam(euroc):
    """imu_T_cam is rigid, equals body_T_cam0 [R_left^T 0; 0 1] (body = IMU here), and at rest the
    specific force (up) points along -y of the rectified camera (image up)."""
    imu_T_cam = euroc.imu_T_cam
    R = imu_T_cam[:3, :3]
    assert np.abs(R.T @ R - np.eye(3)).max() < 1e-12 and np.linalg.det(R) > 0
    assert np.array_equal(imu_T_cam[3], [0, 0, 0, 1])
    np.testing.assert_allclose(imu_T_cam[:3, :3], euroc.cam0.body_T_cam[:3, :3] @ euroc.rectification.R_left.T,
                               atol=1e-15)
    np.testing.assert_array_equal(imu_T_cam[:3, 3], euroc.cam0.body_T_cam[:3, 3])
    at_rest = euroc.imu.samples.between(euroc.frames.times[0], euroc.frames.times[-1])
    f_cam = R.T @ at_rest.linear_acceleration.mean(axis=0)
    assert f_cam[1] < -0.85 * np.linalg.norm(f_cam), f_cam


@needs_euroc
def test_slice_ground_truth_at_rest(euroc):
    """Over the 40 pairs the vehicle stands: the ground-truth IMU moves less than 1 cm."""
    gt = euroc.ground_truth
    inside = (gt.times >= euroc.frames.times[0]) & (gt.times <= euroc.frames.times[-1])
    assert inside.sum() == 40
    p = gt.world_T_imu[inside, :3, 3]
    assert np.linalg.norm(p - p[0], axis=1).max() < 0.01
    R = gt.world_T_imu[:, :3, :3]
    assert np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max() < 1e-12


@needs_euroc
def test_slice_parent_folder_and_readers(euroc):
    """The folder holding mav0 reads as mav0 itself; the single readers give what read_euroc gathers."""
    again = read_euroc(SLICE)
    assert again.root == MAV0 and np.array_equal(again.imu_T_cam, euroc.imu_T_cam)
    assert np.array_equal(read_frames(SLICE).times, euroc.frames.times)
    assert np.array_equal(read_imu(MAV0).samples.time_stamps, euroc.imu.samples.time_stamps)
    assert np.array_equal(read_ground_truth(MAV0).world_T_imu, euroc.ground_truth.world_T_imu)
    assert euroc.notes == ()


# ---------------------------------------------------------------------------------------------- writing sequences


def fmt(x: float) -> str:
    return repr(float(x))


def camera_yaml(body_T_cam, intrinsics, distortion, resolution, rate=20, header=True, model="pinhole",
                dist_model="radial-tangential") -> str:
    entries = [fmt(x) for x in np.ravel(body_T_cam)]
    rows = ",\n         ".join(", ".join(entries[4 * i:4 * i + 4]) for i in range(4))
    return ((("%YAML:1.0\n" if header else "") + "# General sensor definitions.\nsensor_type: camera\n"
             "comment: VI-Sensor cam0 (MT9M034)\n\n# Sensor extrinsics wrt. the body-frame.\n"
             f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{rows}]\n\n"
             + (f"rate_hz: {rate}\n" if rate is not None else "")
             + f"resolution: [{resolution[0]}, {resolution[1]}]\n"
             + (f"camera_model: {model}\n" if model is not None else "")
             + f"intrinsics: [{', '.join(fmt(x) for x in intrinsics)}] #fu, fv, cu, cv\n"
             f"distortion_model: {dist_model}\n"
             f"distortion_coefficients: [{', '.join(fmt(x) for x in distortion)}]\n"))


NOISE = {"gyroscope_noise_density": 1.6968e-04, "gyroscope_random_walk": 1.9393e-05,
         "accelerometer_noise_density": 2.0000e-3, "accelerometer_random_walk": 3.0000e-3}


def imu_yaml(body_T_imu=np.eye(4), noise=NOISE, rate=200) -> str:
    entries = ", ".join(fmt(x) for x in np.ravel(body_T_imu))
    return ("%YAML:1.0\n#Default imu sensor yaml file\nsensor_type: imu\ncomment: VI-Sensor IMU (ADIS16448)\n\n"
            f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{entries}]\nrate_hz: {rate}\n\n"
            + "".join(f"{k}: {fmt(v)}  # [ unit ]\n" for k, v in noise.items()))


def csv_text(header: str | None, stamps, rows, sep: str = ",") -> str:
    lines = [header] if header is not None else []
    for ns, row in zip(stamps, rows):
        lines.append(sep.join([str(int(ns)), *(fmt(x) if not isinstance(x, str) else x for x in row)]))
    return "\n".join(lines) + "\n"


IMU_HEADER = ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],a_RS_S_x [m s^-2],"
              "a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")
GT_HEADER = "#time(ns),px,py,pz,qw,qx,qy,qz,vx,vy,vz,bwx,bwy,bwz,bax,bay,baz"
CAM_HEADER = "#timestamp [ns],filename"

#: EuRoC's cameras (rounded): cam1 0.11 m to the right of cam0, both looking along body z
BODY_T_CAM0 = rigid([[0, -1, 0], [1, 0, 0], [0, 0, 1]], [-0.02, -0.065, 0.01])
BODY_T_CAM1 = rigid([[0, -1, 0], [1, 0, 0], [0, 0, 1]], [-0.02, 0.045, 0.01])
INTRINSICS = (458.654, 457.296, 367.215, 248.375)
DISTORTION = (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)


def write_sequence(root: Path, n_frames: int = 5, n_imu: int = 41, t0: int = 1403715273262142976,
                   body_T_imu=np.eye(4), cams=(BODY_T_CAM0, BODY_T_CAM1), ground_truth: bool = True) -> Path:
    """A small valid ``root/mav0``: cameras at 20 Hz (empty .png files), an IMU at 200 Hz, ground truth."""
    mav0 = root / "mav0"
    rng = np.random.default_rng(n_frames + n_imu)
    stamps = t0 + 50_000_000 * np.arange(n_frames)
    for cam, T in zip(("cam0", "cam1"), cams):
        (mav0 / cam / "data").mkdir(parents=True)
        (mav0 / cam / "sensor.yaml").write_text(camera_yaml(T, INTRINSICS, DISTORTION, (752, 480)))
        (mav0 / cam / "data.csv").write_text(csv_text(CAM_HEADER, stamps, [[f"{s}.png"] for s in stamps]))
        for s in stamps:
            (mav0 / cam / "data" / f"{s}.png").touch()
    (mav0 / "imu0").mkdir()
    (mav0 / "imu0" / "sensor.yaml").write_text(imu_yaml(body_T_imu))
    imu_stamps = t0 + 5_000_000 * np.arange(n_imu)
    imu_rows = np.column_stack([rng.normal(0, 0.1, (n_imu, 3)), rng.normal([9.8, 0, 0], 0.2, (n_imu, 3))])
    (mav0 / "imu0" / "data.csv").write_text(csv_text(IMU_HEADER, imu_stamps, imu_rows))
    (mav0 / "body.yaml").write_text("%YAML:1.0\ncomment: Asctec Firefly MAV\n")
    if ground_truth:
        (mav0 / "state_groundtruth_estimate0").mkdir()
        q = rng.normal(size=(n_frames, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        gt_rows = np.column_stack([rng.normal(size=(n_frames, 3)), q, rng.normal(0, 0.01, (n_frames, 9))])
        (mav0 / "state_groundtruth_estimate0" / "data.csv").write_text(csv_text(GT_HEADER, stamps, gt_rows))
    return mav0


# ---------------------------------------------------------------------------------------------- (2) round trips

finite = st.floats(-50, 50, allow_nan=False, allow_infinity=False)
unit_quaternions = (st.lists(st.floats(-1, 1), min_size=4, max_size=4)
                    .filter(lambda q: np.linalg.norm(q) > 0.1)
                    .map(lambda q: np.asarray(q) / np.linalg.norm(q)))


@st.composite
def rigid_transforms(draw):
    q = draw(unit_quaternions)
    t = draw(st.lists(st.floats(-2, 2), min_size=3, max_size=3))
    return rigid(quat_wxyz(q), t)


@settings(max_examples=40, **SETTINGS)
@given(T=rigid_transforms(), w=st.integers(16, 4000), h=st.integers(16, 3000), data=st.data(),
       rate=st.one_of(st.none(), st.integers(1, 1000), st.floats(0.5, 1000)), header=st.booleans(),
       model=st.sampled_from([None, "pinhole"]), dist_model=st.sampled_from(["radial-tangential", "radtan"]))
def test_camera_yaml_round_trip_property(T, w, h, data, rate, header, model, dist_model):
    """A random valid camera sensor.yaml (any rigid T_BS, focal lengths, principal point inside the image,
    distortion, rate or none, with or without the %YAML line) reads back exactly."""
    fu, fv = data.draw(st.floats(20, 3000), label="fu"), data.draw(st.floats(20, 3000), label="fv")
    cu, cv = data.draw(st.floats(0, w), label="cu"), data.draw(st.floats(0, h), label="cv")
    dist = data.draw(st.lists(st.floats(-1, 1), min_size=4, max_size=4), label="distortion")
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "sensor.yaml"
        path.write_text(camera_yaml(T, (fu, fv, cu, cv), dist, (w, h), rate, header, model, dist_model))
        cam = read_camera_yaml(path)
    assert np.array_equal(cam.body_T_cam, T) and cam.notes == ()
    assert np.array_equal(cam.K, [[fu, 0, cu], [0, fv, cv], [0, 0, 1]])
    assert cam.distortion.tolist() == dist and cam.resolution == (w, h)
    assert cam.rate_hz == (None if rate is None else float(rate)) and cam.source == str(path)


@st.composite
def ns_stamps(draw, n, min_step=1_000_000, max_step=100_000_000):
    t0 = draw(st.integers(10**17, 2 * 10**18))
    steps = draw(st.lists(st.integers(min_step, max_step), min_size=n - 1, max_size=n - 1))
    return np.array([t0, *np.cumsum(steps) + t0], dtype=np.int64)


@settings(max_examples=40, **SETTINGS)
@given(data=st.data(), n=st.integers(2, 30), T=rigid_transforms(),
       header=st.sampled_from([IMU_HEADER, "#timestamp, wx, wy, wz, ax, ay, az", "timestamp,w_x,w_y,w_z,a_x,a_y,a_z",
                               None]),
       sep=st.sampled_from([",", ", ", " , "]),
       noise=st.lists(st.floats(1e-9, 10), min_size=4, max_size=4))
def test_imu_round_trip_property(data, n, T, header, sep, noise):
    """Random IMU rows (stamps 1-100 ms apart, any values) with any header and spaces around the commas,
    and a random T_BS and noise: the samples read back exactly in the IMU frame (rate columns first in the
    file), the stamps within one float64 step of ns / 1e9, body_T_imu and the noise as written."""
    stamps = data.draw(ns_stamps(n), label="stamps")
    rows = np.array(data.draw(st.lists(st.lists(finite, min_size=6, max_size=6), min_size=n, max_size=n),
                              label="rows"))
    values = dict(zip(NOISE, noise))
    with tempfile.TemporaryDirectory() as d:
        (Path(d) / "cam0").mkdir()
        (Path(d) / "cam1").mkdir()
        (Path(d) / "imu0").mkdir()
        (Path(d) / "imu0" / "sensor.yaml").write_text(imu_yaml(T, values))
        (Path(d) / "imu0" / "data.csv").write_text(csv_text(header, stamps, rows, sep))
        imu = read_imu(d)
    s = imu.samples
    assert np.array_equal(s.angular_velocity, rows[:, :3]) and np.array_equal(s.linear_acceleration, rows[:, 3:])
    exact = np.array([seconds(x) for x in stamps])
    assert (np.abs(s.time_stamps - exact) <= np.spacing(exact)).all()
    assert np.array_equal(ns_to_seconds(stamps), s.time_stamps)
    assert np.array_equal(imu.body_T_imu, T)
    assert all(getattr(s.noise, k) == v for k, v in values.items())


@settings(max_examples=40, **SETTINGS)
@given(data=st.data(), n_left=st.integers(2, 25), n_right=st.integers(2, 25))
def test_frames_pairing_property(data, n_left, n_right):
    """Random left and right stamp lists sharing some stamps: the pairs are exactly the common stamps, in
    order, with their own file names; the other rows are counted as unmatched."""
    pool = data.draw(ns_stamps(n_left + n_right), label="pool")
    left = np.sort(data.draw(st.permutations(pool), label="left")[:n_left])
    shared = data.draw(st.lists(st.sampled_from(left.tolist()), min_size=2, max_size=n_left, unique=True),
                       label="shared")
    others = [s for s in pool.tolist() if s not in set(left.tolist())][:max(n_right - len(shared), 0)]
    right = np.sort(np.array(shared + others, dtype=np.int64))
    common = np.intersect1d(left, right)
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        for cam, stamps in (("cam0", left), ("cam1", right)):
            (root / cam / "data").mkdir(parents=True)
            names = [f"{s}_{cam}.png" for s in stamps]
            (root / cam / "data.csv").write_text(csv_text(CAM_HEADER, stamps, [[m] for m in names], ", "))
            for m in names:
                (root / cam / "data" / m).touch()
        (root / "imu0").mkdir()
        frames = read_frames(root)
    assert np.array_equal(frames.stamps_ns, common)
    assert np.array_equal(frames.times, ns_to_seconds(common))
    assert frames.unmatched == left.size + right.size - 2 * common.size
    assert [p.name for p in frames.left_paths] == [f"{s}_cam0.png" for s in common]
    assert [p.name for p in frames.right_paths] == [f"{s}_cam1.png" for s in common]
    assert all(p.parent == root / "cam1" / "data" for p in frames.right_paths)


@settings(max_examples=40, **SETTINGS)
@given(data=st.data(), n=st.integers(2, 20), body_T_imu=st.one_of(st.just(np.eye(4)), rigid_transforms()))
def test_ground_truth_round_trip_property(data, n, body_T_imu):
    """Random ground-truth rows (quaternions w first, their norm off 1 by up to 9e-4): positions,
    velocities and biases read back exactly, the attitude is the normalized quaternion's, composed with
    body_T_imu."""
    stamps = data.draw(ns_stamps(n), label="stamps")
    q = np.array([data.draw(unit_quaternions, label="q") * data.draw(st.floats(1 - 9e-4, 1 + 9e-4), label="scale")
                  for _ in range(n)])
    rest = np.array(data.draw(st.lists(st.lists(finite, min_size=12, max_size=12), min_size=n, max_size=n),
                              label="rows"))
    rows = np.column_stack([rest[:, :3], q, rest[:, 3:]])
    with tempfile.TemporaryDirectory() as d:
        for sub in ("cam0", "cam1", "imu0", "state_groundtruth_estimate0"):
            (Path(d) / sub).mkdir()
        (Path(d) / "state_groundtruth_estimate0" / "data.csv").write_text(csv_text(GT_HEADER, stamps, rows, ", "))
        gt = read_ground_truth(d, body_T_imu)
    assert np.array_equal(gt.times, ns_to_seconds(stamps))
    world_T_body = np.array([rigid(quat_wxyz(q[k]), rows[k, :3]) for k in range(n)])
    np.testing.assert_allclose(gt.world_T_imu, world_T_body @ body_T_imu, rtol=0, atol=1e-12 * (1 + np.abs(rows).max()))
    if np.array_equal(body_T_imu, np.eye(4)):
        assert np.array_equal(gt.world_T_imu[:, :3, 3], rows[:, :3])
    assert np.array_equal(gt.velocity, rows[:, 7:10])
    assert np.array_equal(gt.gyro_bias, rows[:, 10:13]) and np.array_equal(gt.accel_bias, rows[:, 13:16])


# ---------------------------------------------------------------------------------------------- (2) damage

#: file (relative to mav0) -> its columns, for the CSV damages
CSV_FILES = {"cam0/data.csv": CAMERA_COLUMNS, "cam1/data.csv": CAMERA_COLUMNS, "imu0/data.csv": IMU_COLUMNS,
             "state_groundtruth_estimate0/data.csv": GROUND_TRUTH_COLUMNS}
YAML_KEYS = {"cam0/sensor.yaml": ("T_BS", "intrinsics", "resolution", "distortion_model", "distortion_coefficients"),
             "cam1/sensor.yaml": ("T_BS", "intrinsics", "resolution", "distortion_model", "distortion_coefficients"),
             "imu0/sensor.yaml": ("T_BS", *NOISE)}


def _data_lines(text: str) -> list[int]:
    return [i for i, line in enumerate(text.splitlines()) if line.strip() and not line.startswith("#")]


def _damage(draw, mav0: Path, kind: str) -> tuple[Path, set[str]]:
    """Damage one file of ``mav0``; (the file, the keys an error may name)."""
    if kind in ("missing-key", "T_BS-entries", "yaml-not-a-number"):
        name = draw(st.sampled_from(sorted(YAML_KEYS)), label="file")
        path = mav0 / name
        text = path.read_text()
        if kind == "missing-key":
            key = draw(st.sampled_from(YAML_KEYS[name]), label="key")
            if key == "T_BS":
                text = re.sub(r"T_BS:\n(  .*\n)+", "", text)
            else:
                text = re.sub(rf"^{key}:.*\n", "", text, flags=re.M)
            path.write_text(text)
            return path, {key}
        if kind == "T_BS-entries":
            entries = re.search(r"data: \[([^\]]*)\]", text).group(1).replace("\n", " ").split(",")
            count = draw(st.sampled_from([0, 1, 9, 12, 15, 17, 20]), label="entries")
            new = (entries * 2)[:count]
            text = text.replace(re.search(r"data: \[([^\]]*)\]", text).group(0), f"data: [{','.join(new)}]")
            path.write_text(text)
            return path, {"T_BS.data", "T_BS"}
        key = draw(st.sampled_from(["T_BS"] + [k for k in YAML_KEYS[name] if k not in ("T_BS", "distortion_model",
                                                                                    "resolution")]), label="key")
        word = draw(st.sampled_from(["abc", "'1.0x'", "[1, 2]", "{a: 1}", "true", ".nan", ".inf", "~x"]), label="word")
        if key == "T_BS":
            text = re.sub(r"data: \[([^,\]]*)", f"data: [{word}", text)
        elif key in NOISE:
            text = re.sub(rf"^{key}:.*$", f"{key}: {word}", text, flags=re.M)
        else:
            text = re.sub(rf"^{key}: \[([^,\]]*)", f"{key}: [{word}", text, flags=re.M)
        path.write_text(text)
        return path, {key, f"{key}[0]", "T_BS.data[0]"}
    name = draw(st.sampled_from(sorted(CSV_FILES)), label="file")
    if kind == "quaternion-zero":
        name = "state_groundtruth_estimate0/data.csv"
    path, columns = mav0 / name, CSV_FILES[name]
    lines = path.read_text().splitlines()
    rows = _data_lines("\n".join(lines))
    i = draw(st.sampled_from(rows), label="row")
    fields = lines[i].split(",")
    if kind == "csv-not-a-number":
        j = draw(st.integers(0, len(fields) - 1 if name.startswith("cam") is False else 0), label="column")
        fields[j] = draw(st.sampled_from(["abc", "", "nan", "1.5.2", "-", "0x10", "1e999"]), label="word")
        if j == 0:
            fields[j] = draw(st.sampled_from(["abc", "", "1.5e18", "-5", "+140", "14.03"]), label="stamp")
        lines[i] = ",".join(fields)
    elif kind == "stamps-not-increasing":
        k = draw(st.sampled_from([r for r in rows if r != i]), label="other row")
        a, b = sorted((i, k))
        if draw(st.booleans(), label="equal"):
            lines[b] = lines[a].split(",")[0] + "," + ",".join(lines[b].split(",")[1:])
        else:
            lines[a], lines[b] = lines[b], lines[a]
    elif kind == "quaternion-zero":
        fields[4:8] = ["0", "0", "0", "0"] if draw(st.booleans(), label="zero") else ["0.5", "0", "0", "0"]
        lines[i] = ",".join(fields)
    else:  # truncated: cut before the last comma, as a write that stopped there would
        cut = draw(st.integers(1, lines[i].rfind(",")), label="cut")
        lines[i] = lines[i][:cut]
        if draw(st.booleans(), label="last line"):
            lines = lines[:i + 1]
    path.write_text("\n".join(lines) + ("\n" if draw(st.booleans(), label="newline") else ""))
    return path, set(columns)


@settings(max_examples=50, **SETTINGS)
@given(data=st.data(), kind=st.sampled_from(["missing-key", "T_BS-entries", "yaml-not-a-number", "csv-not-a-number",
                                             "stamps-not-increasing", "quaternion-zero", "truncated"]))
def test_damaged_sequence_property(data, kind):
    """One damage to one file of a valid sequence: read_euroc refuses it with one line naming that file
    and a key of it (a missing key is said to be missing)."""
    with tempfile.TemporaryDirectory() as d:
        mav0 = write_sequence(Path(d))
        read_euroc(mav0)  # valid before the damage
        path, keys = _damage(data.draw, mav0, kind)
        with pytest.raises(InputError) as e:
            read_euroc(Path(d))
    msg = assert_clean_input_error(e.value, path)
    key = named_key(msg, path)
    assert key in keys, msg
    if kind == "missing-key":
        assert "missing" in msg, msg
    if kind == "quaternion-zero":
        assert "line" in msg and "quaternion" in msg, msg


# ---------------------------------------------------------------------------------------------- (3) plain cases


def test_layout_errors(tmp_path):
    """Not a folder, a folder without mav0 or without one of cam0/, cam1/, imu0/: one line naming what is missing."""
    with pytest.raises(InputError, match="missing directory"):
        read_euroc(tmp_path / "nowhere")
    (tmp_path / "x.txt").write_text("")
    with pytest.raises(InputError, match="not a directory"):
        read_euroc(tmp_path / "x.txt")
    with pytest.raises(InputError) as e:
        read_euroc(tmp_path)
    msg = assert_clean_input_error(e.value, tmp_path)
    assert "cam0/, cam1/, imu0/" in msg and "no mav0/" in msg
    mav0 = write_sequence(tmp_path / "seq")
    (mav0 / "cam1" / "data.csv").unlink()
    with pytest.raises(InputError) as e:
        read_euroc(mav0)
    assert "missing" in assert_clean_input_error(e.value, mav0 / "cam1" / "data.csv")
    for sub in ("cam1/data", "cam1"):
        for p in (mav0 / sub).iterdir():
            p.unlink()
        (mav0 / sub).rmdir()
    with pytest.raises(InputError) as e:
        find_mav0(mav0.parent)
    assert assert_clean_input_error(e.value, mav0).endswith("missing cam1/")


def test_small_sequence_reads(tmp_path):
    """A written sequence reads whole: no notes, no ground truth without its folder, unmatched frames counted."""
    mav0 = write_sequence(tmp_path / "a")
    seq = read_euroc(mav0)
    assert len(seq.frames) == 5 and seq.imu.samples.num_samples == 41 and len(seq.ground_truth) == 5
    assert seq.notes == () and seq.rectification.baseline == pytest.approx(0.11, rel=1e-12)
    np.testing.assert_allclose(seq.rectification.R_left, np.eye(3), atol=1e-12)  # parallel cameras
    mav0 = write_sequence(tmp_path / "b", n_imu=40, ground_truth=False)
    with open(mav0 / "cam1" / "data.csv", "a") as f:
        f.write("1403715999000000000,1403715999000000000.png\n")  # a right frame alone (its png is absent)
    seq = read_euroc(mav0)
    assert seq.ground_truth is None and seq.frames.unmatched == 1 and len(seq.frames) == 5
    assert any("1 frames without a partner" in n for n in seq.notes)
    assert any("outside the IMU record" in n for n in seq.notes)  # frames span 0.2 s, the IMU 0.195 s


def test_missing_image_is_named(tmp_path):
    mav0 = write_sequence(tmp_path)
    victim = sorted((mav0 / "cam1" / "data").iterdir())[2]
    victim.unlink()
    with pytest.raises(InputError) as e:
        read_frames(mav0)
    assert "missing image" in assert_clean_input_error(e.value, victim)


@pytest.mark.parametrize("model_line, key, word", [
    ("distortion_model: equidistant", "distortion_model", "equidistant"),
    ("distortion_model: fov", "distortion_model", "fov"),
    ("camera_model: omni", "camera_model", "omni"),
    ("camera_model: eucm", "camera_model", "eucm"),
])
def test_unsupported_models_are_named(tmp_path, model_line, key, word):
    path = tmp_path / "sensor.yaml"
    text = camera_yaml(BODY_T_CAM0, INTRINSICS, DISTORTION, (752, 480))
    path.write_text(re.sub(rf"^{key}:.*$", model_line, text, flags=re.M))
    with pytest.raises(InputError) as e:
        read_camera_yaml(path)
    msg = assert_clean_input_error(e.value, path)
    assert named_key(msg, path) == key and word in msg and "not supported" in msg


@pytest.mark.parametrize("change, key, what", [
    (lambda t: t.replace("intrinsics: [458.654", "intrinsics: [-458.654"), "intrinsics", "must be > 0"),
    (lambda t: t.replace("367.215", "967.215"), "intrinsics", "outside"),
    (lambda t: t.replace("[752, 480]", "[752.5, 480]"), "resolution", "whole numbers"),
    (lambda t: t.replace("rate_hz: 20", "rate_hz: -20"), "rate_hz", "> 0"),
    (lambda t: t.replace("rows: 4", "rows: 3"), "T_BS.rows", "expected 4"),
    (lambda t: t.replace("sensor_type: camera", "sensor_type: imu"), "sensor_type", "camera"),
    (lambda t: t.replace("0.0, 1.0]", "0.0, 2.0]"), "T_BS", "last row"),
    (lambda t: t.replace("distortion_coefficients: [", "distortion_coefficients: [0.1, "), "distortion_coefficients",
     "5 numbers, expected 4"),
    (lambda t: t.replace("resolution: [752, 480]", "resolution: [752, 480"), None, "not valid YAML"),
    (lambda t: "- just\n- a list\n", None, "not a YAML mapping"),
])
def test_bad_camera_yaml(tmp_path, change, key, what):
    path = tmp_path / "sensor.yaml"
    path.write_text(change(camera_yaml(BODY_T_CAM0, INTRINSICS, DISTORTION, (752, 480))))
    with pytest.raises(InputError) as e:
        read_camera_yaml(path)
    msg = assert_clean_input_error(e.value, path)
    assert what in msg, msg
    if key is not None:
        assert named_key(msg, path) == key, msg


def test_rotations_of_T_BS(tmp_path):
    """A rotation typed to 5 digits is replaced by the nearest one with a note; a scaled one is refused."""
    R = quat_wxyz([0.9, 0.1, -0.3, 0.2])
    path = tmp_path / "sensor.yaml"
    path.write_text(camera_yaml(rigid(np.round(R, 5), [0.1, 0.2, 0.3]), INTRINSICS, DISTORTION, (752, 480)))
    cam = read_camera_yaml(path)
    assert len(cam.notes) == 1 and "re-orthonormalized" in cam.notes[0]
    Rc = cam.body_T_cam[:3, :3]
    assert np.abs(Rc.T @ Rc - np.eye(3)).max() < 1e-14 and np.abs(Rc - R).max() < 1e-5
    path.write_text(camera_yaml(rigid(1.01 * R, [0.1, 0.2, 0.3]), INTRINSICS, DISTORTION, (752, 480)))
    with pytest.raises(InputError) as e:
        read_camera_yaml(path)
    assert named_key(assert_clean_input_error(e.value, path), path) == "T_BS"


def test_T_BS_as_nested_list_and_opencv_matrix(tmp_path):
    """T_BS as a nested 4x4 list, and an OpenCV !!opencv-matrix, read as the flat form; numbers such as
    1e-05 (text to YAML 1.1) are numbers."""
    T = rigid(quat_wxyz([0.5, 0.5, -0.5, 0.5]), [1e-05, -2.5e-7, 3.0])
    flat = camera_yaml(T, INTRINSICS, DISTORTION, (752, 480))
    nested = re.sub(r"T_BS:\n(  .*\n)+", "T_BS: " + str([[float(x) for x in row] for row in T]) + "\n", flat)
    opencv = flat.replace("T_BS:\n", "T_BS: !!opencv-matrix\n").replace("  cols: 4\n", "  cols: 4\n  dt: d\n")
    for i, text in enumerate((flat, nested, opencv)):
        path = tmp_path / f"sensor{i}.yaml"
        path.write_text(text)
        assert np.array_equal(read_camera_yaml(path).body_T_cam, T), i


def test_csv_headers_and_spaces(tmp_path):
    """Data rows with spaces, CRLF line ends, blank lines and a header without '#' read as plain ones; a
    header-like first row after a '#' header is refused (it is a damaged row, not a second header)."""
    mav0 = write_sequence(tmp_path)
    path = mav0 / "imu0" / "data.csv"
    plain = read_imu(mav0).samples
    lines = path.read_text().splitlines()
    path.write_text("timestamp,wx,wy,wz,ax,ay,az\r\n\r\n" + "\r\n".join(" , ".join(l.split(",")) for l in lines[1:]))
    again = read_imu(mav0).samples
    assert np.array_equal(again.time_stamps, plain.time_stamps)
    assert np.array_equal(again.linear_acceleration, plain.linear_acceleration)
    path.write_text(lines[0] + "\ntimestamp,wx,wy,wz,ax,ay,az\n" + "\n".join(lines[1:]) + "\n")
    with pytest.raises(InputError) as e:
        read_imu(mav0)
    assert named_key(assert_clean_input_error(e.value, path), path) == "timestamp"


def test_imu_stamps_too_dense_or_sparse(tmp_path):
    """Nanosecond stamps 1 ns apart collapse in float64 seconds, stamps seconds apart are not an IMU: both
    refused naming the file (check_imu_samples)."""
    for step, what in ((1, "not strictly increasing"), (2_000_000_000, "not an IMU's own rate")):
        mav0 = write_sequence(tmp_path / str(step))
        path = mav0 / "imu0" / "data.csv"
        stamps = 1403715273262142976 + step * np.arange(10)
        path.write_text(csv_text(IMU_HEADER, stamps, np.ones((10, 6))))
        with pytest.raises(InputError) as e:
            read_imu(mav0)
        assert what in assert_clean_input_error(e.value, path)


def test_swapped_cameras_are_refused(tmp_path):
    """cam1 to the left of cam0: refused naming cam1's T_BS; cameras one above the other too."""
    mav0 = write_sequence(tmp_path / "a", cams=(BODY_T_CAM1, BODY_T_CAM0))
    with pytest.raises(InputError) as e:
        read_euroc(mav0)
    msg = assert_clean_input_error(e.value, mav0 / "cam1" / "sensor.yaml")
    assert named_key(msg, mav0 / "cam1" / "sensor.yaml") == "T_BS" and "LEFT" in msg
    below = BODY_T_CAM0.copy()
    below[0, 3] += 0.11  # body x is the camera's -y: 0.11 m up
    mav0 = write_sequence(tmp_path / "b", cams=(BODY_T_CAM0, below))
    with pytest.raises(InputError) as e:
        read_euroc(mav0)
    assert "vertically" in assert_clean_input_error(e.value, mav0 / "cam1" / "sensor.yaml")


def test_rectify_shapes_and_imu_T_cam(tmp_path):
    """rectify refuses images of another size; imu_T_cam composes body_T_imu^-1 body_T_cam0 R_left^T."""
    seq = read_euroc(write_sequence(tmp_path))
    r = seq.rectification
    with pytest.raises(ValueError):
        r.rectify(np.zeros((48, 64), np.uint8), np.zeros((48, 64), np.uint8))
    left, right = r.rectify(np.zeros((480, 752), np.uint8), np.full((480, 752), 7, np.uint8))
    assert left.shape == right.shape == (480, 752) and right[240, 376] == 7
    body_T_imu = rigid(quat_wxyz([0.2, 0.9, 0.1, -0.3]), [0.1, -0.2, 0.05])
    expected = np.linalg.inv(body_T_imu) @ BODY_T_CAM0 @ rigid(r.R_left.T, np.zeros(3))
    np.testing.assert_allclose(r.imu_T_cam(body_T_imu), expected, atol=1e-14)


def test_ground_truth_with_imu_offset(tmp_path):
    """With an IMU away from the body origin the ground truth is moved to it and says the velocity is the body's."""
    body_T_imu = rigid(np.eye(3), [0.0, 0.0, 0.1])
    mav0 = write_sequence(tmp_path, body_T_imu=body_T_imu)
    seq = read_euroc(mav0)
    plain = read_ground_truth(mav0)
    np.testing.assert_allclose(seq.ground_truth.world_T_imu, plain.world_T_imu @ body_T_imu, atol=1e-15)
    assert len(seq.ground_truth.notes) == 1 and "velocity" in seq.ground_truth.notes[0]
    assert np.array_equal(seq.imu.body_T_imu, body_T_imu)


def test_rectification_from_cameras_is_the_dataset_s(tmp_path):
    mav0 = write_sequence(tmp_path)
    cams = [read_camera_yaml(mav0 / c / "sensor.yaml") for c in ("cam0", "cam1")]
    r = StereoRectification.from_cameras(*cams)
    assert np.array_equal(r.K, read_euroc(mav0).K)
    assert math.isclose(r.baseline, 0.11, rel_tol=1e-12)
