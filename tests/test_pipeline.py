"""backend.pipeline.OnlineRun: the streaming loop that run_sequence and the one-pass image path share."""

from __future__ import annotations

import numpy as np
import pytest

from backend.camera import StereoCamera
from backend.config import FilterConfig
from backend.conventions import ConventionDecision
from backend.errors import InputError
from backend.imu import dead_reckoning, decide_imu_noise
from backend.pipeline import OnlineRun, run_sequence
from synth.scene import SceneConfig, make_scene


@pytest.fixture(scope="module")
def scene():
    return make_scene(SceneConfig(steps=60, seed=4))


def _run(seq, velocity_index: str, config: FilterConfig) -> OnlineRun:
    conventions = ConventionDecision(False, velocity_index, seq.imu_T_cam, {}, "configured", "configured")
    noise = decide_imu_noise(seq.linear_velocity, seq.angular_velocity, None, None, 0.05, 0.002)
    return OnlineRun(StereoCamera(seq.K, seq.baseline), conventions, noise, config)


@pytest.mark.parametrize("velocity_index", ["this", "next"])
def test_online_dead_reckoning_matches_batch(scene, velocity_index):
    """The dead reckoning kept alongside, step by step, equals backend.imu.dead_reckoning; the
    filter in dead-reckoning mode follows it exactly."""
    seq = scene.sequence
    run = _run(seq, velocity_index, FilterConfig(mode="dead-reckoning"))
    for k in range(seq.num_steps):
        run.step(seq.time_stamps[k], seq.linear_velocity[k], seq.angular_velocity[k], *seq.observations(k))
    result = run.result()
    batch = dead_reckoning(seq.time_stamps, seq.linear_velocity, seq.angular_velocity, velocity_index)
    np.testing.assert_allclose(result.dead_reckoning, batch, atol=1e-9)
    np.testing.assert_allclose(result.world_T_imu, batch, atol=1e-9)
    assert result.stats.steps == seq.num_steps


def test_online_run_equals_run_sequence(scene):
    seq = scene.sequence
    config = FilterConfig(pixel_sigma=scene.config.pixel_sigma, velocity_index="this", imu_flip="no")
    batch = run_sequence(seq, config)
    run = OnlineRun(StereoCamera(seq.K, seq.baseline), batch.conventions, batch.imu_noise, config,
                    tracker=seq.tracker)
    for k in range(seq.num_steps):
        run.step(seq.time_stamps[k], seq.linear_velocity[k], seq.angular_velocity[k], *seq.observations(k))
    result = run.result()
    np.testing.assert_allclose(result.world_T_imu, batch.world_T_imu, atol=1e-12)
    assert result.stats.observations_used == batch.stats.observations_used > 0
    # one latency per step, and the summary's percentiles are of them
    s = result.stats
    assert result.step_seconds.shape == (seq.num_steps,) and np.all(result.step_seconds > 0)
    assert s.step_ms_median == pytest.approx(1e3 * np.median(result.step_seconds))
    assert s.step_ms_median <= s.step_ms_p99 <= s.step_ms_max == pytest.approx(1e3 * result.step_seconds.max())
    assert result.step_seconds.sum() <= s.wall_seconds


def test_online_run_refuses_time_going_back(scene):
    seq = scene.sequence
    run = _run(seq, "this", FilterConfig())
    run.step(1.0, seq.linear_velocity[0], seq.angular_velocity[0], *seq.observations(0))
    with pytest.raises(InputError, match="does not increase"):
        run.step(1.0, seq.linear_velocity[1], seq.angular_velocity[1], *seq.observations(1))


def test_repeats_previous_compares_the_shared_features_in_any_id_order():
    """A frame repeats the previous one when every shared feature has identical pixels; sorted ids
    take the compiled merge, unsorted ones the set intersection, with the same answers."""
    from backend.timing import repeats_previous

    rng = np.random.default_rng(0)
    prev_ids = np.array([2, 5, 9, 14])
    prev_px = rng.uniform(0, 500, (4, 4))
    ids = np.array([1, 5, 9, 20])
    px = rng.uniform(0, 500, (4, 4))
    px[1:3] = prev_px[1:3]  # ids 5 and 9 repeat their pixels
    cases = [(ids, px, True)]
    moved = px.copy()
    moved[2, 3] += 1e-9
    cases.append((ids, moved, False))
    cases.append((np.array([0, 3]), px[:2], False))  # nothing shared
    for now_ids, now_px, expected in cases:
        assert repeats_previous(now_ids, now_px, prev_ids, prev_px) is expected
        order = np.arange(now_ids.size)[::-1]  # decreasing ids: the fallback
        assert repeats_previous(now_ids[order], now_px[order], prev_ids, prev_px) is expected
