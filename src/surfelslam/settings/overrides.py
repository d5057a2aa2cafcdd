"""``--set KEY=VALUE`` overrides and :func:`load_config`: defaults, then a config file or preset, then overrides."""

from __future__ import annotations

import dataclasses
import difflib
import tomllib
import types
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TypeVar

from surfelslam.errors import ConfigError, one_line
from surfelslam.settings.presets import resolve_config_path
from surfelslam.settings.tomlio import from_dict, load_toml

C = TypeVar("C")


def _leaf_paths(cls: type, prefix: str = "") -> list[str]:
    out = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = _unwrap_optional(hints[f.name])
        path = f"{prefix}{f.name}"
        out += _leaf_paths(tp, path + ".") if dataclasses.is_dataclass(tp) else [path]
    return out


def _unwrap_optional(tp: Any) -> Any:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return args[0] if len(args) == 1 else tp
    return tp


def parse_set(item: str, cls: type) -> dict[str, Any]:
    """``"icp.min_inliers=300"`` -> ``{"icp": {"min_inliers": 300}}``, the key checked against ``cls``.

    The value is read as a TOML value (``300``, ``0.5``, ``true``, ``"text"``, ``[1, 2]``); anything else is taken
    as a bare string (``tracking.photometric=off``).

    Raises:
        ConfigError: not ``KEY=VALUE``, an unknown key (the message names its full path and close matches), or a
            key that is a table.
    """
    key, sep, text = item.partition("=")
    key = key.strip()
    parts = key.split(".")
    if not sep or not all(parts):
        raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. --set icp.min_inliers=300")
    tp: Any = cls
    for i, name in enumerate(parts):
        here = ".".join(parts[:i])
        if not dataclasses.is_dataclass(tp):
            raise ConfigError(f"--set {one_line(item)}: unknown setting {one_line(key)} ({here} is a setting, "
                              "not a table)")
        names = [f.name for f in dataclasses.fields(tp)]
        if name not in names:
            close = difflib.get_close_matches(key, _leaf_paths(cls), n=3, cutoff=0.6)
            hint = f"did you mean {_or_list(close)}?" if close else (
                f"[{here}] has {', '.join(names)}" if here else f"the top level has {', '.join(names)}")
            raise ConfigError(f"--set {one_line(item)}: unknown setting {one_line(key)} ({hint})")
        tp = _unwrap_optional(typing.get_type_hints(tp)[name])
    if dataclasses.is_dataclass(tp):
        first = dataclasses.fields(tp)[0].name
        raise ConfigError(f"--set {one_line(item)}: {key} is a table, not a setting (set its keys, e.g. "
                          f"{key}.{first}=...)")
    try:
        value = tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        value = text.strip()
    nested: dict[str, Any] = {parts[-1]: value}
    for name in reversed(parts[:-1]):
        nested = {name: nested}
    return nested


def _or_list(items: list[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " or " + items[-1]


def _merge(into: dict[str, Any], more: dict[str, Any]) -> dict[str, Any]:
    for k, v in more.items():
        if isinstance(v, dict) and isinstance(into.get(k), dict):
            _merge(into[k], v)
        else:
            into[k] = v
    return into


def apply_sets(cfg: C, sets: Sequence[str]) -> C:
    """``cfg`` with the ``--set KEY=VALUE`` overrides applied (later ones win)."""
    if not sets:
        return cfg
    cls = type(cfg)
    merged: dict[str, Any] = {}
    for item in sets:
        _merge(merged, parse_set(item, cls))
    try:
        return from_dict(cls, merged, base=cfg)
    except ConfigError as exc:
        for item in sets:  # name the override at fault when it fails alone
            try:
                from_dict(cls, parse_set(item, cls), base=cfg)
            except ConfigError as alone:
                raise ConfigError(f"--set {one_line(item)}: {alone}") from None
        raise ConfigError(f"--set {one_line(' --set '.join(sets))}: {exc}") from None


def load_config(cls: type[C], path: str | Path | None = None, sets: Sequence[str] = ()) -> C:
    """The defaults of ``cls``, overridden by the TOML file or preset ``path``
    (:func:`~surfelslam.settings.presets.resolve_config_path`), overridden by the ``--set`` items."""
    cfg = cls() if path is None else load_toml(cls, resolve_config_path(path))
    return apply_sets(cfg, sets)
