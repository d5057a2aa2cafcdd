"""Configuration: frozen nested dataclasses, loadable from and saved to TOML, checked in one place.

Every threshold of the system is a field of a config dataclass with its unit in the name (``dist_thresh_m``,
``angle_thresh_deg``...). Each subsystem owns its config in its own module; :class:`SlamConfig` in
:mod:`surfelslam.slam.config` gathers them. This module holds the generic mechanics:

- :func:`setting` declares a field with its default, unit, bounds or choices and a one-line meaning;
  :func:`check` marks a method as a rule relating several fields;
- :class:`Config` is the base of every config: lists become tuples and :func:`validate` runs on construction;
- :func:`validate` checks a config tree; every error is one line naming the full TOML path
  (``config: [hybrid.loop_icp] sigma_m must be > 0, got -1``);
- ``to_dict``, ``from_dict`` (strict: unknown keys are errors), ``load_toml``, ``dumps_toml``;
- :func:`iter_tables` walks a config tree; :mod:`surfelslam.config_reference` writes the configuration reference
  page from the settings' metadata (``make docs``).
"""

from __future__ import annotations

import contextvars
import dataclasses
import functools
import math
import numbers
import tomllib
import types
import typing
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

from surfelslam.errors import ConfigError, ConfigValueError

C = TypeVar("C")

_META = "surfelslam"
_CHECK = "__config_check__"
# True while from_dict builds a tree: construction skips validation, from_dict then validates the whole tree
# with the full TOML paths (a nested table's own __post_init__ does not know where it sits)
_DEFERRED: contextvars.ContextVar[bool] = contextvars.ContextVar("surfelslam_config_deferred", default=False)


@dataclasses.dataclass(frozen=True)
class Bounds:
    """What :func:`setting` records in a field's metadata."""

    unit: str | None = None
    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    choices: tuple[Any, ...] | None = None
    allow_inf: bool = False
    min_len: int | None = None
    doc: str = ""

    def describe(self) -> str:
        """``>= 0``, ``in (0, 180]``, ``one of a, b``... ('' when unbounded)."""
        if self.choices is not None:
            return "one of " + ", ".join(str(c) for c in self.choices)
        lo = (f"[{fmt_value(self.ge)}" if self.ge is not None else f"({fmt_value(self.gt)}" if self.gt is not None
              else None)
        hi = (f"{fmt_value(self.le)}]" if self.le is not None else f"{fmt_value(self.lt)})" if self.lt is not None
              else None)
        if lo and hi:
            return f"in {lo}, {hi}"
        if lo:
            return (">= " if lo[0] == "[" else "> ") + lo[1:]
        if hi:
            return ("<= " if hi[-1] == "]" else "< ") + hi[:-1]
        return ""


def setting(
    default: Any = dataclasses.MISSING,
    *,
    default_factory: Callable[[], Any] | Any = dataclasses.MISSING,
    unit: str | None = None,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    choices: tuple[Any, ...] | None = None,
    allow_inf: bool = False,
    min_len: int | None = None,
    doc: str = "",
) -> Any:
    """A config field: its default (or ``default_factory``, for nested configs) and what :func:`validate` checks.

    Numbers must be finite (``allow_inf``: +inf too, whatever the upper bound) and within ``ge`` / ``gt`` / ``le`` /
    ``lt``; strings one of ``choices``; a tuple field's bounds apply to each element, and it needs at least
    ``min_len`` of them. ``unit`` and ``doc`` (what the setting does, one or two short sentences) go to the
    configuration reference.
    """
    if isinstance(default, list):
        raise TypeError("setting: use a tuple, not a list, as a default")
    meta = Bounds(unit, ge, gt, le, lt, None if choices is None else tuple(choices), allow_inf, min_len, doc)
    return dataclasses.field(default=default, default_factory=default_factory, metadata={_META: meta})


def check(fn: Callable[[Any], str | None]) -> Callable[[Any], str | None]:
    """Mark a config method as a rule relating several fields: it returns ``None`` when the rule holds, else one
    line saying what is wrong (field names relative to the config's table). Its docstring is the rule's
    description in the configuration reference."""
    setattr(fn, _CHECK, True)
    return fn


def ordered(low: str, high: str, *, strict: bool = True) -> Callable[[Any], str | None]:
    """A :func:`check` rule ``low < high`` (``strict=False``: ``<=``) between two fields of a config, e.g.
    ``_depth_range = ordered("min_depth_m", "max_depth_m")`` in its class body."""
    op = "<" if strict else "<="

    def rule(cfg: Any) -> str | None:
        a, b = getattr(cfg, low), getattr(cfg, high)
        if a < b or (not strict and a == b):
            return None
        return f"{low} ({fmt_value(a)}) must be {op} {high} ({fmt_value(b)})"

    rule.__doc__ = f"{low} {op} {high}."
    rule.__name__ = f"_{low}_{'lt' if strict else 'le'}_{high}"
    return check(rule)


class Config:
    """Base of the config dataclasses (each also ``@dataclass(frozen=True)``): lists given for tuple fields
    become tuples, and the settings are validated when a config is built (its own fields and rules; nested configs
    validated themselves when they were built)."""

    __slots__ = ()

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            if isinstance(getattr(self, f.name), list):
                object.__setattr__(self, f.name, tuple(getattr(self, f.name)))
        if not _DEFERRED.get():
            _validate(self, type(self).__name__, recurse=False)


# ---------------------------------------------------------------------------------------------------- checks
def fmt_value(v: Any) -> str:
    """A value as a config file would type it: ``-1`` for -1.0, ``inf``, ``'yes'`` for strings."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return f"{v:.12g}"
    if isinstance(v, str):
        return repr(v)
    if isinstance(v, tuple | list):
        return "[" + ", ".join(fmt_value(x) for x in v) + "]"
    return str(v)


def join_path(path: str, key: str) -> str:
    """The TOML path of table ``path``'s key ``key`` (``icp`` + ``levels`` -> ``icp.levels``)."""
    return f"{path}.{key}" if path else key


def _error(path: str, text: str) -> ConfigValueError:
    return ConfigValueError(f"config: [{path}] {text}" if path else f"config: {text}")


@functools.cache
def field_types(cls: type) -> dict[str, Any]:
    """The resolved type of each field of config class ``cls``."""
    return typing.get_type_hints(cls)


@functools.cache
def check_rules(cls: type) -> tuple[Callable[[Any], str | None], ...]:
    """The :func:`check` rules of config class ``cls`` and its bases (a subclass's rule replaces a same-named one)."""
    seen: dict[str, Callable[[Any], str | None]] = {}
    for klass in reversed(cls.__mro__):
        for name, val in vars(klass).items():
            if getattr(val, _CHECK, False):
                seen[name] = val
    return tuple(seen.values())


def field_bounds(f: dataclasses.Field) -> Bounds:
    """What :func:`setting` declared for field ``f`` (no bounds for a plain field)."""
    return f.metadata.get(_META) or Bounds()


def _scalar_problem(v: Any, tp: Any, b: Bounds) -> str | None:
    """Why ``v`` is not a valid value of type ``tp`` within ``b`` (``None``: it is)."""
    if tp is bool:
        ok = isinstance(v, bool) or type(v).__name__ == "bool_"  # numpy's bool too
        return None if ok else f"must be true or false, got {fmt_value(v)}"
    if tp is str:
        if not isinstance(v, str):
            return f"must be a string, got {fmt_value(v)}"
        if b.choices is not None and v not in b.choices:
            return f"must be {b.describe()}, got {fmt_value(v)}"
        return None
    if tp is int:
        if isinstance(v, bool) or not isinstance(v, numbers.Integral):
            return f"must be an integer, got {fmt_value(v)}"
    elif tp is float:
        if isinstance(v, bool) or not isinstance(v, numbers.Real):
            return f"must be a number, got {fmt_value(v)}"
        x = float(v)
        if b.allow_inf and x == math.inf:
            return None
        if math.isnan(x) or math.isinf(x):
            rng = (" and " + b.describe() if b.describe() else "") + (" (or inf)" if b.allow_inf else "")
            return f"must be finite{rng}, got {fmt_value(x)}"
    else:
        return None
    if b.choices is not None:
        return None if v in b.choices else f"must be {b.describe()}, got {fmt_value(v)}"
    if (b.ge is not None and not v >= b.ge) or (b.gt is not None and not v > b.gt):  # the bound it breaks
        return f"must be {Bounds(ge=b.ge, gt=b.gt).describe()}, got {fmt_value(v)}"
    if (b.le is not None and not v <= b.le) or (b.lt is not None and not v < b.lt):
        return f"must be {Bounds(le=b.le, lt=b.lt).describe()}, got {fmt_value(v)}"
    return None


def _field_problem(name: str, v: Any, tp: Any, b: Bounds) -> str | None:
    """``'<name...> must be ..., got ...'`` or ``None``."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        if v is None:
            return None
        tp = next(a for a in typing.get_args(tp) if a is not type(None))
        origin = typing.get_origin(tp)
    if origin is tuple:
        if not isinstance(v, tuple):
            return f"{name} must be a list, got {fmt_value(v)}"
        if b.min_len is not None and len(v) < b.min_len:
            return f"{name} needs at least {b.min_len} value(s), got {fmt_value(v)}"
        elem = typing.get_args(tp)[0] if typing.get_args(tp) else Any
        for i, x in enumerate(v):
            why = _scalar_problem(x, elem, b)
            if why:
                return f"{name}[{i}] {why}"
        return None
    why = _scalar_problem(v, tp, b)
    return f"{name} {why}" if why else None


def _validate(cfg: Any, path: str, recurse: bool) -> None:
    cls = type(cfg)
    hints = field_types(cls)
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            if recurse:
                _validate(v, join_path(path, f.name), True)
            continue
        why = _field_problem(f.name, v, hints.get(f.name, Any), field_bounds(f))
        if why:
            raise _error(path, why)
    for rule in check_rules(cls):
        why = rule(cfg)
        if why:
            raise _error(path, why)


def validate(cfg: Any, path: str = "") -> None:
    """Check config ``cfg`` and every config nested in it: types, finite numbers, bounds and choices of each field
    (each element of a tuple field), then the rules of each class (:func:`check`).

    Raises:
        ConfigValueError: (a :class:`ConfigError`) one line naming the setting by its full TOML path below ``path``,
            e.g. ``config: [icp] photometric_weight must be finite and >= 0, got inf``.
    """
    _validate(cfg, path, recurse=True)


# ------------------------------------------------------------------------------------------------- dict / TOML
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
    own defaults, e.g. ``orb.loop_icp``), not the nested class's own defaults.
    """
    token = _DEFERRED.set(True)
    try:
        cfg = _build(cls, data, where, base)
    finally:
        _DEFERRED.reset(token)
    validate(cfg, where)
    return cfg


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
            lines.append(f"{k} = {toml_value(v)}")
        if scalars:
            lines.append("")
        for k, v in subs.items():
            emit(v, f"{prefix}.{k}" if prefix else k)

    emit(data, "")
    return "\n".join(lines).rstrip() + "\n"


# ------------------------------------------------------------------------------------------------------ tables
def iter_tables(cfg: Any, path: str = "") -> Iterator[tuple[str, Any]]:
    """``(toml_path, config)`` of ``cfg`` and every config nested in it, depth first in field order."""
    yield path, cfg
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            yield from iter_tables(v, join_path(path, f.name))
