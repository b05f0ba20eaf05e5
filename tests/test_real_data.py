"""The estimator on the real KITTI drives in ../shared/data, default configuration.

The bounds are the project's accuracy targets (measured values in the comments; the runs are
deterministic); BENCHMARKS.md has the numbers behind each default.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from vislam.backend.config import Config
from vislam.backend.data.npz import load_sequence
from vislam.backend.data.tum import read_tum
from vislam.backend.evaluation.consistency import trajectory_nees
from vislam.backend.evaluation.metrics import trajectory_errors
from vislam.backend.run.runner import run_sequence
from vislam.backend.run.timing import repeated_steps

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
GT = DATA / "gt"
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"real data not found at {DATA} (../shared/data)")


def _run(name: str, overrides: dict | None = None):
    """The default configuration, with ``{"table.key": value}`` overrides."""
    seq = load_sequence(DATA / name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # NIS health messages; they are in the result
        return run_sequence(seq, Config.from_values(overrides) if overrides else Config())


@pytest.fixture(scope="module")
def run_0027():
    return _run("ece276a_0027.npz")


@pytest.fixture(scope="module")
def run_03():
    return _run("ece276a_03.npz")


@pytest.fixture(scope="module")
def run_0042():
    return _run("ece276a2019_0042.npz")


def _repeated_frames(name: str):
    """(ids, pixels) of every step of a file that repeats the previous frame exactly."""
    seq = load_sequence(DATA / name)
    return [seq.observations(k) for k in np.flatnonzero(repeated_steps(seq))]


def _ate(result, gt_name: str):
    gt_t, gt = read_tum(DATA / "gt" / gt_name)
    est = trajectory_errors(result.time_stamps, result.world_T_imu, gt_t, gt).ate_rmse
    dr = trajectory_errors(result.time_stamps, result.dead_reckoning, gt_t, gt).ate_rmse
    return est, dr


def test_conventions_chosen_as_measured(run_0027, run_03, run_0042):
    """The flip fits ece276a_03 only; the velocity stamped k+1 fits all three files."""
    assert run_03.conventions.imu_flip is True
    assert run_0027.conventions.imu_flip is False
    assert run_0042.conventions.imu_flip is False
    for result in (run_0027, run_03, run_0042):
        assert result.conventions.velocity_index == "next"
    errs = run_03.conventions.errors_px
    assert errs["flip=yes,velocity=next"] < 0.5 * errs["flip=no,velocity=next"]


def test_0027_every_feature_beats_dead_reckoning(run_0027):
    """Heavy velocity noise (0.5 m/s): vision must carry. Measured 3.08 m vs dead reckoning's 16.3 m
    over 703 m; one draw of the velocity noise, whose six other draws give 2.55-3.52 m (mean 3.07 m:
    BENCHMARKS.md, benchmarks/honesty.py). Bound 3.2 m: the single draw's spread is about 0.3 m."""
    est, dr = _ate(run_0027, "ece276a_0027_gt_tum.txt")
    assert dr == pytest.approx(16.3, abs=0.3)  # the dead-reckoning baseline (the IMU's lever arm removed)
    assert est <= 3.2
    stats = run_0027.stats
    # every feature, not a sample: each observation updates, is gated, (re-)starts a landmark or belongs
    # to a repeated frame (whose content froze: its pixels are the previous frame's, used once)
    repeated = sum(ids.size for ids, _ in _repeated_frames("ece276a_0027.npz"))
    assert (stats.observations_used + stats.observations_gated + stats.landmarks_initialized + repeated
            >= 0.99 * stats.observations)
    assert stats.observations_used >= 0.6 * stats.observations
    assert 1.0 <= stats.mean_nis <= 6.0


def test_0027_reanchoring_helps(run_0027):
    """Tracks drift with age (the test on the tracks says so: T1); re-anchoring landmarks after 3
    (near) or 25 (far) observations keeps the covariance nearer the truth than landmarks that live
    as long as their track: position NEES mean 15.6 against 23.1 (ATE 3.08 against 2.95 m)."""
    assert run_0027.decisions.drift.drifting and run_0027.decisions.drift.source == "test"
    off = _run("ece276a_0027.npz", {"drift.reanchor_observations": 0,
                                    "drift.reanchor_far_observations": 0})  # (random walk kept)
    assert off.stats.landmarks_reanchored == 0 < run_0027.stats.landmarks_reanchored
    gt = read_tum(GT / "ece276a_0027_gt_tum.txt")
    nees = {name: trajectory_nees(r.time_stamps, r.world_T_imu, r.pose_covariance, *gt).position.mean
            for name, r in (("on", run_0027), ("off", off))}
    assert nees["on"] < 0.8 * nees["off"]


def test_0042_dead_reckoning_baseline():
    """With the velocity stamped k+1, dead reckoning reproduces the documented 1.6-1.7 m."""
    result = _run("ece276a2019_0042.npz", {"estimator.mode": "dead-reckoning"})
    est, dr = _ate(result, "ece276a2019_0042_gt_tum.txt")
    assert est == pytest.approx(dr)
    assert 1.5 <= dr <= 1.8
    assert result.map_ids.size == 0


def test_0042_vision_does_not_make_weak_vision_worse(run_0042):
    """Target: at most 0.62x dead reckoning (measured 0.93 m vs 1.70 m, 0.55x). With 3.5 observations
    per step vision cannot measure the IMU (no two-view pairs), so its noise comes from the filter's
    innovation likelihood over the first steps (L2), starting from the samples' own white noise;
    the gyro bias is not estimated, and the summary says why."""
    est, dr = _ate(run_0042, "ece276a2019_0042_gt_tum.txt")
    assert est <= 0.62 * dr
    assert run_0042.decisions.imu.linear_source == "innovation likelihood"
    assert np.all(run_0042.decisions.imu.linear_sigma > 3 * run_0042.decisions.imu.white_linear)
    assert run_0042.decisions.gyro_bias.estimated is False
    assert "observations per step" in run_0042.decisions.gyro_bias.reason
    stats = run_0042.stats
    assert stats.observations_used + stats.observations_gated >= 0.75 * stats.observations  # the rest start landmarks
    assert stats.observations_used + stats.observations_gated + stats.landmarks_initialized >= 0.98 * stats.observations


def test_0042_covariance_holds_the_truth(run_0042):
    """Issue target: position NEES mean <= 9 with >= 60 % of the steps inside the 95 % ellipsoid. The
    file's velocities and rates are KITTI's level-frame OXTS columns measured 2.5 m from the frame
    the ground truth follows; 3.5 tracks a step measure neither lever arm nor frame rotation, which
    the covariance carries at their untested priors (V3, V4; measured 1.4, 100 %). Without the
    rotation it misses the truth (measured 23.4, 46 %), the trajectory the same."""
    gt = read_tum(GT / "ece276a2019_0042_gt_tum.txt")
    nees = trajectory_nees(run_0042.time_stamps, run_0042.world_T_imu, run_0042.pose_covariance, *gt).position
    assert nees.mean <= 9.0 and nees.share_inside_95 >= 0.60, nees
    assert run_0042.lever_arm.rotation_prior_sigma_deg is not None
    plain = _run("ece276a2019_0042.npz", {"noise.imu_rotation_sigma": 0.0})
    np.testing.assert_allclose(plain.world_T_imu, run_0042.world_T_imu, rtol=0, atol=1e-8)
    without = trajectory_nees(plain.time_stamps, plain.world_T_imu, plain.pose_covariance, *gt).position
    assert without.mean > 9.0, without


def test_03_bias_state_keeps_the_car_upright(run_03):
    """The IMU's z axis stays within 12 deg of its start at every step; dead reckoning tilts 56 deg
    (gyro bias ~ -0.011 rad/s). Measured 10.4 deg with the defaults (7.7 with the far tracks held
    fixed by a constant 0.05 m/sqrt(s) landmark walk where the defaults give them the walk their
    two-view residuals measure, T2; the alternatives of BENCHMARKS.md's accuracy table range from
    7.1 to 17 deg). 03 has no ground truth, the road is not level, and the filter's own tilt sigma
    reaches 2.0 deg by the end: this proxy moves by 2-3 deg under changes of the model, so the
    bound is a fifth of dead reckoning's tilt, not a number just above one run."""
    def max_tilt(poses):
        z0 = poses[0, :3, 2]
        return np.degrees(np.arccos(np.clip(poses[:, :3, 2] @ z0, -1, 1))).max()

    assert max_tilt(run_03.dead_reckoning) > 45
    assert max_tilt(run_03.world_T_imu) <= 12.0
    assert np.all(run_03.gyro_bias[:2] < -0.005)  # roll and pitch bias found, sign as documented


def test_03_stereo_offset_agrees_with_dead_reckoning(run_03):
    """03's pair measures disparities ~0.56 px short (found from the tracks alone, D2-D3). An
    independent check that needs no vision fit: points triangulated at k with the offset removed,
    carried to k+3 by dead reckoning (the IMU alone) and reprojected miss their pixels least near
    the offset found (the convention test C1 over a grid of offsets)."""
    import dataclasses

    from vislam.backend.run.conventions import reprojection_error

    offset = run_03.decisions.stereo_offset
    assert offset.active and -0.8 < offset.beta0_px < -0.35
    seq = load_sequence(DATA / "ece276a_03.npz")
    c = run_03.conventions

    def error(beta):
        pixels = seq.obs_pixels.copy()
        pixels[:, 2] += beta
        return reprojection_error(dataclasses.replace(seq, obs_pixels=pixels), c.imu_T_cam, c.velocity_index, 3)

    grid = np.arange(-1.5, 0.51, 0.25)
    errors = np.array([error(b) for b in grid])
    best = grid[np.argmin(errors)]
    assert abs(best - offset.beta0_px) <= 0.3  # measured: best -0.75 (4.09 px), found -0.56
    assert error(offset.beta0_px) < 0.95 * error(0.0)  # measured 4.12 against 4.46 px


def test_0027_offset_terms_estimated_and_constant_not_applied(run_0027):
    """0027: no constant offset (+0.04 +- 0.05 px) and a rate term of ~-1.6 px s/rad (4.5 sigma)
    that the default constant model reports but does not apply (BENCHMARKS.md: applying it made
    the estimate worse over six draws of the velocity noise)."""
    offset = run_0027.decisions.stereo_offset
    e = offset.estimate
    assert not offset.active and abs(e["beta_mean_px"]) < 3 * e["beta_mean_se"] + 0.05
    assert e["kappa_px_s"] < -1.0 and e["steps"] >= 200


def test_map_is_sane(run_0027):
    """Mapped landmarks lie near the trajectory and have positive definite covariances."""
    pos, cov = run_0027.map_positions, run_0027.map_covariances
    assert pos.shape[0] == run_0027.map_ids.size > 1000
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    path = run_0027.world_T_imu[:, :3, 3]
    # distance of each landmark to the nearest 10th pose: 90 % within 100 m
    d = np.min(np.linalg.norm(pos[:, None, :] - path[None, ::10, :], axis=2), axis=1)
    assert np.quantile(d, 0.9) < 100


def test_sparse_drive_imu_noise_does_not_jump_with_the_pixel_sigma():
    """(L2, LIKELIHOOD_TIE) on 0042 (3.5 observations a step) the linear IMU sigma comes from the
    innovation likelihood; with a configured pixel sigma of 1.45, 1.5 or 1.55 px the likelihood is
    flat over the smallest candidates, and the search must not stop there: measured 0.074 m/s forward
    at all three (when any candidate a hair below the best counted, it ended at the samples' white
    noise, 0.0027 m/s, at all three, and the run's position NEES went from 360 to 50000)."""
    from vislam.backend.run.decisions import decide

    seq = load_sequence(DATA / "ece276a2019_0042.npz")
    sigmas = []
    for pixel in (1.45, 1.5, 1.55):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            decisions = decide(seq, Config().with_assignments([f"noise.pixel_sigma={pixel}"]))
        assert decisions.imu.linear_source == "innovation likelihood"
        sigmas.append(float(decisions.imu.linear_sigma[0]))
    white = float(decisions.imu.white_linear[0])
    assert min(sigmas) >= 9 * white, (sigmas, white)
    assert max(sigmas) <= 3 * min(sigmas), sigmas
