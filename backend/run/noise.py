"""The IMU noise: white noise per axis estimated from the velocities themselves, and the decision
of what the filter uses (configured, estimated, or raised to a floor) with the gyro-bias decision."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import Config

def estimate_white_noise(signal: np.ndarray) -> np.ndarray:
    """Per-axis sigma of white noise on a smooth signal (N,3), from its second differences.

    For x_k = s_k + n_k with smooth s and white n of std sigma, the second difference
    x_{k+1} - 2 x_k + x_{k-1} has std sqrt(6) sigma; a robust scale (1.4826 MAD) keeps real
    manoeuvres from inflating the estimate:

        sigma = 1.4826 MAD(x_{k+1} - 2 x_k + x_{k-1}) / sqrt(6)                                (N1)
    """
    if signal.shape[0] < 5:
        return np.zeros(signal.shape[1])
    d2 = signal[2:] - 2.0 * signal[1:-1] + signal[:-2]
    mad = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0)
    return 1.4826 * mad / np.sqrt(6.0)


@dataclass
class NoiseDecision:
    """Process noise used, and where it came from (for the summary)."""

    linear_sigma: np.ndarray  # (3,) m/s, used
    angular_sigma: np.ndarray  # (3,) rad/s, used
    linear_estimated: np.ndarray | None  # (3,) white noise estimated from the data, if estimated
    angular_estimated: np.ndarray | None
    source: str  # "estimated" | "configured" | "mixed"
    gyro_bias: bool = True  # the filter estimates the gyro bias
    gyro_bias_reason: str = ""  # why not, when it does not

    def as_dict(self) -> dict:
        def fmt(a):
            return None if a is None else [float(x) for x in a]

        return {
            "linear_velocity_sigma": fmt(self.linear_sigma),
            "angular_velocity_sigma": fmt(self.angular_sigma),
            "linear_velocity_sigma_estimated": fmt(self.linear_estimated),
            "angular_velocity_sigma_estimated": fmt(self.angular_estimated),
            "source": self.source,
            "gyro_bias_estimated": self.gyro_bias,
            "gyro_bias_reason": self.gyro_bias_reason,
        }

    def describe(self) -> str:
        def fmt(a):
            return "[" + ", ".join(f"{x:.3g}" for x in a) + "]"

        text = f"IMU noise ({self.source}): linear {fmt(self.linear_sigma)} m/s, angular {fmt(self.angular_sigma)} rad/s"
        if self.linear_estimated is not None or self.angular_estimated is not None:
            parts = []
            if self.linear_estimated is not None:
                parts.append(f"linear {fmt(self.linear_estimated)} m/s")
            if self.angular_estimated is not None:
                parts.append(f"angular {fmt(self.angular_estimated)} rad/s")
            text += "; white noise estimated from the data: " + ", ".join(parts)
        if not self.gyro_bias:
            text += f"\ngyro bias: not estimated ({self.gyro_bias_reason})"
        return text


def decide_imu_noise(
    linear_velocity: np.ndarray,
    angular_velocity: np.ndarray,
    linear_sigma: float | None,
    angular_sigma: float | None,
    linear_floor: float,
    angular_floor: float,
    estimate_gyro_bias: bool = True,
    observations_per_step: float = float("inf"),
    gyro_bias_min_observations: float = 0.0,
) -> NoiseDecision:
    """Configured sigmas are used as given; unset ones are estimated and raised to the floor:
    sigma = max(sigma_white, floor). The floor stands for the error a velocity signal carries
    without showing it in its step-to-step roughness (scale, misalignment, the GPS/INS solution
    it came from): clean-looking velocities are not believed beyond it, while a file whose white
    noise already exceeds it keeps its estimate.

    The gyro bias is estimated (if configured) only where vision can tell it from track errors:
    with fewer than ``gyro_bias_min_observations`` stereo observations per step on average, a
    handful of far points' slow track drift reads as a rotation rate and the bias state absorbs it.
    """
    lin_est = ang_est = None
    if linear_sigma is None:
        lin_est = estimate_white_noise(linear_velocity)
        lin = np.maximum(lin_est, linear_floor)
    else:
        lin = np.full(3, float(linear_sigma))
    if angular_sigma is None:
        ang_est = estimate_white_noise(angular_velocity)
        ang = np.maximum(ang_est, angular_floor)
    else:
        ang = np.full(3, float(angular_sigma))
    estimated = (lin_est is not None) + (ang_est is not None)
    source = {0: "configured", 1: "mixed", 2: "estimated"}[estimated]
    bias, reason = bool(estimate_gyro_bias), ""
    if not estimate_gyro_bias:
        reason = "estimate_gyro_bias = false"
    elif observations_per_step < gyro_bias_min_observations:
        bias = False
        reason = (f"{observations_per_step:.1f} observations per step < gyro_bias_min_observations = "
                  f"{gyro_bias_min_observations:g}")
    return NoiseDecision(lin, ang, lin_est, ang_est, source, bias, reason)


def decide_noise(config: Config, linear_velocity: np.ndarray, angular_velocity: np.ndarray,
                 observations_per_step: float) -> NoiseDecision:
    """:func:`decide_imu_noise` with the settings of ``config`` (``noise``, ``estimator``)."""
    noise, est = config.noise, config.estimator
    return decide_imu_noise(linear_velocity, angular_velocity, noise.linear_velocity_sigma,
                            noise.angular_velocity_sigma, noise.linear_velocity_sigma_floor,
                            noise.angular_velocity_sigma_floor, est.estimate_gyro_bias, observations_per_step,
                            est.gyro_bias_min_observations)
