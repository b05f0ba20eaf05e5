"""Tests of backend.config: validation, TOML round trip, overrides and error messages."""

from __future__ import annotations

import dataclasses

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from backend.config import FilterConfig, apply_overrides, config_from_dict, load_config, to_toml
from backend.errors import ConfigError, VislamError


def write(tmp_path, text: str, name: str = "config.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_defaults_validate():
    config = FilterConfig()
    assert config.validate() is config
    assert config_from_dict({}) == config
    assert config.mode == "slam" and config.linear_velocity_sigma is None
    text = config.describe()
    assert all(f.name in text for f in dataclasses.fields(FilterConfig))


def test_config_error_is_vislam_error():
    assert issubclass(ConfigError, VislamError)


def test_toml_round_trip_defaults(tmp_path):
    config = FilterConfig()
    assert load_config(write(tmp_path, to_toml(config))) == config


def test_toml_round_trip_changed(tmp_path):
    config = FilterConfig(
        mode="mapping", full_state=True, estimate_gyro_bias=False, imu_flip="yes", velocity_index="next",
        linear_velocity_sigma=0.3, angular_velocity_sigma=1e-6, pixel_sigma=2.5, image_width=1241.0, image_height=376.0,
        gate_probability=0.99, ransac_threshold_px=0.0, nis_window=7, max_consecutive_gated=5, max_depth=55.5,
        gyro_bias_random_walk=3.3e-7, max_state_mib=1e12,
    ).validate()
    text = to_toml(config)
    assert text.startswith("[filter]\n")
    loaded = load_config(write(tmp_path, text))
    assert loaded == config
    assert isinstance(loaded.nis_window, int) and isinstance(loaded.full_state, bool)
    assert loaded.angular_velocity_sigma == 1e-6 and loaded.max_state_mib == 1e12
    partial = dataclasses.replace(config, linear_velocity_sigma=None)  # unset optional: written as a comment
    assert load_config(write(tmp_path, to_toml(partial), "partial.toml")).linear_velocity_sigma is None


@settings(max_examples=50, deadline=None)
@given(
    pixel_sigma=st.floats(1e-300, 1e300),
    gate=st.floats(0.5, 1.0, exclude_min=True, exclude_max=True),
    sigma=st.one_of(st.none(), st.floats(1e-12, 1e6)),
    window=st.integers(1, 10**9),
)
def test_toml_round_trip_property(tmp_path_factory, pixel_sigma, gate, sigma, window):
    config = FilterConfig(pixel_sigma=pixel_sigma, gate_probability=gate, linear_velocity_sigma=sigma, nis_window=window)
    path = tmp_path_factory.mktemp("rt") / "c.toml"
    path.write_text(to_toml(config.validate()))
    assert load_config(path) == config


def test_filter_table_and_flat_keys(tmp_path):
    flat = write(tmp_path, 'pixel_sigma = 2.5\nmode = "mapping"\nnis_window = 7\n', "flat.toml")
    table = write(tmp_path, '[filter]\npixel_sigma = 2.5\nmode = "mapping"\nnis_window = 7\n', "table.toml")
    a, b = load_config(flat), load_config(table)
    assert a == b
    assert (a.pixel_sigma, a.mode, a.nis_window) == (2.5, "mapping", 7)
    assert dataclasses.replace(a, pixel_sigma=1.5, mode="slam", nis_window=50) == FilterConfig()


def test_load_over_base_keeps_other_values(tmp_path):
    base = FilterConfig(pixel_sigma=3.0, max_consecutive_gated=10)
    loaded = load_config(write(tmp_path, "[filter]\nmax_consecutive_gated = 20\n"), base)
    assert (loaded.pixel_sigma, loaded.max_consecutive_gated) == (3.0, 20)
    assert base.max_consecutive_gated == 10  # not modified


def test_int_accepted_for_float_key(tmp_path):
    loaded = load_config(write(tmp_path, "pixel_sigma = 2\n"))
    assert loaded.pixel_sigma == 2.0 and isinstance(loaded.pixel_sigma, float)


def test_unknown_key(tmp_path):
    with pytest.raises(ConfigError, match="pixel_sigm'"):
        config_from_dict({"pixel_sigm": 1.0})
    path = write(tmp_path, "[filter]\nno_such_key = 1\n")
    with pytest.raises(ConfigError, match="no_such_key") as info:
        load_config(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize(
    "key, value",
    [
        ("pixel_sigma", "abc"),
        ("pixel_sigma", True),
        ("pixel_sigma", [1.0]),
        ("nis_window", 2.5),
        ("nis_window", True),
        ("nis_window", "seven"),
        ("full_state", 1),
        ("full_state", "maybe"),
        ("mode", 3),
        ("linear_velocity_sigma", "fast"),
        ("reanchor_observations", 2.5),
    ],
)
def test_wrong_type(key, value):
    with pytest.raises(ConfigError, match=f"'{key}'"):
        config_from_dict({key: value})


def test_wrong_type_in_file(tmp_path):
    path = write(tmp_path, '[filter]\nnis_window = "ten"\n')
    with pytest.raises(ConfigError, match="nis_window"):
        load_config(path)


@pytest.mark.parametrize(
    "key, value",
    [
        ("mode", "fast"),
        ("imu_flip", "maybe"),
        ("velocity_index", "previous"),
        ("repeated_frames", "drop"),
        ("landmark_parametrization", "polar"),
    ],
)
def test_bad_choice(key, value):
    with pytest.raises(ConfigError, match=f"'{key}'.*must be one of"):
        config_from_dict({key: value})


@pytest.mark.parametrize(
    "key, value",
    [
        ("pixel_sigma", 0.0),
        ("pixel_sigma", -1.0),
        ("pixel_sigma", float("nan")),
        ("initial_pose_sigma", float("inf")),
        ("linear_velocity_sigma", -0.1),
        ("gate_probability", 1.0),
        ("gate_probability", 0.5),
        ("min_disparity", -1.0),
        ("nis_window", 0),
        ("max_consecutive_gated", 0),
        ("reanchor_observations", -1),
        ("reanchor_far_observations", -3),
        ("reanchor_far_disparity", float("nan")),
        ("persistent_outlier_steps", -1),
    ],
)
def test_invalid_value(key, value):
    with pytest.raises(ConfigError, match=f"'{key}'"):
        config_from_dict({key: value})


@pytest.mark.parametrize("key, value", [("max_consecutive_gated", -1), ("nis_warn_factor", 0.5)])
def test_invalid_value_not_caught(key, value):
    with pytest.raises(ConfigError, match=f"'{key}'"):
        config_from_dict({key: value})


def test_apply_overrides():
    base = FilterConfig(linear_velocity_sigma=0.3)
    config = apply_overrides(base, ["pixel_sigma=2.5", "mode=mapping", "linear_velocity_sigma=none"])
    assert (config.pixel_sigma, config.mode, config.linear_velocity_sigma) == (2.5, "mapping", None)
    assert base.linear_velocity_sigma == 0.3 and base.pixel_sigma == 1.5  # base untouched
    more = apply_overrides(config, ["full-state=yes", " nis_window = 7 ", "max_depth=auto", "estimate_gyro_bias=off"])
    assert (more.full_state, more.nis_window, more.max_depth, more.estimate_gyro_bias) == (True, 7, None, False)
    assert apply_overrides(base, []) == base


@pytest.mark.parametrize(
    "item, key",
    [("pixel_sigma", "pixel_sigma"), ("pixel_sigma=abc", "pixel_sigma"), ("mode=fast", "mode"), ("bogus=1", "bogus")],
)
def test_apply_overrides_errors(item, key):
    with pytest.raises(ConfigError, match=key):
        apply_overrides(FilterConfig(), [item])


def test_load_errors(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.toml")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(write(tmp_path, "pixel_sigma = = 2\n"))
    with pytest.raises(ConfigError, match="'filter' must be a table"):
        load_config(write(tmp_path, 'filter = "slam"\n'))


def test_top_level_keys_next_to_filter_table_not_ignored(tmp_path):
    path = write(tmp_path, 'pixel_sigma = 2.5\n[filter]\nmode = "mapping"\n')
    try:
        config = load_config(path)
    except ConfigError:
        return  # refusing the mixed file is fine too
    assert config.pixel_sigma == 2.5
