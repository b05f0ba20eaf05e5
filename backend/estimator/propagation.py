"""IMU velocity kinematics: the mean of the prediction, and dead reckoning (pure functions).

For the body twist u_k = [v_k, omega_k] measured in the IMU frame over tau_k = t_{k+1} - t_k,

    world_T_imu_{k+1} = world_T_imu_k exp(tau_k u_k^)                                   (P1)

(the course's prediction of the mean; Barfoot eq. 7.39 for exp). Dead reckoning is (P1) from the
identity with no correction. Which sample drives step k -> k+1, the one stamped k ("this") or
k+1 ("next"), is a convention of the data (``backend.run.conventions`` decides it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import se3

VELOCITY_INDEX_OFFSET = {"this": 0, "next": 1}


@dataclass
class ImuNoise:
    """White noise of the velocity measurements, per axis (the process noise of the prediction)."""

    linear_sigma: np.ndarray  # (3,) m/s
    angular_sigma: np.ndarray  # (3,) rad/s


def step_velocities(linear_velocity: np.ndarray, angular_velocity: np.ndarray, velocity_index: str):
    """Body twist driving each step k -> k+1: the sample stamped k ("this") or k+1 ("next").

    Returns (v (N-1,3), w (N-1,3)).
    """
    offset = VELOCITY_INDEX_OFFSET[velocity_index]
    n = linear_velocity.shape[0]
    return linear_velocity[offset : offset + n - 1], angular_velocity[offset : offset + n - 1]


def dead_reckoning(
    time_stamps: np.ndarray,
    linear_velocity: np.ndarray,
    angular_velocity: np.ndarray,
    velocity_index: str = "this",
    gyro_bias: np.ndarray | None = None,
    world_T_imu0: np.ndarray | None = None,
) -> np.ndarray:
    """world_T_imu (N,4,4) by (P1) from ``world_T_imu0`` (the identity by default), no correction."""
    v, w = step_velocities(linear_velocity, angular_velocity, velocity_index)
    if gyro_bias is not None:
        w = w - gyro_bias
    tau = np.diff(time_stamps)
    twists = np.concatenate([v, w], axis=1) * tau[:, None]
    return compose_steps(se3.exp_se3_batch(twists), world_T_imu0)


def compose_steps(steps: np.ndarray, world_T_imu0: np.ndarray | None = None) -> np.ndarray:
    """Poses (N+1,4,4) T_0 = world_T_imu0 (identity by default), T_{k+1} = T_k steps[k]."""
    poses = np.empty((steps.shape[0] + 1, 4, 4))
    poses[0] = np.eye(4) if world_T_imu0 is None else world_T_imu0
    for k in range(steps.shape[0]):
        np.matmul(poses[k], steps[k], out=poses[k + 1])
    return poses
