"""Settings to and from TOML: ``to_dict``, ``from_dict`` (strict: unknown keys are errors), ``load_toml`` and
``dumps_toml``, which writes a config's user settings, the expert ones that differ from their defaults and the
package version: a run's ``config.toml``, short enough to read, and loading it rebuilds the same config."""

from __future__ import annotations

import dataclasses
import importlib.metadata
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, Protocol, TypeVar

from surfelslam.errors import ConfigError
from surfelslam.settings.fields import _DEFERRED, field_types, is_user_setting, validate

C = TypeVar("C")

#: The top-level key of a written config giving the package version that wrote it (read back and ignored: the
#: settings themselves say what the run did).
VERSION_KEY = "version"
#: The distribution whose version :func:`dumps_toml` writes.
DISTRIBUTION = "surfelslam"
#: Name of a config class's ``ClassVar`` mapping a removed key to what replaced it (a one-line hint).
REMOVED_KEYS_ATTR = "REMOVED_KEYS"


class Readable(Protocol):
    """A file-like path: a :class:`~pathlib.Path` or an ``importlib.resources`` traversable (a packaged preset)."""

    def read_text(self, encoding: str | None = None) -> str: ...


def package_version() -> str:
    """The installed package's version (``unknown`` when it runs from a source tree that was never installed)."""
    try:
        return importlib.metadata.version(DISTRIBUTION)
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def to_dict(cfg: Any) -> dict[str, Any]:
    """Dataclass -> plain nested dict (tuples become lists)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cfg):
        val = getattr(cfg, f.name)
        if dataclasses.is_dataclass(val):
            out[f.name] = to_dict(val)
        elif isinstance(val, tuple):
            out[f.name] = list(val)
        else:
            out[f.name] = val
    return out


def _setting_path(where: str) -> str:
    """``hybrid.loop_icp.sigma_m`` -> ``[hybrid.loop_icp] sigma_m`` (a top-level key stays as it is)."""
    table, _, key = where.rpartition(".")
    return f"[{table}] {key}" if table else key


def _coerce(value: Any, tp: Any, where: str, default: Any = None) -> Any:
    """``value`` as type ``tp``; ``default`` is the field's default (a nested table fills its missing keys from it)."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _coerce(value, args[0], where, default)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"config: [{where}] must be a table")
        return _build(tp, value, where, default if isinstance(default, tp) else None)  # type: ignore[arg-type]
    if origin in (tuple, list):
        if not isinstance(value, list | tuple):
            raise ConfigError(f"config: {_setting_path(where)} must be a list, got {value!r}")
        args = typing.get_args(tp)
        elem = args[0] if args else Any
        items = [_coerce(v, elem, where) for v in value]
        return tuple(items) if origin is tuple else items
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"config: {_setting_path(where)} must be a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"config: {_setting_path(where)} must be an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"config: {_setting_path(where)} must be true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"config: {_setting_path(where)} must be a string, got {value!r}")
        return value
    return value


def _build(cls: type[C], data: dict[str, Any], where: str, base: C | None) -> C:
    """:func:`from_dict` without the final validation (runs with construction-time validation deferred)."""
    hints = field_types(cls)
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = set(data) - names
    if unknown:
        prefix = f"[{where}] " if where else ""
        removed = getattr(cls, REMOVED_KEYS_ATTR, {})
        gone = sorted(unknown & set(removed))
        if gone:  # a key of an older version: say what replaced it
            raise ConfigError(f"config: {prefix}{gone[0]} was removed: {removed[gone[0]]}")
        raise ConfigError(f"config: {prefix}unknown key(s) {sorted(unknown)}; known: {sorted(names)}")
    if base is None:
        try:
            base = cls()
        except TypeError:  # a field without a default: the dict must give it
            base = None
    kwargs = {}
    for key, val in data.items():
        sub = f"{where}.{key}" if where else key
        kwargs[key] = _coerce(val, hints[key], sub, None if base is None else getattr(base, key))
    try:
        return cls(**kwargs) if base is None else dataclasses.replace(base, **kwargs)  # type: ignore[type-var]
    except ConfigError as exc:  # raised by the class's own __post_init__ (one not derived from Config)
        raise ConfigError(f"config: [{where or cls.__name__}] {exc}") from exc
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"config: [{where or cls.__name__}] {exc}") from exc


def from_dict(cls: type[C], data: dict[str, Any], where: str = "", base: C | None = None) -> C:
    """Build dataclass ``cls`` from a (partial) dict; missing keys keep their defaults; then :func:`validate` it
    (errors name the full TOML path below ``where``).

    The defaults are those of ``base`` when given, else of ``cls()``, recursively: a nested table's missing keys
    keep the values its parent gives that field (a ``default_factory`` with other settings than the nested class's
    own defaults, e.g. ``orb.loop_icp``), not the nested class's own defaults. A top-level ``version`` key (what
    :func:`dumps_toml` writes) is ignored unless ``cls`` has such a field.
    """
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    if not where and VERSION_KEY in data and VERSION_KEY not in names:
        if not isinstance(data[VERSION_KEY], str):
            raise ConfigError(f"config: {VERSION_KEY} must be a string, got {data[VERSION_KEY]!r}")
        data = {k: v for k, v in data.items() if k != VERSION_KEY}
    token = _DEFERRED.set(True)
    try:
        cfg = _build(cls, data, where, base)
    finally:
        _DEFERRED.reset(token)
    validate(cfg, where)
    return cfg


def load_toml(cls: type[C], path: str | Path | Readable) -> C:
    """Read a TOML file (or a packaged one) into dataclass ``cls``; errors name the file."""
    path = Path(path) if isinstance(path, str) else path
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read config file ({exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: invalid TOML ({exc})") from None
    except ValueError as exc:  # a path no file can have (a NUL character)
        raise ConfigError(f"{str(path)!r}: cannot read config file ({exc})") from None
    try:
        return from_dict(cls, data)
    except ConfigError as exc:
        raise type(exc)(f"{path}: {exc}") from None


def _toml_char(ch: str) -> str:
    """One character inside a TOML basic string: backslash, quote and the control characters TOML forbids there
    (a newline, NUL, DEL ... in a path given with --set) escaped, so that the written config.toml reads back."""
    if ch in '\\"':
        return "\\" + ch
    if ord(ch) < 0x20 or ord(ch) == 0x7F:
        return f"\\u{ord(ch):04x}"
    return ch


def toml_value(v: Any) -> str:
    """``v`` (bool, int, float, str or a list of them) as a TOML value."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return '"' + "".join(_toml_char(c) for c in v) + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise ConfigError(f"config: cannot write {v!r} as TOML")


def _written(cfg: Any, default: Any, full: bool) -> dict[str, Any]:
    """The nested dict :func:`dumps_toml` writes of config ``cfg``: every user setting, and each expert one that
    differs from ``default`` (the same table of the default config; ``None``: a table without defaults, all of it),
    or every setting (``full``)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cfg):
        val = getattr(cfg, f.name)
        base = getattr(default, f.name) if default is not None else None
        if dataclasses.is_dataclass(val):
            out[f.name] = _written(val, base if type(base) is type(val) else None, full)
        elif full or default is None or is_user_setting(f) or val != base:
            out[f.name] = list(val) if isinstance(val, tuple) else val
    return out


def dumps_toml(cfg: Any, *, full: bool = False) -> str:
    """Config (or nested dict) -> TOML text; ``None`` values and empty tables are omitted.

    Of a config, the text begins with the package version (``version = "0.1.0"``), then gives its user settings and
    the expert ones that differ from the defaults of ``type(cfg)()`` (``full``: every setting): loading it with
    :func:`load_toml` rebuilds an equal config.
    """
    if dataclasses.is_dataclass(cfg):
        try:
            default = type(cfg)()
        except TypeError:  # a config with a required field: no defaults to compare with
            default = None
        data = {VERSION_KEY: package_version(), **_written(cfg, default, full)}
    else:
        data = cfg
    lines: list[str] = []

    def emit(table: dict[str, Any], prefix: str) -> None:
        scalars = {k: v for k, v in table.items() if not isinstance(v, dict) and v is not None}
        subs = {k: v for k, v in table.items() if isinstance(v, dict)}
        if prefix and scalars:
            lines.append(f"[{prefix}]")
        for k, v in scalars.items():
            lines.append(f"{k} = {toml_value(v)}")
        if scalars:
            lines.append("")
        for k, v in subs.items():
            emit(v, f"{prefix}.{k}" if prefix else k)

    emit(data, "")
    return "\n".join(lines).rstrip() + "\n"
