"""backend.chi2: the chi-square upper tail and quantile (X1, X2) against scipy's, and a velocity run's
process without scipy.special or scipy.linalg."""

import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.special import chdtrc, chdtri

from vislam.backend import chi2

DOF = st.one_of(st.integers(1, 40), st.integers(41, 60000))
PROBABILITY = st.floats(1e-5, 1.0 - 1e-7)


@settings(max_examples=300, deadline=None)
@given(dof=DOF, probability=PROBABILITY)
def test_the_quantile_is_scipys(dof, probability):
    expected = chdtri(dof, 1.0 - probability)
    assert chi2.quantile(dof, probability) == pytest.approx(expected, rel=1e-8)


@settings(max_examples=300, deadline=None)
@given(dof=DOF, scale=st.floats(0.0, 4.0))
def test_the_upper_tail_is_scipys(dof, scale):
    x = scale * dof + 1e-3 * scale
    assert chi2.upper_tail(x, dof) == pytest.approx(chdtrc(dof, x), abs=1e-11, rel=1e-9)


@settings(max_examples=100, deadline=None)
@given(dof=st.integers(1, 2000), probability=PROBABILITY)
def test_the_quantile_inverts_the_tail(dof, probability):
    x = chi2.quantile(dof, probability)
    assert chi2.upper_tail(x, dof) == pytest.approx(1.0 - probability, abs=1e-12, rel=1e-8)


def test_the_quantiles_the_filter_uses():
    assert chi2.quantile(4, 0.999) == pytest.approx(18.4668, abs=1e-4)  # the update's gate (U4)
    assert chi2.quantile(3, 0.95) == pytest.approx(7.8147, abs=1e-4)  # the NEES ellipsoid (E4)
    assert chi2.quantile(6, 0.95) == pytest.approx(12.5916, abs=1e-4)
    assert chi2.upper_tail(0.0, 3) == 1.0 and chi2.upper_tail(-1.0, 2) == 1.0


@pytest.mark.parametrize("dof, probability", [(0, 0.5), (2.5, 0.5), (-1, 0.5), (3, 0.0), (3, 1.0), (3, np.nan)])
def test_bad_arguments_are_refused(dof, probability):
    with pytest.raises(ValueError):
        chi2.quantile(dof, probability)


def test_a_velocity_run_imports_neither_scipy_special_nor_scipy_linalg(tmp_path):
    """Their imports (scipy's array-API layer with them) cost a run's start-up 0.2 s: the chi-square
    quantiles are ``backend.chi2``'s and the kernels' BLAS is bound from scipy's cython modules alone
    (``estimator.linalg``). In a fresh interpreter (this one has both), a run of a feature file with
    its decisions, filter and outputs; the filter's results are those of the same run here."""
    from vislam.backend.data.npz import save_sequence
    from vislam.backend.run.runner import run_sequence
    from vislam.synth.scene import SceneConfig, make_scene

    scene = make_scene(SceneConfig(steps=40, seed=2))
    path = tmp_path / "scene.npz"
    save_sequence(scene.sequence, path)
    script = f"""
import sys
import numpy as np
from pathlib import Path
from vislam.backend.data.npz import load_sequence
from vislam.backend.run.runner import run_sequence
from vislam.tools.report import write_run_outputs
result = run_sequence(load_sequence({str(path)!r}))
write_run_outputs(result, Path({str(tmp_path / "out")!r}), "scene.npz", None)
np.save({str(tmp_path / "poses.npy")!r}, result.world_T_imu)
print(sorted(m for m in ("scipy.special", "scipy.linalg", "scipy.stats") if m in sys.modules))
"""
    (tmp_path / "out").mkdir()
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "[]"
    here = run_sequence(scene.sequence).world_T_imu
    assert np.allclose(np.load(tmp_path / "poses.npy"), here, atol=1e-9)
