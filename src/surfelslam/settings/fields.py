"""Settings: frozen nested dataclasses whose fields declare their default, unit, bounds and tier.

Each subsystem owns its config in its own module; :class:`SlamConfig` in :mod:`surfelslam.slam.config` gathers
them. This module holds the generic mechanics:

- :func:`setting` declares a field with its default, unit, bounds or choices, a one-line meaning and its tier:
  ``user=True`` for a choice a user makes (the sensor's depth range, the resolution, the tracker...), else an
  expert constant (still overridable, written to a run's ``config.toml`` only when it differs from its default);
  :func:`check` marks a method as a rule relating several fields;
- :class:`Config` is the base of every config: lists become tuples and :func:`validate` runs on construction;
- :func:`validate` checks a config tree; every error is one line naming the full TOML path
  (``config: [hybrid.loop_icp] sigma_m must be > 0, got -1``);
- :func:`iter_tables` walks a config tree.

TOML reading and writing are in :mod:`surfelslam.settings.tomlio`, ``--set`` overrides in
:mod:`surfelslam.settings.overrides`, the presets in :mod:`surfelslam.settings.presets` and the reference page in
:mod:`surfelslam.settings.reference`.
"""

from __future__ import annotations

import contextvars
import dataclasses
import functools
import math
import numbers
import types
import typing
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

from surfelslam.errors import ConfigValueError

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
    user: bool = False

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
    user: bool = False,
) -> Any:
    """A config field: its default (or ``default_factory``, for nested configs) and what :func:`validate` checks.

    Numbers must be finite (``allow_inf``: +inf too, whatever the upper bound) and within ``ge`` / ``gt`` / ``le`` /
    ``lt``; strings one of ``choices``; a tuple field's bounds apply to each element, and it needs at least
    ``min_len`` of them. ``unit`` and ``doc`` (what the setting does, one or two short sentences) go to the
    configuration reference. ``user``: a choice a user makes (always written to a run's ``config.toml`` and listed
    first in the reference); otherwise an expert constant, written only when it differs from its default.
    """
    if isinstance(default, list):
        raise TypeError("setting: use a tuple, not a list, as a default")
    meta = Bounds(unit, ge, gt, le, lt, None if choices is None else tuple(choices), allow_inf, min_len, doc, user)
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


def is_user_setting(f: dataclasses.Field) -> bool:
    """Whether field ``f`` is a user setting: declared ``setting(..., user=True)``, or a plain dataclass field (the
    dataset options, which the CLI's own options set)."""
    meta = f.metadata.get(_META)
    return True if meta is None else meta.user


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


# ------------------------------------------------------------------------------------------------------ tables
def iter_tables(cfg: Any, path: str = "") -> Iterator[tuple[str, Any]]:
    """``(toml_path, config)`` of ``cfg`` and every config nested in it, depth first in field order."""
    yield path, cfg
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            yield from iter_tables(v, join_path(path, f.name))
