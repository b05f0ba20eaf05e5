"""Synthetic trajectories with exact accelerations, and the samples of a real IMU along them.

Unlike :mod:`~vislam.synth.trajectories` (body velocities integrated step by step), a trajectory here is
a continuous function of time with closed-form derivatives, so a real IMU's samples, the specific force
and the angular rate, can be computed exactly at any rate:

* position ``p(t) = P(tau(t))`` with each axis of ``P`` a :class:`Sinusoids`
  (``offset + slope tau + sum_k A_k sin(w_k tau + phi_k)``);
* attitude ``R(t) = Rz(yaw) Ry(pitch) Rx(roll)`` (``world_T_imu = [[R, p], [0, 1]]``) with each angle a
  :class:`Sinusoids` of ``tau``; a car (``attitude_follows_velocity``) also turns its x axis along its
  velocity: ``yaw += atan2(P'_y, P'_x)``, ``pitch += -atan2(P'_z, |P'_xy|)``;
* ``tau(t)`` is the identity, or, with ``start_at_rest = t_r``, a time warp that holds the trajectory at
  rest with a constant attitude over ``[0, t_r]`` and brings it up to speed over the next ``ramp``
  seconds (``tau' = S((t - t_r) / ramp)``, ``S(x) = 10x^3 - 15x^4 + 6x^5`` on [0, 1], 0 before, 1 after;
  tau, tau' and tau'' in closed form, so the acceleration and its derivative are continuous).

Everything is evaluated by the chain rule from the analytic derivatives (:meth:`InertialTrajectory.evaluate`):

    v = P'(tau) tau',    a = P''(tau) tau'^2 + P'(tau) tau'',    angle_dot = angle'(tau) tau'
    omega_world = yaw_dot e_z + pitch_dot Rz(yaw) e_y + roll_dot Rz(yaw) Ry(pitch) e_x
    omega_body = R^T omega_world

Frames: the world is gravity-aligned with z up (gravity ``g = [0, 0, -9.81]`` by default); the IMU frame
is x forward, y left, z up. :func:`measure_imu` gives the samples of a real IMU in Kalibr's units
(:mod:`~vislam.backend.data.inertial`):

    a_m[k] = R_k^T (a_k - g) + b_a[k] + n_a[k],   n_a ~ N(0, (accelerometer_noise_density / sqrt(dt))^2 I)
    w_m[k] = omega_body_k + b_g[k] + n_g[k],      n_g ~ N(0, (gyroscope_noise_density / sqrt(dt))^2 I)
    b[k+1] = b[k] + random_walk sqrt(dt) xi_k,    xi_k ~ N(0, I)

(about +9.81 m/s^2 on the up axis at rest). Scenarios: :func:`room` (a MAV in an 8 x 8 x 3 m room, like
EuRoC's Vicon room) and :func:`street` (a car). :func:`frame_times` and :func:`frame_truth` give camera
frame stamps and the true states there. All draws come from ``synth._random.generator(seed, stream)``
("trajectory" for the scenarios, "imu" for the samples), so the noise never changes the trajectory.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from ..backend.data.inertial import ADIS16448, ImuNoiseDensities, ImuSamples
from ._random import generator

__all__ = [
    "GRAVITY",
    "ROOM_BOX",
    "ROOM_FLIGHT_BOX",
    "ROOM_MAX_TILT",
    "GYRO_BIAS_RANGE",
    "ACCEL_BIAS_RANGE",
    "Sinusoids",
    "TrajectoryState",
    "InertialTrajectory",
    "room",
    "street",
    "INERTIAL_TRAJECTORIES",
    "InertialTruth",
    "measure_imu",
    "FrameTruth",
    "frame_times",
    "frame_truth",
]

#: Default gravity vector in the world frame (m/s^2), z up
GRAVITY = (0.0, 0.0, -9.81)
#: The room's walls, floor and ceiling: [[x_min, y_min, z_min], [x_max, y_max, z_max]] (m), 8 x 8 x 3 m
ROOM_BOX = np.array([[-4.0, -4.0, 0.0], [4.0, 4.0, 3.0]])
ROOM_BOX.setflags(write=False)
#: Where the room's MAV always is (a bound by construction: the sum of the amplitudes about the centre)
ROOM_FLIGHT_BOX = np.array([[-3.3, -3.3, 0.6], [3.3, 3.3, 2.4]])
ROOM_FLIGHT_BOX.setflags(write=False)
#: Bound on the room's |roll| and |pitch| (rad) by construction (16 + 6 degrees)
ROOM_MAX_TILT = np.deg2rad(22.0)
#: Magnitudes (per axis, uniform, random sign) of the initial biases drawn by :func:`measure_imu`
GYRO_BIAS_RANGE = (0.002, 0.02)  # rad/s
ACCEL_BIAS_RANGE = (0.02, 0.1)  # m/s^2

_CHUNK = 4096  # samples evaluated at a time (bounds the (K, terms) work arrays)


def _readonly(a, shape=None) -> np.ndarray:
    a = np.array(a, dtype=float)
    if shape is not None:
        a = a.reshape(shape)
    a.setflags(write=False)
    return a


# ------------------------------------------------------------------------------------- scalar functions


@dataclass(frozen=True, eq=False)
class Sinusoids:
    """A smooth scalar function ``f(tau) = offset + slope tau + sum_k A_k sin(w_k tau + phi_k)``.

    Its n-th derivative is ``slope [n == 1] + sum_k A_k w_k^n sin(w_k tau + phi_k + n pi / 2)``.

    Parameters
    ----------
    offset, slope : float
        Constant (units of f) and linear rate (units of f per second).
    amplitude, omega, phase : array_like, shape (n,)
        A_k (units of f), angular frequencies w_k (rad/s) and phases phi_k (rad).
    """

    offset: float = 0.0
    slope: float = 0.0
    amplitude: np.ndarray = field(default_factory=lambda: np.zeros(0))
    omega: np.ndarray = field(default_factory=lambda: np.zeros(0))
    phase: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        object.__setattr__(self, "offset", float(self.offset))
        object.__setattr__(self, "slope", float(self.slope))
        arrays = [_readonly(getattr(self, k), (-1,)) for k in ("amplitude", "omega", "phase")]
        if len({a.shape for a in arrays}) != 1:
            raise ValueError(f"amplitude, omega and phase must have the same length, got {[a.size for a in arrays]}")
        if not all(np.all(np.isfinite(a)) for a in arrays) or not np.isfinite(self.offset + self.slope):
            raise ValueError("Sinusoids: every coefficient must be finite")
        for key, a in zip(("amplitude", "omega", "phase"), arrays):
            object.__setattr__(self, key, a)

    @property
    def bound(self) -> float:
        """``sum_k |A_k|``: ``|f(tau) - offset - slope tau| <= bound`` for every tau."""
        return float(np.abs(self.amplitude).sum())

    def derivatives(self, tau: np.ndarray, count: int = 3) -> np.ndarray:
        """``[f, f', f'', ...]`` at ``tau`` (K,): shape (count, K), count in 1..3."""
        tau = np.asarray(tau, dtype=float).reshape(-1)
        if not 1 <= count <= 3:
            raise ValueError(f"count must be 1, 2 or 3, got {count}")
        out = np.empty((count, tau.size))
        out[0] = self.offset + self.slope * tau
        if count > 1:
            out[1] = self.slope
        if count > 2:
            out[2] = 0.0
        if self.amplitude.size == 0:
            return out
        A, w = self.amplitude, self.omega
        for lo in range(0, tau.size, _CHUNK):
            part = slice(lo, lo + _CHUNK)
            angle = tau[part, None] * w + self.phase  # (k, n)
            s = np.sin(angle)  # row sums, not BLAS products: equal times give equal values, on any machine
            out[0, part] += (s * A).sum(axis=1)
            if count > 1:
                out[1, part] += (np.cos(angle) * (A * w)).sum(axis=1)
            if count > 2:
                out[2, part] -= (s * (A * w * w)).sum(axis=1)
        return out

    def __call__(self, tau: np.ndarray) -> np.ndarray:
        """f(tau), shape (K,)."""
        return self.derivatives(tau, 1)[0]


def _random_sinusoids(rng: np.random.Generator, terms, offset: float = 0.0, slope: float = 0.0) -> Sinusoids:
    """``offset + slope tau + sum A sin(2 pi tau / T + phi)`` over ``terms = [(A, T_min, T_max), ...]``:
    T uniform in [T_min, T_max], phi uniform in [0, 2 pi)."""
    amplitude, omega, phase = [], [], []
    for A, period_min, period_max in terms:
        amplitude.append(A)
        omega.append(2.0 * np.pi / rng.uniform(period_min, period_max))
        phase.append(rng.uniform(0.0, 2.0 * np.pi))
    return Sinusoids(offset, slope, amplitude, omega, phase)


# ------------------------------------------------------------------------------------------- rotations


def _rotation_zyx(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """``Rz(yaw) Ry(pitch) Rx(roll)``, (K,) each -> (K,3,3)."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    R = np.empty(yaw.shape + (3, 3))
    R[..., 0, 0] = cy * cp
    R[..., 0, 1] = cy * sp * sr - sy * cr
    R[..., 0, 2] = cy * sp * cr + sy * sr
    R[..., 1, 0] = sy * cp
    R[..., 1, 1] = sy * sp * sr + cy * cr
    R[..., 1, 2] = sy * sp * cr - cy * sr
    R[..., 2, 0] = -sp
    R[..., 2, 1] = cp * sr
    R[..., 2, 2] = cp * cr
    return R


def _world_rate_zyx(yaw, pitch, yaw_dot, pitch_dot, roll_dot) -> np.ndarray:
    """World angular velocity of ZYX Euler angles (K,3):
    ``yaw_dot e_z + pitch_dot Rz(yaw) e_y + roll_dot Rz(yaw) Ry(pitch) e_x``."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    return np.stack([
        -pitch_dot * sy + roll_dot * cy * cp,
        pitch_dot * cy + roll_dot * sy * cp,
        yaw_dot - roll_dot * sp,
    ], axis=-1)


# ------------------------------------------------------------------------------------------ trajectory


class TrajectoryState(NamedTuple):
    """The exact state of an :class:`InertialTrajectory` at K times."""

    time: np.ndarray  # (K,) s
    world_T_imu: np.ndarray  # (K,4,4)
    velocity: np.ndarray  # (K,3) m/s, world frame
    acceleration: np.ndarray  # (K,3) m/s^2, world frame (gravity not included)
    angular_velocity: np.ndarray  # (K,3) rad/s, IMU (body) frame
    angles: np.ndarray  # (K,3) rad: yaw, pitch, roll with R = Rz(yaw) Ry(pitch) Rx(roll)
    angle_rates: np.ndarray  # (K,3) rad/s: their time derivatives

    @property
    def position(self) -> np.ndarray:
        """(K,3) m, world frame."""
        return self.world_T_imu[:, :3, 3]

    @property
    def rotation(self) -> np.ndarray:
        """(K,3,3) world_R_imu."""
        return self.world_T_imu[:, :3, :3]


@dataclass(frozen=True, eq=False)
class InertialTrajectory:
    """A continuous-time IMU trajectory with exact derivatives (module docstring for the equations).

    Parameters
    ----------
    position : tuple of 3 Sinusoids
        ``P(tau)``, the world position (m) of each axis x, y, z.
    yaw, pitch, roll : Sinusoids
        The attitude angles (rad), ``R = Rz(yaw) Ry(pitch) Rx(roll)``.
    duration : float
        Length (s) of the trajectory, from t = 0; the functions are defined at any t, but the scenarios'
        documented ranges hold on [0, duration].
    attitude_follows_velocity : bool
        Add the heading ``atan2(P'_y, P'_x)`` to yaw and the climb ``-atan2(P'_z, |P'_xy|)`` to pitch (a car
        whose x axis points along its velocity); ``P'`` must then never be vertical or zero.
    start_at_rest : float or None
        None: tau = t (moving from t = 0). Otherwise at rest, attitude constant, on [0, start_at_rest] s,
        then up to speed over ``ramp`` s: ``tau' = S(x)``, ``x = (t - start_at_rest) / ramp``,
        ``S(x) = 10x^3 - 15x^4 + 6x^5`` on [0, 1] (0 before, 1 after), ``tau = ramp (x^6 - 3x^5 + 5x^4/2)``
        on [0, 1] (0 before, ``t - start_at_rest - ramp / 2`` after), ``tau'' = 30 x^2 (1 - x)^2 / ramp``.
    ramp : float
        Seconds (> 0) to come up to speed after the rest.
    name : str
        The scenario's name and seed, e.g. ``"room:seed3"``.
    """

    position: tuple
    yaw: Sinusoids
    pitch: Sinusoids
    roll: Sinusoids
    duration: float
    attitude_follows_velocity: bool = False
    start_at_rest: float | None = None
    ramp: float = 2.0
    name: str = ""

    def __post_init__(self) -> None:
        position = tuple(self.position)
        if len(position) != 3 or not all(isinstance(f, Sinusoids) for f in position):
            raise ValueError("position must be 3 Sinusoids (x, y, z)")
        object.__setattr__(self, "position", position)
        for key in ("yaw", "pitch", "roll"):
            if not isinstance(getattr(self, key), Sinusoids):
                raise ValueError(f"{key} must be a Sinusoids")
        duration = float(self.duration)
        if not (np.isfinite(duration) and duration > 0):
            raise ValueError(f"duration must be > 0 s, got {self.duration!r}")
        object.__setattr__(self, "duration", duration)
        ramp = float(self.ramp)
        if not (np.isfinite(ramp) and ramp > 0):
            raise ValueError(f"ramp must be > 0 s, got {self.ramp!r}")
        object.__setattr__(self, "ramp", ramp)
        if self.start_at_rest is not None:
            rest = float(self.start_at_rest)
            if not (np.isfinite(rest) and rest >= 0):
                raise ValueError(f"start_at_rest must be None or >= 0 s, got {self.start_at_rest!r}")
            object.__setattr__(self, "start_at_rest", rest)

    # ------------------------------------------------------------------ time warp

    def warp(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(tau, tau', tau'')`` at times t (K,), each (K,) (class docstring, ``start_at_rest``)."""
        t = np.asarray(t, dtype=float).reshape(-1)
        if self.start_at_rest is None:
            return t.copy(), np.ones_like(t), np.zeros_like(t)
        x = (t - self.start_at_rest) / self.ramp
        inside = (x > 0.0) & (x < 1.0)
        xi = np.where(inside, x, 0.0)
        x2 = xi * xi
        x3 = x2 * xi
        tau = np.where(x >= 1.0, t - self.start_at_rest - 0.5 * self.ramp,
                       self.ramp * x3 * xi * (x2 - 3.0 * xi + 2.5))
        tau = np.where(x <= 0.0, 0.0, tau)
        dtau = np.where(x >= 1.0, 1.0, x3 * (6.0 * x2 - 15.0 * xi + 10.0))
        ddtau = 30.0 * x2 * (1.0 - xi) ** 2 / self.ramp
        return tau, dtau, ddtau

    # ------------------------------------------------------------------ evaluation

    def evaluate(self, t) -> TrajectoryState:
        """The exact state at times ``t`` (K,) (or a scalar: K = 1).

        Returns
        -------
        TrajectoryState
            ``world_T_imu`` (K,4,4), world ``velocity`` = P'(tau) tau' and ``acceleration`` =
            P''(tau) tau'^2 + P'(tau) tau'' (K,3), body ``angular_velocity`` = R^T omega_world (K,3) with
            omega_world = yaw_dot e_z + pitch_dot Rz(yaw) e_y + roll_dot Rz(yaw) Ry(pitch) e_x, and the
            ``angles`` (yaw, pitch, roll) and ``angle_rates`` (K,3).
        """
        t = np.asarray(t, dtype=float).reshape(-1)
        tau, dtau, ddtau = self.warp(t)
        P = np.stack([f.derivatives(tau, 3) for f in self.position], axis=-1)  # (3, K, 3): P, P', P''
        velocity = P[1] * dtau[:, None]
        acceleration = P[2] * (dtau * dtau)[:, None] + P[1] * ddtau[:, None]
        angles, rates = [], []  # values and d/dtau
        for f in (self.yaw, self.pitch, self.roll):
            d = f.derivatives(tau, 2)
            angles.append(d[0])
            rates.append(d[1])
        if self.attitude_follows_velocity:
            (vx, vy, vz), (ax, ay, az) = P[1].T, P[2].T
            rho2 = vx * vx + vy * vy
            rho = np.sqrt(rho2)
            if not np.all(rho > 0):
                raise ValueError(f"{self.name or 'trajectory'}: the heading is undefined where P' is vertical or zero")
            angles[0] = angles[0] + np.arctan2(vy, vx)
            rates[0] = rates[0] + (vx * ay - vy * ax) / rho2
            rho_dot = (vx * ax + vy * ay) / rho
            angles[1] = angles[1] - np.arctan2(vz, rho)
            rates[1] = rates[1] - (rho * az - vz * rho_dot) / (rho2 + vz * vz)
        angles = np.stack(angles, axis=-1)
        angle_rates = np.stack(rates, axis=-1) * dtau[:, None]
        yaw, pitch, roll = angles.T
        R = _rotation_zyx(yaw, pitch, roll)
        omega_world = _world_rate_zyx(yaw, pitch, *angle_rates.T)
        T = np.zeros((t.size, 4, 4))
        T[:, :3, :3] = R
        T[:, :3, 3] = P[0]
        T[:, 3, 3] = 1.0
        return TrajectoryState(t, T, velocity, acceleration, np.einsum("kji,kj->ki", R, omega_world), angles,
                               angle_rates)

    def world_T_imu(self, t) -> np.ndarray:
        """Poses (K,4,4) at times t (K,)."""
        return self.evaluate(t).world_T_imu

    def specific_force(self, t, gravity=GRAVITY) -> np.ndarray:
        """``R^T (a - g)`` (K,3) m/s^2 at times t (K,): what a perfect accelerometer reads."""
        s = self.evaluate(t)
        g = _gravity(gravity)
        return np.einsum("kji,kj->ki", s.rotation, s.acceleration - g)


def _gravity(gravity) -> np.ndarray:
    g = np.asarray(gravity, dtype=float).reshape(-1)
    if g.shape != (3,) or not np.all(np.isfinite(g)):
        raise ValueError(f"gravity must be 3 finite numbers, got {gravity!r}")
    return g


# ------------------------------------------------------------------------------------------- scenarios


def room(duration: float = 60.0, seed=0, *, start_at_rest: float | None = None,
         ramp: float = 2.0) -> InertialTrajectory:
    """A MAV flying in an 8 x 8 x 3 m room (like EuRoC's Vicon room, :data:`ROOM_BOX`).

    Position about the centre (0, 0, 1.5) m, per horizontal axis three sinusoids of amplitudes 1.8, 1.0,
    0.4 m and periods 15-25, 8-14, 4-8 s, vertically 0.6, 0.3 m over 8-16, 4-8 s; so it always stays in
    :data:`ROOM_FLIGHT_BOX` (|x|, |y| <= 3.3 m, 0.6 <= z <= 2.4 m: 0.6 m from walls, floor and ceiling).
    Roll and pitch each 16 deg over 6-12 s plus 6 deg over 2.5-5 s: |roll|, |pitch| <= 22 deg
    (:data:`ROOM_MAX_TILT`), and each reaches >= 10 deg once it has moved for 12 s (in 60 s, 19-22 deg).
    Yaw turns at a mean rate of 0.15-0.3 rad/s (random sign: 1.4-2.9 full turns a minute) plus 0.4-0.8 rad
    over 6-12 s. Measured over seeds 0-19, 60 s: top speed 1.5-2.2 m/s, top |a| 0.75-1.75 m/s^2, top
    |omega| 0.6-1.0 rad/s, top |yaw rate| 0.5-0.9 rad/s. All draws from ``generator(seed, "trajectory")``.

    Parameters
    ----------
    duration : float
        Seconds (> 0).
    seed : int or numpy.random.Generator
    start_at_rest : float or None
        Seconds at rest (hovering, attitude constant) at the start, then ``ramp`` seconds to come up to
        speed (:class:`InertialTrajectory`); None: moving from t = 0.
    ramp : float
        Seconds (> 0).
    """
    rng = generator(seed, "trajectory")
    horizontal = [(1.8, 15.0, 25.0), (1.0, 8.0, 14.0), (0.4, 4.0, 8.0)]
    position = (
        _random_sinusoids(rng, horizontal, offset=0.0),
        _random_sinusoids(rng, horizontal, offset=0.0),
        _random_sinusoids(rng, [(0.6, 8.0, 16.0), (0.3, 4.0, 8.0)], offset=1.5),
    )
    tilt = [(np.deg2rad(16.0), 6.0, 12.0), (np.deg2rad(6.0), 2.5, 5.0)]
    roll = _random_sinusoids(rng, tilt)
    pitch = _random_sinusoids(rng, tilt)
    yaw_rate = rng.uniform(0.15, 0.3) * rng.choice([-1.0, 1.0])
    yaw = _random_sinusoids(rng, [(rng.uniform(0.4, 0.8), 6.0, 12.0)], offset=rng.uniform(-np.pi, np.pi),
                            slope=yaw_rate)
    return InertialTrajectory(position, yaw, pitch, roll, duration, False, start_at_rest, ramp,
                              _name("room", seed))


def _phasors(V: float, speed: tuple, heading: list, tol: float = 1e-10):
    """Coefficients c_j and frequencies nu_j (rad/s) of ``z'(tau) = sum_j c_j exp(i nu_j tau)``, the truncated
    Jacobi-Anger expansion of the horizontal velocity ``s(tau) exp(i h(tau))`` (complex, x + i y) with speed
    ``s = V + b sin(W tau + psi)`` (``speed = (b, W, psi)``) and heading ``h = sum_m a_m sin(W_m tau + psi_m)``
    (``heading = [(a, W, psi), ...]``): ``exp(i a sin x) = sum_n J_n(a) exp(i n x)``. Terms below ``tol V``
    are dropped."""
    from scipy.special import jv

    coef, freq = np.array([1.0 + 0.0j]), np.array([0.0])
    n = np.arange(-30, 31)
    for a, W, psi in heading:
        c = jv(n, a) * np.exp(1j * n * psi)
        keep = np.abs(c) > tol
        coef = (coef[:, None] * c[keep]).reshape(-1)
        freq = (freq[:, None] + n[keep] * W).reshape(-1)
        keep = np.abs(coef) > tol
        coef, freq = coef[keep], freq[keep]
    b, W, psi = speed
    # s = V + (b / 2i) e^{i psi} e^{i W tau} - (b / 2i) e^{-i psi} e^{-i W tau}
    up, down = b / 2j * np.exp(1j * psi), -b / 2j * np.exp(-1j * psi)
    coef = np.concatenate([V * coef, up * coef, down * coef])
    freq = np.concatenate([freq, freq + W, freq - W])
    keep = np.abs(coef) > tol * V
    return coef[keep], freq[keep]


def _integrated(coef: np.ndarray, freq: np.ndarray) -> tuple[Sinusoids, Sinusoids]:
    """x(tau), y(tau) with x + i y = sum_j c_j (exp(i nu_j tau) - 1) / (i nu_j) (+ c_j tau when nu_j = 0):
    z(0) = 0 and z' = sum_j c_j exp(i nu_j tau). As sinusoids: x = sum |c|/nu sin(nu tau + arg c),
    y = sum |c|/nu sin(nu tau + arg c - pi/2), offsets making z(0) = 0."""
    still = np.abs(freq) < 1e-9
    slope = coef[still].sum()
    c, nu = coef[~still], freq[~still]
    A, phi = np.abs(c) / nu, np.angle(c)
    x = Sinusoids(-np.sum(A * np.sin(phi)), slope.real, A, nu, phi)
    y = Sinusoids(-np.sum(A * np.sin(phi - 0.5 * np.pi)), slope.imag, A, nu, phi - 0.5 * np.pi)
    return x, y


def street(duration: float = 60.0, seed=0, *, start_at_rest: float | None = None,
           ramp: float = 6.0) -> InertialTrajectory:
    """A car: planar-ish, its x axis along its velocity (``attitude_follows_velocity``), from the origin.

    The horizontal velocity is ``s(tau) exp(i h(tau))`` expanded exactly into phasors (Jacobi-Anger,
    terms below 1e-10 V dropped) and integrated in closed form, so the position is a sum of sinusoids
    plus a linear term: speed ``s = V + b sin(.)`` with V 8-9 m/s, b 2-3 m/s over 20-40 s (so 5-12 m/s);
    heading ``h = a1 sin(.) + a2 sin(.)`` with a1 0.5-0.9 rad over 50-90 s and a2 0.15-0.3 rad over 12-25 s
    (S-bends of up to +-69 deg about the x axis, yaw rate <= 0.27 rad/s, no loops). Height: 1 m over
    40-80 s plus 0.2 m over 10-20 s (grades of a few %); pitch = the climb angle plus 0.8 deg over 4-10 s
    and 0.3 deg over 1-3 s (|pitch| <= 4.3 deg); roll 1.5 deg over 4-10 s plus 0.5 deg over 1-3 s
    (|roll| <= 2 deg). Measured over seeds 0-19, 60 s: speed 5.3-11.7 m/s, top |a| 0.6-2.2 m/s^2, top
    |yaw rate| 0.07-0.23 rad/s, top |pitch| 1.7-3.5 deg. Draws from ``generator(seed, "trajectory")``.
    Parameters as :func:`room` (the default ramp, 6 s, brings the car from rest to 6-11 m/s at up to
    2-3.6 m/s^2).
    """
    rng = generator(seed, "trajectory")

    def term(a_min, a_max, period_min, period_max):
        return (rng.uniform(a_min, a_max), 2.0 * np.pi / rng.uniform(period_min, period_max),
                rng.uniform(0.0, 2.0 * np.pi))

    V = rng.uniform(8.0, 9.0)
    speed = term(2.0, 3.0, 20.0, 40.0)
    heading = [term(0.5, 0.9, 50.0, 90.0), term(0.15, 0.3, 12.0, 25.0)]
    coef, freq = _phasors(V, speed, heading)
    x, y = _integrated(coef, freq)
    z = _random_sinusoids(rng, [(1.0, 40.0, 80.0), (0.2, 10.0, 20.0)])
    z = Sinusoids(-z(np.zeros(1))[0], 0.0, z.amplitude, z.omega, z.phase)
    pitch = _random_sinusoids(rng, [(np.deg2rad(0.8), 4.0, 10.0), (np.deg2rad(0.3), 1.0, 3.0)])
    roll = _random_sinusoids(rng, [(np.deg2rad(1.5), 4.0, 10.0), (np.deg2rad(0.5), 1.0, 3.0)])
    return InertialTrajectory((x, y, z), Sinusoids(), pitch, roll, duration, True, start_at_rest, ramp,
                              _name("street", seed))


def _name(scenario: str, seed) -> str:
    return f"{scenario}:seed{int(seed)}" if not isinstance(seed, np.random.Generator) else scenario


INERTIAL_TRAJECTORIES = {"room": room, "street": street}


# ------------------------------------------------------------------------------------------- IMU samples


@dataclass(eq=False)
class InertialTruth:
    """The truth behind :func:`measure_imu`'s samples (L of them).

    ``noise_free`` holds the exact specific force ``R^T (a - g)`` and body rate (no bias, no noise) at the
    same stamps; ``accel_bias`` (m/s^2) and ``gyro_bias`` (rad/s) (L,3) the bias in each sample;
    ``world_T_imu`` (L,4,4) and ``velocity`` (L,3) the true states at the stamps; ``gravity`` (3,).
    So ``measured - noise_free - bias`` is the white noise.
    """

    noise_free: ImuSamples
    accel_bias: np.ndarray
    gyro_bias: np.ndarray
    world_T_imu: np.ndarray
    velocity: np.ndarray
    gravity: np.ndarray

    @property
    def time_stamps(self) -> np.ndarray:
        return self.noise_free.time_stamps


def _initial_bias(rng: np.random.Generator, magnitude: tuple, given, name: str) -> np.ndarray:
    drawn = rng.uniform(*magnitude, size=3) * rng.choice([-1.0, 1.0], size=3)  # drawn even when given
    if given is None:
        return drawn
    b = np.broadcast_to(np.asarray(given, dtype=float), (3,)).copy()
    if not np.all(np.isfinite(b)):
        raise ValueError(f"{name} must be finite (a number or 3 values), got {given!r}")
    return b


def _random_walk(rng: np.random.Generator, bias0: np.ndarray, steps: int, step_sigma: float) -> np.ndarray:
    """(steps,3): b[0] = bias0, b[k+1] = b[k] + step_sigma xi_k."""
    xi = rng.standard_normal((steps - 1, 3)) * step_sigma
    return bias0 + np.concatenate([np.zeros((1, 3)), np.cumsum(xi, axis=0)], axis=0)


def measure_imu(
    traj: InertialTrajectory,
    rate_hz: float = 200.0,
    duration: float | None = None,
    noise: ImuNoiseDensities | None = ADIS16448,
    gravity=GRAVITY,
    bias0_gyro=None,
    bias0_accel=None,
    seed=0,
    *,
    start: float = 0.0,
) -> tuple[ImuSamples, InertialTruth]:
    """The samples of a real IMU moving along ``traj``, and their truth.

    Stamps ``t_k = start + k / rate_hz``, k = 0 .. floor(duration rate_hz) (dt = 1 / rate_hz); at each

        a_m[k] = R_k^T (a_k - g) + b_a[k] + n_a[k],    n_a[k] ~ N(0, sigma_a^2 I)
        w_m[k] = omega_body_k + b_g[k] + n_g[k],       n_g[k] ~ N(0, sigma_g^2 I)
        sigma_a = accelerometer_noise_density / sqrt(dt),  sigma_g = gyroscope_noise_density / sqrt(dt)
        b_a[k+1] = b_a[k] + accelerometer_random_walk sqrt(dt) xi_k,   b_g likewise with gyroscope_random_walk

    Parameters
    ----------
    traj : InertialTrajectory
    rate_hz : float
        Sample rate (Hz, > 0).
    duration : float, optional
        Seconds covered from ``start`` (default ``traj.duration - start``).
    noise : ImuNoiseDensities or None
        Continuous-time densities in Kalibr's units (default EuRoC's ADIS16448); None (or zeros): no
        white noise and constant biases. Stored as the samples' ``noise``.
    gravity : array_like, shape (3,)
        g in the world frame (m/s^2).
    bias0_gyro, bias0_accel : array_like, shape (3,), optional
        Biases at the first sample (rad/s, m/s^2). None: drawn per axis with a magnitude uniform in
        :data:`GYRO_BIAS_RANGE` / :data:`ACCEL_BIAS_RANGE` and a random sign.
    seed : int or numpy.random.Generator
        Draws from ``generator(seed, "imu")`` in a fixed order (initial biases, white noise, bias walks),
        so giving a bias or changing the densities changes no other draw.
    start : float
        Stamp of the first sample (s).

    Returns
    -------
    samples : ImuSamples
        ``time_stamps`` (L,), ``linear_acceleration`` (L,3) specific force, ``angular_velocity`` (L,3).
    truth : InertialTruth
    """
    rate_hz, start = float(rate_hz), float(start)
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"rate_hz must be > 0, got {rate_hz!r}")
    if not np.isfinite(start):
        raise ValueError(f"start must be finite, got {start!r}")
    duration = traj.duration - start if duration is None else float(duration)
    if not (np.isfinite(duration) and duration > 0):
        raise ValueError(f"duration must be > 0 s, got {duration!r}")
    count = int(np.floor(duration * rate_hz + 1e-9)) + 1
    if count < 2:
        raise ValueError(f"{duration} s at {rate_hz} Hz is fewer than 2 samples")
    g = _gravity(gravity)
    t = start + np.arange(count) / rate_hz
    dt = 1.0 / rate_hz
    state = traj.evaluate(t)
    force = np.einsum("kji,kj->ki", state.rotation, state.acceleration - g)
    rate = state.angular_velocity

    densities = noise if noise is not None else ImuNoiseDensities(0.0, 0.0, 0.0, 0.0, source="noise-free")
    sigma = densities.discrete(dt)
    rng = generator(seed, "imu")
    b0_gyro = _initial_bias(rng, GYRO_BIAS_RANGE, bias0_gyro, "bias0_gyro")
    b0_accel = _initial_bias(rng, ACCEL_BIAS_RANGE, bias0_accel, "bias0_accel")
    white_accel = rng.standard_normal((count, 3)) * sigma["accelerometer"]
    white_gyro = rng.standard_normal((count, 3)) * sigma["gyroscope"]
    accel_bias = _random_walk(rng, b0_accel, count, sigma["accelerometer_bias_step"])
    gyro_bias = _random_walk(rng, b0_gyro, count, sigma["gyroscope_bias_step"])

    source = f"synthetic:{traj.name or 'trajectory'}:imu{rate_hz:g}Hz"
    samples = ImuSamples(t, force + accel_bias + white_accel, rate + gyro_bias + white_gyro, noise, source)
    truth = InertialTruth(ImuSamples(t.copy(), force, rate, None, source + ":noise-free"), accel_bias, gyro_bias,
                          state.world_T_imu, state.velocity, g)
    return samples, truth


# ------------------------------------------------------------------------------------------- camera frames


@dataclass(eq=False)
class FrameTruth:
    """True states at N camera frame stamps."""

    time_stamps: np.ndarray  # (N,) s
    world_T_imu: np.ndarray  # (N,4,4)
    velocity: np.ndarray  # (N,3) m/s, world frame
    angular_velocity: np.ndarray  # (N,3) rad/s, IMU frame

    @property
    def num_frames(self) -> int:
        return int(self.time_stamps.shape[0])


def frame_times(imu: ImuSamples | np.ndarray, rate_hz: float = 20.0) -> np.ndarray:
    """Camera stamps ``t_0 + j / rate_hz`` (N,), j = 0, 1, ... up to the last IMU stamp, t_0 the first one.

    ``imu`` is an ImuSamples or its stamps. When the IMU's stamps are ``t_0 + k / imu_rate`` (as
    :func:`measure_imu` makes them) and ``imu_rate / rate_hz`` is an integer, each frame stamp is exactly
    (bit for bit) an IMU stamp.
    """
    stamps = np.asarray(imu.time_stamps if isinstance(imu, ImuSamples) else imu, dtype=float).reshape(-1)
    rate_hz = float(rate_hz)
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"rate_hz must be > 0, got {rate_hz!r}")
    if stamps.size == 0:
        raise ValueError("no IMU stamps")
    t0 = stamps[0]
    count = int(np.floor((stamps[-1] - t0) * rate_hz + 1e-9)) + 1
    return t0 + np.arange(count) / rate_hz


def frame_truth(traj: InertialTrajectory, times) -> FrameTruth:
    """The true pose (N,4,4), world velocity (N,3) and body angular velocity (N,3) at ``times`` (N,)."""
    state = traj.evaluate(times)
    return FrameTruth(state.time, state.world_T_imu, state.velocity, state.angular_velocity)
