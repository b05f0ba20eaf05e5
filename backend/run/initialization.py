"""The inertial state at the first frame: from the IMU at rest (Z1-Z5), or in motion from vision and
the IMU together (M1-M4).

At rest (v = 0, R constant) the samples of the first ``window`` seconds measure

    w_m = b_g + n_g,    a_m = R^T (-g) + b_a + n_a                                                (Z1)

so the mean rate is the gyro bias and the mean specific force points up in the IMU frame. The
world frame is gravity-aligned with the first pose at the origin and no yaw: its z axis is the
mean specific force's direction, its x axis the IMU's x axis projected on the horizontal plane
(any other yaw would do: it is unobservable).                                                     (Z2)

Rest is decided from the samples, by how far attitude and velocity wander: the integrals of
(w_m - mean) and (a_m - mean) over the window stay under ``max_attitude_wander_deg`` and
``max_velocity_wander`` (a vibrating rig at rest: EuRoC's before take-off wanders 0.06-0.19 deg
and 0.01-0.04 m/s in 1 s; hovering or turning, 1-5 deg); and, since an IMU cannot tell rest from
a constant velocity, from the images: vision cannot show the camera moving more than
``max_vision_translation`` or turning more than ``max_attitude_wander_deg`` between the first
frame and the last of the window, |t| - 3 sigma_t <= max and |r| - 3 sigma_r <= max (a two-view
fit, D2 of ``backend.run.two_view``: :func:`vision_motion`; EuRoC's before take-off: 3-5 mm, the
tracks 0.4-1.2 px; a car at 8 m/s: 8 m). Where too few tracks last the window, the fits of
successive frames are composed, T = T_K .. T_1, with the covariance of the left perturbation

    Sigma = sum_k Ad(T_K .. T_k+1) C_k Ad(T_K .. T_k+1)^T        (C_k: each fit's, independent)

(an upper bound: a frame's pixel noise enters two successive fits with opposite signs). The
velocity starts with the sigma max(wander, (|t| + sigma_t) / window): what the window allows.  (Z3)

The accelerometer bias's horizontal part cannot be told from a tilt at rest: a bias b tilts the
estimate by |b_horizontal| / g. The covariance says so: with the bias prior sigma_ba0 per axis,

    g^ phi = R_hat db_a   (to first order; rows x, y: phi_x = -(R db_a)_y / g, phi_y = (R db_a)_x / g)   (Z4)

so roll and pitch start with sigma_ba0 / g each and fully correlated with the bias; yaw and position
start at (nearly) zero uncertainty (the first pose defines them), the velocity at the measured
wander (Z3), the gyro bias at the standard error of its mean.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..data.inertial import ImuNoiseDensities, ImuSamples
from ..estimator.inertial import BA, BG, CORE_INERTIAL, NU, PHI, RHO, InertialMean, integrate_samples
from ..geometry.camera import StereoCamera

if TYPE_CHECKING:
    from .two_view import Tolerances

__all__ = ["RestOptions", "Initialization", "VisionMotion", "initialize_at_rest", "rest_test", "vision_motion",
           "MotionOptions",
           "initialize_in_motion", "initialize_in_motion_over"]


@dataclass(frozen=True)
class RestOptions:
    """Options of the initialization at rest (Z3, Z4)."""

    window: float = 1.0  # seconds of IMU after the first frame that are averaged
    min_window: float = 0.2  # fewer seconds than this: not tested
    max_attitude_wander_deg: float = 0.5  # Z3
    max_velocity_wander: float = 0.1  # m/s, Z3
    max_vision_translation: float = 0.02  # m, Z3: the camera's motion over the window seen by vision
    accel_bias_sigma0: float = 0.1  # m/s^2 per axis: the prior of the accelerometer bias (Z4)
    min_velocity_sigma0: float = 1e-3  # m/s: the velocity at rest is known to its measured wander (Z3), at least this
    pose_sigma0: float = 1e-6  # position (m) and yaw (rad): the frame is defined by the first pose


@dataclass(frozen=True)
class Initialization:
    """How the inertial state started (``how``: "at rest", Z1-Z5, or "in motion", M1-M4) and what was
    found; ``mean`` and ``covariance`` (15,15) of the core error state (J1) when ``ok``, else the
    ``reason``."""

    ok: bool
    reason: str
    mean: InertialMean | None = None
    covariance: np.ndarray | None = None
    measured: dict = field(default_factory=dict)
    how: str = "at rest"

    @property
    def at_rest(self) -> bool:
        """Started at rest (Z1-Z5)."""
        return self.ok and self.how == "at rest"

    def describe(self) -> str:
        m = self.measured
        if not self.ok:
            return f"inertial initialization: not {self.how} ({self.reason})"
        g = np.asarray(m["gravity_in_imu"])
        if self.how == "in motion":
            v = np.asarray(m["velocity"])
            return (f"inertial initialization: in motion from {m['frames']} frames over {m['window_s']:.2f} s (vision's "
                    f"poses against the IMU: rotation residual {m['rotation_residual_deg']:.3f} deg, gravity fitted "
                    f"{m['gravity_fit_norm']:.3f} m/s^2 long); up (minus gravity) in the IMU frame [{g[0]:+.4f}, {g[1]:+.4f}, "
                    f"{g[2]:+.4f}]; velocity [{v[0]:+.3f}, {v[1]:+.3f}, {v[2]:+.3f}] m/s; gyro bias "
                    f"[{', '.join(f'{x:+.5f}' for x in m['gyro_bias'])}] rad/s; roll and pitch +- "
                    f"{m['tilt_sigma_deg']:.2f} deg (the fit's and an accelerometer bias of "
                    f"{m['accel_bias_sigma0']:g} m/s^2)")
        seen = ""
        if "vision_translation" in m:
            how = "one fit" if m["vision_links"] == 1 else f"{m['vision_links']} successive fits chained"
            seen = (f"; vision: {1e3 * m['vision_translation']:.1f} +- {1e3 * m['vision_translation_sigma']:.1f} mm, "
                    f"{m['vision_rotation_deg']:.2f} +- {m['vision_rotation_sigma_deg']:.2f} deg ({how})")
        return (f"inertial initialization: at rest over {m['window_s']:.2f} s ({m['samples']} samples; attitude wander "
                f"{m['attitude_wander_deg']:.2f} deg, velocity wander {m['velocity_wander']:.3f} m/s{seen}); up (minus gravity) in the "
                f"IMU frame [{g[0]:+.4f}, {g[1]:+.4f}, {g[2]:+.4f}], |specific force| {m['specific_force']:.4f} m/s^2; "
                f"gyro bias [{', '.join(f'{x:+.5f}' for x in m['gyro_bias'])}] rad/s; roll and pitch +- "
                f"{m['tilt_sigma_deg']:.2f} deg (an accelerometer bias of {m['accel_bias_sigma0']:g} m/s^2 cannot be "
                "told from a tilt at rest)")

    def as_dict(self) -> dict:
        return {"how": self.how, "ok": self.ok, "reason": self.reason,
                **{k: (np.asarray(v).tolist() if isinstance(v, np.ndarray) else v) for k, v in self.measured.items()}}


@dataclass(frozen=True)
class VisionMotion:
    """The camera's motion between the first frame and the last of a window, seen by vision (Z3):
    ``translation`` (m) and ``rotation_deg`` of the two-view fit (``links`` 1) or of the successive
    frames' fits composed (``links`` of them), with the standard deviations of each (the largest of
    the covariance's translation and rotation blocks)."""

    translation: float
    rotation_deg: float
    translation_sigma: float
    rotation_sigma_deg: float
    links: int


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


#: Tracks a fit of two successive frames needs when fits are chained over the rest window (Z3): a
#: stereo two-view fit has 5 equations a point beyond its own 3 unknowns for 6 of motion
CHAIN_MIN_POINTS = 6


def _fit_frames(seq, a: int, b: int, Ia_R_Ib: np.ndarray, tolerance: Tolerances, min_points: int = 12):
    """The two-view fit (D2) of frames a and b, started from the gyro's rotation ``Ia_R_Ib`` (3,3) and a
    robust translation (:func:`_motion_guess`), on the tracks that agree with that start (gross
    mismatches, which an undamped fit can follow even from the right answer, left out), with the
    sequence's ``tolerance`` (``two_view.tolerances``); None when fewer than ``min_points`` remain or
    the fit fails."""
    from .two_view import fit_pair, matched_pixels

    K = seq.K
    cam = (K[0, 0], K[1, 1], K[0, 2], K[1, 2], seq.baseline)
    R_ic = np.asarray(seq.imu_T_cam, dtype=float)[:3, :3]
    za, zb = matched_pixels(seq, a, b)
    if za.shape[0] < min_points:
        return None
    guess, agree = _motion_guess(za, zb, cam, R_ic.T @ Ia_R_Ib.T @ R_ic)
    if agree.sum() < min_points:
        return None
    return fit_pair(za[agree], zb[agree], cam, min_points=min_points, step=a, gap=b - a, initial=guess,
                    tolerance=tolerance)


def vision_motion(seq, window: float, gyro_bias: np.ndarray) -> VisionMotion | None:
    """(Z3) the camera's motion between the first frame and the last one of the first ``window``
    seconds: the two-view fit of the two (D2, started from the gyro's rotation with ``gyro_bias``
    removed), or where too few tracks last that long, the fits of successive frames composed (each
    on at least ``CHAIN_MIN_POINTS`` tracks), with their covariance (module docstring); None when
    neither can be fitted."""
    from ..geometry import se3
    from .two_view import tolerances

    t = seq.time_stamps
    last = int(np.searchsorted(t, t[0] + window, side="right")) - 1
    if last < 1:
        return None
    R = integrate_samples(seq.imu, t[:last + 1], gyro_bias)[0]
    tolerance = tolerances(seq.obs_pixels)
    direct = _fit_frames(seq, 0, last, R[last], tolerance)
    if direct is not None:
        T, cov, links = direct.b_T_a, direct.motion_covariance, 1
    else:
        T, cov, links = np.eye(4), np.zeros((6, 6)), last
        for k in range(1, last + 1):
            step = _fit_frames(seq, k - 1, k, R[k - 1].T @ R[k], tolerance, CHAIN_MIN_POINTS)
            if step is None:
                return None
            A = se3.adjoint(step.b_T_a)  # the chain so far seen through this link (left perturbations)
            cov = A @ cov @ A.T + step.motion_covariance
            T = step.b_T_a @ T
    return VisionMotion(float(np.linalg.norm(T[:3, 3])), float(np.degrees(np.linalg.norm(se3.log_so3(T[:3, :3])))),
                        float(np.sqrt(np.linalg.eigvalsh(cov[:3, :3])[-1])),
                        float(np.degrees(np.sqrt(np.linalg.eigvalsh(cov[3:, 3:])[-1]))), links)


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
                       options: RestOptions = RestOptions(), seen=False) -> Initialization:
    """(Z1-Z5) the inertial state at ``t0`` (the first frame) if the IMU is at rest over the window
    after it and vision agrees: ``seen`` is :func:`vision_motion` of the window (None where it could
    not be fitted, False: no images); else an :class:`Initialization` with ``at_rest`` False and the
    reason."""
    m = rest_test(imu, t0, options.window)
    if seen is not False:
        if seen is None:
            return Initialization(False, "vision cannot fit the first frame to the last of the first "
                                         f"{options.window:g} s (the scene changed)", measured=m)
        m.update(vision_translation=seen.translation, vision_rotation_deg=seen.rotation_deg,
                 vision_translation_sigma=seen.translation_sigma, vision_rotation_sigma_deg=seen.rotation_sigma_deg,
                 vision_links=seen.links)
        if (seen.translation - 3.0 * seen.translation_sigma > options.max_vision_translation
                or seen.rotation_deg - 3.0 * seen.rotation_sigma_deg > options.max_attitude_wander_deg):
            return Initialization(False, f"vision sees the camera move {seen.translation:.3f} +- "
                                         f"{seen.translation_sigma:.3f} m and turn {seen.rotation_deg:.2f} +- "
                                         f"{seen.rotation_sigma_deg:.2f} deg in the first {options.window:g} s (at most "
                                         f"{options.max_vision_translation:g} m, {options.max_attitude_wander_deg:g} deg "
                                         f"within 3 sigma)", measured=m)
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
    P = _first_pose_and_bias_prior(R, g, options.accel_bias_sigma0, options.pose_sigma0)
    moved = (m.get("vision_translation", 0.0) + m.get("vision_translation_sigma", 0.0)) / max(m["window_s"], 1e-9)  # (Z3)
    P[NU, NU] = np.eye(3) * max(m["velocity_wander"], moved, options.min_velocity_sigma0) ** 2
    se = m["gyro_se"]
    if noise is not None:  # the white noise's share when the vibration is smaller than it (never on a real rig)
        se = np.maximum(se, noise.gyroscope_noise_density / np.sqrt(max(m["window_s"], 1e-9)))
    P[BG, BG] = np.diag(se**2)
    m.update(gravity_in_imu=m["accel_mean"] / np.linalg.norm(m["accel_mean"]),
             specific_force=float(np.linalg.norm(m["accel_mean"])), gyro_bias=m["gyro_mean"],
             tilt_sigma_deg=float(np.degrees(options.accel_bias_sigma0 / g)), accel_bias_sigma0=options.accel_bias_sigma0)
    return Initialization(True, "", mean, 0.5 * (P + P.T), m)


def _first_pose_and_bias_prior(R: np.ndarray, g: float, accel_bias_sigma0: float, pose_sigma0: float) -> np.ndarray:
    """The core covariance (15,15) of (J1) a start shares, at rest (Z4) or in motion (M4): the
    first position and yaw known to ``pose_sigma0`` (they define the frame), and the accelerometer
    bias db_a ~ N(0, s^2 I), s = ``accel_bias_sigma0``, which the attitude R (3,3) cannot tell from a
    tilt: phi = C db_a for roll and pitch with C = [-R[1]; R[0]; 0] / |g|."""
    P = np.zeros((CORE_INERTIAL, CORE_INERTIAL))
    P[RHO, RHO] = np.eye(3) * pose_sigma0**2
    s2 = accel_bias_sigma0**2
    C = np.zeros((3, 3))
    C[0] = -R[1] / g
    C[1] = R[0] / g
    P[PHI, PHI] = s2 * C @ C.T
    P[5, 5] += pose_sigma0**2  # yaw
    P[PHI, BA] = s2 * C
    P[BA, PHI] = s2 * C.T
    P[BA, BA] = np.eye(3) * s2
    return P


# ------------------------------------------------------------------------------------------ in motion
@dataclass(frozen=True)
class MotionOptions:
    """Options of the initialization in motion (M1-M4)."""

    window: float = 1.0  # seconds of frames after the first one
    min_frames: int = 5  # at least this many frame pairs chained
    min_points: int = 12  # points of a two-view fit
    accel_bias_sigma0: float = RestOptions.accel_bias_sigma0  # the same accelerometer bias prior (Z4)
    pose_sigma0: float = RestOptions.pose_sigma0  # the same first pose: it defines the frame
    max_gravity_misfit: float = 0.1  # refuse when the fitted gravity's length is off by more than this share
    max_rotation_residual_deg: float = 0.5  # ... or vision's rotations and the gyro's differ by more (RMS)
    max_tilt_sigma_deg: float = 2.0  # a longer window while gravity's direction is more uncertain than this


def _motion_guess(za: np.ndarray, zb: np.ndarray, cam, b_R_a: np.ndarray, inlier_px: float = 10.0):
    """(a camera motion b_T_a (4,4) to start a two-view fit from, the matches (n,) bool it agrees with):
    for motions too large to start from none. The rotation ``b_R_a`` (3,3) is the gyro's; the
    translation the weighted median over the matched stereo points of Pb - b_R_a Pa per axis (weights
    disparity^4, a triangulated depth's inverse variance, capped at the upper quartile's: the
    disparity of a gross mismatch can be any), or no translation where more points agree with that;
    the points of frame a it moves within ``inlier_px`` of their pixels in frame b (uL, vL, uR) are the
    matches kept (gross mismatches, which an undamped fit from a good start can still follow, are left
    out)."""
    fx, fy, cx, cy, b = cam
    camera = StereoCamera(np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), b)
    da, db = za[:, 0] - za[:, 2], zb[:, 0] - zb[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        Pa, Pb = camera.triangulate(za), camera.triangulate(zb)
    ok = (da > 0) & (db > 0) & np.isfinite(Pa).all(axis=1) & np.isfinite(Pb).all(axis=1)
    T = np.eye(4)
    T[:3, :3] = b_R_a
    if ok.sum() < 3:
        return T, ok
    t = Pb[ok] - Pa[ok] @ b_R_a.T
    d = np.minimum(da[ok], db[ok])
    w = np.minimum(d, np.quantile(d, 0.75)) ** 4  # capped: one gross mismatch of a large disparity cannot outweigh the rest
    for axis in range(3):
        order = np.argsort(t[:, axis])
        cum = np.cumsum(w[order])
        T[axis, 3] = t[order[np.searchsorted(cum, 0.5 * cum[-1])], axis]
    best = None
    for translation in (T[:3, 3].copy(), np.zeros(3)):  # the median, or none (at rest few far points mislead it)
        q = Pa @ b_R_a.T + translation
        with np.errstate(divide="ignore", invalid="ignore"):
            iz = 1.0 / q[:, 2]
            err = np.maximum.reduce([np.abs(fx * q[:, 0] * iz + cx - zb[:, 0]),
                                     np.abs(fy * q[:, 1] * iz + cy - zb[:, 1]),
                                     np.abs(fx * (q[:, 0] - b) * iz + cx - zb[:, 2])])
        agree = ok & (q[:, 2] > 0) & (err <= inlier_px)
        if best is None or agree.sum() > best[1].sum():
            best = (translation, agree)
    T[:3, 3] = best[0]
    return T, best[1]


def _chain_vision(seq, frames: range, min_points: int, imu_rotations: np.ndarray, max_skip: int = 3):
    """(M1) the frames chained (a list of indices, the first one first), the IMU poses I0_T_Ik (K,4,4)
    of those frames relative to the first and the covariance (K,6,6) of each position-and-rotation
    (summed along the chain), from two-view fits of successive frames (:func:`_fit_frames`; stereo
    gives the metric scale), each started from the gyro's rotation ``imu_rotations`` (one per frame of
    ``frames``, I0_R_Ik); a frame that cannot be fitted to the last chained one is skipped (at most
    ``max_skip`` in a row); (None, None, None) when the chain breaks."""
    from .two_view import tolerances

    tolerance = tolerances(seq.obs_pixels)
    imu_T_cam = np.asarray(seq.imu_T_cam, dtype=float)
    cam_T_imu = np.linalg.inv(imu_T_cam)
    R_ic = imu_T_cam[:3, :3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3], Ad[3:, 3:] = R_ic, R_ic
    used, poses, covs = [frames[0]], [np.eye(4)], [np.zeros((6, 6))]
    a = frames[0]
    while a < frames[-1]:
        fit = None
        for b in range(a + 1, min(a + 1 + max_skip, frames[-1] + 1)):
            fit = _fit_frames(seq, a, b, imu_rotations[a - frames[0]].T @ imu_rotations[b - frames[0]], tolerance,
                              min_points)
            if fit is not None:
                break
        if fit is None:
            return None, None, None
        step = imu_T_cam @ np.linalg.inv(fit.b_T_a) @ cam_T_imu  # Ia_T_Ib
        poses.append(poses[-1] @ step)
        Rw = poses[-1][:3, :3]  # the step's perturbation is in frame Ib (a right perturbation of Ia_T_Ib)
        Aw = np.zeros((6, 6))
        Aw[:3, :3], Aw[3:, 3:] = Rw, Rw
        covs.append(covs[-1] + Aw @ Ad @ fit.motion_covariance @ Ad.T @ Aw.T)
        used.append(b)
        a = b
    return used, np.array(poses), np.array(covs)


def initialize_in_motion(seq, gravity: np.ndarray, noise: ImuNoiseDensities | None = None,
                         options: MotionOptions = MotionOptions()) -> Initialization:
    """:func:`initialize_in_motion_over` the first ``options.window`` seconds, then twice and three times
    that while gravity's direction stays more uncertain than ``options.max_tilt_sigma_deg`` (a fast,
    straight start: vision's positions over 1 s barely tell gravity from a velocity); the last try's
    outcome, refused (``ok`` False) if still too uncertain: a filter started that far from the truth
    would not be consistent."""
    out = None
    for factor in (1.0, 2.0, 3.0):
        out = initialize_in_motion_over(seq, gravity, noise, dataclasses.replace(options, window=factor * options.window))
        if out.ok and out.measured["tilt_sigma_deg"] <= options.max_tilt_sigma_deg:
            return out
        if not out.ok and _window_end(seq.time_stamps, factor * options.window, options) > seq.num_steps:
            break  # the sequence is too short for this window, let alone a longer one
    if out.ok:
        return Initialization(False, f"gravity's direction stays uncertain by +- {out.measured['tilt_sigma_deg']:.1f} deg "
                                     f"over {out.measured['window_s']:.1f} s of frames (at most "
                                     f"{options.max_tilt_sigma_deg:g})", measured=out.measured, how="in motion")
    return out


def _window_end(t: np.ndarray, window: float, options: MotionOptions) -> int:
    """The frames (from the first) a start in motion over ``window`` seconds of stamps ``t`` uses."""
    return max(int(np.searchsorted(t, t[0] + window, side="right")), options.min_frames + 1)


def initialize_in_motion_over(seq, gravity: np.ndarray, noise: ImuNoiseDensities | None = None,
                              options: MotionOptions = MotionOptions()) -> Initialization:
    """The inertial state at the first frame of the inertial sequence ``seq`` while it moves:

    (M1) vision: the IMU poses I0_T_Ik of the frames of the first ``window`` seconds, chained from
    two-view fits of consecutive frames (metric from stereo);
    (M2) the gyro bias b_g: Gauss-Newton on  log(R_imu,k(b_g)^T R_vis,k) = 0  over those frames, R_imu,k
    the rotation integrated from the samples (J3); its covariance from the last frame's rotation
    covariance (the chain's errors are correlated: the fit's scatter would understate it);
    (M3) gravity g0 and velocity v0 in the first IMU frame: with the samples integrated from rest
    without gravity (positions dp_k), the positions seen by vision are p_k = v0 t_k + g0 t_k^2 / 2 + dp_k,
    linear in (v0, g0): generalized least squares with the chain's covariance (independent increments:
    Cov(p_j, p_k) = Sigma_min(j,k)), then v0 again with |g0| = |g|;
    (M4) the world: up = -g0 (Z2), the velocity in it, the covariance of (v0, g0) from the fit, the
    accelerometer bias's tilt correlation as at rest (Z4: a constant bias is a gravity error).
    Returns ``at_rest`` False with the reason when vision cannot carry the window."""

    imu = seq.imu
    t = seq.time_stamps
    last = _window_end(t, options.window, options)
    if last > seq.num_steps:
        return Initialization(False, f"{seq.num_steps} frames, {options.min_frames + 1} needed to start in motion",
                              how="in motion")

    frames, poses, covs = _chain_vision(seq, range(0, last), options.min_points,
                                        integrate_samples(imu, t[:last], np.zeros(3))[0])
    if frames is None:
        return Initialization(False, "vision cannot follow the first frames (no two-view fit with "
                                     f"{options.min_points} points within 3 frames)", how="in motion")
    # (M2) the gyro bias, Gauss-Newton with a numerical Jacobian (3 unknowns)
    from ..geometry import se3

    bg = np.zeros(3)
    R_vis = poses[:, :3, :3]

    def rot_residual(b):
        Rs, _, _ = integrate_samples(imu, t[list(frames)], b)
        return np.concatenate([se3.log_so3(Rs[k].T @ R_vis[k]) for k in range(1, len(frames))])

    for _ in range(3):
        r0 = rot_residual(bg)
        J = np.stack([(rot_residual(bg + e) - r0) / 1e-4 for e in np.eye(3) * 1e-4], axis=1)
        step = np.linalg.lstsq(J, -r0, rcond=None)[0]
        bg = bg + step
        if np.abs(step).max() < 1e-7:
            break
    r_rot = rot_residual(bg)
    # its covariance from the last frame's rotation alone: the chain's errors are correlated (each frame's
    # pixel noise enters two fits), so the residuals' scatter about the fitted slope would understate it
    J_end = J[-3:]
    J_inv = np.linalg.inv(J_end)
    R_end = R_vis[-1]  # the residual log(R_imu^T R_vis) is in the last frame's body axes
    bg_cov = J_inv @ (R_end.T @ covs[-1][3:, 3:] @ R_end) @ J_inv.T
    # (M3) gravity and velocity in the first IMU frame
    Rs, dp, _ = integrate_samples(imu, t[list(frames)], bg)  # from I0, zero velocity, no gravity
    tk = t[list(frames)] - t[0]
    n = len(frames) - 1
    A = np.zeros((3 * n, 6))
    y = np.zeros(3 * n)
    C = np.zeros((3 * n, 3 * n))  # the chain's positions: independent increments, Cov(p_j, p_k) = Sigma_min(j,k)
    for i, k in enumerate(range(1, len(frames))):
        A[3 * i:3 * i + 3, :3] = np.eye(3) * tk[k]
        A[3 * i:3 * i + 3, 3:] = np.eye(3) * 0.5 * tk[k] ** 2
        y[3 * i:3 * i + 3] = poses[k, :3, 3] - dp[k]
        for j in range(i + 1):
            C[3 * i:3 * i + 3, 3 * j:3 * j + 3] = covs[j + 1][:3, :3]
            C[3 * j:3 * j + 3, 3 * i:3 * i + 3] = covs[j + 1][:3, :3]
    L = np.linalg.cholesky(C + 1e-12 * np.eye(3 * n))
    Aw = np.linalg.solve(L, A)  # generalized least squares, whitened
    yw = np.linalg.solve(L, y)
    x, *_ = np.linalg.lstsq(Aw, yw, rcond=None)
    resid = yw - Aw @ x
    scale = max(float(resid @ resid) / max(resid.size - 6, 1), 1.0)  # the fit's own scatter, never below vision's
    x_cov = np.linalg.inv(Aw.T @ Aw) * scale
    g_norm = float(np.linalg.norm(gravity))
    fitted = float(np.linalg.norm(x[3:]))
    rot_rms = float(np.degrees(np.sqrt(np.mean(r_rot**2))))
    if abs(fitted - g_norm) > options.max_gravity_misfit * g_norm or rot_rms > options.max_rotation_residual_deg:
        return Initialization(False, f"vision's first {tk[-1]:.2f} s and the IMU disagree: gravity fitted {fitted:.2f} "
                                     f"m/s^2 long (|g| = {g_norm:g}), rotations {rot_rms:.3f} deg apart after the gyro "
                                     "bias", how="in motion")
    g0 = x[3:] * g_norm / fitted
    v0 = np.linalg.lstsq(Aw[:, :3], np.linalg.solve(L, y - A[:, 3:] @ g0), rcond=None)[0]
    # (M4) the world and the covariance
    R = gravity_aligned_rotation(-g0)
    T = np.eye(4)
    T[:3, :3] = R
    mean = InertialMean(T, R @ v0, bg, np.zeros(3))
    P = _first_pose_and_bias_prior(R, g_norm, options.accel_bias_sigma0, options.pose_sigma0)
    P[NU, NU] = R @ x_cov[:3, :3] @ R.T
    P[BG, BG] = bg_cov
    s2 = options.accel_bias_sigma0**2
    # the gravity direction's own uncertainty from the fit, projected on roll and pitch (world frame)
    G = R @ x_cov[3:, 3:] @ R.T / g_norm**2
    tilt = np.zeros((3, 3))
    tilt[:2, :2] = [[G[1, 1], -G[1, 0]], [-G[0, 1], G[0, 0]]]
    P[PHI, PHI] += tilt
    # the fit's velocity and gravity errors are correlated (p = v0 t + g0 t^2/2): with nu = -R e_v and
    # phi = -M R e_g / |g| (M e = e_z x e, the tilt a gravity error makes), Cov(nu, phi) = R C_vg R^T M^T / |g|
    M = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    P[NU, PHI] = R @ x_cov[:3, 3:] @ R.T @ M.T / g_norm
    P[PHI, NU] = P[NU, PHI].T
    up = -g0 / g_norm
    measured = {"frames": len(frames), "window_s": float(tk[-1]), "gravity_in_imu": up, "gyro_bias": bg,
                "velocity": R @ v0, "speed": float(np.linalg.norm(v0)),
                "gravity_fit_norm": float(np.linalg.norm(x[3:])),
                "rotation_residual_deg": rot_rms,
                "tilt_sigma_deg": float(np.degrees(np.sqrt(s2 / g_norm**2 + np.trace(G[:2, :2]) / 2))),
                "accel_bias_sigma0": options.accel_bias_sigma0}
    return Initialization(True, "", mean, 0.5 * (P + P.T), measured, how="in motion")
