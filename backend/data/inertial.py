"""Samples of a real IMU (specific force and angular rate at their own rate) and its noise in Kalibr's units.

A real IMU gives, in its own frame, the specific force ``a_m = R^T (a - g) + b_a + n_a`` (m/s^2:
about +9.81 along the up axis at rest) and the angular rate ``w_m = w + b_g + n_g`` (rad/s), at
100-1000 Hz, never a velocity. :class:`ImuSamples` holds them with their stamps; its noise, when
known, is an :class:`ImuNoiseDensities` in Kalibr's continuous-time units (the names of Kalibr's
``imu.yaml`` and of EuRoC's ``sensor.yaml``):

==================================  =================  =================================
key                                 unit               meaning
==================================  =================  =================================
``accelerometer_noise_density``     m/s^2 / sqrt(Hz)   white noise n_a
``accelerometer_random_walk``       m/s^3 / sqrt(Hz)   the accelerometer bias's random walk
``gyroscope_noise_density``         rad/s / sqrt(Hz)   white noise n_g
``gyroscope_random_walk``           rad/s^2 / sqrt(Hz) the gyroscope bias's random walk
==================================  =================  =================================

Over a sample interval dt the white noise has standard deviation ``density / sqrt(dt)`` per
sample, the bias moves by ``random_walk * sqrt(dt)`` (:meth:`ImuNoiseDensities.discrete`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .sequence import check_numeric, check_shape, input_error

__all__ = ["ImuNoiseDensities", "ImuSamples", "KALIBR_KEYS", "ADIS16448", "check_imu_samples", "check_noise_densities"]

#: Kalibr's names of the four noise values, in the order of ImuNoiseDensities' fields
KALIBR_KEYS = ("accelerometer_noise_density", "accelerometer_random_walk",
               "gyroscope_noise_density", "gyroscope_random_walk")
#: Largest plausible IMU sample interval (s): slower records are not an IMU's own rate
MAX_IMU_STEP = 1.0


@dataclass(frozen=True)
class ImuNoiseDensities:
    """Continuous-time IMU noise in Kalibr's units (module docstring); ``source`` says where it came from."""

    accelerometer_noise_density: float  # m/s^2/sqrt(Hz)
    accelerometer_random_walk: float  # m/s^3/sqrt(Hz)
    gyroscope_noise_density: float  # rad/s/sqrt(Hz)
    gyroscope_random_walk: float  # rad/s^2/sqrt(Hz)
    source: str = ""

    def discrete(self, dt: float) -> dict[str, float]:
        """Per-sample standard deviations over a sample interval ``dt`` (s): white noise
        ``density / sqrt(dt)`` (m/s^2, rad/s) and the bias step ``random_walk * sqrt(dt)``."""
        r = 1.0 / np.sqrt(dt)
        return {"accelerometer": self.accelerometer_noise_density * r, "gyroscope": self.gyroscope_noise_density * r,
                "accelerometer_bias_step": self.accelerometer_random_walk * np.sqrt(dt),
                "gyroscope_bias_step": self.gyroscope_random_walk * np.sqrt(dt)}

    def as_dict(self) -> dict:
        out = {k: float(getattr(self, k)) for k in KALIBR_KEYS}
        out["source"] = self.source
        return out


#: The ADIS16448 of EuRoC's VI-Sensor, as its ``imu0/sensor.yaml`` gives it
ADIS16448 = ImuNoiseDensities(2.0e-3, 3.0e-3, 1.6968e-4, 1.9393e-5, source="ADIS16448 (EuRoC's sensor.yaml)")


def check_noise_densities(src: str, values: dict) -> ImuNoiseDensities:
    """An :class:`ImuNoiseDensities` from ``values`` (Kalibr's keys); each finite and > 0, else InputError."""
    out = []
    for key in KALIBR_KEYS:
        if key not in values:
            raise input_error(src, key, "missing (give all four of " + ", ".join(KALIBR_KEYS) + ")")
        a = check_numeric(src, key, np.asarray(values[key]))
        if a.size != 1:
            raise input_error(src, key, f"expected one number, got shape {a.shape}")
        v = float(a.reshape(()))
        if not v > 0:
            raise input_error(src, key, f"must be > 0, got {v:g}")
        out.append(v)
    return ImuNoiseDensities(*out, source=src)


@dataclass(eq=False)
class ImuSamples:
    """IMU samples in the IMU frame: ``time_stamps`` (L,) s strictly increasing, ``linear_acceleration``
    (L,3) specific force m/s^2, ``angular_velocity`` (L,3) rad/s; ``noise`` their densities if known."""

    time_stamps: np.ndarray
    linear_acceleration: np.ndarray
    angular_velocity: np.ndarray
    noise: ImuNoiseDensities | None = None
    source: str = ""

    @property
    def num_samples(self) -> int:
        return int(self.time_stamps.shape[0])

    @property
    def rate_hz(self) -> float:
        """The median sample rate."""
        return float(1.0 / np.median(np.diff(self.time_stamps)))

    def between(self, t0: float, t1: float) -> "ImuSamples":
        """The samples whose stamps lie in [t0, t1], plus the nearest one on each side when it exists
        (what integrating from t0 to t1 needs)."""
        t = self.time_stamps
        i0 = max(int(np.searchsorted(t, t0, side="right")) - 1, 0)
        i1 = min(int(np.searchsorted(t, t1, side="left")) + 1, t.size)
        return ImuSamples(t[i0:i1], self.linear_acceleration[i0:i1], self.angular_velocity[i0:i1], self.noise,
                          self.source)


def check_imu_samples(src: str, time_stamps, linear_acceleration, angular_velocity,
                      noise: ImuNoiseDensities | None = None,
                      keys=("imu_time_stamps", "imu_linear_acceleration", "imu_angular_velocity")) -> ImuSamples:
    """Validated :class:`ImuSamples` from arrays of shapes (L,), (L,3), (L,3) (or (1,L), (3,L), (3,L), the
    .npz layout's); one-line InputError naming ``src`` and the key otherwise. Stamps in seconds, strictly
    increasing, at least 2, no gap over MAX_IMU_STEP."""
    kt, ka, kw = keys
    t = check_numeric(src, kt, np.asarray(time_stamps))
    if t.ndim == 2 and t.shape[0] == 1:
        t = t[0]
    if t.ndim != 1:
        raise input_error(src, kt, f"expected shape (1,L) or (L,), got {t.shape}")
    L = t.shape[0]
    if L < 2:
        raise input_error(src, kt, f"need at least 2 IMU samples, got {L}")
    arrays = []
    for key, a in ((ka, linear_acceleration), (kw, angular_velocity)):
        a = check_numeric(src, key, np.asarray(a))
        if a.shape == (3, L) and L != 3:
            a = a.T
        check_shape(src, key, a, (L, 3), f"(3,{L}) or ({L},3)")
        arrays.append(np.ascontiguousarray(a, dtype=np.float64))
    steps = np.diff(t)
    bad = np.flatnonzero(~(steps > 0))
    if bad.size:
        i = int(bad[0]) + 1
        raise input_error(src, kt, f"IMU stamps not strictly increasing: [{i}] = {t[i]:.9g} <= [{i - 1}] = {t[i - 1]:.9g}")
    if np.median(steps) > MAX_IMU_STEP:
        raise input_error(src, kt, f"median IMU step {np.median(steps):.6g} s: not seconds, or not an IMU's own rate "
                                   "(stamps in nanoseconds? divide them by 1e9)")
    if steps.max() > MAX_IMU_STEP:
        i = int(np.argmax(steps)) + 1
        raise input_error(src, kt, f"a gap of {steps[i - 1]:.6g} s in the IMU record between samples {i - 1} and {i}")
    return ImuSamples(np.ascontiguousarray(t, dtype=np.float64), arrays[0], arrays[1], noise, src)
