"""The body (right perturbation) error model of the course formulation (ECE276A, Barfoot ch. 7-9).

The pose error is a right perturbation of the mean, world_T_imu = mu exp(xi^), xi = [rho, theta]
in R^6; the gyro bias and the landmark parameters theta_i (``backend.estimator.landmarks``: world
xyz or anchored inverse depth) are vector space errors. For the body twist u = [v, omega - b_g]
over tau = t_{k+1} - t_k:

    mu <- mu exp(tau u^)                                                                  (P1)
    xi <- exp(-tau u-curlyhat) xi - tau J_r(tau u) [0; I] db + w,   w ~ N(0, W)
    P_xx <- F P_xx F^T + Q,  P_x,L <- F P_x,L,   F = [[exp(-tau u-curlyhat), -tau J_r E], [0, I]]   (B1)

with Q = diag(sigma_v^2, sigma_omega^2) tau^2 on the pose and the bias random walk on b_g; a residual
lever arm in the state (V1 of ``backend.estimator.lever_arm``) has the columns J_r(tau u) E_r.

Observation of landmark j in the stereo pair (course eq. z = Ks pi(cam_T_imu T^-1 m)), with the
landmark as a homogeneous point w = A (e + B theta) (L1):

    s = mu^-1 w,   q = cam_T_imu s,   z = Ks pi(q)
    dz/dxi    = -Ks dpi/dq cam_T_imu s^odot     (T^-1 w = exp(-xi^) mu^-1 w ~ s - xi^ s)
    dz/dtheta =  Ks dpi/dq cam_T_imu mu^-1 A B                                             (B2)

First-estimate Jacobians (Huang, Mourikis & Roumeliotis 2008; ``first_estimate_jacobians``): (B2)
is evaluated at each landmark's first estimate, so the unobservable directions get no spurious
information; the residual uses the current estimate.                                        (B3)

A new landmark theta = g(z, mu) from its first stereo observation has the Jacobians J_z and
J_xi of (L2) (``backend.estimator.landmarks.initialize``) and enters by (A1).                  (B4)

The correction adds dx: mu <- mu exp(dx_xi^), b_g += dx_b, theta += dx_theta.
"""

from __future__ import annotations

import numpy as np

from ..geometry import se3
from ..geometry.camera import dpi_dq, pi
from . import landmarks
from .layout import BIAS, LEVER_ROWS, POSE, SQRT_HALF, landmark_rows
from .lever_arm import SensitivityTransition, twist_columns
from .model import ErrorModel
from .state import FilterState
from .state_helper import CoreTransition, NewLandmarks
from .update import Innovation, innovation_covariance, three_rows


class BodyModel(ErrorModel):
    """The right perturbation mu exp(xi^) (module docstring), for xyz or inverse-depth landmarks;
    ``first_estimate_jacobians``: (B3)."""

    def __init__(self, *args, first_estimate_jacobians: bool = True, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.fej = first_estimate_jacobians
        per = ("theta_first",) if self.fej else ()
        self.per_landmark = per + (("anchors",) if self.parametrization != "xyz" else ())

    # ---------------------------------------------------------------- prediction (B1)
    def predict(self, state, twist, q, dt, bias_walk_var) -> CoreTransition | None:
        step = se3.exp_se3(twist)
        self.predict_mean_only(state, step)
        if not self.estimate_pose:
            return None
        Phi = np.eye(state.core)  # the disparity offset's and the lever arm's rows are constant
        Phi[POSE, POSE] = se3.adjoint(se3.inverse(step))  # exp(-tau u-curlyhat) = Ad(exp(tau u^)^-1)
        q_var = np.zeros(state.core)
        q_var[POSE] = q * q
        J_r = se3.right_jacobian_se3(twist)
        if self.estimate_bias:
            Phi[POSE, BIAS] = -dt * J_r[:, 3:6]
            q_var[BIAS] = bias_walk_var
        if state.lever_row is None:
            return CoreTransition(Phi, q_var)
        g = J_r @ twist_columns(twist, rotation=state.carries_rotation)  # (V1, V4): the lever arm's columns of F
        if state.lever_share:  # (V2) its sensitivity column only
            return SensitivityTransition(CoreTransition(Phi, q_var), state.lever_row, g)
        Phi[POSE, state.lever_row:state.lever_row + LEVER_ROWS] = g
        return CoreTransition(Phi, q_var)

    # ---------------------------------------------------------------- observation (B2, B3)
    def _project(self, state: FilterState, mu_inv: np.ndarray, theta: np.ndarray, slots: np.ndarray):
        """q = cam_T_imu mu^-1 A (e + B theta) (k,4) and d(mu^-1 w)/d theta ((4,3) or (k,4,3)) (L1)."""
        kind = self.parametrization
        local = landmarks.local_point(kind, theta)
        if kind == "xyz":  # anchors are the identity
            w_world = local
            dw_dtheta = mu_inv @ landmarks.basis(kind)  # the same for every landmark
        else:
            anchors = state.anchors[slots]
            w_world = np.einsum("kij,kj->ki", anchors, local)
            dw_dtheta = mu_inv @ anchors @ landmarks.basis(kind)
        return w_world @ (self.cam_T_imu @ mu_inv).T, dw_dtheta

    def observe(self, state: FilterState, slots: np.ndarray, pixels: np.ndarray):
        """(B2) in the 3-row form (U1): residual (k,3), off_row (k,) (the residual of (vL - vR)/sqrt 2,
        no state in it), H_xi (k,3,6), H_theta (k,3,3) and a mask of points in front of the camera."""
        mu_inv = se3.inverse(state.mu)
        q, dw_dtheta = self._project(state, mu_inv, state.theta[slots], slots)
        in_front = q[:, 2] > 0.1 * np.abs(q[:, 3])
        q[~in_front, 2] = np.abs(q[~in_front, 3]) + 1.0  # placeholder, those rows are gated out
        Ks = self.camera.Ks
        residual = pixels - pi(q) @ Ks.T
        if self.fej:  # (B3): the Jacobians at each landmark's first estimate
            q, dw_dtheta = self._project(state, mu_inv, state.theta_first[slots], slots)
            q[~in_front, 2] = np.abs(q[~in_front, 3]) + 1.0
        s_imu = q @ self.imu_T_cam.T
        dz_dimu = Ks @ dpi_dq(q) @ self.cam_T_imu  # (k,4,4): d z / d s_imu
        H_theta = dz_dimu @ dw_dtheta
        if self.estimate_pose:
            H_xi = -dz_dimu @ se3.odot(s_imu)
        else:
            H_xi = np.zeros((slots.size, 4, 6))
        off_row = (residual[:, 1] - residual[:, 3]) * SQRT_HALF
        return three_rows(residual), off_row, three_rows(H_xi), three_rows(H_theta), in_front

    def innovation(self, state, slots, pixels, pixel_var) -> Innovation:
        residual, off_row, H_x, H_m, in_front = self.observe(state, slots, pixels)
        H_x = np.ascontiguousarray(H_x.reshape(-1, 6))
        H_m = np.ascontiguousarray(H_m)
        HP, S, nis = innovation_covariance(state.P, H_x, H_m, slots, pixel_var, residual, off_row, state.core)
        return Innovation(residual, off_row, H_x, H_m, HP, S, nis, in_front)

    # ---------------------------------------------------------------- landmarks (B4)
    def initialize(self, state, pixels, sigma) -> NewLandmarks:
        theta, anchors, J_z, J_xi = landmarks.initialize(self.parametrization, self.camera, pixels, state.mu,
                                                         self.imu_T_cam, sigma or None)
        n = pixels.shape[0]
        J_xi = J_xi.reshape(3 * n, 6) if self.estimate_pose else np.zeros((3 * n, 6))
        return NewLandmarks(theta, anchors, J_xi, J_z)

    def correct(self, state, dx) -> None:
        if self.estimate_pose:
            state.mu = state.mu @ se3.exp_se3(dx[POSE])
            state.gyro_bias = state.gyro_bias + dx[BIAS]
        state.theta += dx[state.core:].reshape(-1, 3)

    def world_landmarks(self, state, slots):
        P, rows = state.considered_state(slots)  # (V2) with a considered lever arm's share
        idx = landmark_rows(state.core, rows)
        cov = P[idx[:, :, None], idx[:, None, :]]  # the 3x3 diagonal blocks
        anchors = state.anchors[slots] if state.anchors is not None else None
        return landmarks.to_world(self.parametrization, state.theta[slots], anchors, cov)

    def pose_covariance(self, state) -> np.ndarray:
        return state.covariance_of(POSE)
