"""Tests of vislam.backend.geometry.camera: the stereo observation model, triangulation, their
Jacobians against finite differences, and the unscented expected triangulation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from vislam.backend.geometry.camera import StereoCamera, dpi_dq, pi
from helpers import numeric_jacobian

SETTINGS = settings(max_examples=60, deadline=None)

K_KITTI = np.array([[718.856, 0.0, 607.1928], [0.0, 718.856, 185.2157], [0.0, 0.0, 1.0]])
CAM = StereoCamera(K=K_KITTI, baseline=0.537)


@st.composite
def _points_in_front(draw, max_n: int = 20) -> np.ndarray:
    """Points with depth 1-80 m inside a generous frustum around the image."""
    n = draw(st.integers(1, max_n))
    depth = draw(arrays(float, n, elements=st.floats(1.0, 80.0)))
    lateral = draw(arrays(float, (n, 2), elements=st.floats(-1.0, 1.0)))
    return np.column_stack([lateral * depth[:, None], depth])


def projection_jacobian(cam: StereoCamera, p_in_cam: np.ndarray) -> np.ndarray:
    """Reference dz/dp of the observation model z = Ks pi([p; 1]), in closed form; (..., 3) -> (..., 4, 3):
    rows uL: [fx, 0, -fx x/z]/z, vL and vR: [0, fy, -fy y/z]/z, uR: [fx, 0, -fx (x - b)/z]/z."""
    p = np.asarray(p_in_cam, dtype=float)
    x, y, inv_z = p[..., 0], p[..., 1], 1.0 / p[..., 2]
    J = np.zeros(p.shape[:-1] + (4, 3))
    J[..., 0, 0] = J[..., 2, 0] = cam.fx * inv_z
    J[..., 1, 1] = J[..., 3, 1] = cam.fy * inv_z
    J[..., 0, 2] = -cam.fx * x * inv_z * inv_z
    J[..., 2, 2] = -cam.fx * (x - cam.baseline) * inv_z * inv_z
    J[..., 1, 2] = J[..., 3, 2] = -cam.fy * y * inv_z * inv_z
    return J


def triangulation_jacobian(cam: StereoCamera, z: np.ndarray) -> np.ndarray:
    """d triangulate / d z at the pixels z; (..., 4) -> (..., 3, 4)."""
    return cam.triangulate_with_jacobian(z)[1]


def triangulate_mean(cam: StereoCamera, z: np.ndarray, pixel_sigma: float) -> np.ndarray:
    """The unscented expected triangulation of pixels z under N(0, pixel_sigma^2 I4) noise; (..., 4) -> (..., 3)."""
    return cam.triangulate_with_jacobian(z, pixel_sigma)[0]


def test_ks_structure():
    fx, fy, cx, cy, b = 718.856, 718.856, 607.1928, 185.2157, 0.537
    expected = np.array([[fx, 0, cx, 0], [0, fy, cy, 0], [fx, 0, cx, -fx * b], [0, fy, cy, 0]])
    assert np.array_equal(CAM.Ks, expected)
    assert (CAM.fx, CAM.fy, CAM.cx, CAM.cy) == (fx, fy, cx, cy)


@SETTINGS
@given(_points_in_front())
def test_project_disparity_and_rows(p_in_cam):
    z = CAM.project(p_in_cam)
    assert z.shape == (len(p_in_cam), 4)
    assert np.allclose(z[:, 0] - z[:, 2], CAM.fx * CAM.baseline / p_in_cam[:, 2], rtol=1e-12, atol=1e-9)
    assert np.array_equal(z[:, 1], z[:, 3])
    assert np.allclose(z[:, 0], CAM.fx * p_in_cam[:, 0] / p_in_cam[:, 2] + CAM.cx, rtol=1e-12, atol=1e-9)


@SETTINGS
@given(_points_in_front())
def test_triangulate_inverts_project(p_in_cam):
    assert np.allclose(CAM.triangulate(CAM.project(p_in_cam)), p_in_cam, rtol=1e-9, atol=1e-9)


def test_single_point_shapes():
    p = np.array([1.0, -0.5, 12.0])
    z = CAM.project(p)
    assert z.shape == (4,)
    assert np.allclose(z, CAM.project(p[None])[0])
    assert np.allclose(CAM.triangulate(z), p)
    point, J = CAM.triangulate_with_jacobian(z)
    assert point.shape == (3,) and J.shape == (3, 4)
    point, J = CAM.triangulate_with_jacobian(z, 0.5)
    assert point.shape == (3,) and J.shape == (3, 4)
    assert CAM.triangulate_with_jacobian(np.stack([z, z]).reshape(2, 1, 4))[1].shape == (2, 1, 3, 4)
    q = np.append(p, 1.0)
    assert pi(q).shape == (4,)
    assert dpi_dq(q).shape == (4, 4)


@SETTINGS
@given(_points_in_front(max_n=5))
def test_projection_jacobian_finite_differences(p_in_cam):
    """The observation model's dz/dp (closed form, and Ks dpi/dq [I3; 0]) against finite
    differences of project."""
    J = projection_jacobian(CAM, p_in_cam)
    assert J.shape == (len(p_in_cam), 4, 3)
    q = np.column_stack([p_in_cam, np.ones(len(p_in_cam))])
    assert np.allclose(CAM.Ks @ dpi_dq(q)[..., :3], J, rtol=1e-12, atol=1e-12 * np.abs(J).max())
    for p, J_p in zip(p_in_cam, J):
        numeric = numeric_jacobian(CAM.project, p, eps=1e-5 * p[2])
        assert np.allclose(J_p, numeric, rtol=1e-6, atol=1e-6 * np.abs(J_p).max())


@SETTINGS
@given(_points_in_front(max_n=5))
def test_triangulation_jacobian_finite_differences(p_in_cam):
    z = CAM.project(p_in_cam)
    points, J = CAM.triangulate_with_jacobian(z)
    assert J.shape == (len(p_in_cam), 3, 4)
    assert np.array_equal(points, CAM.triangulate(z))
    for z_i, J_i in zip(z, J):
        numeric = numeric_jacobian(CAM.triangulate, z_i, eps=1e-4)
        assert np.allclose(J_i, numeric, rtol=1e-6, atol=1e-6 * np.abs(J_i).max())
    # with pixel noise the point moves to the expected triangulation; the Jacobian stays the one at z
    assert np.array_equal(CAM.triangulate_with_jacobian(z, 0.5)[1], J)


@SETTINGS
@given(_points_in_front(max_n=5), st.floats(-2.0, 2.0))
def test_dpi_dq_finite_differences(p_in_cam, w):
    q = np.column_stack([p_in_cam, np.full(len(p_in_cam), w)])
    J = dpi_dq(q)
    for q_i, J_i in zip(q, J):
        numeric = numeric_jacobian(pi, q_i, eps=1e-6 * q_i[2])
        assert np.allclose(J_i, numeric, rtol=1e-6, atol=1e-8 * np.abs(J_i).max())


def test_projection_jacobian_is_inverse_of_triangulation_jacobian():
    p_in_cam = np.array([[1.0, -0.5, 12.0], [-3.0, 1.0, 40.0]])
    product = triangulation_jacobian(CAM, CAM.project(p_in_cam)) @ projection_jacobian(CAM, p_in_cam)
    assert np.allclose(product, np.eye(3), atol=1e-10)


@pytest.mark.parametrize(
    "K, baseline",
    [(np.eye(2), 0.5), (K_KITTI, 0.0), (K_KITTI, -1.0), (K_KITTI, float("nan")), (-K_KITTI, 0.5)],
)
def test_invalid_camera_rejected(K, baseline):
    with pytest.raises(ValueError):
        StereoCamera(K=K, baseline=baseline)


def test_camera_is_frozen():
    with pytest.raises(AttributeError):
        CAM.baseline = 1.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        CAM.K[0, 0] = 1.0


def test_triangulate_mean_matches_monte_carlo_expectation():
    """The unscented mean equals the sample mean of triangulated noisy pixels (the depth bias of
    1/disparity) to within the Monte Carlo error, where the plain triangulation does not."""
    rng = np.random.default_rng(0)
    sigma = 0.5
    p = np.array([[3.0, -1.0, 40.0], [-8.0, 2.0, 25.0], [1.0, 0.5, 60.0]])
    z = CAM.project(p)
    mean = triangulate_mean(CAM, z, sigma)
    samples = CAM.triangulate(z[None] + rng.normal(0.0, sigma, (400_000,) + z.shape))
    sample_mean = samples.mean(axis=0)
    stderr = samples.std(axis=0) / np.sqrt(samples.shape[0])
    assert np.all(np.abs(mean - sample_mean) < 5 * stderr + 1e-3 * np.abs(p[:, 2:]))
    bias = sample_mean[:, 2] - p[:, 2]
    assert np.all(bias > 10 * stderr[:, 2])  # the plain triangulation is measurably too near
    assert np.all(np.abs(mean[:, 2] - sample_mean[:, 2]) < 0.1 * bias)
    # second order: E[depth] ~ depth (1 + 2 sigma^2 / d^2)
    d = z[:, 0] - z[:, 2]
    np.testing.assert_allclose(mean[:, 2], p[:, 2] * (1 + 2 * sigma**2 / d**2), rtol=2e-3)


def test_triangulate_mean_equals_the_nine_point_unscented_transform():
    """The shortcut (vL, vR enter linearly, so only the uL and uR sigma points are evaluated) is the
    full 2N+1 = 9 point transform with weights -1/3 and 1/6."""
    rng = np.random.default_rng(3)
    z = CAM.project(np.column_stack([rng.uniform(-10, 10, 50), rng.uniform(-2, 2, 50), rng.uniform(4, 80, 50)]))
    c = np.sqrt(3.0) * 1.5
    shifts = np.concatenate([c * np.eye(4), -c * np.eye(4)])
    full = -CAM.triangulate(z) / 3.0 + CAM.triangulate(z[:, None, :] + shifts).sum(axis=1) / 6.0
    valid = z[:, 0] - z[:, 2] > 2 * c  # (elsewhere the plain triangulation, tested below)
    assert 20 < valid.sum() < z.shape[0]
    np.testing.assert_allclose(triangulate_mean(CAM, z, 1.5)[valid], full[valid], rtol=1e-12, atol=1e-12)


def test_triangulate_mean_falls_back_where_the_expansion_fails():
    z = CAM.project(np.array([[1.0, 0.0, 500.0], [1.0, 0.0, 20.0]]))  # disparities 0.77 px and 19 px
    mean = triangulate_mean(CAM, z, 1.0)
    np.testing.assert_array_equal(mean[0], CAM.triangulate(z[0]))
    assert mean[1, 2] > CAM.triangulate(z[1])[2]
