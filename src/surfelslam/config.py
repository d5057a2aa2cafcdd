"""Configuration: nested dataclasses, loadable from and saved to TOML.

Every threshold of the system is a field of a dataclass with its unit in the name
(``dist_thresh_m``, ``angle_thresh_deg``...). Each subsystem owns its config dataclass in its
own module; :class:`SlamConfig` in :mod:`surfelslam.pipeline` gathers them. This module only
provides the generic mechanics: ``to_dict``, ``from_dict`` (strict: unknown keys are errors),
``load_toml`` and ``dumps_toml``.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from surfelslam.errors import ConfigError

C = TypeVar("C")


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
        return from_dict(tp, value, where, default if isinstance(default, tp) else None)
    if origin in (tuple, list):
        if not isinstance(value, list | tuple):
            raise ConfigError(f"config: {where} must be a list, got {value!r}")
        args = typing.get_args(tp)
        elem = args[0] if args else Any
        items = [_coerce(v, elem, where) for v in value]
        return tuple(items) if origin is tuple else items
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"config: {where} must be a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"config: {where} must be an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"config: {where} must be true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"config: {where} must be a string, got {value!r}")
        return value
    return value


def from_dict(cls: type[C], data: dict[str, Any], where: str = "", base: C | None = None) -> C:
    """Build dataclass ``cls`` from a (partial) dict; missing keys keep their defaults.

    The defaults are those of ``base`` when given, else of ``cls()``, recursively: a nested table's missing keys
    keep the values its parent gives that field (a ``default_factory`` with other settings than the nested class's
    own defaults, e.g. ``orb.loop_icp``), not the nested class's own defaults.
    """
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = set(data) - names
    if unknown:
        prefix = f"[{where}] " if where else ""
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
        return cls(**kwargs) if base is None else dataclasses.replace(base, **kwargs)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"config: [{where or cls.__name__}] {exc}") from exc


def load_toml(cls: type[C], path: str | Path) -> C:
    """Read a TOML file into dataclass ``cls``; errors name the file."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read config file ({exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: invalid TOML ({exc})") from None
    try:
        return from_dict(cls, data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def _toml_value(v: Any) -> str:
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
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise ConfigError(f"config: cannot write {v!r} as TOML")


def dumps_toml(cfg: Any) -> str:
    """Dataclass (or nested dict) -> TOML text; ``None`` values are omitted."""
    data = to_dict(cfg) if dataclasses.is_dataclass(cfg) else cfg
    lines: list[str] = []

    def emit(table: dict[str, Any], prefix: str) -> None:
        scalars = {k: v for k, v in table.items() if not isinstance(v, dict) and v is not None}
        subs = {k: v for k, v in table.items() if isinstance(v, dict)}
        if prefix and scalars:
            lines.append(f"[{prefix}]")
        for k, v in scalars.items():
            lines.append(f"{k} = {_toml_value(v)}")
        if scalars:
            lines.append("")
        for k, v in subs.items():
            emit(v, f"{prefix}.{k}" if prefix else k)

    emit(data, "")
    return "\n".join(lines).rstrip() + "\n"
