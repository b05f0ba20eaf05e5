"""Shared test helpers (imported by the test modules; pytest puts tests/ on sys.path)."""

from __future__ import annotations

import numpy as np

from vislam.backend.estimator import tracks


def numeric_jacobian(f, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Central finite differences of f at x: (..., x.size), one column per coordinate of x."""
    cols = []
    for i in range(x.size):
        dx = np.zeros_like(x, dtype=float)
        dx[i] = eps
        cols.append((f(x + dx) - f(x - dx)) / (2 * eps))
    return np.stack(cols, axis=-1)


# (U1) of backend.estimator.update: the orthogonal change of the 4 pixel rows [uL, vL, uR, vR] into
# the 3 rows the filter keeps, [uL, (vL + vR)/sqrt 2, uR], and the fourth, (vL - vR)/sqrt 2
_S = np.sqrt(0.5)
THREE_ROWS = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, _S, 0.0, _S], [0.0, 0.0, 1.0, 0.0]])
OFF_ROW = np.array([0.0, _S, 0.0, -_S])


def four_rows(three: np.ndarray, off: np.ndarray | float = 0.0) -> np.ndarray:
    """Back from the 3-row form (..., 3, n) with the fourth row's values ``off`` to the 4 pixel rows."""
    return THREE_ROWS.T @ three + OFF_ROW[:, None] * np.asarray(off)[..., None, None]


def slots_of(ekf, ids) -> np.ndarray:
    """State slots of the track ``ids`` in a VisualInertialEKF (-1 where not in the state)."""
    return tracks.slots_of(np.asarray(ids, dtype=np.int64), *ekf.state.index)


def observation_model(ekf, slots: np.ndarray, pixels: np.ndarray):
    """The filter's observation model of landmarks ``slots`` seen at ``pixels`` (k,4), whatever its error
    model, from the prior innovation it updates with (``ekf.model.innovation``), in the 3-row form (U1):
    residual (k,3), off_row (k,), H_xi (k,3,6), H_theta (k,3,3), in_front (k,)."""
    inn = ekf.model.innovation(ekf.state, np.asarray(slots, dtype=np.int64), np.asarray(pixels, dtype=float),
                               ekf.config.noise.pixel_sigma**2)
    return inn.residual, inn.off_row, inn.H_x.reshape(-1, 3, 6), inn.H_m, inn.in_front


def assert_clean_input_error(err: BaseException, path) -> str:
    """A one-line InputError starting with the file's name; returns the message."""
    from vislam.backend.errors import InputError

    assert isinstance(err, InputError), repr(err)
    msg = str(err)
    assert "\n" not in msg and "\r" not in msg, msg
    assert msg.startswith(f"{path}:"), msg
    return msg


def named_key(msg: str, path) -> str:
    """The key of ``<file>: key '<key>': ...``."""
    prefix = f"{path}: key '"
    assert msg.startswith(prefix), f"no key named: {msg}"
    return msg[len(prefix):].split("'", 1)[0]


#: the arrays of a synthetic ``synth.scene.Scene`` and of its sequence that two equal scenes share exactly
SCENE_ARRAYS = ("world_T_imu_true", "twists_true", "landmark_ids", "landmark_positions", "landmark_point_index",
                "points", "gyro_bias_true", "outlier")
SEQUENCE_ARRAYS = ("time_stamps", "linear_velocity", "angular_velocity", "obs_ptr", "obs_ids", "obs_pixels")


def assert_same_scene_arrays(a, b) -> None:
    """Every array of two synthetic scenes and of their sequences equal, bit for bit."""
    import numpy as np

    for name in SCENE_ARRAYS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for name in SEQUENCE_ARRAYS:
        np.testing.assert_array_equal(getattr(a.sequence, name), getattr(b.sequence, name), err_msg=name)


def street_file(folder, steps: int):
    """The default synthetic street of ``steps`` steps saved as ``folder/street_<steps>.npz``; its path.
    (1500 steps: a run of a few seconds, long enough to be interrupted.)"""
    from pathlib import Path

    from vislam.backend.data.npz import save_sequence
    from vislam.synth.scene import SceneConfig, make_scene

    path = Path(folder) / f"street_{steps}.npz"
    save_sequence(make_scene(SceneConfig(steps=steps)).sequence, path)
    return path
