"""The stereo pair's disparity offset, identified from the tracks rather than assumed zero.

A rectified pair whose right image is offset (a principal-point difference after rectification)
or exposed a few milliseconds apart from the left one (the rig turns between the two exposures)
measures every disparity off by an amount the calibration does not say. On a highway, where
most points have a disparity of 5-10 px, 1 px of it makes every depth 10-20 % too long, and the
filter's scale with it. The model, per step k,

    d_measured = d_true + beta_k,    beta_k = beta_0 + kappa * omega_y(k)                       (D1)

with ``omega_y`` the angular rate about the camera's y axis (rad/s; from the IMU through
``cam_T_imu``): ``beta_0`` (px) a constant offset, ``kappa = fx dt`` (px s/rad) the first-order
effect of a right image exposed ``dt`` seconds after the left one while the rig turns.

Identification, from vision alone (no IMU translation, no ground truth): for a spread of steps,
a two-view bundle adjustment of the points seen at k and k+1: each point's true (u, v, disparity)
at k, the free rigid motion k -> k+1 and ``beta_k`` minimize the robust (Huber, 1 px) error of
all eight measured pixels (both images, both frames; Gauss-Newton, points eliminated by the
Schur complement); pairs whose rows disagree are left out, and after a first fit the points
with a residual beyond ``TRIM_PX`` are dropped and the fit repeated (gross mismatches)           (D2)

A wrong offset warps depth non-uniformly (``z = fx b / (d - beta)``), which no rigid motion
explains; so ``beta_k`` is observable where the step's points span a range of disparities.
Then ``beta_k`` is regressed on ``omega_y(k)`` with weights ``1 / var(beta_k)`` and a
Huber-reweighted fit                                                                             (D3)

``conventions.stereo_offset = "constant"`` (the default) removes the weighted mean of ``beta_k``
when it differs from 0 by more than ``SIGNIFICANCE`` standard errors and ``MIN_EFFECT_PX``;
``"rate"`` removes ``beta_0 + kappa omega_y`` when ``kappa`` is significant likewise (at the
drive's spread of rates), else the constant; ``"off"`` estimates nothing. Both terms are always
estimated and reported. The constant is the default because it is what the data supports: on
KITTI 01 (frames 0-50, one steady turn) and KITTI-360 (03) the offset is a constant (-1.4 and
-0.56 px; on 03 dead reckoning's own reprojection test has its best offset at -0.6 to -0.75 px),
while the rate term found on KITTI 07 (ece276a_0027, 4-6 standard errors) made the estimate worse
over six draws of its velocity noise (BENCHMARKS.md). The run removes an offset only if the
IMU does not contradict it (``backend.run.runner.checked_offset``: dead reckoning's reprojection
test C1 must not get worse). The correction moves the right pixel: ``uR <- uR + beta_k``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..data.sequence import Sequence
from ..geometry import se3

__all__ = ["StereoOffset", "identify_stereo_offset", "camera_rate_y"]

#: A term is applied when its estimate exceeds this many standard errors (``auto``).
SIGNIFICANCE = 4.0
#: ... and changes a disparity by more than this (px) at the drive's rates: below it a correction is immaterial.
MIN_EFFECT_PX = 0.05
#: At most this many steps enter the identification (spread evenly over the sequence).
MAX_STEPS = 300
#: The offset is estimated from at least this many step pairs, else not at all.
MIN_STEPS = 10
#: A step needs this many points seen at k and k+1 with a disparity above MIN_DISPARITY.
MIN_POINTS = 12
MIN_DISPARITY = 1.0
#: Huber threshold (px) of the per-step fit.
HUBER_PX = 1.0
#: A pair is used only if its rows agree within this (px) in both frames ...
ROW_PX = 2.0
#: ... and, after a first fit, every one of its eight residuals is within this (px).
TRIM_PX = 3.0


@dataclass
class StereoOffset:
    """The disparity offset model (D1) applied to a run, with the numbers behind it."""

    beta0_px: float = 0.0  # applied constant offset
    kappa_px_s: float = 0.0  # applied px per rad/s of omega_y
    estimate: dict = field(default_factory=dict)  # beta0, kappa with their standard errors, steps used
    source: str = "off"  # "auto, constant" | "auto, rate" | "off"

    @property
    def active(self) -> bool:
        return self.beta0_px != 0.0 or self.kappa_px_s != 0.0

    def offsets(self, omega_y: np.ndarray | float) -> np.ndarray | float:
        """beta_k (px) for camera-y angular rates ``omega_y`` (rad/s)  (D1)."""
        return self.beta0_px + self.kappa_px_s * omega_y

    def correct(self, pixels: np.ndarray, omega_y: float) -> np.ndarray:
        """Pixels (n,4) with the right column moved by beta_k: d_true = d_measured - beta_k."""
        if not self.active or pixels.shape[0] == 0:
            return pixels
        out = np.array(pixels, dtype=float, copy=True)
        out[:, 2] += self.offsets(omega_y)
        return out

    def corrected(self, seq: Sequence, imu_T_cam: np.ndarray) -> Sequence:
        """``seq`` with every step's right pixels moved by its beta_k (D1)."""
        if not self.active:
            return seq
        omega = camera_rate_y(seq.angular_velocity, imu_T_cam)
        pixels = seq.obs_pixels.copy()
        pixels[:, 2] += np.repeat(self.offsets(omega), np.diff(seq.obs_ptr))
        return dataclasses.replace(seq, obs_pixels=pixels)

    def as_dict(self) -> dict:
        return {"beta0_px": self.beta0_px, "kappa_px_per_rad_s": self.kappa_px_s, "decided_by": self.source,
                "estimate": self.estimate}

    def describe(self) -> str:
        e = self.estimate
        if self.source == "off" and not e:
            return "stereo disparity offset: not estimated (conventions.stereo_offset = off)"
        if "rejected" in e:
            return f"stereo disparity offset: none applied ({self.source}; {e['rejected']})"
        if "beta_mean_px" not in e:
            return (f"stereo disparity offset: not identifiable ({e.get('steps', 0)} step pairs with enough points seen "
                    f"at k and k+1, {MIN_STEPS} needed); none applied")
        fx = e.get("fx", 1.0)
        found = f"mean {e['beta_mean_px']:+.2f} +- {e['beta_mean_se']:.2f} px"
        if np.isfinite(e["kappa_se"]):
            found += (f"; beta_0 {e['beta0_px']:+.2f} +- {e['beta0_se']:.2f} px, kappa {e['kappa_px_s']:+.2f} +- "
                      f"{e['kappa_se']:.2f} px s/rad (a right exposure {1e3 * e['kappa_px_s'] / fx:+.2f} ms after the left)")
        found += f"; {e['steps']} steps"
        if not self.active:
            return f"stereo disparity offset: none applied ({self.source}; estimated {found})"
        if self.kappa_px_s == 0.0:
            b = self.beta0_px
            applied = f"the pair measures disparities {abs(b):.2f} px {'short' if b < 0 else 'long'}: d_true = d {-b:+.2f} px"
        else:
            applied = f"d_true = d - ({self.beta0_px:+.2f} px {self.kappa_px_s:+.2f} px s/rad * omega_y)"
        return f"stereo disparity offset removed ({self.source}): {applied}; estimated {found}"


def camera_rate_y(angular_velocity: np.ndarray, imu_T_cam: np.ndarray) -> np.ndarray:
    """omega about the camera's y axis (N,) from IMU-frame angular rates (N,3): R_cam_imu w."""
    R_cam_imu = np.asarray(imu_T_cam, dtype=float)[:3, :3].T
    return np.asarray(angular_velocity, dtype=float).reshape(-1, 3) @ R_cam_imu[1]


def _predict(T: np.ndarray, beta: float, p: np.ndarray, cam, jacobians: bool = False):
    """Predicted pixels (n,8), ``uL vL uR vR`` at k then at k+1, of the points ``p`` (n,3) = (u, v,
    true disparity) at k moved by ``T`` (4,4, camera k -> k+1) and seen with the offset ``beta``
    (D1-D2). With ``jacobians``: also d/dp (n,8,3) and d/d(delta, beta) (n,8,7), where
    ``T <- exp(delta^) T``, ``delta = (rho, phi)`` (so dq/drho = I, dq/dphi = -q^)."""
    fx, fy, cx, cy, baseline = cam
    fb = fx * baseline
    n = p.shape[0]
    depth = fb / p[:, 2]
    x = np.stack([(p[:, 0] - cx) * depth / fx, (p[:, 1] - cy) * depth / fy, depth], axis=1)
    q = x @ T[:3, :3].T + T[:3, 3]
    z = np.maximum(q[:, 2], 1e-6)
    u = fx * q[:, 0] / z + cx
    v = fy * q[:, 1] / z + cy
    pred = np.stack([p[:, 0], p[:, 1], p[:, 0] - p[:, 2] - beta, p[:, 1],
                     u, v, u - fb / z - beta, v], axis=1)
    if not jacobians:
        return pred
    Jp = np.zeros((n, 8, 3))
    Jp[:, 0, 0] = Jp[:, 2, 0] = 1.0
    Jp[:, 1, 1] = Jp[:, 3, 1] = 1.0
    Jp[:, 2, 2] = -1.0
    # d pi / d q for the rows uL, vL, uR, vR at k+1
    iz = 1.0 / z
    P = np.zeros((n, 4, 3))
    P[:, 0, 0] = P[:, 2, 0] = fx * iz
    P[:, 0, 2] = -fx * q[:, 0] * iz * iz
    P[:, 2, 2] = P[:, 0, 2] + fb * iz * iz
    P[:, 1, 1] = P[:, 3, 1] = fy * iz
    P[:, 1, 2] = P[:, 3, 2] = -fy * q[:, 1] * iz * iz
    dx_dp = np.zeros((n, 3, 3))
    dx_dp[:, 0, 0] = depth / fx
    dx_dp[:, 1, 1] = depth / fy
    dx_dp[:, :, 2] = -x / p[:, 2:3]
    Jp[:, 4:, :] = P @ (T[:3, :3] @ dx_dp)
    Jg = np.zeros((n, 8, 7))
    Jg[:, 4:, 0:3] = P
    hat = np.zeros((n, 3, 3))
    hat[:, 0, 1], hat[:, 0, 2], hat[:, 1, 2] = -q[:, 2], q[:, 1], -q[:, 0]
    hat[:, 1, 0], hat[:, 2, 0], hat[:, 2, 1] = q[:, 2], -q[:, 1], q[:, 0]
    Jg[:, 4:, 3:6] = -P @ hat
    Jg[:, 2, 6] = Jg[:, 6, 6] = -1.0
    return pred, Jp, Jg


def _fit_step(za: np.ndarray, zb: np.ndarray, cam) -> tuple[float, float] | None:
    """(beta_k, its variance) of one step pair, or None (D2): :func:`_bundle_adjust` of the pairs
    whose rows agree (|vL - vR| <= ``ROW_PX`` in both frames), then again from the start on the
    points whose eight residuals all stay within ``TRIM_PX`` (gross mismatches removed, not only
    down-weighted); None when fewer than ``MIN_POINTS`` remain or a third of them is trimmed."""
    rows = (np.abs(za[:, 1] - za[:, 3]) <= ROW_PX) & (np.abs(zb[:, 1] - zb[:, 3]) <= ROW_PX)
    za, zb = za[rows], zb[rows]
    if za.shape[0] < MIN_POINTS:
        return None
    first = _bundle_adjust(za, zb, cam)
    if first is None:
        return None
    keep = np.abs(first[2]).max(axis=1) <= TRIM_PX
    if keep.sum() < max(MIN_POINTS, 2 * za.shape[0] / 3):
        return None
    second = _bundle_adjust(za[keep], zb[keep], cam)
    if second is None or np.abs(second[2]).max() > TRIM_PX:
        return None
    return second[0], second[1]


def _bundle_adjust(za: np.ndarray, zb: np.ndarray, cam, iterations: int = 8):
    """(beta, its variance, residuals (n,8)) or None: the two-view bundle adjustment (D2) over the
    motion, the offset and every point's (u, v, disparity) at k, Huber-weighted Gauss-Newton with
    the points eliminated (Schur complement). Both frames' pixels are measurements, so noise in
    either does not bias beta (triangulating at k and fitting k+1 alone would: errors in variables)."""
    z = np.concatenate([za, zb], axis=1)  # (n,8)
    T = np.eye(4)
    beta = 0.0
    p = np.stack([za[:, 0], za[:, 1], za[:, 0] - za[:, 2]], axis=1)
    for _ in range(iterations):
        pred, Jp, Jg = _predict(T, beta, p, cam, jacobians=True)
        r = pred - z
        if not np.all(np.isfinite(r)):
            return None
        a = np.abs(r)
        w = np.where(a <= HUBER_PX, 1.0, HUBER_PX / np.maximum(a, 1e-12))
        JpW = (Jp * w[:, :, None]).transpose(0, 2, 1)  # (n,3,8)
        Hpp = JpW @ Jp + 1e-9 * np.eye(3)
        Hpg = JpW @ Jg  # (n,3,7)
        Jg2 = Jg.reshape(-1, 7)
        Hgg = Jg2.T @ (Jg2 * w.reshape(-1, 1))
        bp = (JpW @ r[:, :, None])[:, :, 0]
        bg = Jg2.T @ (w * r).reshape(-1)
        try:
            Hpp_inv = np.linalg.inv(Hpp)
            HgpHinv = Hpg.transpose(0, 2, 1) @ Hpp_inv  # (n,7,3)
            S = Hgg - (HgpHinv @ Hpg).sum(axis=0)
            rhs = bg - (HgpHinv @ bp[:, :, None]).sum(axis=0)[:, 0]
            dg = -np.linalg.solve(S + 1e-9 * np.eye(7), rhs)
        except np.linalg.LinAlgError:
            return None
        dp = -(Hpp_inv @ (bp + Hpg @ dg)[:, :, None])[:, :, 0]
        T = se3.exp_se3(dg[:6]) @ T
        beta += dg[6]
        p += dp
        p[:, 2] = np.maximum(p[:, 2], 1e-3)
        if abs(dg[6]) < 1e-4 and np.all(np.abs(dg[:6]) < 1e-6):
            break
    r = _predict(T, beta, p, cam) - z
    inliers = np.abs(r) <= 3 * HUBER_PX
    dof = int(inliers.sum()) - 3 * z.shape[0] - 7
    if dof < 20 or not np.all(np.isfinite(r)):
        return None
    sigma2 = float(np.sum(r[inliers] ** 2) / dof)
    try:
        var = float(np.linalg.inv(S)[6, 6]) * sigma2
    except np.linalg.LinAlgError:
        return None
    if not (np.isfinite(beta) and np.isfinite(var) and var > 0 and abs(beta) < 20):
        return None
    return float(beta), var, r


def step_offsets(seq: Sequence, max_steps: int = MAX_STEPS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(steps k, beta_k, var(beta_k)) of up to ``max_steps`` step pairs spread over ``seq``  (D2)."""
    K = seq.K
    cam = (K[0, 0], K[1, 1], K[0, 2], K[1, 2], seq.baseline)
    n = seq.num_steps
    candidates = np.arange(n - 1)
    if candidates.size > max_steps:
        candidates = np.unique(np.linspace(0, n - 2, max_steps).round().astype(np.int64))
    ks, betas, variances = [], [], []
    for k in candidates:
        ids_a, za = seq.observations(k)
        ids_b, zb = seq.observations(k + 1)
        common, ia, ib = np.intersect1d(ids_a, ids_b, assume_unique=True, return_indices=True)
        za, zb = za[ia], zb[ib]
        keep = (za[:, 0] - za[:, 2] > MIN_DISPARITY) & (zb[:, 0] - zb[:, 2] > MIN_DISPARITY)
        if keep.sum() < MIN_POINTS:
            continue
        fit = _fit_step(za[keep], zb[keep], cam)
        if fit is not None:
            ks.append(int(k))
            betas.append(fit[0])
            variances.append(fit[1])
    return np.array(ks, dtype=np.int64), np.array(betas), np.array(variances)


def _regress(A: np.ndarray, beta: np.ndarray, var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted, Huber-reweighted least squares beta ~ A c (D3), weights 1 / var: (c, standard
    errors), the errors inflated by the reduced chi-square when the scatter exceeds the variances."""
    w0 = 1.0 / var
    w = w0.copy()
    p = A.shape[1]
    for _ in range(20):
        coef = np.linalg.solve(A.T @ (A * w[:, None]) + 1e-12 * np.eye(p), A.T @ (w * beta))
        r = (beta - A @ coef) * np.sqrt(w0)
        scale = max(1.4826 * float(np.median(np.abs(r))), 1e-12)
        a = np.abs(r) / scale
        w = w0 * np.where(a <= 1.345, 1.0, 1.345 / np.maximum(a, 1e-12))
    r = (beta - A @ coef) * np.sqrt(w0)
    chi2 = float(np.sum(w / w0 * r**2) / max(r.size - p, 1))
    cov = np.linalg.inv(A.T @ (A * w[:, None])) * max(chi2, 1.0)
    return coef, np.sqrt(np.diag(cov))


def identify_stereo_offset(seq: Sequence, imu_T_cam: np.ndarray, model: str = "constant",
                           max_steps: int = MAX_STEPS) -> StereoOffset:
    """The offset (D1) of ``seq`` with the extrinsic ``imu_T_cam``, estimated (D2-D3) and applied as
    ``model`` says: "constant" the weighted mean of beta_k, "rate" beta_0 + kappa omega_y (the
    rate term only where it is significant, else the constant), each only where it is significant
    (``SIGNIFICANCE`` standard errors and ``MIN_EFFECT_PX``); "off" estimates nothing."""
    model = str(model)
    if model == "off":
        return StereoOffset(source="off")
    ks, beta, var = step_offsets(seq, max_steps)
    source = f"auto, {model}"
    if ks.size < MIN_STEPS:
        return StereoOffset(estimate={"steps": int(ks.size)}, source=source)
    omega = camera_rate_y(seq.angular_velocity, imu_T_cam)
    g = 0.5 * (omega[ks] + omega[np.minimum(ks + 1, omega.size - 1)])
    spread = float(np.std(g))
    (mean,), (mean_se,) = _regress(np.ones_like(g)[:, None], beta, var)
    estimate = {"beta_mean_px": float(mean), "beta_mean_se": float(mean_se), "steps": int(ks.size),
                "omega_y_std": spread, "fx": float(seq.K[0, 0])}
    coef, se = np.array([mean, 0.0]), np.array([mean_se, np.inf])
    if spread >= 1e-3:
        coef, se = _regress(np.stack([np.ones_like(g), g], axis=1), beta, var)
    estimate.update(beta0_px=float(coef[0]), beta0_se=float(se[0]), kappa_px_s=float(coef[1]), kappa_se=float(se[1]))
    rate_shown = np.isfinite(se[1]) and abs(coef[1]) > max(SIGNIFICANCE * se[1], MIN_EFFECT_PX / max(spread, 1e-12))
    if model == "rate" and rate_shown:
        return StereoOffset(float(coef[0]), float(coef[1]), estimate, source)
    if abs(mean) > max(SIGNIFICANCE * mean_se, MIN_EFFECT_PX):
        return StereoOffset(float(mean), 0.0, estimate, source)
    return StereoOffset(0.0, 0.0, estimate, source)
