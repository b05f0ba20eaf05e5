"""The run loop (``backend.run.online.OnlineRun``, ``backend.run.runner``): the step-by-step filter
that run_sequence and the image path share, and the conventions decided from a stream's first steps."""

from __future__ import annotations

import numpy as np
import pytest

from vislam.backend.config import Config
from vislam.backend.errors import InputError
from vislam.backend.estimator.propagation import dead_reckoning
from vislam.backend.geometry.camera import StereoCamera
from vislam.backend.run.conventions import decide_conventions
from vislam.backend.run.decisions import decide
from vislam.backend.run.noise import estimate_white_noise
from vislam.backend.run.online import OnlineRun
from vislam.backend.run.runner import decide_online, decisive, run_sequence, run_stream
from vislam.backend.run.stereo_offset import identify_stereo_offset
from vislam.synth.scene import SceneConfig, make_scene


@pytest.fixture(scope="module")
def scene():
    return make_scene(SceneConfig(steps=60, seed=4))


@pytest.fixture(scope="module")
def long_scene():
    """200 steps whose convention test is first decisive after 50 steps."""
    return make_scene(SceneConfig(steps=200, seed=3))


def _run(seq, velocity_index: str, config: Config) -> OnlineRun:
    """An OnlineRun with the extrinsic as given and ``velocity_index``, the IMU noise the white noise of
    the samples (the decisions of a dead-reckoning run, which uses no vision)."""
    decisions = decide(seq, Config.from_values({"estimator.mode": "dead-reckoning", "conventions.imu_flip": "no",
                                                "conventions.velocity_index": velocity_index}))
    c = decisions.conventions
    assert (c.imu_flip, c.velocity_index, c.flip_source, c.velocity_source) == (False, velocity_index, "configured",
                                                                                "configured")
    np.testing.assert_array_equal(c.imu_T_cam, seq.imu_T_cam)
    assert not decisions.velocity.active and not decisions.stereo_offset.active
    return OnlineRun(StereoCamera(seq.K, seq.baseline), decisions, config)


@pytest.mark.parametrize("velocity_index", ["this", "next"])
def test_online_dead_reckoning_matches_batch(scene, velocity_index):
    """The dead reckoning kept alongside, step by step, equals
    ``backend.estimator.propagation.dead_reckoning``; the filter in dead-reckoning mode follows it
    exactly."""
    seq = scene.sequence
    run = _run(seq, velocity_index, Config.from_values({"estimator.mode": "dead-reckoning"}))
    for k in range(seq.num_steps):
        run.step(seq.time_stamps[k], seq.linear_velocity[k], seq.angular_velocity[k], *seq.observations(k))
    result = run.result()
    batch = dead_reckoning(seq.time_stamps, seq.linear_velocity, seq.angular_velocity, velocity_index)
    np.testing.assert_allclose(result.dead_reckoning, batch, atol=1e-9)
    np.testing.assert_allclose(result.world_T_imu, batch, atol=1e-9)
    assert result.stats.steps == seq.num_steps


def test_online_run_equals_run_sequence(scene):
    seq = scene.sequence
    config = Config.from_values({"noise.pixel_sigma": scene.config.pixel_sigma, "conventions.velocity_index": "this",
                                 "conventions.imu_flip": "no"})
    batch = run_sequence(seq, config)
    run = OnlineRun(StereoCamera(seq.K, seq.baseline), batch.decisions, config)
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
    assert result.step_seconds.sum() <= s.filter_seconds


def test_online_run_refuses_time_going_back(scene):
    seq = scene.sequence
    run = _run(seq, "this", Config())
    run.step(1.0, seq.linear_velocity[0], seq.angular_velocity[0], *seq.observations(0))
    with pytest.raises(InputError, match="does not increase"):
        run.step(1.0, seq.linear_velocity[1], seq.angular_velocity[1], *seq.observations(1))


def test_repeats_previous_compares_the_shared_features_in_any_id_order():
    """A frame repeats the previous one when every shared feature has identical pixels; sorted ids
    take the compiled merge, unsorted ones the set intersection, with the same answers."""
    from vislam.backend.run.timing import repeats_previous

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


def _same_applied(a, b) -> bool:
    """Two ``Decisions`` that the filter applies alike: the conventions, no offset or velocity
    correction applied, the same IMU and pixel noise, drift and gyro bias."""
    return ((a.conventions.imu_flip, a.conventions.velocity_index) == (b.conventions.imu_flip, b.conventions.velocity_index)
            and np.array_equal(a.imu_T_cam, b.imu_T_cam)
            and not (a.stereo_offset.active or b.stereo_offset.active)
            and not (a.velocity.active or b.velocity.active)
            and np.array_equal(a.imu.linear_sigma, b.imu.linear_sigma)
            and np.array_equal(a.imu.angular_sigma, b.imu.angular_sigma)
            and a.pixels.sigma == b.pixels.sigma and a.drift.drifting == b.drift.drifting
            and a.gyro_bias.estimated == b.gyro_bias.estimated)


def test_run_stream_with_online_conventions_equals_run_sequence(long_scene):
    """``run_stream`` over ``seq.steps()`` with ``imu_velocities`` decides from the first steps; when
    that decision is the whole file's (``run_sequence``), the trajectory is the same: the steps read
    to decide are filtered too, none is lost. The IMU and pixel noise are configured (the scene's):
    identified, they would be measured on fewer steps than the whole file's."""
    seq = long_scene.sequence
    config = Config.from_values({"noise.pixel_sigma": long_scene.config.pixel_sigma,  # conventions: auto
                                 "noise.linear_velocity_sigma": long_scene.config.linear_sigma,
                                 "noise.angular_velocity_sigma": long_scene.config.angular_sigma})
    batch = run_sequence(seq, config)
    said = []
    stream = run_stream(seq.steps(), StereoCamera(seq.K, seq.baseline), seq.imu_T_cam, config,
                        imu_velocities=(seq.linear_velocity, seq.angular_velocity), tracker=seq.tracker,
                        say=said.append)
    first = [line for line in said if line.startswith("decided from the first ")]
    assert len(first) == 1 and int(first[0].split()[4]) < seq.num_steps  # decided from part of the stream
    assert stream.decisions.steps == int(first[0].split()[4]) and batch.decisions.steps == seq.num_steps
    online, whole = stream.conventions, batch.conventions
    assert online.errors_px and online.flip_source == "auto" == online.velocity_source  # a decision is made
    assert (online.imu_flip, online.velocity_index) == (whole.imu_flip, whole.velocity_index)
    np.testing.assert_array_equal(online.imu_T_cam, whole.imu_T_cam)
    assert _same_applied(stream.decisions, batch.decisions)
    # the white noise (N1) is the whole stream's (imu_velocities), not that of the steps read
    np.testing.assert_array_equal(stream.decisions.imu.white_linear, batch.decisions.imu.white_linear)
    np.testing.assert_array_equal(stream.decisions.imu.white_angular, batch.decisions.imu.white_angular)
    np.testing.assert_array_equal(stream.time_stamps, seq.time_stamps)
    np.testing.assert_allclose(stream.world_T_imu, batch.world_T_imu, atol=1e-12)
    assert stream.stats.observations_used == batch.stats.observations_used > 0
    assert stream.stats.steps == seq.num_steps and stream.stats.setup_seconds > 0


class _Counting:
    """An iterator over ``steps`` that counts the steps taken from it."""

    def __init__(self, steps):
        self._steps = iter(steps)
        self.taken = 0

    def __iter__(self):
        return self

    def __next__(self):
        step = next(self._steps)
        self.taken += 1
        return step


def _decide_online(steps, seq, config, num_steps=None):
    stream = _Counting(steps)
    decisions, read, seconds = decide_online(stream, StereoCamera(seq.K, seq.baseline), seq.imu_T_cam, config,
                                             (seq.linear_velocity, seq.angular_velocity), num_steps)
    assert len(read) == stream.taken and seconds >= 0.0  # every step taken is returned
    return decisions, read, stream


def _assert_first_steps(read, steps):
    assert len(read) <= len(steps)
    for got, want in zip(read, steps):
        assert got[0] == want[0]
        for a, b in zip(got[1:], want[1:]):
            np.testing.assert_array_equal(a, b)


#: Every noise configured: with the stereo offset off, the convention test is all decide_online waits for.
CONFIGURED_NOISE = {"noise.pixel_sigma": 0.5, "noise.linear_velocity_sigma": 0.2, "noise.angular_velocity_sigma": 0.01}


def test_decide_online_reads_until_decisive(long_scene):
    """Without the stereo offset and with every noise configured: from 20 steps on, every 10, the
    convention test runs on the steps read so far; the first decisive one ends the reading. The
    decision is the test's on those steps, the white noise (N1) is from the whole stream's
    velocities, and the stream goes on at the first step not read. With a noise left to identify,
    the reading goes on to ``conventions.online_steps``."""
    seq = long_scene.sequence
    config = Config.from_values({"conventions.stereo_offset": "off", **CONFIGURED_NOISE})
    steps = list(seq.steps())
    decisions, read, stream = _decide_online(steps, seq, config)
    conventions = decisions.conventions
    n = len(read)
    assert 30 <= n < config.conventions.online_steps and n % 10 == 0  # a test before it is not decisive
    assert decisions.steps == n
    _assert_first_steps(read, steps)
    for k in range(20, n, 10):  # the earlier tests were not decisive
        assert not decisive(decide_conventions(seq.subset(k)).errors_px)
    expected = decide_conventions(seq.subset(n))
    assert decisive(expected.errors_px)
    assert conventions.errors_px == expected.errors_px
    assert (conventions.imu_flip, conventions.velocity_index) == (expected.imu_flip, expected.velocity_index)
    assert not decisions.stereo_offset.active and not decisions.stereo_offset.estimate
    # the white noise of the whole stream, not of the steps read
    np.testing.assert_array_equal(decisions.imu.white_linear, estimate_white_noise(seq.linear_velocity))
    np.testing.assert_array_equal(decisions.imu.white_angular, estimate_white_noise(seq.angular_velocity))
    assert not np.array_equal(decisions.imu.white_linear, estimate_white_noise(seq.linear_velocity[:n]))
    assert next(stream)[0] == seq.time_stamps[n]  # nothing read beyond
    for key in CONFIGURED_NOISE:  # a noise to identify needs the steps
        unset = config.with_values({key: None})
        assert len(_decide_online(steps, seq, unset)[1]) == unset.conventions.online_steps


def test_decide_online_reads_online_steps_for_the_stereo_offset(long_scene):
    """With the stereo offset (the default) the reading goes on to ``conventions.online_steps``:
    the conventions are decided from every step read, and so is the offset."""
    seq = long_scene.sequence
    config = Config()
    steps = list(seq.steps())
    decisions, read, stream = _decide_online(steps, seq, config)
    n = config.conventions.online_steps
    assert len(read) == n and decisions.steps == n
    _assert_first_steps(read, steps)
    assert decisions.conventions.errors_px == decide_conventions(seq.subset(n)).errors_px
    expected = identify_stereo_offset(seq.subset(n), decisions.imu_T_cam)
    assert decisions.stereo_offset.estimate == expected.estimate
    assert next(stream)[0] == seq.time_stamps[n]


def test_decide_online_reads_at_most_online_steps(scene):
    """Without motion every variant fits alike and no test is decisive: the reading stops at
    ``conventions.online_steps``, at the stream's ``num_steps``, or where the stream ends."""
    seq = scene.sequence
    still = [(t, np.zeros(3), np.zeros(3), ids, pixels) for t, _, _, ids, pixels in seq.steps()]
    config = Config.from_values({"conventions.online_steps": 45, "conventions.stereo_offset": "off", **CONFIGURED_NOISE})
    decisions, read, stream = _decide_online(still, seq, config)
    conventions = decisions.conventions
    assert len(read) == 45 and not decisive(conventions.errors_px)
    assert len(conventions.errors_px) == 4 and np.isfinite(list(conventions.errors_px.values())).all()
    _assert_first_steps(read, still)
    assert next(stream)[0] == seq.time_stamps[45]
    _, read, _ = _decide_online(still, seq, config, num_steps=33)
    assert len(read) == 33
    _, read, stream = _decide_online(still[:12], seq, config)
    assert len(read) == 12 and stream.taken == 12
    _assert_first_steps(read, still)
    with pytest.raises(InputError, match="no steps"):
        _decide_online([], seq, config)
