"""SLAM on the default synthetic street (the scene `vislam demo` uses), against exact ground truth."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from vislam.backend.evaluation.metrics import trajectory_errors
from vislam.backend.run.runner import run_sequence
from vislam.synth.scene import SceneConfig, make_scene


def _run(**scene_options):
    scene = make_scene(SceneConfig(scenario="street", seed=0, **scene_options))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        # as `vislam demo` runs it: the filter on the scene's own noise (static landmarks, exact tracks)
        result = run_sequence(scene.sequence, scene.config.filter_config())
    return scene, result


def _ate(scene, result, poses=None):
    t = scene.sequence.time_stamps
    return trajectory_errors(t, result.world_T_imu if poses is None else poses, t, scene.world_T_imu_true)


@pytest.fixture(scope="module")
def street():
    """The default street scene with the default noise (what `vislam demo` runs)."""
    return _run()


def test_slam_beats_dead_reckoning(street):
    """Measured: 0.093 m vs 1.44 m over 429 m."""
    scene, result = street
    est, dr = _ate(scene, result), _ate(scene, result, result.dead_reckoning)
    assert est.ate_rmse <= dr.ate_rmse / 5
    assert est.ate_rmse <= 0.005 * est.path_length


def test_landmarks_near_the_path_are_mapped_within_0_3_m(street):
    """Median position error of mapped landmarks within 20 m of the true path (measured 0.25 m)."""
    scene, result = street
    truth = scene.landmark_positions[result.map_ids]
    path = scene.world_T_imu_true[:, :3, 3]
    distance = np.min(np.linalg.norm(truth[:, None, :] - path[None, ::5, :], axis=2), axis=1)
    near = distance <= 20.0
    assert near.sum() > 1000
    error = np.linalg.norm(result.map_positions - truth, axis=1)
    assert np.median(error[near]) <= 0.3


def test_gross_outliers_barely_change_the_trajectory(street):
    """5 % gross outliers: ATE within 1.5x of the outlier-free run (measured 0.086 m vs 0.093 m)."""
    scene, result = street
    noisy_scene, noisy = _run(outlier_share=0.05)
    assert noisy_scene.outlier.mean() == pytest.approx(0.05, abs=0.01)
    assert noisy.stats.gated_share >= 0.04  # the outliers are found, not absorbed
    assert _ate(noisy_scene, noisy).ate_rmse <= 1.5 * _ate(scene, result).ate_rmse


def test_filter_is_consistent_on_its_own_model(street):
    """Pixel noise as configured: the mean NIS per used observation is near its expectation 4."""
    _, result = street
    assert 3.0 <= result.stats.mean_nis <= 5.0
    assert result.stats.gated_share < 0.02
    assert result.stats.health_messages == []


def test_gyro_bias_estimated(street):
    scene, result = street
    np.testing.assert_allclose(result.gyro_bias, scene.gyro_bias_true[-1], atol=1e-3)
