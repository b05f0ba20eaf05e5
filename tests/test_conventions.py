"""The convention test on synthetic data, where the truth is known: synthetic data
made by the course formulation must come out as k."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vislam.backend.run.conventions import IMU_FLIP, decide_conventions
from vislam.synth.scene import SceneConfig, make_scene


@pytest.mark.parametrize("velocity_index", ["this", "next"])
def test_velocity_timing_recovered(velocity_index):
    scene = make_scene(SceneConfig(steps=200, seed=3, velocity_index=velocity_index))
    decision = decide_conventions(scene.sequence)
    assert decision.velocity_index == velocity_index
    assert decision.imu_flip is False
    other = "next" if velocity_index == "this" else "this"
    errs = decision.errors_px
    assert errs[f"flip=no,velocity={velocity_index}"] < errs[f"flip=no,velocity={other}"]


def test_flip_recovered():
    """A file whose extrinsic has the IMU's y and z axes flipped is detected and corrected."""
    scene = make_scene(SceneConfig(steps=200, seed=4))
    seq = scene.sequence
    wrong = dataclasses.replace(seq, imu_T_cam=IMU_FLIP @ seq.imu_T_cam, _cam_T_imu_file=None)
    decision = decide_conventions(wrong)
    assert decision.imu_flip is True
    np.testing.assert_allclose(decision.imu_T_cam, seq.imu_T_cam, atol=1e-12)


def test_configured_choice_is_not_tested():
    scene = make_scene(SceneConfig(steps=50, seed=5))
    decision = decide_conventions(scene.sequence, imu_flip="no", velocity_index="next")
    assert (decision.imu_flip, decision.velocity_index) == (False, "next")
    assert decision.errors_px == {} and decision.flip_source == "configured"
