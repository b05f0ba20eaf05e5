"""Tests of vislam.backend.config (the estimator's tables), vislam.backend.options (the typed-table
mechanism) and the front end's [tracker] table (vislam.frontend.config): validation, coercion,
TOML round trip, overrides and error messages naming ``table.key``."""

from __future__ import annotations

import dataclasses
import enum
import typing
from dataclasses import dataclass, field
from typing import Optional

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vislam.backend.config import (
    Choice,
    Config,
    ErrorModel,
    Mode,
    Parametrization,
    RepeatedFrames,
    VelocityIndex,
)
from vislam.backend.errors import ConfigError, VislamError
from vislam.backend.options import OptionSet, OptionTable
from vislam.frontend.config import FundamentalMethod, TrackerConfig

TABLES = ("estimator", "noise", "update", "landmarks", "drift", "health", "conventions", "input", "execution")


def write(tmp_path, text: str, name: str = "config.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


# ---------------------------------------------------------------------------------------------- defaults


def test_defaults_validate():
    config = Config()
    assert config.validate() is config
    assert Config.from_values({}) == config
    assert tuple(config.tables()) == TABLES
    assert config.estimator.mode == "slam" and config.noise.linear_velocity_sigma is None
    assert config.noise.pixel_sigma is None  # identified from the data (N2) unless set
    assert config.conventions.repeated_frames == "freeze" and config.conventions.velocity_correction == "auto"
    text = config.describe()
    for name, table in config.tables().items():
        assert f"[{name}]" in text
        assert all(f.name in text for f in dataclasses.fields(table))
    nested = config.as_dict()
    assert set(nested) == set(TABLES)
    assert nested["noise"]["pixel_sigma"] is None and nested["landmarks"]["parametrization"] == "xyz"


def test_config_error_is_vislam_error():
    assert issubclass(ConfigError, VislamError)


# ---------------------------------------------------------------------------------------------- TOML round trip


def test_toml_round_trip_defaults(tmp_path):
    config = Config()
    assert Config.load(write(tmp_path, config.to_toml())) == config


def test_toml_round_trip_changed(tmp_path):
    config = Config.from_values({
        "estimator.mode": "mapping", "estimator.full_state": True, "estimator.estimate_gyro_bias": False,
        "conventions.imu_flip": "yes", "conventions.velocity_index": "next",
        "noise.linear_velocity_sigma": 0.3, "noise.angular_velocity_sigma": 1e-6, "noise.pixel_sigma": 2.5,
        "input.image_width": 1241.0, "input.image_height": 376.0,
        "update.gate_probability": 0.99, "update.ransac_threshold_px": 0.0, "health.nis_window": 7,
        "update.max_consecutive_gated": 5, "landmarks.max_depth": 55.5,
        "noise.gyro_bias_random_walk": 3.3e-7, "estimator.max_state_mib": 1e12,
    })
    text = config.to_toml()
    assert text.startswith("[estimator]\n")
    assert all(f"[{name}]\n" in text for name in TABLES)
    loaded = Config.load(write(tmp_path, text))
    assert loaded == config
    assert isinstance(loaded.health.nis_window, int) and isinstance(loaded.estimator.full_state, bool)
    assert isinstance(loaded.estimator.mode, Mode) and isinstance(loaded.conventions.imu_flip, Choice)
    assert loaded.noise.angular_velocity_sigma == 1e-6 and loaded.estimator.max_state_mib == 1e12
    partial = config.with_values({"noise.linear_velocity_sigma": None})  # unset optional: written as a comment
    assert "# linear_velocity_sigma" in partial.to_toml()
    assert Config.load(write(tmp_path, partial.to_toml(), "partial.toml")).noise.linear_velocity_sigma is None


def test_toml_round_trip_unset_optional_with_a_default(tmp_path):
    """An optional key unset although its default is a value (landmarks.max_depth: no depth limit)."""
    config = Config.from_values({"landmarks.max_depth": None})
    assert config.landmarks.max_depth is None
    assert Config.load(write(tmp_path, config.to_toml())).landmarks.max_depth is None


def _strategy_of(key: str, kind: type, optional: bool) -> st.SearchStrategy:
    """Valid values of one option: its type's values inside the range the table's check accepts."""
    special = {
        "update.gate_probability": st.floats(0.5, 1.0, exclude_min=True, exclude_max=True),
        "health.nis_warn_factor": st.floats(1.0, 1e100, exclude_min=True),
        "estimator.window": st.one_of(st.just(0), st.integers(2, 10**9)),  # 0: off, else at least 2 clones
        "update.huber_probability": st.one_of(st.just(0.0), st.floats(0.5, 1.0, exclude_min=True, exclude_max=True)),
        "drift.track_test_probability": st.one_of(st.just(0.0), st.floats(1e-300, 0.5, exclude_max=True)),
    }
    if key in special:
        values = special[key]
    elif issubclass(kind, enum.Enum):
        values = st.sampled_from(list(kind))
    elif kind is bool:
        values = st.booleans()
    elif kind is int:
        values = st.integers(1, 10**9)
    elif kind is float:
        values = st.floats(1e-300, 1e100)  # the range of a number option (backend.options)
    else:  # pragma: no cover - a new option type: extend the strategy
        raise AssertionError(f"no strategy for {key}: {kind}")
    return st.one_of(st.none(), values) if optional else values


def _valid_config_values() -> st.SearchStrategy:
    """{"table.key": value} over every option of every table, with the rules across keys respected."""
    strategies = {}
    for name, table in Config.table_types().items():
        hints = typing.get_type_hints(table)
        for f in dataclasses.fields(table):
            kind = hints[f.name]
            args = typing.get_args(kind)
            optional = type(None) in args
            if optional:
                kind = next(a for a in args if a is not type(None))
            strategies[f"{name}.{f.name}"] = _strategy_of(f"{name}.{f.name}", kind, optional)

    def consistent(values: dict) -> dict:
        values = dict(values)
        if values["input.image_width"] is None or values["input.image_height"] is None:  # both or neither
            values["input.image_width"] = values["input.image_height"] = None
        if values["estimator.error_model"] == ErrorModel.INVARIANT:  # the invariant model needs xyz landmarks
            values["landmarks.parametrization"] = Parametrization.XYZ
        return values

    return st.fixed_dictionaries(strategies).map(consistent)


@settings(max_examples=50, deadline=None)
@given(values=_valid_config_values())
def test_toml_round_trip_property(tmp_path_factory, values):
    config = Config.from_values(values)
    path = tmp_path_factory.mktemp("rt") / "c.toml"
    path.write_text(config.to_toml())
    loaded = Config.load(path)
    assert loaded == config
    assert loaded.as_dict() == config.as_dict()


# ---------------------------------------------------------------------------------------------- reading files


def test_load_tables(tmp_path):
    path = write(tmp_path, '[noise]\npixel_sigma = 2.5\n[estimator]\nmode = "mapping"\n[health]\nnis_window = 7\n')
    config = Config.load(path)
    assert (config.noise.pixel_sigma, config.estimator.mode, config.health.nis_window) == (2.5, "mapping", 7)
    assert config.with_values({"noise.pixel_sigma": None, "estimator.mode": "slam", "health.nis_window": 50}) == Config()


def test_filter_table_and_flat_keys_are_refused_naming_the_new_place(tmp_path):
    flat = write(tmp_path, 'pixel_sigma = 2.5\nmode = "mapping"\n', "flat.toml")
    with pytest.raises(ConfigError, match="'pixel_sigma' is now 'noise.pixel_sigma'") as info:
        Config.load(flat)
    assert str(flat) in str(info.value)
    table = write(tmp_path, "[filter]\npixel_sigma = 2.5\n", "table.toml")
    with pytest.raises(ConfigError, match=r"\[filter\].*'pixel_sigma' is now 'noise.pixel_sigma'") as info:
        Config.load(table)
    assert str(table) in str(info.value)
    renamed = write(tmp_path, "[filter]\nlandmark_parametrization = \"xyz\"\n", "renamed.toml")
    with pytest.raises(ConfigError, match="'landmarks.parametrization'"):
        Config.load(renamed)


def test_top_level_keys_next_to_tables_are_refused(tmp_path):
    path = write(tmp_path, 'pixel_sigma = 2.5\n[estimator]\nmode = "mapping"\n')
    with pytest.raises(ConfigError, match="'pixel_sigma' is now 'noise.pixel_sigma'"):
        Config.load(path)


def test_load_over_base_keeps_other_values(tmp_path):
    base = Config.from_values({"noise.pixel_sigma": 3.0, "update.max_consecutive_gated": 10})
    loaded = Config.load(write(tmp_path, "[update]\nmax_consecutive_gated = 20\n"), base)
    assert (loaded.noise.pixel_sigma, loaded.update.max_consecutive_gated) == (3.0, 20)
    assert base.update.max_consecutive_gated == 10  # not modified


def test_int_accepted_for_float_key(tmp_path):
    loaded = Config.load(write(tmp_path, "[noise]\npixel_sigma = 2\n"))
    assert loaded.noise.pixel_sigma == 2.0 and isinstance(loaded.noise.pixel_sigma, float)


def test_tracker_table_is_the_front_ends(tmp_path):
    path = write(tmp_path, '[noise]\npixel_sigma = 2.5\n[tracker]\ntarget_tracks = 200\nfundamental_method = "ransac"\n')
    config = Config.load(path, foreign=("tracker",))
    assert config == Config().with_values({"noise.pixel_sigma": 2.5})
    with pytest.raises(ConfigError, match=r"unknown table \[tracker\]"):  # not skipped unless named foreign
        Config.load(path)
    tracker = TrackerConfig.load(path)  # reads [tracker] only
    assert tracker == TrackerConfig.from_values({"target_tracks": 200, "fundamental_method": "ransac"})
    assert tracker.fundamental_method is FundamentalMethod.RANSAC
    assert TrackerConfig.load(write(tmp_path, "[noise]\npixel_sigma = 2.5\n", "no_tracker.toml")) == TrackerConfig()
    base = TrackerConfig.from_values({"grid_cols": 6})
    assert (TrackerConfig.load(path, base).grid_cols, TrackerConfig.load(path, base).target_tracks) == (6, 200)
    bad = write(tmp_path, "[tracker]\ntarget_trakcs = 200\n", "bad.toml")
    with pytest.raises(ConfigError, match="'tracker.target_trakcs'") as info:
        TrackerConfig.load(bad)
    assert str(bad) in str(info.value)
    with pytest.raises(ConfigError, match="'tracker.lk_window'"):
        TrackerConfig.load(write(tmp_path, "[tracker]\nlk_window = 14\n", "even.toml"))
    # a config.toml of an image run: every table; each reader takes its own
    both = write(tmp_path, config.to_toml() + "\n" + tracker.to_toml(), "both.toml")
    assert Config.load(both, foreign=("tracker",)) == config and TrackerConfig.load(both) == tracker


# ---------------------------------------------------------------------------------------------- refusals


def test_unknown_key(tmp_path):
    with pytest.raises(ConfigError, match="'noise.pixel_sigm'"):
        Config.from_values({"noise.pixel_sigm": 1.0})
    with pytest.raises(ConfigError, match="unknown config key 'pixel_sigm'"):
        Config.from_values({"pixel_sigm": 1.0})
    path = write(tmp_path, "[noise]\nno_such_key = 1\n")
    with pytest.raises(ConfigError, match="'noise.no_such_key'") as info:
        Config.load(path)
    assert str(path) in str(info.value)


def test_unknown_table(tmp_path):
    with pytest.raises(ConfigError, match=r"unknown table \[nosie\]"):
        Config.from_values({"nosie": {"sigma": 1.0}})
    path = write(tmp_path, "[bogus]\nsigma = 1\n")
    with pytest.raises(ConfigError, match=r"unknown table \[bogus\]") as info:
        Config.load(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize(
    "key, new",
    [
        ("pixel_sigma", "noise.pixel_sigma"),
        ("landmark_parametrization", "landmarks.parametrization"),
        ("convention_horizon", "conventions.horizon"),
        ("online_convention_steps", "conventions.online_steps"),
        ("mode", "estimator.mode"),
        ("ransac_threshold_px", "update.ransac_threshold_px"),
        ("image_width", "input.image_width"),
    ],
)
def test_flat_keys_are_refused_naming_the_new_place(key, new):
    with pytest.raises(ConfigError, match=f"'{key}' is now '{new}'"):
        Config.from_values({key: 1})
    with pytest.raises(ConfigError, match=f"'{key}' is now '{new}'"):
        Config().with_assignments([f"{key}=1"])


@pytest.mark.parametrize(
    "key, value",
    [
        ("noise.pixel_sigma", "abc"),
        ("noise.pixel_sigma", True),
        ("noise.pixel_sigma", [1.0]),
        ("health.nis_window", 2.5),
        ("health.nis_window", True),
        ("health.nis_window", "seven"),
        ("estimator.full_state", 2),
        ("estimator.full_state", 1.0),
        ("estimator.full_state", "maybe"),
        ("estimator.mode", 3),
        ("noise.linear_velocity_sigma", "fast"),
        ("drift.reanchor_observations", 2.5),
    ],
)
def test_wrong_type(key, value):
    with pytest.raises(ConfigError, match=f"'{key}'"):
        Config.from_values({key: value})


def test_bool_as_0_or_1_in_file_as_on_the_command_line(tmp_path):
    """`full_state = 0` in TOML means what `--set estimator.full_state=0` means."""
    for text, expect in (("0", False), ("1", True), ("false", False)):
        path = write(tmp_path, f"[estimator]\nfull_state = {text}\n")
        assert Config.load(path).estimator.full_state is expect
        assert Config.from_values({"estimator.full_state": text}).estimator.full_state is expect


def test_wrong_type_in_file(tmp_path):
    path = write(tmp_path, '[health]\nnis_window = "ten"\n')
    with pytest.raises(ConfigError, match="'health.nis_window'") as info:
        Config.load(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize(
    "key, value",
    [
        ("estimator.mode", "fast"),
        ("estimator.error_model", "left"),
        ("conventions.imu_flip", "maybe"),
        ("conventions.velocity_index", "previous"),
        ("conventions.repeated_frames", "drop"),
        ("landmarks.parametrization", "polar"),
        ("drift.track_drift", "sometimes"),
    ],
)
def test_bad_choice(key, value):
    with pytest.raises(ConfigError, match=f"'{key}'.*must be one of"):
        Config.from_values({key: value})


@pytest.mark.parametrize(
    "key, value",
    [
        ("noise.pixel_sigma", 0.0),
        ("noise.pixel_sigma", -1.0),
        ("noise.pixel_sigma", float("nan")),
        ("noise.initial_pose_sigma", float("inf")),
        ("noise.linear_velocity_sigma", -0.1),
        ("update.gate_probability", 1.0),
        ("update.gate_probability", 0.5),
        ("update.ransac_threshold_px", -1.0),
        ("landmarks.min_disparity", -1.0),
        ("health.nis_window", 0),
        ("update.max_consecutive_gated", 0),
        ("drift.reanchor_observations", -1),
        ("drift.reanchor_far_observations", -3),
        ("drift.reanchor_far_disparity", float("nan")),
        ("update.persistent_outlier_steps", -1),
    ],
)
def test_invalid_value(key, value):
    with pytest.raises(ConfigError, match=f"'{key}'"):
        Config.from_values({key: value})


@pytest.mark.parametrize("key, value", [("update.max_consecutive_gated", -1), ("health.nis_warn_factor", 0.5)])
def test_invalid_value_not_caught(key, value):
    with pytest.raises(ConfigError, match=f"'{key}'"):
        Config.from_values({key: value})


def test_negative_ransac_threshold_is_refused():
    with pytest.raises(ConfigError) as info:
        Config.from_values({"update.ransac_threshold_px": -1})
    assert str(info.value) == "config key 'update.ransac_threshold_px': must be a finite number >= 0, got -1.0"
    assert Config.from_values({"update.ransac_threshold_px": 0}).update.ransac_threshold_px == 0.0  # 0: off


def test_invariant_error_model_needs_xyz_landmarks():
    with pytest.raises(ConfigError, match="'estimator.error_model'.*landmarks.parametrization"):
        Config.from_values({"landmarks.parametrization": "inverse-depth"})
    with pytest.raises(ConfigError, match="'estimator.error_model'"):
        Config.from_values({"estimator.error_model": "invariant", "landmarks.parametrization": "inverse-depth"})
    body = Config.from_values({"estimator.error_model": "body", "landmarks.parametrization": "inverse-depth"})
    assert body.landmarks.parametrization is Parametrization.INVERSE_DEPTH
    with pytest.raises(ConfigError, match="'estimator.error_model'"):  # nor through a later change
        body.with_values({"estimator.error_model": "invariant"})


def test_image_size_both_or_neither():
    with pytest.raises(ConfigError, match="'input.image_width' and 'input.image_height'"):
        Config.from_values({"input.image_width": 1241.0})
    config = Config.from_values({"input.image_width": 1241, "input.image_height": 376})
    assert config.input.image_size == (1241.0, 376.0) and Config().input.image_size is None


# ---------------------------------------------------------------------------------------------- overrides


def test_from_values_coerces_strings():
    config = Config.from_values({
        "estimator.full_state": "yes", "estimator.estimate_gyro_bias": "off", "health.nis_window": "7",
        "noise.pixel_sigma": "2", "noise.linear_velocity_sigma": "none", "landmarks.max_depth": "auto",
        "conventions.imu_flip": "yes", "estimator.mode": "dead-reckoning",
    })
    assert config.estimator.full_state is True and config.estimator.estimate_gyro_bias is False
    assert config.health.nis_window == 7 and isinstance(config.health.nis_window, int)
    assert config.noise.pixel_sigma == 2.0 and isinstance(config.noise.pixel_sigma, float)
    assert config.noise.linear_velocity_sigma is None and config.landmarks.max_depth is None
    assert config.conventions.imu_flip is Choice.YES and config.estimator.mode is Mode.DEAD_RECKONING
    # a table given as a dict of its keys is the same as "table.key" keys
    assert Config.from_values({"noise": {"pixel_sigma": 2.0}}) == Config.from_values({"noise.pixel_sigma": 2.0})


def test_with_values_leaves_the_original():
    base = Config.from_values({"noise.pixel_sigma": 3.0})
    changed = base.with_values({"noise.pixel_sigma": "0.5", "update.max_consecutive_gated": "4"})
    assert (changed.noise.pixel_sigma, changed.update.max_consecutive_gated) == (0.5, 4)
    assert (base.noise.pixel_sigma, base.update.max_consecutive_gated) == (3.0, 3)
    assert base.with_values({}) == base


def test_with_assignments():
    base = Config.from_values({"noise.linear_velocity_sigma": 0.3})
    config = base.with_assignments(["noise.pixel_sigma=2.5", "estimator.mode=mapping", "noise.linear_velocity_sigma=none"])
    assert (config.noise.pixel_sigma, config.estimator.mode, config.noise.linear_velocity_sigma) == (2.5, "mapping", None)
    assert base.noise.linear_velocity_sigma == 0.3 and base.noise.pixel_sigma is None  # base untouched
    more = config.with_assignments(["estimator.full-state=yes", " health.nis_window = 7 ", "landmarks.max_depth=auto",
                                    "estimator.estimate_gyro_bias=off"])
    assert (more.estimator.full_state, more.health.nis_window, more.landmarks.max_depth,
            more.estimator.estimate_gyro_bias) == (True, 7, None, False)
    assert base.with_assignments([]) == base
    # the front end's table is skipped when named foreign
    assert base.with_assignments(["tracker.target_tracks=100"], foreign=("tracker",)) == base


@pytest.mark.parametrize(
    "item, key",
    [
        ("noise.pixel_sigma", "noise.pixel_sigma"),
        ("noise.pixel_sigma=abc", "noise.pixel_sigma"),
        ("estimator.mode=fast", "estimator.mode"),
        ("bogus=1", "bogus"),
        ("noise.bogus=1", "noise.bogus"),
        ("pixel_sigma=2", "noise.pixel_sigma"),
        ("tracker.target_tracks=100", "'tracker.target_tracks'"),
    ],
)
def test_with_assignments_errors(item, key):
    with pytest.raises(ConfigError, match=key):
        Config().with_assignments([item])


def test_load_errors(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        Config.load(tmp_path / "missing.toml")
    with pytest.raises(ConfigError, match="not valid TOML"):
        Config.load(write(tmp_path, "[noise]\npixel_sigma = = 2\n"))
    with pytest.raises(ConfigError, match="'filter'"):
        Config.load(write(tmp_path, 'filter = "slam"\n'))


# ---------------------------------------------------------------------------------------------- choices


@pytest.mark.parametrize(
    "member, text",
    [(Mode.DEAD_RECKONING, "dead-reckoning"), (ErrorModel.BODY, "body"), (Parametrization.INVERSE_DEPTH, "inverse-depth"),
     (Choice.AUTO, "auto"), (VelocityIndex.NEXT, "next"), (RepeatedFrames.SKIP, "skip"),
     (FundamentalMethod.MAGSAC, "magsac")],
)
def test_choices_are_their_strings(member, text):
    assert member == text and text == member
    assert hash(member) == hash(text)
    assert {text: 1}[member] == 1 and {member: 1}[text] == 1
    assert str(member) == text and f"{member}" == text and f"{member:>20}" == f"{text:>20}"
    assert member != text + "x"
    assert type(member)(text) is member


# ---------------------------------------------------------------------------------------------- the mechanism


class Colour(enum.Enum):
    RED = "red"
    BLUE = "blue"


@dataclass
class ToyOptions(OptionTable):
    TABLE = "toy"
    count: int = 1
    scale: float = 1.0
    label: str = "a"
    flag: bool = False
    limit: Optional[float] = None
    colour: Colour = Colour.RED

    def check(self) -> None:
        self.require_at_least(1, "count")
        self.require_positive("limit", optional=True)


@dataclass
class OtherOptions(OptionTable):
    TABLE = "other"
    level: int = 0


@dataclass
class ToySet(OptionSet):
    toy: ToyOptions = field(default_factory=ToyOptions)
    other: OtherOptions = field(default_factory=OtherOptions)

    @classmethod
    def moved(cls, key: str) -> str | None:
        return {"number": "toy.count"}.get(key)

    def check(self) -> None:
        if self.toy.flag and self.other.level > 5:
            raise ConfigError("config key 'toy.flag': not with other.level > 5")


def test_option_table_coerces_and_validates():
    assert ToyOptions.keys() == ["count", "scale", "label", "flag", "limit", "colour"]
    toy = ToyOptions.from_values({"count": "3", "scale": 2, "label": "x", "flag": "on", "limit": "0.5", "colour": "blue"})
    assert toy == ToyOptions(count=3, scale=2.0, label="x", flag=True, limit=0.5, colour=Colour.BLUE)
    assert isinstance(toy.scale, float) and toy.colour is Colour.BLUE
    assert ToyOptions.from_values({"limit": "none"}, toy).limit is None and toy.limit == 0.5  # base untouched
    assert toy.as_dict() == {"count": 3, "scale": 2.0, "label": "x", "flag": True, "limit": 0.5, "colour": "blue"}
    assert toy.describe().splitlines()[0].strip() == "[toy]"
    for values, needle in [({"cuont": 1}, "unknown config key 'toy.cuont'"), ({"count": 0}, "'toy.count': must be"),
                           ({"count": 1.5}, "'toy.count': expected an integer"), ({"flag": "perhaps"}, "'toy.flag'"),
                           ({"colour": "green"}, "'toy.colour': must be one of red, blue"),
                           ({"label": 3}, "'toy.label': expected a string"), ({"limit": -1.0}, "'toy.limit'")]:
        with pytest.raises(ConfigError, match=needle):
            ToyOptions.from_values(values)


def test_option_table_toml(tmp_path):
    toy = ToyOptions(count=4, scale=1e-300, label='say "hi" \\ bye', flag=True, limit=None, colour=Colour.BLUE)
    text = toy.to_toml()
    assert text.startswith("[toy]\n") and "# limit =" in text
    assert ToyOptions.load(write(tmp_path, text)) == toy
    assert ToyOptions.load(write(tmp_path, "[other]\nlevel = 2\n", "other.toml")) == ToyOptions()
    with pytest.raises(ConfigError, match="'toy' must be a table"):
        ToyOptions.load(write(tmp_path, "toy = 3\n", "flat.toml"))


def test_option_set(tmp_path):
    config = ToySet.from_values({"toy.count": "2", "other": {"level": 3}})
    assert (config.toy.count, config.other.level) == (2, 3)
    assert config.as_dict() == {"toy": ToyOptions(count=2).as_dict(), "other": {"level": 3}}
    assert ToySet.load(write(tmp_path, config.to_toml())) == config
    assert config.with_assignments(["other.level=4"]).other.level == 4 and config.other.level == 3
    with pytest.raises(ConfigError, match="'number' is now 'toy.count'"):
        ToySet.from_values({"number": 2})
    with pytest.raises(ConfigError, match=r"table \[misc\] is not used: its key 'number' is now 'toy.count'"):
        ToySet.from_values({"misc": {"number": 2}})
    with pytest.raises(ConfigError, match="unknown config key 'toy.nope'"):
        ToySet.from_values({"toy.nope": 2})
    with pytest.raises(ConfigError, match="'toy.flag': not with"):  # the rule across tables
        ToySet.from_values({"toy.flag": True, "other.level": 6})
    assert ToySet.from_values({"extra.key": 1, "extra": {"a": 1}}, foreign=("extra",)) == ToySet()


def test_derived_config_shares_no_table_with_its_base():
    """A config made from another (with_values, from_values over a base) owns its tables: changing
    one of them leaves the base as it was."""
    a = Config()
    b = a.with_values({"noise.pixel_sigma": 2.0})
    assert all(getattr(b, name) is not table for name, table in a.tables().items())
    b.update.gate_probability = 0.9
    assert a.update.gate_probability == Config().update.gate_probability


@given(st.floats(1e100, 1.7e308, exclude_min=True), st.booleans(), st.booleans())
@settings(max_examples=50, deadline=None)
def test_numbers_beyond_the_range_of_an_option_are_refused_property(value, negative, as_text):
    """A number option beyond 1e100 in magnitude (1e308 as a pixel sigma overflows where it is
    squared) is refused in one line naming the key, from TOML values and --set text alike."""
    value = -value if negative else value
    with pytest.raises(ConfigError) as e:
        Config.from_values({"noise.pixel_sigma": repr(value) if as_text else value})
    message = str(e.value)
    assert "noise.pixel_sigma" in message and "out of range" in message and "\n" not in message
