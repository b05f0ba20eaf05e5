"""The inertial state at the first frame, from the IMU at rest (Z1-Z4).

At rest (v = 0, R constant) the samples of the first ``window`` seconds measure

    w_m = b_g + n_g,    a_m = R^T (-g) + b_a + n_a                                                (Z1)

so the mean rate is the gyro bias and the mean specific force points up in the IMU frame. The
world frame is gravity-aligned with the first pose at the origin and no yaw: its z axis is the
mean specific force's direction, its x axis the IMU's x axis projected on the horizontal plane
(any other yaw would do: it is unobservable).                                                     (Z2)

Rest is decided from the samples alone, by how far attitude and velocity wander: the integrals
of (w_m - mean) and (a_m - mean) over the window stay under ``max_attitude_wander_deg`` and
``max_velocity_wander`` (a vibrating rig at rest: EuRoC's before take-off wanders 0.06-0.19 deg
and 0.01-0.04 m/s in 1 s; hovering or turning, 1-5 deg).                                         (Z3)

The accelerometer bias's horizontal part cannot be told from a tilt at rest: a bias b tilts the
estimate by |b_horizontal| / g. The covariance says so: with the bias prior sigma_ba0 per axis,

    g^ phi = R_hat db_a   (to first order; rows x, y: phi_x = -(R db_a)_y / g, phi_y = (R db_a)_x / g)   (Z4)

so roll and pitch start with sigma_ba0 / g each and fully correlated with the bias; yaw and position
start at (nearly) zero uncertainty (the first pose defines them), the velocity at the measured
wander (Z3), the gyro bias at the standard error of its mean.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..data.inertial import ImuNoiseDensities, ImuSamples
from ..estimator.inertial import BA, BG, CORE_INERTIAL, NU, PHI, RHO, InertialMean

__all__ = ["RestOptions", "Initialization", "initialize_at_rest", "rest_test"]


@dataclass(frozen=True)
class RestOptions:
    """Options of the initialization at rest (Z3, Z4)."""

    window: float = 1.0  # seconds of IMU after the first frame that are averaged
    min_window: float = 0.2  # fewer seconds than this: not tested
    max_attitude_wander_deg: float = 0.5  # Z3
    max_velocity_wander: float = 0.1  # m/s, Z3
    accel_bias_sigma0: float = 0.1  # m/s^2 per axis: the prior of the accelerometer bias (Z4)
    min_velocity_sigma0: float = 1e-3  # m/s: the velocity at rest is known to its measured wander (Z3), at least this
    pose_sigma0: float = 1e-6  # position (m) and yaw (rad): the frame is defined by the first pose


@dataclass(frozen=True)
class Initialization:
    """How the inertial state started and what was found; ``mean`` and ``covariance`` (15,15) of
    the core error state (J1) when ``at_rest``."""

    at_rest: bool
    reason: str
    mean: InertialMean | None = None
    covariance: np.ndarray | None = None
    measured: dict = field(default_factory=dict)

    def describe(self) -> str:
        m = self.measured
        if not self.at_rest:
            return f"inertial initialization: not at rest ({self.reason})"
        g = np.asarray(m["gravity_in_imu"])
        return (f"inertial initialization: at rest over {m['window_s']:.2f} s ({m['samples']} samples; attitude wander "
                f"{m['attitude_wander_deg']:.2f} deg, velocity wander {m['velocity_wander']:.3f} m/s); gravity in the "
                f"IMU frame [{g[0]:+.4f}, {g[1]:+.4f}, {g[2]:+.4f}], |specific force| {m['specific_force']:.4f} m/s^2; "
                f"gyro bias [{', '.join(f'{x:+.5f}' for x in m['gyro_bias'])}] rad/s; roll and pitch +- "
                f"{m['tilt_sigma_deg']:.2f} deg (an accelerometer bias of {m['accel_bias_sigma0']:g} m/s^2 cannot be "
                "told from a tilt at rest)")

    def as_dict(self) -> dict:
        return {"at_rest": self.at_rest, "reason": self.reason,
                **{k: (np.asarray(v).tolist() if isinstance(v, np.ndarray) else v) for k, v in self.measured.items()}}


def rest_test(imu: ImuSamples, t0: float, window: float) -> dict:
    """(Z3) the wander of attitude (deg) and velocity (m/s) over [t0, t0 + window], with the means."""
    t = imu.time_stamps
    sel = (t >= t0) & (t <= t0 + window)
    n = int(sel.sum())
    out = {"samples": n, "window_s": float(t[sel][-1] - t[sel][0]) if n > 1 else 0.0}
    if n < 3:
        return out
    dt = np.gradient(t[sel])[:, None]
    w, a = imu.angular_velocity[sel], imu.linear_acceleration[sel]
    w_mean, a_mean = w.mean(0), a.mean(0)
    out.update(gyro_mean=w_mean, accel_mean=a_mean,
               attitude_wander_deg=float(np.degrees(np.linalg.norm(np.cumsum((w - w_mean) * dt, 0), axis=1).max())),
               velocity_wander=float(np.linalg.norm(np.cumsum((a - a_mean) * dt, 0), axis=1).max()),
               gyro_se=w.std(0) / np.sqrt(n))
    # (Z5) white-noise densities of the samples at rest, vibration included: std sqrt(dt), RMS over the axes
    root_dt = np.sqrt(float(np.median(np.diff(t[sel]))))
    out.update(gyroscope_density_at_rest=float(np.sqrt(np.mean(w.var(0)))) * root_dt,
               accelerometer_density_at_rest=float(np.sqrt(np.mean(a.var(0)))) * root_dt)
    return out


def gravity_aligned_rotation(up_in_imu: np.ndarray) -> np.ndarray:
    """(Z2) world_R_imu (3,3) whose world z is ``up_in_imu`` (3,) and whose yaw is zero (the IMU's x
    axis projected on the horizontal plane is the world's x; its y axis when x points up)."""
    z = up_in_imu / np.linalg.norm(up_in_imu)
    ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - (ref @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])  # rows: the world axes in IMU coordinates


def initialize_at_rest(imu: ImuSamples, t0: float, gravity: np.ndarray, noise: ImuNoiseDensities | None = None,
                       options: RestOptions = RestOptions()) -> Initialization:
    """(Z1-Z4) the inertial state at ``t0`` (the first frame) if the IMU is at rest over the window
    after it; else an :class:`Initialization` with ``at_rest`` False and the reason."""
    m = rest_test(imu, t0, options.window)
    if m.get("window_s", 0.0) < options.min_window or "gyro_mean" not in m:
        return Initialization(False, f"{m.get('window_s', 0.0):.2f} s of IMU after the first frame, "
                                     f"{options.min_window:g} s needed", measured=m)
    if m["attitude_wander_deg"] > options.max_attitude_wander_deg or m["velocity_wander"] > options.max_velocity_wander:
        return Initialization(False, f"attitude wander {m['attitude_wander_deg']:.2f} deg (at most "
                                     f"{options.max_attitude_wander_deg:g}), velocity wander {m['velocity_wander']:.3f} "
                                     f"m/s (at most {options.max_velocity_wander:g}) over {m['window_s']:.2f} s",
                              measured=m)
    g = float(np.linalg.norm(gravity))
    R = gravity_aligned_rotation(m["accel_mean"])
    T = np.eye(4)
    T[:3, :3] = R
    mean = InertialMean(T, np.zeros(3), m["gyro_mean"].copy(), np.zeros(3))
    P = np.zeros((CORE_INERTIAL, CORE_INERTIAL))
    P[RHO, RHO] = np.eye(3) * options.pose_sigma0**2
    P[NU, NU] = np.eye(3) * max(m["velocity_wander"], options.min_velocity_sigma0) ** 2
    se = m["gyro_se"]
    if noise is not None:  # the white noise's share when the vibration is smaller than it (never on a real rig)
        se = np.maximum(se, noise.gyroscope_noise_density / np.sqrt(max(m["window_s"], 1e-9)))
    P[BG, BG] = np.diag(se**2)
    # (Z4): phi = C db_a for roll and pitch, yaw independent; db_a ~ N(0, s^2 I)
    s2 = options.accel_bias_sigma0**2
    C = np.zeros((3, 3))
    C[0] = -R[1] / g
    C[1] = R[0] / g
    P[PHI, PHI] = s2 * C @ C.T
    P[3 + 2, 3 + 2] += options.pose_sigma0**2
    P[PHI, BA] = s2 * C
    P[BA, PHI] = s2 * C.T
    P[BA, BA] = np.eye(3) * s2
    m.update(gravity_in_imu=m["accel_mean"] / np.linalg.norm(m["accel_mean"]),
             specific_force=float(np.linalg.norm(m["accel_mean"])), gyro_bias=m["gyro_mean"],
             tilt_sigma_deg=float(np.degrees(options.accel_bias_sigma0 / g)), accel_bias_sigma0=options.accel_bias_sigma0)
    return Initialization(True, "", mean, 0.5 * (P + P.T), m)
