"""Stereo image renderer (vislam.synth.render) and procedural textures (vislam.synth.textures)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vislam.backend.geometry import se3
from vislam.synth import textures
from vislam.synth.observe import kitti_calibration
from vislam.synth.render import SKY, Plane, build_street_planes, render_image, render_pair, write_kitti_sequence
from vislam.synth.trajectories import street

CAL = kitti_calibration()
SQUARES = (10, 6)  # checker squares (columns, rows) -> 9 x 5 inner corners
SQUARE = 32  # texels


def _plane_in_camera(centre, R, width, texture) -> Plane:
    """A rectangle of ``width`` metres (height from the texture's aspect) centred at ``centre``
    in the left camera frame, spanned by R's x (texture rows) and y (texture columns) axes, for
    world_T_imu = identity (so world_T_cam = imu_T_cam)."""
    h, w = texture.shape
    height = width * h / w
    ex, ey = R[:, 0], R[:, 1]
    c0 = np.asarray(centre, dtype=float) - 0.5 * width * ex - 0.5 * height * ey
    cam = np.array([c0, c0 + width * ex, c0 + width * ex + height * ey, c0 + height * ey])
    world_T_cam = CAL.imu_T_cam
    return Plane(cam @ world_T_cam[:3, :3].T + world_T_cam[:3, 3], texture)


def _to_camera(points_world: np.ndarray) -> np.ndarray:
    cam_T_world = se3.inverse(CAL.imu_T_cam)
    return points_world @ cam_T_world[:3, :3].T + cam_T_world[:3, 3]


def _detect(img: np.ndarray) -> np.ndarray:
    found, corners = cv2.findChessboardCorners(img, (SQUARES[0] - 1, SQUARES[1] - 1), flags=cv2.CALIB_CB_ADAPTIVE_THRESH)
    assert found
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    return cv2.cornerSubPix(img, corners.astype(np.float32), (5, 5), (-1, -1), crit).reshape(-1, 2).astype(float)


def _match(detected: np.ndarray, expected: np.ndarray) -> np.ndarray:
    """expected rows reordered to the detected corners (nearest; the detector's order is free)."""
    d = np.linalg.norm(detected[:, None] - expected[None], axis=2)
    j = d.argmin(axis=1)
    assert len(set(j.tolist())) == expected.shape[0]  # one-to-one
    assert d[np.arange(j.size), j].max() < 1.0
    return expected[j]


def exp_so3(w: np.ndarray) -> np.ndarray:
    """The rotation exp(w^) (Rodrigues)."""
    return se3.exp_so3_and_left_jacobian(np.asarray(w, dtype=float))[0]


POSES = {
    "fronto": (np.eye(3), (0.13, 0.07, 3.0)),
    "oblique": (exp_so3(np.array([0.0, 0.6, 0.0])) @ exp_so3(np.array([0.25, 0.0, 0.0])), (-0.3, 0.0, 3.5)),
}


@pytest.fixture(scope="module", params=sorted(POSES))
def checker_scene(request):
    R, centre = POSES[request.param]
    tex = textures.checkerboard(SQUARES, SQUARE, border=1)
    plane = _plane_in_camera(centre, R, 3.0, tex)
    left, right = render_pair([plane], np.eye(4), CAL)
    p_cam = _to_camera(plane.point(textures.checkerboard_corners(SQUARES, SQUARE, border=1)))
    z = CAL.camera.project(p_cam)  # (n, 4) uL vL uR vR
    return request.param, left, right, z, p_cam


def test_checker_corners_match_projection(checker_scene):
    name, left, _, z, _ = checker_scene
    found = _detect(left)
    err = found - _match(found, z[:, :2])
    assert np.abs(err).max() <= 0.1, name
    assert np.abs(err.mean(axis=0)).max() <= 0.03, name  # no systematic (convention) offset


def test_checker_stereo_rows_and_disparity(checker_scene):
    name, left, right, z, p_cam = checker_scene
    fl, fr = _detect(left), _detect(right)
    zl = _match(fl, z[:, :2])
    zr = _match(fr, z[:, 2:])
    # pair the detections through their 3-D corner
    il = np.array([np.flatnonzero((z[:, :2] == row).all(axis=1))[0] for row in zl])
    ir = np.array([np.flatnonzero((z[:, 2:] == row).all(axis=1))[0] for row in zr])
    L = fl[np.argsort(il)]
    R = fr[np.argsort(ir)]
    assert np.abs(fr - zr).max() <= 0.1, name
    assert np.abs(L[:, 1] - R[:, 1]).max() < 0.1, name
    disparity = CAL.camera.fx * CAL.baseline / p_cam[:, 2]
    assert np.abs((L[:, 0] - R[:, 0]) - disparity).max() < 0.1, name


def _bilinear_zero_border(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear interpolation at OpenCV coordinates (x, y), zero outside the image."""
    pad = np.zeros((img.shape[0] + 2, img.shape[1] + 2))
    pad[1:-1, 1:-1] = img
    x, y = x + 1.0, y + 1.0
    inside = (x >= 0) & (x <= pad.shape[1] - 1) & (y >= 0) & (y <= pad.shape[0] - 1)
    x0 = np.clip(np.floor(x), 0, pad.shape[1] - 2).astype(int)
    y0 = np.clip(np.floor(y), 0, pad.shape[0] - 2).astype(int)
    fx, fy = np.clip(x - x0, 0, 1), np.clip(y - y0, 0, 1)
    value = (
        pad[y0, x0] * (1 - fx) * (1 - fy) + pad[y0, x0 + 1] * fx * (1 - fy)
        + pad[y0 + 1, x0] * (1 - fx) * fy + pad[y0 + 1, x0 + 1] * fx * fy
    )
    return np.where(inside, value, 0.0)


def test_texture_convention_and_antialiased_edge():
    """A 4 x 2 texture on a fronto-parallel plane, magnified 32x: each pixel is the bilinear
    interpolation of the texture at its ray's continuous texture coordinates (s, t) (texel (i, j)
    centred on (i + 1/2, j + 1/2), OpenCV coordinates (s - 1/2, t - 1/2)), blended over the sky
    with the coverage interpolated the same way (1/2 on the geometric edge, one texel wide)."""
    tex = np.array([[10, 60, 110, 160], [210, 35, 85, 135]], dtype=np.uint8)
    depth = 4.0
    plane = _plane_in_camera((0.03, -0.02, depth), np.eye(3), 0.7, tex)
    img = render_image([plane], se3.inverse(CAL.imu_T_cam), CAL.K, CAL.image_size)
    c0 = _to_camera(plane.corners[:1])[0]
    texel = 0.7 / 4  # metres
    v, u = np.mgrid[120:260, 470:760].astype(float)
    x = (u - CAL.camera.cx) / CAL.camera.fx * depth
    y = (v - CAL.camera.cy) / CAL.camera.fy * depth
    s, t = (x - c0[0]) / texel, (y - c0[1]) / texel
    colour = _bilinear_zero_border(tex.astype(float), s - 0.5, t - 0.5)
    alpha = _bilinear_zero_border(np.ones(tex.shape), s - 0.5, t - 0.5)
    expected = SKY * (1 - alpha) + colour
    # tolerance: OpenCV's warp quantizes texture coordinates to 1/32 texel and weights to 1/32,
    # and the composite is uint8 (measured max 1.3 grey levels)
    assert np.abs(img[120:260, 470:760] - expected).max() <= 2.0
    assert (alpha == 0).any() and (alpha == 1).any() and ((alpha > 0.2) & (alpha < 0.8)).sum() > 100
    # texel centres carry their values; half coverage on the left edge line s = 0
    for j in range(2):
        for i in range(4):
            uu, vv = CAL.camera.project(_to_camera(plane.point([[i + 0.5, j + 0.5]])))[0, :2]
            assert abs(int(img[int(round(vv)), int(round(uu))]) - int(tex[j, i])) <= 4


def test_plane_straddling_the_camera_is_clipped_not_mirrored():
    """A long wall on the left from 10 m behind to 30 m ahead: drawn in front, nothing right of
    its vanishing line (rays to the right meet its plane only behind the camera)."""
    tex = textures.bricks(np.random.default_rng(1), (1024, 256))
    cam = np.array([[-3.0, -2.0, -10.0], [-3.0, -2.0, 30.0], [-3.0, 2.0, 30.0], [-3.0, 2.0, -10.0]])
    world_T_cam = CAL.imu_T_cam
    plane = Plane(cam @ world_T_cam[:3, :3].T + world_T_cam[:3, 3], tex)
    left, _ = render_pair([plane], np.eye(4), CAL)
    cx = CAL.camera.cx
    assert (left[:, int(cx) + 1 :] == SKY).all()
    # a point 5 m ahead on the wall shows its texel
    p = plane.point([[15.0 / 40.0 * 1024 + 0.5, 128.5]])
    u, v = CAL.camera.project(_to_camera(p))[0, :2]
    assert abs(int(left[int(round(v)), int(round(u))]) - int(tex[128, int(15.0 / 40.0 * 1024)])) <= 40
    assert (left[:, : int(cx) - 80] != SKY).mean() > 0.5
    # entirely behind: nothing drawn
    behind = Plane((cam - [0.0, 0.0, 40.0]) @ world_T_cam[:3, :3].T + world_T_cam[:3, 3], tex)
    assert (render_pair([behind], np.eye(4), CAL)[0] == SKY).all()


def test_plane_validation():
    tex = np.zeros((4, 4), dtype=np.uint8)
    square = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    Plane(square, tex)
    with pytest.raises(ValueError):
        Plane(square + [[0, 0, 0], [0, 0, 0], [0, 0, 0.1], [0, 0, 0]], tex)  # not planar
    with pytest.raises(ValueError):
        Plane(square[[0, 2, 1, 3]], tex)  # not in order around the quad
    with pytest.raises(ValueError):
        Plane(square, tex.astype(float))
    # (corners, texture) tuples are accepted as planes
    board = textures.checkerboard((4, 3), 8)
    p = _plane_in_camera((0.0, 0.0, 3.0), np.eye(3), 1.0, board)
    a = render_pair([p], np.eye(4), CAL)
    b = render_pair([(p.corners, board)], np.eye(4), CAL)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) and (a[0] != SKY).any()


@pytest.mark.parametrize("make", [textures.bricks, textures.blobs, textures.glyphs])
def test_textures_have_corners_and_are_deterministic(make):
    tex = make(np.random.default_rng(7), (512, 512))
    assert tex.shape == (512, 512) and tex.dtype == np.uint8
    corners = cv2.goodFeaturesToTrack(tex, 2000, 0.01, 8)
    assert corners is not None and len(corners) >= 100
    assert np.array_equal(tex, make(np.random.default_rng(7), (512, 512)))


@pytest.fixture(scope="module")
def street_world():
    traj = street(20, 0.1, seed=3)
    return traj, build_street_planes(traj.world_T_imu, np.random.default_rng(3))


def test_street_renders_textured_rectified_pairs(street_world):
    traj, planes = street_world
    left, right = render_pair(planes, traj.world_T_imu[10], CAL)
    assert left.shape == right.shape == (CAL.height, CAL.width) and left.dtype == np.uint8
    assert (left == SKY).mean() < 0.5
    pts = cv2.goodFeaturesToTrack(left, 2000, 0.01, 10)
    assert len(pts) >= 300
    # rectified: KLT from left to right moves features along rows, leftwards
    moved, ok, _ = cv2.calcOpticalFlowPyrLK(left, right, pts, None, winSize=(21, 21), maxLevel=3)
    d = (moved - pts).reshape(-1, 2)[ok.ravel() == 1]
    assert np.median(np.abs(d[:, 1])) < 0.1
    assert np.median(d[:, 0]) < 0
    again = render_pair(planes, traj.world_T_imu[10], CAL)
    assert np.array_equal(again[0], left) and np.array_equal(again[1], right)


def test_write_kitti_sequence_layout(tmp_path, street_world):
    traj, planes = street_world
    poses, times = traj.world_T_imu[:3], traj.time_stamps[:3] + 5.0
    out = write_kitti_sequence(tmp_path / "seq", (poses, times, CAL), planes)
    for folder in ("image_0", "image_1"):
        names = sorted(p.name for p in (out / folder).iterdir())
        assert names == ["000000.png", "000001.png", "000002.png"]
        img = cv2.imread(str(out / folder / "000001.png"), cv2.IMREAD_UNCHANGED)
        assert img.shape == (CAL.height, CAL.width) and img.dtype == np.uint8
    left, right = render_pair(planes, poses[1], CAL)
    assert np.array_equal(cv2.imread(str(out / "image_0" / "000001.png"), cv2.IMREAD_UNCHANGED), left)
    assert np.array_equal(cv2.imread(str(out / "image_1" / "000001.png"), cv2.IMREAD_UNCHANGED), right)
    P = {}
    for line in (out / "calib.txt").read_text().splitlines():
        key, values = line.split(":")
        P[key] = np.array(values.split(), dtype=float).reshape(3, 4)
    assert set(P) == {"P0", "P1"}
    assert np.allclose(P["P0"][:, :3], CAL.K) and np.allclose(P["P1"][:, :3], CAL.K)
    assert np.allclose(P["P0"][:, 3], 0.0)
    assert -P["P1"][0, 3] / P["P1"][0, 0] == pytest.approx(CAL.baseline, rel=1e-12)
    t = np.loadtxt(out / "times.txt")
    assert t.shape == (3,) and np.allclose(t, times - times[0], atol=1e-6) and t[0] == 0.0
    T = np.loadtxt(out / "poses.txt").reshape(-1, 3, 4)
    assert np.allclose(T, (poses @ CAL.imu_T_cam)[:, :3], atol=1e-5)


def test_write_kitti_sequence_from_scene(tmp_path):
    from vislam.synth.scene import SceneConfig, make_scene

    scene = make_scene(SceneConfig(steps=2, seed=4))
    out = write_kitti_sequence(tmp_path, scene)
    assert len(list((out / "image_0").glob("*.png"))) == 2
    assert len((out / "times.txt").read_text().splitlines()) == 2
