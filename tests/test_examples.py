"""examples/: the README's API example runs as written and its online loop equals run_sequence."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "online_api.py"


def test_readme_shows_the_example_file():
    code = EXAMPLE.read_text()
    body = code[code.index('"""', 3) + 3:].strip()
    assert f"```python\n{body}\n```" in (ROOT / "README.md").read_text()


def test_example_runs_and_the_online_loop_equals_run_sequence(tmp_path):
    """Run from a directory outside the project (only the installed package is imported)."""
    done = subprocess.run([sys.executable, str(EXAMPLE)], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    positions = [np.array(m.split(), dtype=float)
                 for m in re.findall(r"final position \[([^\]]+)\]", done.stdout)]
    assert len(positions) == 2
    np.testing.assert_allclose(positions[1], positions[0], atol=1e-3)
    assert np.linalg.norm(positions[0]) > 10  # the scene moves: the comparison is not of two zeros


def test_filter_limits_its_own_blas_threads():
    """predict and update run with execution.blas_threads BLAS threads whatever the process uses;
    close() gives the process its setting back."""
    from threadpoolctl import threadpool_info, threadpool_limits

    import vislam
    from vislam.synth.scene import SceneConfig, make_scene

    seq = make_scene(SceneConfig(steps=3, seed=0)).sequence
    seen = []
    with threadpool_limits(2, user_api="blas"):  # the caller's setting
        config = vislam.Config().with_values({"noise.pixel_sigma": 1.5})  # a filter built directly needs one
        ekf = vislam.VisualInertialEKF(vislam.StereoCamera(seq.K, seq.baseline), seq.imu_T_cam, config,
                                       vislam.ImuNoise(np.full(3, 0.2), np.full(3, 0.01)))
        model_predict = ekf.model.predict

        def spy(*args, **kwargs):
            seen.append([i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"])
            return model_predict(*args, **kwargs)

        ekf.model.predict = spy
        steps = list(seq.steps())
        ekf.update(steps[0][3], steps[0][4])
        ekf.predict(0.1, steps[1][1], steps[1][2])
        ekf.close()
        after = [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]
    assert seen and all(n == 1 for n in seen[0])
    assert all(n == 2 for n in after) or not after  # the caller's setting is back after close()
