"""Monte Carlo consistency: the NEES formulas, the runner with a pluggable executor, and `vislam mc`."""

from __future__ import annotations

import argparse
import json
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2
from threadpoolctl import threadpool_info

from vislam.backend.config import Config
from vislam.backend.evaluation.consistency import (
    SKIP_STEPS,
    average_band,
    landmark_nees,
    monte_carlo,
    pose_nees,
    run_one,
)
from vislam.backend.geometry import se3
from vislam.synth.scene import Scene, SceneConfig, SceneFactory, make_scene


def _random_spd(rng: np.random.Generator, n: int, scale: float) -> np.ndarray:
    A = rng.standard_normal((n, n))
    return scale * (A @ A.T / n + 0.1 * np.eye(n))


def test_pose_nees_is_chi2_6_for_right_perturbed_samples():
    rng = np.random.default_rng(1)
    P = _random_spd(rng, 6, 0.02)
    mu = se3.exp_se3(rng.standard_normal(6))
    xis = rng.multivariate_normal(np.zeros(6), P, size=2000)
    values = np.array([pose_nees(mu, P, mu @ se3.exp_se3(xi)) for xi in xis])
    assert abs(values.mean() - 6.0) <= 0.5  # std of the mean: sqrt(12 / 2000) = 0.08
    assert pose_nees(mu, P, mu) == pytest.approx(0.0, abs=1e-20)
    assert pose_nees(mu, np.zeros((6, 6)), mu) == np.inf  # singular covariance


def test_landmark_nees_is_chi2_3():
    rng = np.random.default_rng(2)
    K = 2000
    C = np.stack([_random_spd(rng, 3, 0.5) for _ in range(K)])
    truth = rng.uniform(-50, 50, (K, 3))
    est = truth + np.einsum("kij,kj->ki", np.linalg.cholesky(C), rng.standard_normal((K, 3)))
    values = landmark_nees(est, C, truth)
    assert values.shape == (K,)
    assert abs(values.mean() - 3.0) <= 0.5  # std of the mean: sqrt(6 / 2000) = 0.055
    assert landmark_nees(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3))).shape == (0,)


def test_average_band():
    lo, hi = average_band(6, 1)
    assert (lo, hi) == pytest.approx((chi2.ppf(0.025, 6), chi2.ppf(0.975, 6)))
    lo, hi = average_band(6, 20)
    assert lo < 6.0 < hi and (lo, hi) == pytest.approx((4.58, 7.61), abs=0.01)


def _assert_same_scene(a, b) -> None:
    """Every array of two scenes and of their sequences equal."""
    for name, value in vars(a).items():
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(value, getattr(b, name), err_msg=name)
    arrays = [name for name, value in vars(a.sequence).items() if isinstance(value, np.ndarray)]
    assert {"obs_ptr", "obs_ids", "obs_pixels", "linear_velocity", "angular_velocity"} <= set(arrays)
    for name in arrays:
        np.testing.assert_array_equal(getattr(a.sequence, name), getattr(b.sequence, name), err_msg=name)


def test_scene_factory_is_make_scene_with_a_noise_seed():
    """``SceneFactory(config)(s)`` is ``make_scene(config, noise_seed=s)``, array for array."""
    cfg = SceneConfig(scenario="street", steps=50, landmark_density=0.5, seed=3)
    factory = SceneFactory(cfg)
    for seed in (3, 7):
        scene = factory(seed)
        assert isinstance(scene, Scene) and scene.config == cfg
        _assert_same_scene(scene, make_scene(cfg, noise_seed=seed))


def test_scene_factory_keeps_geometry_and_reproduces_make_scene():
    cfg = SceneConfig(scenario="street", steps=50, landmark_density=0.5, seed=3)
    factory = SceneFactory(cfg)
    same = factory(cfg.seed)
    reference = make_scene(cfg)
    for key in ("obs_ptr", "obs_ids", "obs_pixels", "linear_velocity", "angular_velocity"):
        np.testing.assert_array_equal(getattr(same.sequence, key), getattr(reference.sequence, key))
    np.testing.assert_array_equal(same.landmark_positions, reference.landmark_positions)
    other = factory(7)
    np.testing.assert_array_equal(other.world_T_imu_true, reference.world_T_imu_true)
    np.testing.assert_array_equal(other.points, reference.points)
    assert not np.array_equal(other.sequence.linear_velocity, reference.sequence.linear_velocity)
    # every track id of the new noise still maps to its true point
    np.testing.assert_array_equal(other.landmark_positions, other.points[other.landmark_point_index])


def test_scene_factory_gyro_bias_replaces_the_scene_bias():
    """``factory(s, gyro_bias=b)`` is the scene of the config with gyro bias b, same noise seed: the
    true bias is b at every step (no bias walk) and only the angular velocities change, by b - b0."""
    cfg = SceneConfig(scenario="street", steps=50, landmark_density=0.5, seed=3)
    factory = SceneFactory(cfg)
    plain = factory(7)
    bias = np.array([0.004, -0.003, 0.0015])
    biased = factory(7, gyro_bias=bias)
    _assert_same_scene(biased, make_scene(replace(cfg, gyro_bias=tuple(bias)), noise_seed=7))
    assert factory.config == cfg  # the factory's own scene is unchanged
    np.testing.assert_array_equal(biased.gyro_bias_true, np.tile(bias, (cfg.steps, 1)))
    assert not np.allclose(plain.gyro_bias_true, bias)
    np.testing.assert_allclose(biased.sequence.angular_velocity - plain.sequence.angular_velocity,
                               np.tile(bias - plain.gyro_bias_true[0], (cfg.steps, 1)), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(biased.sequence.linear_velocity, plain.sequence.linear_velocity)
    np.testing.assert_array_equal(biased.sequence.obs_pixels, plain.sequence.obs_pixels)
    np.testing.assert_array_equal(biased.world_T_imu_true, plain.world_T_imu_true)
    _assert_same_scene(factory(7, gyro_bias=None), plain)


@pytest.fixture(scope="module")
def tiny_mc():
    """5 noise realizations of a 100-step street at half landmark density, filter on its own model."""
    scene = SceneFactory(SceneConfig(scenario="street", steps=100, landmark_density=0.5, seed=0))
    config = scene.config.filter_config()
    filters_before = list(warnings.filters)
    blas_before = [p["num_threads"] for p in threadpool_info()]
    ticks = []
    with ThreadPoolExecutor(max_workers=2) as executor:
        result = monte_carlo(scene, config, runs=5, seed0=0, executor=executor, progress=ticks.append)
        assert executor.submit(int).result() == 0  # a caller's executor is left open
    side_effects = (filters_before == list(warnings.filters), blas_before == [p["num_threads"] for p in threadpool_info()])
    return scene, config, result, ticks, side_effects


def test_monte_carlo_shapes_with_a_thread_pool(tiny_mc):
    scene, _, result, ticks, (filters_kept, blas_kept) = tiny_mc
    assert sorted(ticks) == [1, 2, 3, 4, 5]
    assert result.runs == 5 and result.steps == 100
    assert result.pose_nees_mean.shape == (100,) and result.nis_per_step.shape == (100,)
    assert np.all(np.isfinite(result.pose_nees_mean))
    assert result.per_run_pose_nees.shape == (5,) and result.ate_estimate.shape == (5,)
    assert result.noise_seeds == [0, 1, 2, 3, 4]
    for value in (result.pose_nees_time_average, result.landmark_nees_mean, result.nis_mean, result.pose_nees_in_band):
        assert np.isfinite(value)
    assert result.landmark_count > 100 and result.nis_count > 1000
    lo, hi = result.pose_nees_band
    assert (lo, hi) == pytest.approx(average_band(6, 5))
    assert np.all(result.ate_estimate < result.ate_dead_reckoning)
    json.dumps(result.as_dict(), default=lambda a: np.asarray(a).tolist())  # plain data
    assert filters_kept and blas_kept  # process-wide settings restored after the interleaved runs


def test_monte_carlo_runs_are_the_seeded_single_runs(tiny_mc):
    scene, config, result, _, _ = tiny_mc
    trace = run_one(scene, config, noise_seed=3)
    assert trace.pose_nees[SKIP_STEPS:].mean() == pytest.approx(result.per_run_pose_nees[3], rel=1e-9)
    assert trace.mean_nis == pytest.approx(result.per_run_nis[3], rel=1e-9)
    assert result.nis_expected == 4.0 and trace.dof == 4 * int(trace.nis_count.sum())  # 4 dof an observation


def test_the_nis_is_judged_against_its_degrees_of_freedom():
    """A window's feature seen n times has 4n - 3 degrees of freedom (W5): the runs' NIS per
    observation is judged against the expectation their degrees of freedom give, not 4."""
    from vislam.backend.evaluation.consistency import RunTrace, summarize

    rng = np.random.default_rng(11)
    traces = []
    for seed in range(6):
        n = rng.integers(2, 14, size=(50, 10))  # 10 features a step, each seen n times
        dof = (4 * n - 3).sum(axis=1)
        traces.append(RunTrace(noise_seed=seed, pose_nees=rng.chisquare(6, 50), nis_sum=rng.chisquare(dof).astype(float),
                               nis_count=n.sum(axis=1), landmark_nees=rng.chisquare(3, 20), ate_estimate=0.1,
                               ate_dead_reckoning=1.0, nis_dof=dof))
    result = summarize(traces, skip=0)
    expected = sum(int(t.nis_dof.sum()) for t in traces) / sum(int(t.nis_count.sum()) for t in traces)
    assert result.nis_expected == pytest.approx(expected) and result.nis_expected < 3.9
    line = [m for m in result._metric_lines(*result.pose_nees_band) if m.startswith("NIS")][0]
    assert f"consistent with {round(expected, 3):g}" in line and "4n - 3" in line


def test_filter_is_consistent_on_its_own_model(tiny_mc):
    """Measured (seed 0, noise seeds 0-4): NIS 4.05 per observation, pose NEES 7.6 averaged over steps
    10-99 (runs 3.8-11.6), landmark NEES 3.3 (first-order update, update.second_order = false: 4.05,
    7.5, 3.4). Five runs of 100 steps spread widely (the 5-run band of the pose NEES is [3.4, 9.4]).
    Bounds: NIS [3.0, 5.0], pose NEES [2, 20] (about twice the spread of the 5-run averages
    measured): they catch a wrong pixel_sigma or a broken update; the 20-run tests below hold the band."""
    _, _, result, _, _ = tiny_mc
    assert 3.0 <= result.nis_mean <= 5.0
    assert 2.0 <= result.pose_nees_time_average <= 20.0
    assert 1.0 <= result.landmark_nees_mean <= 15.0


def test_monte_carlo_refuses_bad_arguments():
    from vislam.backend.errors import ConfigError

    scene = SceneFactory(SceneConfig(steps=20, landmark_density=0.5))
    with pytest.raises(ConfigError):
        monte_carlo(scene, Config(), runs=0)
    with pytest.raises(ConfigError):
        monte_carlo(scene, Config.from_values({"estimator.mode": "mapping"}), runs=1)


def test_mc_command_writes_json_and_plot(tmp_path, capsys):
    from vislam.tools.commands import mc

    parser = argparse.ArgumentParser()
    mc.add_parser(parser.add_subparsers(dest="command"))
    out = tmp_path / "mc"
    args = parser.parse_args(["mc", "--runs", "2", "--steps", "40", "--landmark-density", "0.5", "--true-noise",
                              "--out", str(out), "--set", "update.ransac_threshold_px=2.5"])
    assert args.func(args) == 0  # default workers: a process pool
    data = json.loads((out / "consistency.json").read_text())
    assert data["runs"] == 2 and data["steps"] == 40
    assert len(data["pose_nees"]["mean_per_step"]) == 40
    # --true-noise: the scene's own noise under --set
    assert data["filter"]["noise"]["pixel_sigma"] == 0.5 and data["filter"]["update"]["ransac_threshold_px"] == 2.5
    assert (out / "nees.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 3 and lines[0].startswith("pose NEES")


def test_filter_is_consistent_over_20_runs():
    """Over 20 runs of the default street scene (300 steps), the run-averaged pose NEES lies
    in its 95 % band for >= 90 % of the steps after the first 10 (measured: 100 %, time average
    6.23; 95 % and 6.74 with the first-order update), the NIS per observation is at its expectation
    and the landmark NEES near 3 (3.17).
    The filter is given the scene's own noise model; each run draws its gyro bias from the prior."""
    scene = SceneConfig(scenario="street", steps=300, seed=0)
    config = scene.filter_config()
    result = monte_carlo(SceneFactory(scene), config, runs=20, seed0=0)
    assert result.pose_nees_in_band >= 0.90
    assert 5.5 <= result.pose_nees_time_average <= 7.5
    assert abs(result.nis_mean - 4.0) <= 0.05
    assert 2.7 <= result.landmark_nees_mean <= 4.2


def test_filter_with_identified_noise_is_consistent_over_20_runs():
    """The same 20 runs with the noise identified from each run's data (the defaults, as `vislam run`
    and `vislam mc` run), not told the scene's: the run-averaged pose NEES lies in its 95 % band for
    >= 90 % of the steps (measured 99 %, time average 6.35; 90 % and 6.90 with the first-order update)."""
    scene = SceneConfig(scenario="street", steps=300, seed=0)
    result = monte_carlo(SceneFactory(scene), Config(), runs=20, seed0=0)
    assert result.pose_nees_in_band >= 0.90
    assert 5.5 <= result.pose_nees_time_average <= 7.5


def test_the_runs_mean_interval_and_its_verdict():
    """The interval of the mean comes from the spread of the runs' own means (Student t), and the
    verdict says which way and by how much a NEES or NIS misses its expectation."""
    from vislam.backend.evaluation.consistency import consistency_verdict, run_mean_interval

    values = np.array([2.7, 2.8, 2.75, 2.72, 2.78, np.nan])  # a run without landmarks: left out
    lo, hi = run_mean_interval(values)
    half = 2.7764451 * np.std(values[:5], ddof=1) / np.sqrt(5)  # t(0.975, 4)
    assert lo == pytest.approx(2.75 - half, rel=1e-6) and hi == pytest.approx(2.75 + half, rel=1e-6)
    text = consistency_verdict(3.0, values, "the map's covariances")
    assert "interval of the 5 runs' mean" in text and "8 % below 3" in text and "pessimistic" in text
    assert "overconfident" in consistency_verdict(4.0, [4.4, 4.5, 4.6], "the innovations' covariances")
    assert consistency_verdict(4.0, [3.9, 4.1, 4.0], "x").endswith("consistent with 4")
    assert consistency_verdict(3.0, [2.0], "x") == "one run: no interval of the mean"


@pytest.mark.parametrize("factor, verdict", [(1.0, "consistent with 6"), (1.5, "overconfident"), (0.6, "pessimistic")])
def test_the_pose_nees_line_says_what_the_runs_time_averages_give(factor, verdict):
    """The pose NEES line carries the interval of the runs' time averages (E1): each run is one
    independent sample however long its errors persist. Runs whose NEES is ``factor`` x chi2(6) at
    every step: 1 holds 6, 1.5 is flagged overconfident, 0.6 pessimistic; consistency.json has the
    same interval."""
    from vislam.backend.evaluation.consistency import RunTrace, run_mean_interval, summarize

    rng = np.random.default_rng(11)
    traces = [RunTrace(noise_seed=i, pose_nees=factor * rng.chisquare(6, 60), nis_sum=rng.chisquare(20, 60),
                       nis_count=np.full(60, 5), landmark_nees=rng.chisquare(3, 50), ate_estimate=0.1,
                       ate_dead_reckoning=1.0) for i in range(20)]
    result = summarize(traces)
    line = result.summary_lines()[0]
    assert line.startswith("pose NEES (6 dof)") and "interval of the 20 runs' mean" in line
    assert line.endswith(verdict) if factor == 1.0 else verdict in line
    lo, hi = run_mean_interval(result.per_run_pose_nees)
    assert (lo <= 6.0 <= hi) == (factor == 1.0)
    assert result.as_dict()["pose_nees"]["interval_of_run_mean"] == [lo, hi]
