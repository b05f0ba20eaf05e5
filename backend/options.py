"""Typed tables of options: the one mechanism behind every vislam configuration.

A component's options are a dataclass deriving from :class:`OptionTable`, one TOML table
(``[noise]``, ``[update]``, ``[tracker]``, ...). A configuration is a dataclass of tables deriving
from :class:`OptionSet`. Both read values from TOML and from the command line's
``--set TABLE.KEY=VALUE`` strings, coerce them to the declared field types (bool, int, float,
str, an :class:`enum.Enum`, or ``Optional`` of those), validate them, list them at the start of a
run and write them back as TOML. Unknown tables and keys, and values of the wrong type, are
refused with a :class:`~vislam.backend.errors.ConfigError` naming the key.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import math
import typing
from pathlib import Path
from typing import Any, ClassVar, Iterable, Mapping, TypeVar

from .errors import ConfigError
from .reading import read_regular_file

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

__all__ = ["OptionTable", "OptionSet", "read_toml", "parse_assignment", "printable_name"]

T = TypeVar("T", bound="OptionTable")
S = TypeVar("S", bound="OptionSet")


#: The largest configuration file read (vislam's own config.toml is ~3 KiB)
MAX_CONFIG_BYTES = 2**20


def read_toml(path: str | Path) -> dict[str, Any]:
    """The tables of a TOML file; ConfigError naming the file otherwise (missing, not a regular
    file, over :data:`MAX_CONFIG_BYTES`, not UTF-8, not TOML, nested deeper than Python recurses)."""
    path = Path(path)
    data = read_regular_file(path, MAX_CONFIG_BYTES, "config file", ConfigError)
    try:
        return tomllib.loads(data.decode("utf-8-sig"))  # a leading byte-order mark is skipped
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start}); a config file is TOML") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    except RecursionError:
        raise ConfigError(f"{path}: arrays or tables nested too deeply to be a configuration") from None


def printable_name(name: str) -> str:
    """A key or table name as it may appear in a one-line message (line breaks and other control
    characters escaped)."""
    return name if name.isprintable() else repr(name)[1:-1]


#: The range of an integer option (larger ones cannot be a count or a size)
_INT_LIMIT = 2**63 - 1
#: The range of a number option: every sigma, length and time fits, and squares and products of
#: them stay finite in float64 (1e308 as a pixel sigma would overflow where it is squared)
_FLOAT_LIMIT = 1e100


def parse_assignment(item: str) -> tuple[str, str]:
    """``TABLE.KEY=VALUE`` of the command line's ``--set`` -> (``table.key`` with - as _, value)."""
    if "=" not in item:
        raise ConfigError(f"--set {item!r}: expected TABLE.KEY=VALUE")
    key, value = item.split("=", 1)
    return key.strip().replace("-", "_"), value


@functools.lru_cache(maxsize=None)
def _field_types(cls: type) -> dict[str, tuple[type, bool]]:
    """Field name -> (value type, optional) of an option dataclass (read once per class)."""
    hints = typing.get_type_hints(cls)
    out = {}
    for f in dataclasses.fields(cls):
        kind, optional = hints[f.name], False
        args = typing.get_args(kind)
        if type(None) in args:
            kind, optional = next(a for a in args if a is not type(None)), True
        out[f.name] = (kind, optional)
    return out


@functools.lru_cache(maxsize=None)
def _table_types(cls: type) -> dict[str, type]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def _coerce(kind: type, optional: bool, value: Any, key: str) -> Any:
    """``value`` (from TOML, or a command-line string) as ``kind``; ConfigError naming ``key``."""
    if isinstance(value, str) and kind is not str:
        text = value.strip()
        if optional and text.lower() in ("none", "null", "auto", ""):
            return None
        if issubclass(kind, enum.Enum):
            value = text
        elif kind is bool:
            if text.lower() in ("1", "true", "yes", "on"):
                return True
            if text.lower() in ("0", "false", "no", "off"):
                return False
            raise ConfigError(f"config key '{key}': expected true or false, got {value!r}")
        elif kind is int:
            try:
                value = int(text)
            except ValueError:
                raise ConfigError(f"config key '{key}': expected an integer, got {_short(value)}") from None
        elif kind is float:
            try:
                value = float(text)
            except ValueError:
                raise ConfigError(f"config key '{key}': expected a number, got {_short(value)}") from None
    if value is None and optional:
        return None
    if isinstance(kind, type) and issubclass(kind, enum.Enum):
        try:
            return kind(value.value if isinstance(value, enum.Enum) else value)
        except ValueError:
            choices = ", ".join(str(m.value) for m in kind)
            raise ConfigError(f"config key '{key}': must be one of {choices}, got {value!r}") from None
    if kind is bool:
        if type(value) is int and value in (0, 1):  # as `--set KEY=0` / `=1` accept
            return bool(value)
        if not isinstance(value, bool):
            raise ConfigError(f"config key '{key}': expected true or false, got {value!r}")
        return value
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"config key '{key}': expected an integer, got {_short(value)}")
        if abs(value) > _INT_LIMIT:
            raise ConfigError(f"config key '{key}': integer out of range (|value| > 2**63 - 1), got {_short(value)}")
        return value
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"config key '{key}': expected a number, got {_short(value)}")
        try:
            number = float(value)
        except OverflowError:
            raise ConfigError(f"config key '{key}': number out of range, got {_short(value)}") from None
        if math.isfinite(number) and abs(number) > _FLOAT_LIMIT:
            raise ConfigError(f"config key '{key}': number out of range (|value| > {_FLOAT_LIMIT:g}), got "
                              f"{_short(value)}")
        return number
    if not isinstance(value, str):
        raise ConfigError(f"config key '{key}': expected a string, got {value!r}")
    return value


def _short(value: Any) -> str:
    """``repr(value)`` cut to 60 characters, for a one-line message."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _toml_value(value: Any) -> str:
    if isinstance(value, enum.Enum):
        value = value.value
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(value)


def _shown(value: Any) -> Any:
    return value.value if isinstance(value, enum.Enum) else value


class OptionTable:
    """Base of a dataclass of options that is one TOML table, ``[TABLE]``.

    Subclasses are ``@dataclass``es with typed, defaulted fields, set ``TABLE`` and override
    :meth:`check` (called by :meth:`validate`) to refuse values out of range with :meth:`fail`.
    """

    TABLE: ClassVar[str] = ""

    # -- validation
    def check(self) -> None:
        """Raise ConfigError (through :meth:`fail`) on a value out of range; the types are checked already."""

    def fail(self, key: str, what: str) -> typing.NoReturn:
        raise ConfigError(f"config key '{self.TABLE}.{key}': {what}, got {getattr(self, key, None)!r}")

    def require(self, key: str, ok: bool, what: str) -> None:
        """:meth:`fail` with ``what`` unless ``ok``."""
        if not ok:
            self.fail(key, what)

    def require_positive(self, *keys: str, optional: bool = False) -> None:
        """Each key a finite number > 0 (or unset, with ``optional``)."""
        for key in keys:
            value = getattr(self, key)
            if optional and value is None:
                continue
            self.require(key, value is not None and math.isfinite(value) and value > 0,
                         "must be a finite number > 0" + (" or unset" if optional else ""))

    def require_at_least(self, low: float, *keys: str) -> None:
        """Each key a finite number >= ``low``."""
        for key in keys:
            value = getattr(self, key)
            self.require(key, math.isfinite(value) and value >= low, f"must be a finite number >= {low:g}")

    def validate(self: T) -> T:
        """Check every field's type and range; return self (ConfigError otherwise)."""
        for name, (kind, optional) in _field_types(type(self)).items():
            setattr(self, name, _coerce(kind, optional, getattr(self, name), f"{self.TABLE}.{name}"))
        self.check()
        return self

    # -- construction
    @classmethod
    def keys(cls) -> list[str]:
        return [f.name for f in dataclasses.fields(cls)]

    @classmethod
    def from_values(cls: type[T], values: Mapping[str, Any], base: T | None = None) -> T:
        """A table with ``values`` (key -> value, coerced) applied over ``base`` (default: the
        defaults), validated."""
        out = dataclasses.replace(base) if base is not None else cls()
        types = _field_types(cls)
        for key, value in values.items():
            if key not in types:
                raise ConfigError(f"unknown config key '{cls.TABLE}.{printable_name(key)}' (the [{cls.TABLE}] table has: "
                                  f"{', '.join(cls.keys())})")
            setattr(out, key, _coerce(*types[key], value, f"{cls.TABLE}.{key}"))
        return out.validate()

    @classmethod
    def load(cls: type[T], path: str | Path, base: T | None = None) -> T:
        """The ``[TABLE]`` table of a TOML file over ``base`` (other tables are not read; a file
        without the table gives ``base`` or the defaults)."""
        table = read_toml(path).get(cls.TABLE, {})
        if not isinstance(table, dict):
            raise ConfigError(f"{path}: key '{cls.TABLE}' must be a table")
        try:
            return cls.from_values(table, base)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None

    # -- output
    def as_dict(self) -> dict[str, Any]:
        return {f.name: _shown(getattr(self, f.name)) for f in dataclasses.fields(self)}

    def describe(self) -> str:
        """``[table]`` and one ``key = value`` line per option (printed at the start of a run)."""
        width = max(len(k) for k in self.keys())
        lines = [f"  [{self.TABLE}]"]
        lines += [f"    {k:<{width}} = {v!r}" for k, v in self.as_dict().items()]
        return "\n".join(lines)

    def to_toml(self) -> str:
        """The ``[table]`` in TOML; an unset optional key is a comment where unset is its default,
        else ``"none"`` (which reads back as unset)."""
        lines = [f"[{self.TABLE}]"]
        defaults = type(self)()
        for key in self.keys():
            value = getattr(self, key)
            if value is None and getattr(defaults, key) is None:
                lines.append(f"# {key} =   # unset")
            elif value is None:
                lines.append(f'{key} = "none"   # unset')
            else:
                lines.append(f"{key} = {_toml_value(value)}")
        return "\n".join(lines) + "\n"


class OptionSet:
    """Base of a dataclass whose fields are :class:`OptionTable` s: a whole configuration.

    Subclasses may override :meth:`check` for rules across tables and :meth:`moved` to name the
    new place of a key that is no longer accepted.
    """

    # -- the tables
    @classmethod
    def table_types(cls) -> dict[str, type[OptionTable]]:
        """Table name -> its OptionTable class."""
        return _table_types(cls)

    def tables(self) -> dict[str, OptionTable]:
        return {name: getattr(self, name) for name in self.table_types()}

    @classmethod
    def moved(cls, key: str) -> str | None:
        """The ``table.key`` that replaced an old key name, if any (for the error message)."""
        return None

    def check(self) -> None:
        """Rules that involve more than one table (ConfigError)."""

    def validate(self: S) -> S:
        for table in self.tables().values():
            table.validate()
        self.check()
        return self

    # -- construction
    @classmethod
    def _refuse(cls, key: str, where: str = "") -> typing.NoReturn:
        new = cls.moved(key) or cls.moved(key.rpartition(".")[2])
        if new == key:  # a quoted "table.key" at the top of a TOML file: one name, not a table
            table, _, leaf = key.partition(".")
            raise ConfigError(f"{where}config key '{printable_name(key)}' is one quoted name; write it in its "
                              f"table: [{table}] {leaf} = ... (or unquoted {key} = ...)")
        if new is not None:
            raise ConfigError(f"{where}config key '{printable_name(key)}' is now '{new}' (options are grouped in tables: "
                              f"{', '.join(cls.table_types())})")
        raise ConfigError(f"{where}unknown config key '{printable_name(key)}' (expected TABLE.KEY with a table of "
                          f"{', '.join(cls.table_types())})")

    @classmethod
    def _grouped(cls, values: Mapping[str, Any], foreign: Iterable[str] = ()) -> dict[str, dict[str, Any]]:
        """``{"table.key": v}`` and ``{"table": {"key": v}}`` alike -> {table: {key: v}}."""
        types, skip = cls.table_types(), set(foreign)
        grouped: dict[str, dict[str, Any]] = {}
        for key, value in values.items():
            # a table of a TOML file is one name (["noise."] is not [noise]); --set's TABLE.KEY is split
            table, _, leaf = (key, "", "") if isinstance(value, Mapping) else key.partition(".")
            if table in skip:
                continue
            if table not in types:
                if not leaf and isinstance(value, Mapping):  # an unknown table: name where its first moved key went
                    inner = next((k for k in value if cls.moved(k) is not None), None)
                    if inner is not None:
                        raise ConfigError(f"table [{printable_name(table)}] is not used: its key '{inner}' is now '{cls.moved(inner)}' "
                                          f"(tables: {', '.join(types)})")
                    raise ConfigError(f"unknown table [{printable_name(table)}] (tables: {', '.join(types)})")
                cls._refuse(key)
            if leaf:
                grouped.setdefault(table, {})[leaf] = value
            elif isinstance(value, Mapping):
                grouped.setdefault(table, {}).update(value)
            else:
                cls._refuse(key)
        return grouped

    @classmethod
    def from_values(cls: type[S], values: Mapping[str, Any], base: S | None = None,
                    foreign: Iterable[str] = ()) -> S:
        """A configuration with ``values`` over ``base`` (default: the defaults), validated. Keys are
        ``"table.key"`` (or a table name with a dict of keys); tables in ``foreign`` (another
        component's, such as ``tracker``) are skipped. The result shares no table with ``base``."""
        out = cls(**{name: dataclasses.replace(table) for name, table in base.tables().items()}) if base is not None \
            else cls()
        for table, items in cls._grouped(values, foreign).items():
            setattr(out, table, cls.table_types()[table].from_values(items, getattr(out, table)))
        return out.validate()

    def with_values(self: S, values: Mapping[str, Any]) -> S:
        """A copy with ``values`` applied (see :meth:`from_values`)."""
        return type(self).from_values(values, self)

    def with_assignments(self: S, assignments: Iterable[str], foreign: Iterable[str] = ()) -> S:
        """A copy with ``TABLE.KEY=VALUE`` strings applied (the command line's ``--set``)."""
        return type(self).from_values(dict(parse_assignment(a) for a in assignments), self, foreign)

    @classmethod
    def load(cls: type[S], path: str | Path, base: S | None = None, foreign: Iterable[str] = ()) -> S:
        """Read a TOML file of ``[table]`` s over ``base``; tables in ``foreign`` are skipped."""
        data = read_toml(path)
        for key, value in data.items():
            if not isinstance(value, dict) and key not in set(foreign):
                cls._refuse(key, f"{path}: ")
        try:
            return cls.from_values(data, base, foreign)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None

    # -- output
    def as_dict(self) -> dict[str, dict[str, Any]]:
        return {name: table.as_dict() for name, table in self.tables().items()}

    def describe(self) -> str:
        return "\n".join(table.describe() for table in self.tables().values())

    def to_toml(self) -> str:
        return "\n".join(table.to_toml() for table in self.tables().values())
