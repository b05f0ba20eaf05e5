"""Tests of backend.estimator.ekf.VisualInertialEKF (with its FilterState and error models) on small
synthetic stereo problems (no data files).

The scene: a KITTI-like stereo camera on a car driving forward at ~8 m/s with gentle turns,
landmarks 5-40 m ahead, exact projections plus Gaussian pixel noise, and velocities with white
noise. Every landmark has one contiguous track (its id is never seen again after the track ends).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from vislam.backend.config import Config
from vislam.backend.data.sequence import Sequence
from vislam.backend.errors import FilterError, HealthWarning
from vislam.backend.estimator import covariance, update
from vislam.backend.estimator.body import BodyModel
from vislam.backend.estimator.ekf import ImuNoise, StepStats, VisualInertialEKF, check_full_state_size, make_error_model
from vislam.backend.estimator.invariant import InvariantModel
from vislam.backend.estimator.layout import BIAS, CORE, POSE, landmark_rows, state_dimension
from vislam.backend.estimator.propagation import dead_reckoning
from vislam.backend.estimator.state import ID, TRACK_ROWS, FilterState
from vislam.backend.estimator.state_helper import NewLandmarks, StateHelper
from vislam.backend.estimator.tracks import slots_of as slots_of_index
from vislam.backend.geometry import se3
from vislam.backend.geometry.camera import StereoCamera
from vislam.backend.run.runner import run_sequence
from helpers import OFF_ROW, THREE_ROWS, four_rows, numeric_jacobian, observation_model, slots_of

K_KITTI = np.array([[718.856, 0.0, 607.19], [0.0, 718.856, 185.22], [0.0, 0.0, 1.0]])
BASELINE = 0.537
CAMERA = StereoCamera(K_KITTI, BASELINE)
IMU_T_CAM = np.eye(4)
IMU_T_CAM[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
IMU_T_CAM[:3, 3] = [1.1, -0.3, 0.75]
CAM_T_IMU = se3.inverse(IMU_T_CAM)
WIDTH, HEIGHT = 1241.0, 376.0
DT = 0.1
PARAMETRIZATIONS = ("xyz", "inverse-depth")

LIN_SIGMA, ANG_SIGMA, PIX_SIGMA = 0.2, 0.01, 0.5
NOISE = ImuNoise(np.full(3, LIN_SIGMA), np.full(3, ANG_SIGMA))


@pytest.fixture(autouse=True)
def _single_blas_thread():
    """One BLAS thread: deterministic sums (the gates make decisions on them) and faster small products."""
    with threadpool_limits(limits=1):
        yield


# ----------------------------------------------------------------------------------------------
# synthetic problems


@dataclasses.dataclass
class Drive:
    t: np.ndarray  # (N,)
    poses: np.ndarray  # (N,4,4) true world_T_imu, poses[0] = I
    v_true: np.ndarray  # (N,3) body twist driving step k -> k+1 (velocity index "this")
    w_true: np.ndarray
    v_meas: np.ndarray  # with white noise
    w_meas: np.ndarray
    points: np.ndarray  # (M,3) world landmarks
    visible: np.ndarray  # (N,M) bool, one contiguous run per landmark
    pixels: np.ndarray  # (N,M,4) exact projections (nan where not visible)
    noisy: np.ndarray  # (N,M,4) with pixel noise

    def observations(self, k: int, noisy: bool = True):
        ids = np.flatnonzero(self.visible[k])
        return ids, (self.noisy if noisy else self.pixels)[k, ids].copy()

    @property
    def n(self) -> int:
        return self.t.size


def make_drive(n: int, seed: int = 0, density: float = 2.5, track=(3, 30), pix_sigma: float = PIX_SIGMA) -> Drive:
    """``density`` landmarks per step of path; track lengths capped at a random length in ``track``."""
    rng = np.random.default_rng(seed)
    extra = 60  # path beyond the end, so that landmarks ahead of the last poses exist
    t = np.arange(n + extra) * DT
    v = np.stack([8.0 + np.sin(0.3 * t), 0.05 * np.sin(0.7 * t), np.zeros_like(t)], axis=1)
    w = np.stack([0.01 * np.sin(0.9 * t), 0.01 * np.cos(0.5 * t), 0.08 * np.sin(0.25 * t)], axis=1)
    poses = [np.eye(4)]
    for k in range(n + extra - 1):
        poses.append(poses[-1] @ se3.exp_se3(DT * np.concatenate([v[k], w[k]])))
    poses = np.array(poses)
    m = int(density * (n + extra))
    anchor = rng.integers(0, n + extra, m)
    local = np.stack(
        [rng.uniform(0.0, 0.9, m), rng.uniform(-20.0, 20.0, m), rng.uniform(-1.5, 4.0, m), np.ones(m)], axis=1
    )
    points = np.einsum("mij,mj->mi", poses[anchor], local)[:, :3]
    pixels = np.full((n, m, 4), np.nan)
    for k in range(n):
        c_T_w = CAM_T_IMU @ se3.inverse(poses[k])
        p_cam = points @ c_T_w[:3, :3].T + c_T_w[:3, 3]
        ok = (p_cam[:, 2] > 5.0) & (p_cam[:, 2] < 40.0)
        z = CAMERA.project(np.where(ok[:, None], p_cam, [0.0, 0.0, 1.0]))
        ok &= (z[:, 0] >= 0) & (z[:, 0] < WIDTH) & (z[:, 2] >= 0) & (z[:, 1] >= 0) & (z[:, 1] < HEIGHT)
        pixels[k, ok] = z[ok]
    visible = ~np.isnan(pixels[:, :, 0])
    for j in range(m):  # the first contiguous run only, capped
        idx = np.flatnonzero(visible[:, j])
        visible[:, j] = False
        if idx.size == 0:
            continue
        end = idx[0]
        while end + 1 < n and not np.isnan(pixels[end + 1, j, 0]):
            end += 1
        end = min(end, idx[0] + int(rng.integers(*track)) - 1)
        visible[idx[0] : end + 1, j] = True
    pixels[~visible] = np.nan
    noisy = pixels + rng.normal(0.0, pix_sigma, pixels.shape)
    return Drive(
        t=t[:n], poses=poses[:n], v_true=v[:n], w_true=w[:n],
        v_meas=v[:n] + rng.normal(0.0, LIN_SIGMA, (n, 3)), w_meas=w[:n] + rng.normal(0.0, ANG_SIGMA, (n, 3)),
        points=points, visible=visible, pixels=pixels, noisy=noisy,
    )


def run_filter(drive: Drive, config: Config, steps: int | None = None, clean_velocity: bool = False,
               on_step=None):
    """Online loop: update at step 0, then predict + update. Returns (ekf, poses (steps,4,4), [StepStats])."""
    steps = drive.n if steps is None else steps
    ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, config, NOISE)
    v, w = (drive.v_true, drive.w_true) if clean_velocity else (drive.v_meas, drive.w_meas)
    poses = [ekf.world_T_imu.copy()]
    all_stats = [ekf.update(*drive.observations(0))]
    for k in range(steps - 1):
        ekf.predict(drive.t[k + 1] - drive.t[k], v[k], w[k])
        ids, pix = drive.observations(k + 1)
        if on_step is not None:
            pix = on_step(k + 1, ekf, ids, pix)
        all_stats.append(ekf.update(ids, pix))
        poses.append(ekf.world_T_imu.copy())
    return ekf, np.array(poses), all_stats


def to_sequence(drive: Drive) -> Sequence:
    counts = drive.visible.sum(axis=1)
    ptr = np.zeros(drive.n + 1, dtype=np.int64)
    np.cumsum(counts, out=ptr[1:])
    ids = np.concatenate([np.flatnonzero(row) for row in drive.visible]).astype(np.int64)
    pixels = np.concatenate([drive.noisy[k, drive.visible[k]] for k in range(drive.n)])
    return Sequence(
        time_stamps=drive.t.copy(), linear_velocity=drive.v_meas.copy(), angular_velocity=drive.w_meas.copy(),
        K=K_KITTI.copy(), baseline=BASELINE, imu_T_cam=IMU_T_CAM.copy(), obs_ptr=ptr, obs_ids=ids,
        obs_pixels=pixels, num_features=drive.points.shape[0], source="<synthetic>",
    )


def slam_config(values: dict | None = None) -> Config:
    """The noise of the synthetic drives and known conventions, with ``values`` ({"table.key": value}) over them."""
    merged = {"noise.pixel_sigma": PIX_SIGMA, "noise.linear_velocity_sigma": LIN_SIGMA,
              "noise.angular_velocity_sigma": ANG_SIGMA, "conventions.imu_flip": "no",
              "conventions.velocity_index": "this",
              "drift.track_drift": "no"}  # exact tracks; the drift model is tested on its own below
    merged.update(values or {})
    if merged.get("landmarks.parametrization", "xyz") != "xyz":
        merged.setdefault("estimator.error_model", "body")  # the invariant error needs world xyz landmarks
    return Config.from_values(merged)


#: The pixel noise of a filter built directly (``noise.pixel_sigma`` has no default: a run identifies it).
DEFAULT_PIXEL_SIGMA = 1.5


def bare_config(values: dict | None = None) -> Config:
    """Defaults with a pixel noise (``DEFAULT_PIXEL_SIGMA``) and ``values`` over them, for a filter built directly."""
    return Config.from_values({"noise.pixel_sigma": DEFAULT_PIXEL_SIGMA, **(values or {})})


def body_config(values: dict | None = None) -> Config:
    """``bare_config`` with the body (right perturbation) error model and ``values`` over them."""
    return bare_config({"estimator.error_model": "body", **(values or {})})


def random_pose(rng, angle: float = 0.6, spread: float = 5.0) -> np.ndarray:
    return se3.exp_se3(np.concatenate([rng.normal(0.0, spread, 3), rng.normal(0.0, angle, 3)]))


def random_spd(rng, n: int, scale: float) -> np.ndarray:
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T / n + 0.2 * np.eye(n))


def rel_err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def homogeneous(p: np.ndarray) -> np.ndarray:
    return np.append(p, 1.0)


@pytest.fixture(scope="module")
def drive200() -> Drive:
    return make_drive(200, seed=0)


# ----------------------------------------------------------------------------------------------
# 1-3 prediction


@pytest.mark.parametrize(
    "dt, v, w, bias",
    [
        (0.1, [8.0, 0.1, -0.05], [0.01, -0.02, 0.08], [0.0, 0.0, 0.0]),
        (0.5, [3.0, -1.0, 0.5], [0.4, -0.7, 1.1], [0.0, 0.0, 0.0]),
        (1e-3, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]),
        (0.2, [5.0, 0.0, 0.0], [0.0, 0.0, 0.3], [0.01, -0.02, 0.05]),
    ],
)
def test_prediction_mean(dt, v, w, bias):
    rng = np.random.default_rng(3)
    mu0 = random_pose(rng)
    ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, body_config(), NOISE, world_T_imu=mu0)
    ekf.state.gyro_bias = np.array(bias, dtype=float)
    ekf.predict(dt, np.array(v), np.array(w))
    expected = mu0 @ se3.exp_se3(dt * np.concatenate([v, np.subtract(w, bias)]))
    np.testing.assert_allclose(ekf.world_T_imu, expected, rtol=0, atol=1e-12)


def _pose_only_filter(rng, P0: np.ndarray, mu0: np.ndarray) -> VisualInertialEKF:
    tiny = ImuNoise(np.full(3, 1e-12), np.full(3, 1e-12))
    ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, body_config({"estimator.estimate_gyro_bias": False}), tiny,
                            world_T_imu=mu0)
    ekf.state.P[:] = 0.0
    ekf.state.P[POSE, POSE] = P0
    return ekf


def test_prediction_covariance_monte_carlo():
    rng = np.random.default_rng(11)
    mu0 = random_pose(rng)
    P0 = random_spd(rng, 6, 1e-3)
    dt, v, w = 0.5, np.array([6.0, 0.5, -0.2]), np.array([0.3, -0.2, 0.9])
    ekf = _pose_only_filter(rng, P0, mu0)
    ekf.predict(dt, v, w)
    step = se3.exp_se3(dt * np.concatenate([v, w]))
    mu_new_inv = se3.inverse(ekf.world_T_imu)
    xi = rng.multivariate_normal(np.zeros(6), P0, size=2000)
    logs = np.array([se3.log_se3(mu_new_inv @ mu0 @ se3.exp_se3(x) @ step) for x in xi])
    sample_cov = logs.T @ logs / len(logs)  # the mean is known to be zero
    P = ekf.state.P[POSE, POSE] - np.diag(np.full(6, 1e-24) * dt * dt)
    assert rel_err(sample_cov, P) < 0.10
    assert rel_err(P, P0) > 0.3  # the prediction did transform the covariance
    assert np.all(ekf.state.P[BIAS] == 0.0) and np.all(ekf.state.P[:, BIAS] == 0.0)

    # without sampling error: mu_new^-1 T_new = exp((Ad(exp(-dt u)) xi)^) exactly, so a filter
    # started from the sample covariance of the xi must predict the sample covariance of the logs
    exact = _pose_only_filter(rng, xi.T @ xi / len(xi), mu0)
    exact.predict(dt, v, w)
    np.testing.assert_allclose(exact.state.P[POSE, POSE], sample_cov, rtol=0, atol=1e-9 * np.abs(sample_cov).max())


def test_gyro_bias_jacobian():
    rng = np.random.default_rng(5)
    mu0 = random_pose(rng)
    sigma_b = 0.01
    bias0 = np.array([0.002, -0.004, 0.003])
    dt, v, w = 0.4, np.array([7.0, 0.3, -0.1]), np.array([0.2, -0.5, 0.9])

    def filter_with_bias(bias):
        ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, body_config({"estimator.estimate_gyro_bias": True}), NOISE,
                                world_T_imu=mu0)
        ekf.state.P[:] = 0.0
        ekf.state.P[BIAS, BIAS] = sigma_b**2 * np.eye(3)
        ekf.state.gyro_bias = np.array(bias, dtype=float)
        return ekf

    ekf = filter_with_bias(bias0)
    ekf.predict(dt, v, w)
    mu_new = ekf.world_T_imu.copy()

    def mean_error(delta):  # right-perturbation error of the predicted mean when the bias is bias0 + delta
        other = filter_with_bias(bias0 + delta)
        other.predict(dt, v, w)
        return se3.log_se3(se3.inverse(mu_new) @ other.world_T_imu)

    J_fd = numeric_jacobian(mean_error, np.zeros(3), 1e-6)
    twist = dt * np.concatenate([v, w - bias0])
    J_closed = -dt * se3.right_jacobian_se3(twist)[:, 3:6]
    assert rel_err(J_fd, J_closed) < 1e-6
    cross = ekf.state.P[POSE, BIAS]
    assert rel_err(cross, J_fd * sigma_b**2) < 1e-6
    np.testing.assert_allclose(cross, J_closed * sigma_b**2, rtol=1e-12, atol=1e-18)
    assert np.allclose(ekf.state.P[BIAS, POSE], cross.T, rtol=1e-12, atol=0)
    # pose block: J sigma_b^2 J^T plus the process noise
    Q = np.diag(np.concatenate([NOISE.linear_sigma**2, NOISE.angular_sigma**2]) * dt * dt)
    np.testing.assert_allclose(ekf.state.P[POSE, POSE], sigma_b**2 * J_closed @ J_closed.T + Q, rtol=1e-10,
                               atol=1e-18)


def test_no_bias_states_without_bias_estimation():
    ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, bare_config({"estimator.estimate_gyro_bias": False}), NOISE)
    for _ in range(5):
        ekf.predict(0.1, np.array([8.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.2]))
    assert np.all(ekf.state.P[BIAS] == 0.0) and np.all(ekf.state.P[:, BIAS] == 0.0)
    assert np.all(ekf.gyro_bias == 0.0)


# ----------------------------------------------------------------------------------------------
# 4-5 observation model and landmark initialization


def _world_point_from_parameters(kind: str, theta: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    """Homogeneous world point of a landmark, from the documented parametrizations (backend.estimator.landmarks)."""
    if kind == "xyz":
        return homogeneous(theta)
    alpha, beta, rho = theta
    return anchor @ np.array([alpha, beta, 1.0, rho])


def _pixels(mu: np.ndarray, w_world: np.ndarray) -> np.ndarray:
    q = CAM_T_IMU @ se3.inverse(mu) @ w_world
    return CAMERA.Ks @ (q / q[2])


def _anchor_of(ekf: VisualInertialEKF, slot: int) -> np.ndarray:
    """The anchor frame of a landmark (the filter stores none for xyz: there it is the identity)."""
    return np.eye(4) if ekf.model.parametrization == "xyz" else ekf.state.anchors[slot].copy()


@pytest.mark.parametrize("kind", PARAMETRIZATIONS)
def test_observation_jacobians(kind):
    rng = np.random.default_rng(7)
    mu0 = random_pose(rng)
    config = body_config({"landmarks.parametrization": kind})
    ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, config, NOISE, world_T_imu=mu0)
    ekf.state.P[POSE, POSE] = random_spd(rng, 6, 1e-4)
    p_cam = np.array([[2.0, -1.0, 15.0], [-6.0, 0.5, 8.0], [0.3, 1.2, 35.0], [9.0, -2.0, 22.0]])
    z0 = CAMERA.project(p_cam)
    ids = np.array([3, 7, 8, 20])
    assert ekf.update(ids, z0).initialized == 4

    # move the pose so that the linearization point differs from the initialization pose
    ekf.predict(0.1, np.array([2.0, 0.1, 0.0]), np.array([0.02, -0.01, 0.05]))
    mu = ekf.world_T_imu.copy()
    slots = slots_of(ekf, ids)
    z_meas = z0 + 3.0
    z_meas[:, 3] += 1.0  # vL != vR: the fourth row (U1) has a residual too
    residual, off_row, H_xi, H_theta, in_front = observation_model(ekf, slots, z_meas)
    assert in_front.all()
    for k, slot in enumerate(slots):
        theta = ekf.state.theta[slot].copy()
        anchor = _anchor_of(ekf, slot)
        w0 = _world_point_from_parameters(kind, theta, anchor)
        r4 = z_meas[k] - _pixels(mu, w0)
        np.testing.assert_allclose(residual[k], THREE_ROWS @ r4, rtol=0, atol=1e-8)
        assert off_row[k] == pytest.approx(OFF_ROW @ r4, abs=1e-8)
        J_pose = numeric_jacobian(lambda d: _pixels(mu @ se3.exp_se3(d), w0), np.zeros(6), 1e-6)
        J_param = numeric_jacobian(
            lambda th: _pixels(mu, _world_point_from_parameters(kind, th, anchor)), theta, 1e-7 * max(1.0, np.abs(theta).max())
        )
        assert rel_err(H_xi[k], THREE_ROWS @ J_pose) < 1e-5
        assert rel_err(H_theta[k], THREE_ROWS @ J_param) < 1e-5
        assert np.abs(OFF_ROW @ J_pose).max() < 1e-6 * np.abs(J_pose).max()  # no state in the fourth row
        if kind == "xyz":  # the parameters are the world position itself
            J_pos = numeric_jacobian(lambda m: _pixels(mu, homogeneous(m)), w0[:3], 1e-6)
            assert rel_err(H_theta[k], THREE_ROWS @ J_pos) < 1e-5


def test_observation_jacobian_mapping_mode_has_no_pose_columns():
    ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, bare_config({"estimator.mode": "mapping"}), NOISE)
    z = CAMERA.project(np.array([[1.0, 0.5, 12.0]]))
    ekf.update(np.array([0]), z)
    _, _, H_xi, H_theta, _ = observation_model(ekf, np.array([0]), z)
    assert np.all(H_xi == 0.0) and np.abs(H_theta).max() > 0.0
    assert np.all(ekf.state.P[:CORE] == 0.0)


@pytest.mark.parametrize("kind", PARAMETRIZATIONS)
def test_landmark_initialization(kind):
    rng = np.random.default_rng(9)
    mu0 = random_pose(rng)
    sigma_pix = 0.8
    # the linearized model (no unbiased triangulation); the mean shift is tested in test_camera
    config = body_config({"landmarks.parametrization": kind, "noise.pixel_sigma": sigma_pix,
                          "landmarks.unbiased_triangulation": False})
    ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, config, NOISE, world_T_imu=mu0)
    P_core = random_spd(rng, CORE, 1e-3)  # pose and gyro bias, correlated
    ekf.state.P[:] = P_core
    p_cam = np.array([[2.0, -1.0, 15.0], [-6.0, 0.5, 8.0], [0.3, 1.2, 35.0]])
    z = CAMERA.project(p_cam) + rng.normal(0.0, 0.5, (3, 4))
    ids = np.array([4, 10, 11])
    stats = ekf.update(ids, z)
    assert (stats.initialized, stats.used, stats.active) == (3, 0, 3)
    np.testing.assert_array_equal(ekf.state.P[:CORE, :CORE], P_core)

    def world(d, zi):  # m = mu exp(d^) imu_T_cam triangulate(z)
        return (mu0 @ se3.exp_se3(d) @ IMU_T_CAM @ homogeneous(CAMERA.triangulate(zi)))[:3]

    J_xi = np.concatenate([numeric_jacobian(lambda d: world(d, zi), np.zeros(6), 1e-6) for zi in z])  # (9,6)
    J_z = [numeric_jacobian(lambda zz: world(np.zeros(6), zz), zi, 1e-4) for zi in z]
    expected_cov = J_xi @ P_core[POSE, POSE] @ J_xi.T
    for i in range(3):
        expected_cov[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] += sigma_pix**2 * J_z[i] @ J_z[i].T

    map_ids, map_pos, map_cov = ekf.landmark_map()
    np.testing.assert_array_equal(map_ids, ids)
    for i in range(3):
        np.testing.assert_allclose(map_pos[i], world(np.zeros(6), z[i]), rtol=1e-12, atol=1e-10)
        assert rel_err(map_cov[i], expected_cov[3 * i : 3 * i + 3, 3 * i : 3 * i + 3]) < 1e-4

    # the state block in world coordinates: dm/dtheta (identity for xyz) maps parameters to positions
    slots = slots_of(ekf, ids)
    J_world = np.zeros((9, 9))
    for i, slot in enumerate(slots):
        anchor = _anchor_of(ekf, slot)

        def position(th):
            w = _world_point_from_parameters(kind, th, anchor)
            return w[:3] / w[3]

        J_world[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = numeric_jacobian(position, ekf.state.theta[slot].copy(), 1e-8)
    P = ekf.state.P
    cols = (CORE + 3 * slots[:, None] + np.arange(3)).ravel()
    world_block = J_world @ P[np.ix_(cols, cols)] @ J_world.T
    assert rel_err(world_block, expected_cov) < 1e-4  # includes the landmark-landmark cross terms
    world_cross = J_world @ P[cols, :CORE]
    assert rel_err(world_cross[:, POSE], J_xi @ P_core[POSE, POSE]) < 1e-4
    assert rel_err(world_cross[:, BIAS], J_xi @ P_core[POSE, BIAS]) < 1e-4
    np.testing.assert_allclose(P, P.T, rtol=0, atol=1e-15 * np.abs(P).max())


def test_initialization_defers_too_small_disparity_and_too_far():
    config = bare_config({"landmarks.min_disparity": 2.0, "landmarks.max_depth": 60.0})
    ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, config, NOISE)
    fb = CAMERA.fx * BASELINE
    # depths: 20 m (ok), 70 m (too far: disparity 5.5 px), 300 m (disparity 1.3 px < 2), zero disparity
    z = CAMERA.project(np.array([[1.0, 0.0, 20.0], [1.0, 0.0, 70.0], [1.0, 0.0, 300.0], [1.0, 0.0, 1.0]]))
    z[3, 2] = z[3, 0]
    assert fb / 70.0 > 2.0
    stats = ekf.update(np.arange(4), z)
    assert (stats.initialized, stats.deferred, ekf.num_active) == (1, 3, 1)
    assert ekf.landmark_map()[0].tolist() == [0]


def filter_before_an_update(error_model: str, values: dict | None = None):
    """A filter 20 steps into a synthetic drive and predicted to step 20, with that step's pixels
    (k,4) of landmarks in its state and their slots (k,) (at least 10); no RANSAC, a wide gate."""
    drive = make_drive(30, seed=3)
    config = slam_config({"estimator.error_model": error_model, "update.ransac_threshold_px": 0.0,
                          "update.gate_probability": 0.999999, **(values or {})})
    ekf, _, _ = run_filter(drive, config, steps=20)
    ekf.predict(DT, drive.v_meas[19], drive.w_meas[19])
    ids, pix = drive.observations(20)
    slots = slots_of(ekf, ids)
    pix, slots = pix[slots >= 0], slots[slots >= 0]
    assert slots.size >= 10
    return ekf, pix, slots


@pytest.mark.parametrize("error_model", ["invariant", "body"])
def test_three_row_update_equals_four_row_joseph_update(error_model):
    """The 3-row update (backend.estimator.update module docstring, U1-U2) against the textbook 4-row Joseph form
    K = P H^T S^-1,  P+ = (I - K H) P (I - K H)^T + K R K^T,  dx = K r  on the same linearization (the
    first-order update: U7's terms, tested with it in test_second_order.py, off)."""
    ekf, pix, slots = filter_before_an_update(error_model, {"update.second_order": False})
    residual, off_row, H_x3, H_m3, in_front = observation_model(ekf, slots, pix)
    assert in_front.all()
    r4 = four_rows(residual[:, :, None], off_row)[:, :, 0]  # the pixel rows, as a textbook filter has them
    H_x, H_m = four_rows(H_x3), four_rows(H_m3)
    D = ekf.state.P.shape[0]
    H = np.zeros((4 * slots.size, D))
    for i, j in enumerate(slots):
        H[4 * i : 4 * i + 4, :6] = H_x[i]
        H[4 * i : 4 * i + 4, CORE + 3 * j : CORE + 3 * j + 3] = H_m[i]
    R = PIX_SIGMA**2 * np.eye(H.shape[0])
    P = ekf.state.P.copy()
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T
    IKH = np.eye(D) - K @ H
    P_ref = IKH @ P @ IKH.T + K @ R @ K.T
    dx_ref = K @ r4.ravel()
    nis_ref = sum(r4[i] @ np.linalg.solve(S[4 * i : 4 * i + 4, 4 * i : 4 * i + 4], r4[i]) for i in range(slots.size))

    st = ekf.state
    mu, theta, bias = st.mu.copy(), st.theta.copy(), st.gyro_bias.copy()
    ekf.model.correct(st, dx_ref)
    mu_ref, theta_ref = st.mu, st.theta
    st.mu, st.theta, st.gyro_bias = mu, theta, bias
    stats = StepStats()
    ekf._joint_update(slots, pix, stats)
    assert stats.used == slots.size
    assert stats.nis_sum == pytest.approx(nis_ref, rel=1e-9)
    scale = np.abs(P_ref).max()
    assert np.abs(st.P - P_ref).max() <= 1e-9 * scale
    assert np.abs(st.mu - mu_ref).max() <= 1e-9
    assert np.abs(st.theta - theta_ref).max() <= 1e-9


# ----------------------------------------------------------------------------------------------
# 6-7 whole runs


def test_covariance_symmetric_positive_definite():
    drive = make_drive(50, seed=1)
    worst = []

    def check(k, ekf, ids, pix):
        P = ekf.state.P
        worst.append(np.abs(P - P.T).max() / np.abs(P).max())
        return pix

    ekf, _, stats = run_filter(drive, slam_config(), on_step=check)
    P = ekf.state.P
    assert P.shape[0] > CORE + 3 * 20
    assert max(worst) <= 1e-15
    assert np.abs(P - P.T).max() <= 1e-15 * np.abs(P).max()
    assert np.linalg.eigvalsh(0.5 * (P + P.T)).min() > 0.0
    assert ekf.health.messages == []


def test_covariance_exactly_symmetric_after_every_step():
    drive = make_drive(50, seed=1)
    ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, slam_config(), NOISE)
    ekf.update(*drive.observations(0))
    asymmetric_steps = []
    for k in range(drive.n - 1):
        ekf.predict(DT, drive.v_meas[k], drive.w_meas[k])
        ekf.update(*drive.observations(k + 1))
        if not np.array_equal(ekf.state.P, ekf.state.P.T):
            asymmetric_steps.append(k + 1)
    assert asymmetric_steps == []


@pytest.mark.parametrize("error_model", ["invariant", "body"])
def test_slam_beats_dead_reckoning(drive200, error_model):
    ekf, poses, stats = run_filter(drive200, slam_config({"estimator.error_model": error_model}))
    truth = drive200.poses
    dr = dead_reckoning(drive200.t, drive200.v_meas, drive200.w_meas, "this")
    err_slam = np.linalg.norm(poses[-1, :3, 3] - truth[-1, :3, 3])
    err_dr = np.linalg.norm(dr[-1, :3, 3] - truth[-1, :3, 3])
    assert err_dr > 0.5  # the noisy velocities do drift
    assert err_slam < err_dr / 3.0
    used = sum(s.used for s in stats)
    mean_nis = sum(s.nis_sum for s in stats) / used
    assert 1.0 <= mean_nis <= 8.0
    visible = drive200.visible.sum(axis=1)
    assert 30 <= visible.mean() <= 50
    tracked = visible[1:].sum() - sum(s.initialized for s in stats[1:])  # observations of landmarks in the state
    assert used > 0.95 * tracked
    assert sum(s.marginalized for s in stats) > 200  # tracks do end and new ids start
    assert ekf.health.messages == []


# ----------------------------------------------------------------------------------------------
# 8-9 full state, mapping and dead-reckoning modes (through run_sequence)


@pytest.fixture(scope="module")
def seq60() -> Sequence:
    return to_sequence(make_drive(60, seed=2, density=1.2, track=(2, 12)))


@pytest.mark.parametrize("error_model", ["invariant", "body"])
def test_full_state_matches_marginalized(seq60, error_model):
    steps = np.repeat(np.arange(seq60.num_steps), np.diff(seq60.obs_ptr))
    for i in np.unique(seq60.obs_ids):  # no landmark is seen again after its track ends
        seen = steps[seq60.obs_ids == i]
        assert seen[-1] - seen[0] == seen.size - 1
    marg = run_sequence(seq60, slam_config({"estimator.full_state": False, "estimator.error_model": error_model}))
    full = run_sequence(seq60, slam_config({"estimator.full_state": True, "estimator.error_model": error_model}))
    assert marg.stats.observations_used > 500
    assert full.stats.active_landmarks_max > 2 * marg.stats.active_landmarks_max
    assert marg.stats.observations_used == full.stats.observations_used
    np.testing.assert_allclose(full.world_T_imu[:, :3, 3], marg.world_T_imu[:, :3, 3], rtol=0, atol=1e-8)
    np.testing.assert_allclose(full.world_T_imu[:, :3, :3], marg.world_T_imu[:, :3, :3], rtol=0, atol=1e-8)
    np.testing.assert_array_equal(full.map_ids, marg.map_ids)


def _relabel_segments(seq: Sequence, near: int, far: int, far_disparity: float) -> Sequence:
    """The re-anchoring rule (R1, R2 of backend.estimator.tracks) written as new track ids: track i's
    s-th landmark gets id 1000 i + s; its first segment is shortened by i mod limit (limit from the
    anchoring disparity)."""
    limit = lambda px: far if px[0] - px[2] < far_disparity else near  # noqa: E731
    state: dict[int, list[int]] = {}  # id -> [count, segment, limit]
    new_ids = np.empty_like(seq.obs_ids)
    for row, (i, px) in enumerate(zip(seq.obs_ids.tolist(), seq.obs_pixels)):
        if i not in state:
            lim = limit(px)
            state[i] = [1 + i % lim, 0, lim]
        else:
            st = state[i]
            st[0] += 1
            if st[0] > st[2]:
                st[:] = [1, st[1] + 1, limit(px)]
        new_ids[row] = 1000 * i + state[i][1]
    return dataclasses.replace(seq, obs_ids=new_ids, num_features=int(new_ids.max()) + 1)


@pytest.mark.parametrize("error_model", ["invariant", "body"])
def test_reanchoring_equals_tracks_cut_into_new_landmarks(error_model):
    """Re-anchoring (backend.estimator.tracks docstring) marginalizes a landmark and starts a new one from the same
    observation: the same filter as one that sees each track segment as a separate track."""
    seq = to_sequence(make_drive(80, seed=5, density=1.5, track=(8, 30)))
    near, far, far_disparity = 3, 7, 20.0  # depth 5-40 m here: disparity 10-77 px
    walk = {"drift.pixel_walk": 0.05, "drift.pixel_walk_per_disparity": 0.002,  # the same walk by depth in both (R3)
            "noise.lever_arm_sigma": 0.5}  # and the same considered lever arm (V2; N3 sees the relabelled tracks apart)
    on = run_sequence(seq, slam_config({"estimator.error_model": error_model, "drift.track_drift": "yes",
                                        "drift.reanchor_observations": near, "drift.reanchor_far_observations": far,
                                        "drift.reanchor_far_disparity": far_disparity, **walk}))
    cut = run_sequence(_relabel_segments(seq, near, far, far_disparity),  # same random walk, no re-anchoring
                       slam_config({"estimator.error_model": error_model, "drift.track_drift": "yes",
                                    "drift.reanchor_observations": 0, "drift.reanchor_far_observations": 0, **walk}))
    assert on.stats.landmarks_dropped == 0 == cut.stats.landmarks_dropped  # (a dropped track restarts its phase)
    assert on.stats.landmarks_reanchored > 300
    assert on.stats.landmarks_initialized == cut.stats.landmarks_initialized
    assert on.stats.observations_used == cut.stats.observations_used
    np.testing.assert_allclose(on.world_T_imu, cut.world_T_imu, rtol=0, atol=1e-9)
    # the map keeps one estimate per track (the most certain of its segments)
    assert np.unique(on.map_ids).size == on.map_ids.size == np.unique(cut.map_ids // 1000).size
    best = {}
    for i, c in zip(cut.map_ids.tolist(), cut.map_covariances):
        t = float(np.trace(c))
        if i // 1000 not in best or t < best[i // 1000][0]:
            best[i // 1000] = (t, i)
    order = np.searchsorted(cut.map_ids, [best[i][1] for i in on.map_ids.tolist()])
    np.testing.assert_allclose(on.map_positions, cut.map_positions[order], rtol=0, atol=1e-9)


def test_persistent_ransac_outliers_are_not_rescued():
    """A track rejected by the RANSAC update.persistent_outlier_steps times in a row is not rescued;
    the count follows the track id (across re-anchoring) and any other outcome resets it."""

    def count(ekf, slots, rejected):  # what the filter's step does with the RANSAC's rejections
        return update.count_rejections_inplace(ekf.state.outlier_run, slots, np.array(rejected, dtype=bool),
                                               ekf.config.update.persistent_outlier_steps)

    drive = make_drive(10, seed=6)
    ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, slam_config({"update.persistent_outlier_steps": 3}), NOISE)
    ekf.update(*drive.observations(0))
    slots = np.arange(4)
    a, b, c, d = ekf.state.ids[:4].tolist()
    steps = [[1, 1, 0, 1], [1, 1, 1, 1], [1, 0, 1, 1], [1, 1, 1, 1], [0, 1, 1, 1]]
    flagged = [count(ekf, slots, r).tolist() for r in steps]
    assert flagged == [[False] * 4, [False] * 4, [True, False, False, True], [True, False, True, True],
                       [False, False, True, True]]
    assert _outlier_counts(ekf) == {b: 2, c: 4, d: 5}  # a was reset by its inlier step
    # d leaves the state as at re-anchoring (its track goes on) and comes back: the count goes on;
    # c's track ends: its count ends with it
    ids, pixels = drive.observations(0)
    ekf._remove(np.isin(ekf.state.ids, [c, d]), to_map=True, ended=ekf.state.ids == c)
    assert _outlier_counts(ekf) == {b: 2, d: 5}
    back = ids == d
    ekf.update(ids[back], pixels[back])
    slot = slots_of(ekf, [d])
    assert count(ekf, slot, [True]).tolist() == [True]
    assert _outlier_counts(ekf) == {d: 6}  # b was not seen in that step: its track ended
    off = VisualInertialEKF(CAMERA, IMU_T_CAM, slam_config({"update.persistent_outlier_steps": 0}), NOISE)
    off.update(*drive.observations(0))
    for k in range(1, 6):  # never counted when the rule is off
        off.predict(DT, drive.v_true[k - 1], drive.w_true[k - 1])
        off.update(*drive.observations(k))
    assert _outlier_counts(off) == {}


def _outlier_counts(ekf: VisualInertialEKF) -> dict:
    """Track id -> steps in a row the RANSAC rejected it (nonzero only), in the state or not."""
    counts = {int(i): int(r) for i, r in zip(ekf.state.ids, ekf.state.outlier_run) if r}
    counts.update(ekf.state.outlier_stash)
    return counts


def test_no_reanchoring_in_full_state(seq60):
    """With drifting tracks modelled, a full state keeps every landmark: none is re-anchored (the same
    run without the full state re-anchors)."""
    values = {"drift.track_drift": "yes", "drift.reanchor_observations": 2, "drift.reanchor_far_observations": 2}
    result = run_sequence(seq60, slam_config({"estimator.full_state": True, **values}))
    assert result.decisions.drift.drifting and result.decisions.drift.source == "configured"
    assert result.config.drift.track_drift == "yes"
    assert result.stats.landmarks_reanchored == 0
    assert run_sequence(seq60, slam_config(values)).stats.landmarks_reanchored > 0


@pytest.fixture(scope="module")
def drift_scenes():
    """120 steps of the synthetic rig: exact tracks (white noise only), and tracks that all drift
    (0.3 px/step median, synth.track_errors)."""
    from vislam.synth.scene import SceneConfig, make_scene
    from vislam.synth.track_errors import TrackErrors

    return {drifting: make_scene(SceneConfig(steps=120, seed=4, track_errors=TrackErrors(
        **(dict(pixel_sigma=0.25, drift_share=1.0, drift_median=0.3) if drifting else {})))).sequence
        for drifting in (False, True)}


@pytest.mark.parametrize("tracker, drifting", [("", True), ("vislam", True), ("synthetic", False),
                                               ("someone else", False)])
def test_track_drift_auto_follows_the_test_on_the_tracks(drift_scenes, tracker, drifting):
    """drift.track_drift = "auto": decided by the test on the tracks (T1: two-view residuals growing
    with the step gap), whatever the file's tracker key says (reported only): drifting tracks are
    modelled (landmarks re-anchored) even under vislam's own tracker key, exact ones are not even
    under an unknown tracker."""
    seq = dataclasses.replace(drift_scenes[drifting], tracker=tracker)
    result = run_sequence(seq, Config.from_values({"drift.track_drift": "auto", "drift.reanchor_observations": 2}))
    drift = result.decisions.drift
    assert drift.source == "test" and drift.drifting is drifting and drift.tracker == tracker
    assert (drift.ratio > 1.0 + max(0.1, 4.0 * drift.ratio_se)) is drifting
    assert result.config.drift.track_drift == ("yes" if drifting else "no")
    assert (result.stats.landmarks_reanchored > 0) is drifting
    said = result.decisions.drift.describe(result.config)
    assert said.startswith(f"track drift: {'yes' if drifting else 'no'} (") and "two-view residuals" in said
    assert said in result.decisions.describe(result.config).splitlines()
    assert (f"'{tracker}'" in said) is bool(tracker)


def test_landmark_random_walk_only_with_track_drift():
    """The random walk inflates the landmark block at each prediction only when tracks drift."""
    drive = make_drive(10, seed=6)
    inflation = {}
    for drift in ("yes", "no"):
        config = slam_config({"drift.track_drift": drift, "drift.landmark_random_walk": 0.3})
        ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, config, NOISE)
        ekf.update(*drive.observations(0))
        n = ekf.num_active
        before = np.diag(ekf.state.P)[CORE:].copy()
        ekf.predict(DT, drive.v_true[0], drive.w_true[0])
        inflation[drift] = np.diag(ekf.state.P)[CORE:CORE + 3 * n] - before
    assert n > 10
    np.testing.assert_allclose(inflation["yes"] - inflation["no"], 0.3**2 * DT, rtol=1e-9)


def test_mapping_mode_poses_are_dead_reckoning(seq60):
    result = run_sequence(seq60, slam_config({"estimator.mode": "mapping"}))
    dr = dead_reckoning(seq60.time_stamps, seq60.linear_velocity, seq60.angular_velocity, "this")
    np.testing.assert_allclose(result.world_T_imu, dr, rtol=0, atol=1e-12)  # (dr: batched exp)
    np.testing.assert_allclose(result.dead_reckoning, dr, rtol=0, atol=1e-12)
    assert result.map_ids.size > 50
    assert np.all(result.gyro_bias == 0.0)


@pytest.mark.parametrize("kind", PARAMETRIZATIONS)
def test_mapping_mode_landmark_covariance_shrinks(kind):
    drive = make_drive(40, seed=3, density=1.0, track=(10, 30))
    traces: dict[int, list[float]] = {}

    def record(ekf, seen):  # world covariance trace of each landmark observed this step
        ids, _, cov = ekf.landmark_map()
        for i, c in zip(ids.tolist(), cov):
            if i in seen:
                traces.setdefault(i, []).append(float(np.trace(c)))

    config = slam_config({"estimator.mode": "mapping", "landmarks.parametrization": kind})
    ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, config, NOISE)
    ids, pix = drive.observations(0)
    ekf.update(ids, pix)
    record(ekf, set(ids.tolist()))
    for k in range(drive.n - 1):
        ekf.predict(DT, drive.v_true[k], drive.w_true[k])
        ids, pix = drive.observations(k + 1)
        stats = ekf.update(ids, pix)
        assert stats.gated == 0
        np.testing.assert_array_equal(ekf.world_T_imu, drive.poses[k + 1])
        record(ekf, set(ids.tolist()))
    long_tracks = [tr for tr in traces.values() if len(tr) >= 8]
    assert len(long_tracks) > 10
    for tr in long_tracks:
        assert tr[-1] < 0.5 * tr[0]
        assert np.all(np.diff(tr) <= 1e-9 * tr[0])
    ids, pos, _ = ekf.landmark_map()
    assert np.median(np.linalg.norm(pos - drive.points[ids], axis=1)) < 0.5


def test_dead_reckoning_mode_makes_no_map(seq60):
    result = run_sequence(seq60, slam_config({"estimator.mode": "dead-reckoning"}))
    dr = dead_reckoning(seq60.time_stamps, seq60.linear_velocity, seq60.angular_velocity, "this")
    np.testing.assert_allclose(result.world_T_imu, dr, rtol=0, atol=1e-12)  # (dr: batched exp)
    assert result.map_ids.size == 0 and result.map_positions.shape == (0, 3)
    assert result.stats.landmarks_initialized == 0 and result.stats.observations_used == 0


# ----------------------------------------------------------------------------------------------
# 10 gating


@pytest.mark.parametrize("robust", [True, False], ids=["ransac", "chi2-only"])
def test_outlier_is_gated(robust):
    drive = make_drive(30, seed=4)
    config = slam_config() if robust else slam_config({"update.ransac_threshold_px": 0.0})
    k_bad = 20
    bad_id = []

    def corrupt(k, ekf, ids, pix):
        if k == k_bad:
            tracked = np.flatnonzero(slots_of(ekf, ids) >= 0).tolist()
            j = tracked[len(tracked) // 2]
            bad_id.append(int(ids[j]))
            pix = pix.copy()
            pix[j, [0, 2]] += 50.0  # a 50 px horizontal mismatch in both images
        return pix

    _, clean_poses, clean_stats = run_filter(drive, config, steps=k_bad + 1)
    ekf, poses, stats = run_filter(drive, config, steps=k_bad + 1, on_step=corrupt)
    assert stats[k_bad].gated >= 1
    assert stats[k_bad].used == clean_stats[k_bad].used - 1
    assert ekf.state.gated_run[slots_of(ekf, bad_id)[0]] == 1
    assert np.linalg.norm(poses[k_bad, :3, 3] - clean_poses[k_bad, :3, 3]) < 0.05
    assert np.array_equal(poses[:k_bad], clean_poses[:k_bad])


# ----------------------------------------------------------------------------------------------
# 11 full-state refusal


def test_full_state_size_refused():
    config = bare_config({"estimator.full_state": True, "estimator.max_state_mib": 1.0})
    check_full_state_size(100, config.estimator.max_state_mib)  # 309^2 * 8 B = 0.73 MiB
    with pytest.raises(FilterError, match="max_state_mib"):
        check_full_state_size(120, config.estimator.max_state_mib)  # 369^2 * 8 B = 1.04 MiB
    with pytest.raises(FilterError, match="max_state_mib"):
        VisualInertialEKF(CAMERA, IMU_T_CAM, config, NOISE, expected_landmarks=1000)
    VisualInertialEKF(CAMERA, IMU_T_CAM, config.with_values({"estimator.full_state": False}), NOISE,
                      expected_landmarks=1000)


def test_full_state_refused_by_run_sequence(seq60):
    big = dataclasses.replace(seq60, num_features=100_000)
    with pytest.raises(FilterError):
        run_sequence(big, slam_config({"estimator.full_state": True, "estimator.max_state_mib": 64.0}))


# ----------------------------------------------------------------------------------------------
# 12 health


def test_health_reports_inconsistent_nis():
    """Pixel noise 10x noise.pixel_sigma. The gate is opened (and RANSAC off) so that the NIS the monitor
    sees is not truncated at the gate; the test below covers the default gates."""
    drive = make_drive(60, seed=5, pix_sigma=10 * PIX_SIGMA)
    config = slam_config({"health.nis_window": 10, "update.gate_probability": 0.999999,
                          "update.ransac_threshold_px": 0.0})
    with pytest.warns(HealthWarning, match="inconsistent"):  # a RuntimeWarning of vislam's own category
        ekf, _, _ = run_filter(drive, config)
    assert len(ekf.health.messages) >= 1
    assert all("inconsistent" in message for message in ekf.health.messages)


def test_health_reports_inconsistent_nis_with_default_gates():
    silent = []
    for seed in range(5, 13):
        drive = make_drive(120, seed=seed, pix_sigma=10 * PIX_SIGMA)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            ekf, _, stats = run_filter(drive, slam_config())
        gated = sum(s.gated for s in stats)
        assert gated > 0.9 * (gated + sum(s.used for s in stats))  # the filter rejects nearly everything
        if not ekf.health.messages:
            silent.append(seed)
    assert silent == []


def test_health_one_message_per_episode_with_hysteresis():
    """An episode starts outside [4/f, 4 f] and ends only inside [4/sqrt f, 4 sqrt f] (f = 3): a NIS
    hovering at the band's edge is one episode, a return to 4 and a new excursion a second one."""
    from vislam.backend.estimator.health import HealthMonitor

    monitor = HealthMonitor(window=1, warn_factor=3.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for step, nis in enumerate([4.0, 1.2, 1.4, 1.2, 1.4, 2.0, 1.2, 4.0, 1.2, 4.0, 13.0, 11.0, 13.0, 6.0]):
            monitor.add_nis(step, 100 * nis, 100)
    assert [m.split(":")[0] for m in monitor.messages] == ["step 1", "step 8", "step 10"]
    assert monitor._inconsistent is False  # 6.0 < 4 sqrt 3: the last episode is over


def test_health_quiet_when_consistent():
    drive = make_drive(60, seed=5)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        ekf, _, _ = run_filter(drive, slam_config({"health.nis_window": 10}))
    assert ekf.health.messages == []


def test_marginalized_landmark_keeps_estimate():
    drive = make_drive(10, seed=6)
    ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, slam_config({"landmarks.parametrization": "xyz"}), NOISE)
    ekf.update(*drive.observations(0))
    ids0, pos0, cov0 = ekf.landmark_map()
    ekf.predict(DT, drive.v_meas[0], drive.w_meas[0])
    before_ids, before_pos, before_cov = ekf.landmark_map()
    stats = ekf.update(np.zeros(0, dtype=np.int64), np.zeros((0, 4)))  # every track ends
    assert stats.marginalized == ids0.size and ekf.num_active == 0 and ekf.state.P.shape == (CORE, CORE)
    ids, pos, cov = ekf.landmark_map()
    np.testing.assert_array_equal(ids, before_ids)
    np.testing.assert_array_equal(pos, before_pos)
    np.testing.assert_array_equal(cov, before_cov)


@pytest.mark.parametrize("kind", ["xyz", "inverse-depth"])
def test_points_at_near_infinite_depth_do_not_break_the_filter(kind):
    """A feature with 1e-4 px disparity (xyz: ~4e6 m away, covariance ~1e13) among good ones:
    the run goes on, the pose stays accurate and P stays positive definite."""
    drive = make_drive(40, seed=2)
    far_id = 10**6

    def add_far_point(k, ekf, ids, pix):
        far = np.array([[640.0, 120.0, 640.0 - 1e-4, 120.0]])
        return np.vstack([pix, far]) if ids.size else pix

    def run(with_far: bool):
        config = slam_config({"landmarks.parametrization": kind})
        ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, config, NOISE)
        ekf.update(*drive.observations(0))
        for k in range(drive.n - 1):
            ekf.predict(drive.t[k + 1] - drive.t[k], drive.v_meas[k], drive.w_meas[k])
            ids, pix = drive.observations(k + 1)
            if with_far:
                ids, pix = np.append(ids, far_id), add_far_point(k + 1, ekf, ids, pix)
            ekf.update(ids, pix)
        return ekf

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        plain, far = run(False), run(True)
    assert np.linalg.norm(far.world_T_imu[:3, 3] - plain.world_T_imu[:3, 3]) < 0.05
    assert np.linalg.eigvalsh(0.5 * (far.state.P + far.state.P.T)).min() > 0


# ----------------------------------------------------------------------------------------------
# 13 the filter's state (backend.estimator.state) and its error model


def _landmark_batch(rng, ids):
    """Distinct parameters, anchors, counts and limits for landmarks ``ids``, and their Jacobians
    (NewLandmarks) for StateHelper.augment."""
    n = len(ids)
    theta = rng.normal(0.0, 10.0, (n, 3))
    anchors = np.array([random_pose(rng) for _ in range(n)])
    counts = rng.integers(1, 5, n)
    limits = rng.integers(5, 30, n)
    new = NewLandmarks(theta, anchors, rng.normal(size=(3 * n, 6)), rng.normal(size=(n, 3, 4)))
    return np.array(ids, dtype=np.int64), theta, anchors, counts, limits, new


def test_filter_state_keeps_landmarks_in_one_slot_order():
    """StateHelper.augment appends P's rows (A1) and theta, the track rows, theta_first and the
    anchors in the same order; StateHelper.marginalize drops the same slots from all of them and
    from P's rows and columns, returns the new slot of each old one, rebuilds the id look-up, and
    stashes the RANSAC rejection runs of removed tracks that go on (not ended; nonzero only),
    which come back when such a track's landmark is added again."""
    rng = np.random.default_rng(21)
    st = FilterState(theta_first=np.zeros((0, 3)), anchors=np.zeros((0, 4, 4)))
    StateHelper.set_prior(st, random_spd(rng, CORE, 1.0))
    ids1, theta1, anchors1, counts1, limits1, new1 = _landmark_batch(rng, [40, 7, 23])
    StateHelper.augment(st, ids1, new1, 0.3, counts1, limits1)
    ids2, theta2, anchors2, counts2, limits2, new2 = _landmark_batch(rng, [5, 31])
    P1 = st.P.copy()
    StateHelper.augment(st, ids2, new2, 0.3, counts2, limits2)
    np.testing.assert_array_equal(st.P, covariance.augment(P1, new2.J_xi, new2.J_z, 0.3))

    ids = np.concatenate([ids1, ids2])
    theta = np.concatenate([theta1, theta2])
    anchors = np.concatenate([anchors1, anchors2])
    assert st.num_landmarks == 5 and st.track.shape == (len(TRACK_ROWS), 5)
    assert st.P.shape == (state_dimension(CORE, 5),) * 2
    np.testing.assert_array_equal(st.ids, ids)
    np.testing.assert_array_equal(st.track[ID], ids)
    np.testing.assert_array_equal(st.theta, theta)
    np.testing.assert_array_equal(st.theta_first, theta)
    np.testing.assert_array_equal(st.anchors, anchors)
    np.testing.assert_array_equal(st.obs_count, np.concatenate([counts1, counts2]))
    np.testing.assert_array_equal(st.obs_limit, np.concatenate([limits1, limits2]))
    assert np.all(st.gated_run == 0) and np.all(st.outlier_run == 0)
    np.testing.assert_array_equal(slots_of_index(np.array([31, 40, 6, 5, 7, 23]), *st.index), [4, 0, -1, 3, 1, 2])

    # the filter's corrections and counting between the steps: theta moves away from theta_first
    st.theta = st.theta + rng.normal(0.0, 0.5, st.theta.shape)
    moved = st.theta.copy()
    st.gated_run[:] = [1, 0, 2, 0, 1]
    st.outlier_run[:] = [2, 1, 3, 0, 4]
    track = st.track.copy()
    P = st.P.copy()

    mask = np.array([True, False, True, True, False])  # ids 40, 23, 5 leave
    ended = np.array([False, False, True, False, False])  # 23's track ended; 40's and 5's may go on
    remap = StateHelper.marginalize(st, mask, ended)
    np.testing.assert_array_equal(remap, [-1, 0, -1, -1, 1])
    keep = np.array([1, 4])
    rows = np.concatenate([np.arange(CORE), landmark_rows(CORE, keep).ravel()])
    np.testing.assert_array_equal(rows[CORE:], CORE + 3 * np.repeat(keep, 3) + np.tile(np.arange(3), 2))
    np.testing.assert_array_equal(st.P, P[np.ix_(rows, rows)])
    np.testing.assert_array_equal(st.track, track[:, keep])
    np.testing.assert_array_equal(st.ids, [7, 31])
    np.testing.assert_array_equal(st.theta, moved[keep])
    np.testing.assert_array_equal(st.theta_first, theta[keep])
    np.testing.assert_array_equal(st.anchors, anchors[keep])
    np.testing.assert_array_equal(st.gated_run, [0, 1])
    np.testing.assert_array_equal(st.outlier_run, [1, 4])
    np.testing.assert_array_equal(slots_of_index(np.array([31, 40, 7, 23, 5]), *st.index), [1, -1, 0, -1, -1])
    assert st.outlier_stash == {40: 2}  # 23 ended, 5 had no rejection run

    # 40's track comes back (re-anchored) with a new landmark 99: its run returns from the stash
    ids3, theta3, anchors3, counts3, limits3, new3 = _landmark_batch(rng, [99, 40])
    StateHelper.augment(st, ids3, new3, 0.3, counts3, limits3)
    np.testing.assert_array_equal(st.ids, [7, 31, 99, 40])
    np.testing.assert_array_equal(st.outlier_run, [1, 4, 0, 2])
    np.testing.assert_array_equal(st.theta_first[2:], theta3)
    np.testing.assert_array_equal(st.anchors[2:], anchors3)
    assert st.outlier_stash == {}
    np.testing.assert_array_equal(slots_of_index(np.array([40, 99]), *st.index), [3, 2])

    # no ``ended``: every removed track may go on
    remap = StateHelper.marginalize(st, np.array([False, True, False, True]))
    np.testing.assert_array_equal(remap, [0, -1, 1, -1])
    np.testing.assert_array_equal(st.ids, [7, 99])
    assert st.outlier_stash == {31: 4, 40: 2}
    assert st.P.shape == (CORE + 6, CORE + 6)


def test_filter_state_without_per_landmark_extras():
    """A model that reads neither first estimates nor anchors: they stay None through adds and removals."""
    rng = np.random.default_rng(22)
    st = FilterState()
    ids, theta, _, counts, limits, new = _landmark_batch(rng, [3, 1, 2])
    StateHelper.augment(st, ids, dataclasses.replace(new, anchors=None), 1.0, counts, limits)
    remap = StateHelper.marginalize(st, np.array([False, True, False]), np.array([False, True, False]))
    np.testing.assert_array_equal(remap, [0, -1, 1])
    np.testing.assert_array_equal(st.theta, theta[[0, 2]])
    assert st.theta_first is None and st.anchors is None


def test_state_helper_refuses_a_prior_of_the_wrong_size_or_after_landmarks():
    """set_prior takes the core's covariance only, and only before the first landmark."""
    st = FilterState()
    with pytest.raises(ValueError, match=r"\(9,9\)"):
        StateHelper.set_prior(st, np.eye(CORE + 3))
    rng = np.random.default_rng(23)
    ids, _, _, counts, limits, new = _landmark_batch(rng, [1])
    StateHelper.augment(st, ids, dataclasses.replace(new, anchors=None), 1.0, counts, limits)
    with pytest.raises(ValueError, match="landmarks"):
        StateHelper.set_prior(st, np.eye(CORE))


@pytest.mark.parametrize(
    "error_model, kind, mode, bias, fej",
    [
        ("invariant", "xyz", "slam", True, True),
        ("invariant", "xyz", "mapping", False, True),
        ("body", "xyz", "slam", True, True),
        ("body", "xyz", "slam", False, False),
        ("body", "inverse-depth", "mapping", True, True),
        ("body", "inverse-depth", "slam", True, False),
    ],
)
def test_make_error_model_follows_the_config(error_model, kind, mode, bias, fej):
    """estimator.error_model picks InvariantModel or BodyModel, with the landmark parametrization,
    whether the pose (mode "slam") and the gyro bias are estimated, and for the body model the
    per-landmark arrays it reads (theta_first with first_estimate_jacobians, anchors for inverse depth)."""
    config = bare_config({"estimator.error_model": error_model, "landmarks.parametrization": kind,
                          "estimator.mode": mode, "estimator.estimate_gyro_bias": bias,
                          "estimator.first_estimate_jacobians": fej})
    model = make_error_model(config, CAMERA, IMU_T_CAM)
    assert type(model) is (InvariantModel if error_model == "invariant" else BodyModel)
    assert model.parametrization == kind
    assert model.estimate_pose is (mode == "slam")
    assert model.estimate_bias is bias
    assert model.camera is CAMERA
    np.testing.assert_array_equal(model.imu_T_cam, IMU_T_CAM)
    np.testing.assert_allclose(model.cam_T_imu, CAM_T_IMU, rtol=0, atol=1e-15)
    expected = () if error_model == "invariant" else (
        (("theta_first",) if fej else ()) + (("anchors",) if kind != "xyz" else ()))
    assert tuple(model.per_landmark) == expected
    ekf = VisualInertialEKF(CAMERA, IMU_T_CAM, config, NOISE)
    assert type(ekf.model) is type(model)
    assert (ekf.state.theta_first is not None) is ("theta_first" in expected)
    assert (ekf.state.anchors is not None) is ("anchors" in expected)


def test_default_error_model_is_invariant():
    assert type(make_error_model(Config(), CAMERA, IMU_T_CAM)) is InvariantModel


# ------------------------------------------------------------------ health H3: vision that did (almost) nothing


def test_vision_check_no_observations_says_dead_reckoning():
    """H3: a run with no valid observation at all is dead reckoning alone (slam) / stereo triangulations (mapping)."""
    from vislam.backend.estimator.health import vision_check

    message = vision_check(0, 0, 0)
    assert "no valid stereo observation" in message and "dead reckoning alone" in message
    mapping = vision_check(0, 0, 0, slam=False)
    assert "stereo triangulations alone" in mapping and "dead reckoning" not in mapping


@pytest.mark.parametrize("gated", [0, 37])
def test_vision_check_none_used(gated):
    """H3: observations but none used (gated or not) names the counts and says dead reckoning; no division by zero."""
    from vislam.backend.estimator.health import vision_check

    message = vision_check(120, 0, gated)
    assert f"none of the 120 observations was used ({gated} gated)" in message
    assert "dead reckoning alone" in message and "pixel_sigma" in message
    assert "stereo triangulations alone" in vision_check(120, 0, gated, slam=False)


def test_vision_check_gated_share_threshold():
    """H3: above MAX_GATED_SHARE (0.9) gated the run is close to dead reckoning; at or below it, no message."""
    from vislam.backend.estimator.health import MAX_GATED_SHARE, vision_check

    assert MAX_GATED_SHARE == 0.9
    message = vision_check(1000, 5, 95)
    assert "95.0 % of the observations were gated (only 5 used)" in message
    assert "close to dead reckoning" in message
    assert "mostly stereo triangulations" in vision_check(1000, 5, 95, slam=False)
    assert vision_check(1000, 10, 90) is None  # exactly 90 %: not above
    assert vision_check(1000, 9, 91) is not None
    assert vision_check(1000, 500, 0) is None
    assert vision_check(1000, 500, 0, slam=False) is None


def test_health_all_gated_window_reports_inconsistent():
    """H1: a full window whose every observation is gated (used = 0) reports 'filter inconsistent'
    once, without dividing by zero; an incomplete window or fewer than 20 observations seen does not."""
    from vislam.backend.estimator.health import HealthMonitor

    monitor = HealthMonitor(window=3, warn_factor=3.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        monitor.add_nis(0, 0.0, 0, 10)
        monitor.add_nis(1, 0.0, 0, 10)  # window not full yet
    assert monitor.messages == []
    with pytest.warns(HealthWarning, match="filter inconsistent"):
        monitor.add_nis(2, 0.0, 0, 10)
    assert len(monitor.messages) == 1
    assert monitor.messages[0].startswith("step 2: filter inconsistent with its noise model: no observation used and "
                                          "100 % gated")
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        monitor.add_nis(3, 0.0, 0, 10)  # the same episode: no second message
    assert len(monitor.messages) == 1

    few = HealthMonitor(window=3, warn_factor=3.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        for step in range(5):
            few.add_nis(step, 0.0, 0, 6)  # 18 seen per window: too few to judge
    assert few.messages == []


def test_health_gated_count_toward_the_minimum():
    """H1: 5 used + 30 gated is enough to judge (the early return counts gated observations):
    a NIS in band but 86 % gated is reported."""
    from vislam.backend.estimator.health import HealthMonitor

    monitor = HealthMonitor(window=1, warn_factor=3.0)
    with pytest.warns(RuntimeWarning):
        monitor.add_nis(0, 4.0 * 5, 5, 30)
    assert monitor.messages == [("step 0: filter inconsistent with its noise model: mean NIS per observation 4.00 "
                                 "(expected about 4) and 86 % gated over the last 1 steps; the data moved away from "
                                 "the noise the run identified (a change of scene, a tracker losing lock): check the "
                                 "frames around it; a larger noise.pixel_sigma or IMU noise trades accuracy for "
                                 "consistency")]


def test_health_all_gated_episode_ends_and_recurs():
    """H1: an all-gated episode ends once the window is consistent again, and a new all-gated
    stretch is a second episode (the NaN mean of used = 0 does not stick)."""
    from vislam.backend.estimator.health import HealthMonitor

    monitor = HealthMonitor(window=2, warn_factor=3.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for step in range(3):
            monitor.add_nis(step, 0.0, 0, 25)
        assert monitor._inconsistent is True
        for step in range(3, 6):
            monitor.add_nis(step, 4.0 * 25, 25, 0)
        assert monitor._inconsistent is False
        for step in range(6, 9):
            monitor.add_nis(step, 0.0, 0, 25)
    assert [m.split(":")[0] for m in monitor.messages] == ["step 1", "step 7"]


@pytest.fixture(scope="module")
def h3_scene():
    from vislam.synth.scene import SceneConfig, make_scene

    return make_scene(SceneConfig(steps=80))


def _h3_messages(result) -> list[str]:
    return [m for m in result.stats.health_messages if "dead reckoning" in m or "stereo triangulations" in m]


def _run_warned(seq, values: dict):
    """run_sequence with Config.from_values(values), the RuntimeWarnings recorded."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = run_sequence(seq, Config.from_values(values))
    return result, [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]


def test_h3_all_gated_slam_run_says_dead_reckoning(h3_scene):
    """H3 end to end: pixel_sigma 1e-300 gates every observation; the slam run's health messages
    (and a RuntimeWarning) say the trajectory is dead reckoning alone, after H1's 'filter inconsistent'."""
    result, warned = _run_warned(h3_scene.sequence, {"noise.pixel_sigma": 1e-300})
    stats = result.stats
    assert stats.observations > 0 and stats.observations_used == 0 and stats.observations_gated > 0
    h3 = _h3_messages(result)
    assert len(h3) == 1
    counts = f"{stats.observations} observations was used ({stats.observations_gated} gated)"
    assert h3[0].startswith(f"none of the {counts}")
    assert "dead reckoning alone" in h3[0]
    assert h3[0] in warned
    assert any("filter inconsistent" in m for m in stats.health_messages)


def test_h3_all_gated_mapping_run_says_stereo_triangulations(h3_scene):
    """H3 end to end: the same all-gated run in mode mapping says its map is stereo triangulations alone."""
    result, warned = _run_warned(h3_scene.sequence, {"noise.pixel_sigma": 1e-300, "estimator.mode": "mapping"})
    h3 = _h3_messages(result)
    assert len(h3) == 1 and "the map holds stereo triangulations alone" in h3[0]
    assert h3[0] in warned


def test_h3_huge_velocities_say_dead_reckoning(h3_scene):
    """H3 end to end: linear velocities times 1e6 make every prediction miss; the slam run says dead reckoning."""
    seq = dataclasses.replace(h3_scene.sequence, linear_velocity=h3_scene.sequence.linear_velocity * 1e6)
    result, warned = _run_warned(seq, {})
    h3 = _h3_messages(result)
    assert result.stats.observations_used == 0 or result.stats.gated_share > 0.9
    assert len(h3) == 1 and "dead reckoning" in h3[0] and h3[0] in warned


def _without_observations(seq) -> Sequence:
    n = seq.num_steps
    return Sequence.from_steps(seq.time_stamps, seq.linear_velocity, seq.angular_velocity,
                               [np.zeros(0, np.int64)] * n, [np.zeros((0, 4))] * n, seq.K, seq.baseline,
                               seq.imu_T_cam)


@pytest.mark.parametrize("mode, words", [("slam", "the trajectory is dead reckoning alone"),
                                         ("mapping", "the map holds stereo triangulations alone")])
def test_h3_run_without_observations(h3_scene, mode, words):
    """H3 end to end: a sequence with no observation at all gets 'no valid stereo observation' in slam and mapping."""
    seq = _without_observations(h3_scene.sequence)
    assert seq.num_observations == 0
    result, warned = _run_warned(seq, {"estimator.mode": mode})
    assert result.stats.health_messages == [f"no valid stereo observation in the input: {words}"]
    assert result.stats.health_messages[0] in warned


@pytest.mark.parametrize("case", ["all gated", "no observations"])
def test_h3_dead_reckoning_mode_gets_no_message(h3_scene, case):
    """H3 end to end: mode dead-reckoning is not meant to see: no health message and no RuntimeWarning."""
    seq = _without_observations(h3_scene.sequence) if case == "no observations" else h3_scene.sequence
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        result = run_sequence(seq, Config.from_values({"noise.pixel_sigma": 1e-300 if case == "all gated" else 1.5,
                                                       "estimator.mode": "dead-reckoning"}))
    assert result.stats.health_messages == []


def test_h3_normal_synthetic_run_has_no_h3_message(h3_scene):
    """H3 end to end: a normal synthetic slam run (the scene's own noise) uses its observations, no H3 message."""
    result, warned = _run_warned(h3_scene.sequence, {
        "noise.pixel_sigma": h3_scene.config.pixel_sigma,
        "noise.linear_velocity_sigma": float(np.max(h3_scene.config.linear_sigma)),
        "noise.angular_velocity_sigma": float(np.max(h3_scene.config.angular_sigma))})
    stats = result.stats
    assert stats.observations_used > 0.5 * stats.observations and stats.gated_share < 0.9
    assert _h3_messages(result) == []
    assert not any("dead reckoning" in m for m in warned)
