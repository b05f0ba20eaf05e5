"""Tests of vislam.backend.evaluation.metrics (ATE / RPE via evo) on synthetic trajectories."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vislam.backend.errors import InputError
from vislam.backend.evaluation.metrics import (
    TrajectoryErrors,
    alignment_scale,
    associate,
    ate_per_pose,
    trajectory_errors,
)

N = 200  # even, so alternating offsets cancel exactly over the closed circle


def circle(n: int = N, radius: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """Closed circle with a z wave and a turning, rolling body; stamps 0.1 s apart."""
    theta = 2.0 * np.pi * np.arange(n) / n
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = radius * np.cos(theta)
    poses[:, 1, 3] = radius * np.sin(theta)
    poses[:, 2, 3] = 1.0 + 0.5 * np.sin(2.0 * theta)
    angles = np.column_stack([theta + np.pi / 2, 0.1 * np.sin(3 * theta), 0.05 * np.cos(theta)])
    poses[:, :3, :3] = Rotation.from_euler("ZYX", angles).as_matrix()
    return 100.0 + 0.1 * np.arange(n), poses


def random_se3(seed: int = 7) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = rng.uniform(-20.0, 20.0, 3)
    return T


def test_rigidly_moved_copy_has_zero_error():
    t, gt = circle()
    est = random_se3() @ gt  # another world frame
    est_before, gt_before, t_before = est.copy(), gt.copy(), t.copy()

    errors = trajectory_errors(t, est, t, gt)
    assert isinstance(errors, TrajectoryErrors)
    assert errors.ate_rmse < 1e-9 and errors.ate_max < 1e-9
    assert errors.rpe_trans_rmse < 1e-9 and errors.rpe_rot_rmse_deg < 1e-6
    assert errors.num_matched == N and errors.alignment == "se3"
    # the circle (~31 m) is shorter than the default 100 m: fall back to 10 frames
    assert (errors.rpe_delta, errors.rpe_unit) == (10.0, "frames")
    assert errors.path_length == pytest.approx(N * 2 * 5.0 * np.sin(np.pi / N), rel=0.02)
    # the caller's arrays are untouched (evo aligns in place)
    np.testing.assert_array_equal(est, est_before)
    np.testing.assert_array_equal(gt, gt_before)
    np.testing.assert_array_equal(t, t_before)

    metres = trajectory_errors(t, est, t, gt, rpe_delta=5.0)
    assert (metres.rpe_delta, metres.rpe_unit) == (5.0, "m")
    assert metres.rpe_trans_rmse < 1e-9

    d = errors.as_dict()
    assert set(d) == {
        "ate_rmse", "ate_mean", "ate_median", "ate_max", "rpe_trans_rmse", "rpe_rot_rmse_deg",
        "rpe_delta", "rpe_unit", "num_matched", "path_length", "alignment",
    }
    assert all(type(v) in (float, int, str) for v in d.values())


def test_alternating_offset_gives_known_errors():
    """p_est_i = p_gt_i + (-1)^i d z. Over an even number of samples of the closed circle
    the offsets sum to zero and are uncorrelated with every coordinate, so the optimal
    alignment is the identity and ATE = d for every pose. Relative motions over an odd
    number of frames are off by 2 d, over an even number by 0."""
    d = 0.03
    t, gt = circle()
    est = gt.copy()
    est[:, 2, 3] += d * (-1.0) ** np.arange(N)
    moved = random_se3(11) @ est

    errors = trajectory_errors(t, moved, t, gt, rpe_delta=11, rpe_unit="frames")
    assert errors.ate_rmse == pytest.approx(d, abs=1e-9)
    assert errors.ate_mean == pytest.approx(d, abs=1e-9)
    assert errors.ate_median == pytest.approx(d, abs=1e-9)
    assert errors.ate_max == pytest.approx(d, abs=1e-9)
    assert errors.rpe_trans_rmse == pytest.approx(2 * d, abs=1e-9)
    assert errors.rpe_rot_rmse_deg < 1e-6
    assert (errors.rpe_delta, errors.rpe_unit) == (11.0, "frames")

    even = trajectory_errors(t, moved, t, gt, rpe_delta=10, rpe_unit="frames")
    assert even.rpe_trans_rmse < 1e-9

    per_pose = ate_per_pose(t, moved, t, gt)
    assert per_pose.shape == (N,)
    np.testing.assert_allclose(per_pose, d, atol=1e-9)
    stamps, per_pose2 = ate_per_pose(t, moved, t, gt, return_stamps=True)
    np.testing.assert_array_equal(stamps, t)
    np.testing.assert_array_equal(per_pose2, per_pose)


def test_sim3_removes_scale_se3_does_not():
    t, gt = circle()
    est = gt.copy()
    est[:, :3, 3] *= 1.5
    est = random_se3(3) @ est

    se3 = trajectory_errors(t, est, t, gt)
    sim3 = trajectory_errors(t, est, t, gt, sim3=True)
    assert sim3.alignment == "sim3" and se3.alignment == "se3"
    assert sim3.ate_rmse < 1e-9
    assert sim3.rpe_trans_rmse < 1e-9
    assert alignment_scale(t, est, t, gt) == pytest.approx(1 / 1.5, rel=1e-9)  # the estimate shrunk onto gt
    assert se3.ate_rmse > 1.0  # half the radius, roughly
    assert se3.rpe_trans_rmse > 0.1


def test_association_by_time():
    t, gt = circle()
    # every other estimate, stamps jittered by up to 3 ms, plus some outside ground truth
    idx = np.arange(0, N, 2)
    jitter = np.random.default_rng(0).uniform(-0.003, 0.003, idx.size)
    est_t = np.concatenate([t[idx] + jitter, t[-1] + [1.0, 2.0]])
    est = np.concatenate([gt[idx], gt[-2:]])

    est_m, gt_m, t_m = associate(est_t, est, t, gt)
    assert est_m.shape == (N // 2, 4, 4) and gt_m.shape == (N // 2, 4, 4)
    np.testing.assert_array_equal(est_m, gt_m)
    np.testing.assert_array_equal(t_m, est_t[: N // 2])

    errors = trajectory_errors(est_t, est, t, gt)
    assert errors.num_matched == N // 2 and errors.ate_rmse < 1e-9


def test_too_few_matches():
    t, gt = circle()
    est_t = np.array([t[0], t[1], t[-1] + 5.0, t[-1] + 6.0])
    est = gt[:4]
    with pytest.raises(InputError, match="only 2"):
        trajectory_errors(est_t, est, t, gt)
    with pytest.raises(InputError, match="only 0"):
        associate(t + 1000.0, gt, t, gt)


def test_few_poses_fallback_and_bad_input():
    t, gt = circle(n=3)
    errors = trajectory_errors(t, gt, t, gt)
    assert errors.num_matched == 3 and (errors.rpe_delta, errors.rpe_unit) == (2.0, "frames")
    bad = gt.copy()
    bad[1, 0, 3] = np.nan
    with pytest.raises(InputError, match="non-finite"):
        trajectory_errors(t, bad, t, gt)
    with pytest.raises(InputError, match="strictly increasing"):
        trajectory_errors(t[::-1].copy(), gt, t, gt)
