"""Trajectory error metrics (ATE, RPE) of an estimate against ground truth, computed with evo.

* ATE: the estimate is aligned to the ground truth with Umeyama's method (SE(3) by default,
  Sim(3) on request, or only the first matched poses put on each other: evo's ``--align_origin``)
  using all time-matched positions; ATE is the translation error
  ``|p_gt_i - p_est_aligned_i|`` per matched pose, summarised as RMSE / mean / median / max.   (M1)
* RPE: for pose pairs ``(i, j)`` a fixed distance apart, the error of the relative motion
  ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)``; translation RMSE (metres) and rotation-angle RMSE
  (degrees). Pairs are all pairs whose ground-truth path distance is ``delta`` metres (10 %
  tolerance), or ``delta`` frames apart. If the ground truth path is shorter than ``delta``
  (or, in frames, has too few poses) the delta falls back to ``min(10, N-1)`` frames, and
  ``rpe_delta`` / ``rpe_unit`` report what was used. RPE uses the aligned estimate (only
  the Sim(3) scale matters for it).                                                              (M2)

evo is imported inside the functions (it is slow to import). The caller's arrays are never
modified (evo aligns in place, so it works on copies).
"""

from __future__ import annotations

import copy
import inspect
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ..errors import InputError

__all__ = ["TrajectoryErrors", "Alignment", "alignment", "associate", "associate_indices", "trajectory_errors",
           "ate_per_pose", "aligned_poses", "alignment_scale", "evo_results", "require_matches"]

MIN_MATCHES = 3
FALLBACK_DELTA_FRAMES = 10


@dataclass
class TrajectoryErrors:
    """Summary of an estimate's errors against ground truth (see the module docstring)."""

    ate_rmse: float  # metres, after alignment
    ate_mean: float
    ate_median: float
    ate_max: float
    rpe_trans_rmse: float  # metres
    rpe_rot_rmse_deg: float  # degrees
    rpe_delta: float  # in rpe_unit
    rpe_unit: str  # "m" or "frames"
    num_matched: int  # poses matched in time
    path_length: float  # metres, along the matched ground-truth poses
    alignment: str  # "se3", "sim3" or "origin"

    def as_dict(self) -> dict:
        """Plain-Python dict (floats, ints, strings) of all fields."""
        out = asdict(self)
        for key, value in out.items():
            if isinstance(value, np.generic):
                out[key] = value.item()
        return out


def _check(t: Any, poses: Any, what: str) -> tuple[np.ndarray, np.ndarray]:
    stamps = np.array(t, dtype=float)  # copies
    arr = np.array(poses, dtype=float)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise ValueError(f"{what} poses must have shape (N, 4, 4), got {arr.shape}")
    if stamps.shape != (arr.shape[0],):
        raise ValueError(f"{what} time stamps must have shape ({arr.shape[0]},), got {stamps.shape}")
    if not np.all(np.isfinite(stamps)):
        raise InputError(f"{what}: non-finite time stamp")
    if not np.all(np.isfinite(arr)):
        index = int(np.flatnonzero(~np.isfinite(arr).all(axis=(1, 2)))[0])
        raise InputError(f"{what}: non-finite pose at index {index} (t = {stamps[index]:.6f})")
    if len(stamps) > 1 and not np.all(np.diff(stamps) > 0):
        raise InputError(f"{what}: time stamps are not strictly increasing")
    return stamps, arr


def require_matches(est_t: Any, gt_t: Any, source: str, max_diff: float = 0.01) -> int:
    """The number of time stamps ``est_t`` that have a ground-truth stamp within ``max_diff`` s;
    InputError naming ``source`` when fewer than 3 do (checked before a run, not after it)."""
    est = np.asarray(est_t, dtype=float)
    gt = np.sort(np.asarray(gt_t, dtype=float))  # at least one stamp (read_tum refuses an empty file)
    idx = np.searchsorted(gt, est)
    before, after = gt[np.clip(idx - 1, 0, gt.size - 1)], gt[np.clip(idx, 0, gt.size - 1)]
    matched = int(np.sum(np.minimum(np.abs(before - est), np.abs(after - est)) <= max_diff))
    if matched < MIN_MATCHES:
        raise InputError(
            f"{source}: only {matched} of the data's {est.size} time stamps ({est.min():.6f} .. {est.max():.6f} s) "
            f"have a ground-truth stamp within {max_diff} s (ground truth spans {gt.min():.6f} .. {gt.max():.6f} s); "
            f"at least {MIN_MATCHES} are needed")
    return matched


def _evo_trajectory(t: np.ndarray, poses: np.ndarray, name: str):
    from evo.core.trajectory import PoseTrajectory3D

    return PoseTrajectory3D(timestamps=t.copy(), poses_se3=[p.copy() for p in poses], name=name)


def _matching_indices(et: np.ndarray, gt: np.ndarray, max_diff: float) -> tuple[np.ndarray, np.ndarray]:
    """evo's nearest-stamp association (``evo.core.sync.associate_trajectories``: from the trajectory
    with fewer poses, each stamp to the nearest of the other within ``max_diff``), as indices."""
    from evo.core.sync import matching_time_indices

    if len(gt) > len(et):
        est_index, gt_index = matching_time_indices(et, gt, max_diff)
    else:
        gt_index, est_index = matching_time_indices(gt, et, max_diff)
    matched = len(est_index)
    if matched < MIN_MATCHES:
        raise InputError(
            f"only {matched} estimated pose(s) match a ground-truth time stamp within "
            f"{max_diff} s; at least {MIN_MATCHES} are needed"
        )
    return np.asarray(est_index, dtype=np.int64), np.asarray(gt_index, dtype=np.int64)


def _associated(est_t, est_poses, gt_t, gt_poses, max_diff: float):
    """evo trajectories (est, gt) of the time-matched poses."""
    et, ep = _check(est_t, est_poses, "estimate")
    gt, gp = _check(gt_t, gt_poses, "ground truth")
    if len(et) == 0 or len(gt) == 0:
        raise InputError(
            f"too few poses to compare: estimate {len(et)}, ground truth {len(gt)}"
        )
    i, j = _matching_indices(et, gt, max_diff)
    return _evo_trajectory(et[i], ep[i], "estimate"), _evo_trajectory(gt[j], gp[j], "ground truth")


def associate_indices(est_t: Any, gt_t: Any, max_diff: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """The pairs :func:`associate` matches, as indices: nearest time stamp within ``max_diff`` s (evo).

    Parameters
    ----------
    est_t : (N,) array, seconds, strictly increasing
    gt_t : (G,) array, seconds, strictly increasing
    max_diff : float
        Largest stamp difference (s) of a pair; a TUM file's stamps (``%.6f``) differ from the data's
        by up to 5e-7 s.

    Returns
    -------
    est_index, gt_index : (M,) int64 arrays
        ``est_t[est_index]`` and ``gt_t[gt_index]`` are the matched stamps. Raises :class:`InputError`
        if fewer than 3 match.
    """
    et = np.array(est_t, dtype=float)
    gt = np.array(gt_t, dtype=float)
    for what, stamps in (("estimate", et), ("ground truth", gt)):
        if stamps.ndim != 1:
            raise ValueError(f"{what} time stamps must have shape (N,), got {stamps.shape}")
        if not np.all(np.isfinite(stamps)):
            raise InputError(f"{what}: non-finite time stamp")
        if len(stamps) > 1 and not np.all(np.diff(stamps) > 0):
            raise InputError(f"{what}: time stamps are not strictly increasing")
    if len(et) == 0 or len(gt) == 0:
        raise InputError(f"too few poses to compare: estimate {len(et)}, ground truth {len(gt)}")
    return _matching_indices(et, gt, max_diff)


def associate(
    est_t: Any, est_poses: Any, gt_t: Any, gt_poses: Any, max_diff: float = 0.01
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Match estimated and ground-truth poses by nearest time stamp (within ``max_diff`` s).

    Returns ``(est_poses_matched (M,4,4), gt_poses_matched (M,4,4), t (M,))`` with ``t`` the
    estimate's stamps of the matches. Raises :class:`InputError` if fewer than 3 match.
    """
    est_sync, ref_sync = _associated(est_t, est_poses, gt_t, gt_poses, max_diff)
    return (
        np.array(est_sync.poses_se3),
        np.array(ref_sync.poses_se3),
        np.array(est_sync.timestamps, dtype=float),
    )


@dataclass(frozen=True)
class Alignment:
    """``p -> scale * rotation @ p + translation`` (poses: ``T -> [[s R, t], [0, 1]] T`` with the
    rotation part ``R R_T``), moving an estimate onto the ground truth; what evo's ``align`` /
    ``align_origin`` applied to the matched poses."""

    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    scale: float  # 1 unless Sim(3)
    kind: str  # "se3", "sim3" or "origin"
    ate_rmse: float  # m, over the matched poses after alignment

    @property
    def name(self) -> str:
        """How the estimate was aligned, as the plots and the screen say it."""
        return {"se3": "SE(3)", "sim3": "Sim(3)", "origin": "first poses"}[self.kind]

    def apply(self, points: Any) -> np.ndarray:
        """Aligned points: (K, 3) -> (K, 3)."""
        return self.scale * np.asarray(points, dtype=float) @ self.rotation.T + self.translation

    def apply_poses(self, poses: Any) -> np.ndarray:
        """Aligned poses: (N, 4, 4) -> (N, 4, 4), as evo moves a trajectory (scale, then transform)."""
        out = np.array(poses, dtype=float)
        out[:, :3, 3] = self.apply(out[:, :3, 3])
        out[:, :3, :3] = self.rotation @ out[:, :3, :3]
        return out


def _alignment_kind(sim3: bool, origin: bool) -> str:
    if sim3 and origin:
        raise ValueError("sim3 and origin alignment exclude each other (as evo's --align and --align_origin)")
    return "origin" if origin else "sim3" if sim3 else "se3"


def _aligned(est_t, est_poses, gt_t, gt_poses, sim3: bool, max_diff: float, origin: bool = False):
    """(aligned estimate, ground truth, :class:`Alignment`): evo trajectories of the matched poses,
    the estimate moved by evo's Umeyama ``align`` (``origin``: ``align_origin``)."""
    from evo.core.geometry import GeometryException

    kind = _alignment_kind(sim3, origin)
    est_sync, ref_sync = _associated(est_t, est_poses, gt_t, gt_poses, max_diff)
    est_aligned = copy.deepcopy(est_sync)
    if origin:
        T = est_aligned.align_origin(ref_sync)
        rotation, translation, scale = T[:3, :3], T[:3, 3], 1.0
    else:
        try:
            rotation, translation, scale = est_aligned.align(ref_sync, correct_scale=sim3)
        except GeometryException as exc:
            raise InputError(
                f"cannot align the estimate to the ground truth ({exc}); are the "
                f"{ref_sync.num_poses} matched positions all on one straight line?"
            ) from exc
    gap = est_aligned.positions_xyz - ref_sync.positions_xyz
    ate = float(np.sqrt(np.mean(np.sum(gap**2, axis=1))))
    found = Alignment(np.array(rotation, dtype=float), np.array(translation, dtype=float), float(scale), kind, ate)
    return est_aligned, ref_sync, found


def alignment(
    est_t: Any, est_poses: Any, gt_t: Any, gt_poses: Any, *, sim3: bool = False, origin: bool = False,
    max_diff: float = 0.01,
) -> Alignment:
    """The alignment of an estimate to the ground truth that its ATE uses (see the module docstring).

    Parameters
    ----------
    est_t : (N,) array, seconds
    est_poses : (N, 4, 4) array
    gt_t : (G,) array, seconds
    gt_poses : (G, 4, 4) array
    sim3 : bool
        Also fit the scale (Umeyama, Sim(3)).
    origin : bool
        Put the first matched estimate pose on its ground truth instead (evo's ``align_origin``).
    max_diff : float
        Largest stamp difference (s) of a matched pair.

    Returns
    -------
    Alignment
        Raises :class:`InputError` when fewer than 3 poses match or the matched positions are degenerate.
    """
    return _aligned(est_t, est_poses, gt_t, gt_poses, sim3, max_diff, origin)[2]


def _ape(est_aligned, ref):
    from evo.core.metrics import APE, PoseRelation

    ape = APE(PoseRelation.translation_part)
    ape.process_data((ref, est_aligned))
    return ape


def _rpe(est_aligned, ref, delta: float, unit: str) -> tuple[float, float, float, str]:
    from evo.core.filters import FilterException
    from evo.core.metrics import RPE, PoseRelation, StatisticsType, Unit

    n = ref.num_poses
    fallback = (float(min(FALLBACK_DELTA_FRAMES, n - 1)), "frames")
    if unit == "m":
        if not delta > 0:
            raise ValueError(f"rpe_delta must be positive, got {delta}")
        use = (float(delta), "m") if ref.path_length >= delta else fallback
    elif unit == "frames":
        if not (delta >= 1 and float(delta).is_integer()):
            raise ValueError(f"rpe_delta in frames must be a positive integer, got {delta}")
        use = (float(delta), "frames") if delta <= n - 1 else fallback
    else:
        raise ValueError(f"rpe_unit must be 'm' or 'frames', got {unit!r}")

    extra = {}
    if "pairs_from_reference" in inspect.signature(RPE.__init__).parameters:
        extra["pairs_from_reference"] = True  # delta measured along the ground truth

    def run(d: float, u: str) -> tuple[float, float]:
        values = []
        for relation in (PoseRelation.translation_part, PoseRelation.rotation_angle_deg):
            rpe = RPE(
                relation,
                delta=d if u == "m" else int(d),
                delta_unit=Unit.meters if u == "m" else Unit.frames,
                all_pairs=True,
                **extra,
            )
            rpe.process_data((ref, est_aligned))
            values.append(float(rpe.get_statistic(StatisticsType.rmse)))
        return values[0], values[1]

    try:
        trans, rot = run(*use)
    except FilterException:  # no pair at that distance (e.g. one huge gap): frames instead
        if use == fallback:
            raise
        use = fallback
        trans, rot = run(*use)
    return trans, rot, use[0], use[1]


def trajectory_errors(
    est_t: Any,
    est_poses: Any,
    gt_t: Any,
    gt_poses: Any,
    *,
    sim3: bool = False,
    rpe_delta: float = 100.0,
    rpe_unit: str = "m",
    max_diff: float = 0.01,
    origin: bool = False,
) -> TrajectoryErrors:
    """ATE and RPE of an estimate against ground truth (see the module docstring).

    Poses are ``world_T_imu`` ``(N, 4, 4)`` with stamps ``(N,)`` in seconds; they are
    matched by nearest stamp within ``max_diff``; ``origin``: the first matched poses put on each
    other instead of Umeyama's alignment. Raises :class:`InputError` if fewer than 3 poses match or
    the alignment is degenerate.
    """
    from evo.core.metrics import StatisticsType

    est_aligned, ref, _ = _aligned(est_t, est_poses, gt_t, gt_poses, sim3, max_diff, origin)
    ape = _ape(est_aligned, ref)
    rpe_trans, rpe_rot, used_delta, used_unit = _rpe(est_aligned, ref, rpe_delta, rpe_unit)
    return TrajectoryErrors(
        ate_rmse=float(ape.get_statistic(StatisticsType.rmse)),
        ate_mean=float(ape.get_statistic(StatisticsType.mean)),
        ate_median=float(ape.get_statistic(StatisticsType.median)),
        ate_max=float(ape.get_statistic(StatisticsType.max)),
        rpe_trans_rmse=rpe_trans,
        rpe_rot_rmse_deg=rpe_rot,
        rpe_delta=used_delta,
        rpe_unit=used_unit,
        num_matched=int(ref.num_poses),
        path_length=float(ref.path_length),
        alignment=_alignment_kind(sim3, origin),
    )


def ate_per_pose(
    est_t: Any,
    est_poses: Any,
    gt_t: Any,
    gt_poses: Any,
    *,
    sim3: bool = False,
    max_diff: float = 0.01,
    return_stamps: bool = False,
    origin: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Translation error (metres) of every matched pose after alignment, as ``(M,)``; in
    the order of ``associate(...)``. With ``return_stamps`` returns ``(t (M,), errors)``,
    ready for ``vislam.tools.plots.plot_errors_over_time``."""
    est_aligned, ref, _ = _aligned(est_t, est_poses, gt_t, gt_poses, sim3, max_diff, origin)
    errors = np.array(_ape(est_aligned, ref).error, dtype=float)
    if return_stamps:
        return np.array(est_aligned.timestamps, dtype=float), errors
    return errors


def aligned_poses(
    est_t: Any, est_poses: Any, gt_t: Any, gt_poses: Any, *, sim3: bool = False, max_diff: float = 0.01,
    origin: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamps (M,), aligned estimate (M,4,4), ground truth (M,4,4)) of the matched poses, the
    estimate moved onto the ground truth by the same alignment as :func:`trajectory_errors`."""
    est_aligned, ref, _ = _aligned(est_t, est_poses, gt_t, gt_poses, sim3, max_diff, origin)
    return (np.array(est_aligned.timestamps, dtype=float), np.array(est_aligned.poses_se3, dtype=float),
            np.array(ref.poses_se3, dtype=float))


def alignment_scale(est_t: Any, est_poses: Any, gt_t: Any, gt_poses: Any, *, max_diff: float = 0.01) -> float:
    """The scale a Sim(3) (Umeyama) alignment of the matched poses applies to the estimate, as in
    ``trajectory_errors(..., sim3=True)``: < 1 when the estimate's path is longer than the
    ground truth's."""
    return _aligned(est_t, est_poses, gt_t, gt_poses, True, max_diff)[2].scale


def evo_results(
    est_t: Any,
    est_poses: Any,
    gt_t: Any,
    gt_poses: Any,
    *,
    sim3: bool = False,
    origin: bool = False,
    rpe_delta: float = 100.0,
    rpe_unit: str = "m",
    max_diff: float = 0.01,
    est_name: str = "estimate",
    ref_name: str = "ground truth",
):
    """evo's APE and RPE results of the translation part (``evo.main_ape.ape``, ``evo.main_rpe.rpe``
    on the matched poses, with the alignment and the pairs of :func:`trajectory_errors`: pass its
    ``rpe_delta`` and ``rpe_unit``), the objects ``evo_ape`` / ``evo_rpe --save_results`` write and
    ``evo_res`` compares (``evo.tools.file_interface.save_res_file``).

    Returns
    -------
    (ape, rpe) : two ``evo.core.result.Result``
    """
    from evo.core.metrics import PoseRelation, Unit
    from evo.main_ape import ape
    from evo.main_rpe import rpe

    kind = _alignment_kind(sim3, origin)
    est_sync, ref_sync = _associated(est_t, est_poses, gt_t, gt_poses, max_diff)
    est_sync.name, ref_sync.name = est_name, ref_name
    how = dict(align=kind != "origin", correct_scale=kind == "sim3", align_origin=kind == "origin")
    ape_result = ape(copy.deepcopy(ref_sync), copy.deepcopy(est_sync), PoseRelation.translation_part, **how)
    unit = {"m": Unit.meters, "frames": Unit.frames}[rpe_unit]
    rpe_result = rpe(copy.deepcopy(ref_sync), copy.deepcopy(est_sync), PoseRelation.translation_part,
                     delta=rpe_delta if rpe_unit == "m" else int(rpe_delta), delta_unit=unit, all_pairs=True,
                     pairs_from_reference=True, **how)
    return ape_result, rpe_result
