"""The configuration reference page (Markdown), generated from the settings' metadata (``make docs``).

One section per TOML table: its settings (key, default, unit, bounds or choices, meaning), the rules relating them
and its sub-tables. ``tests/test_config.py`` checks that ``docs/config_reference.md`` is current.
"""

from __future__ import annotations

import dataclasses
import re
import types
import typing
from typing import Any

from surfelslam.settings.fields import check_rules, field_bounds, field_types, is_user_setting, iter_tables, join_path
from surfelslam.settings.tomlio import REMOVED_KEYS_ATTR, toml_value


def _md(text: str) -> str:
    """Docstring text as one Markdown table cell / paragraph (Sphinx roles and double backticks to code spans)."""
    text = re.sub(r":[a-z]+:`~?([^`]+)`", r"`\1`", " ".join(text.split()))
    return text.replace("``", "`").replace("|", "\\|")


def _summary(doc: str | None) -> str:
    """A class docstring up to its ``Attributes:`` section."""
    return (doc or "").split("Attributes:")[0].strip()


def _attribute_docs(doc: str | None) -> dict[str, str]:
    """``name -> text`` of a Google-style ``Attributes:`` section (the fallback meaning of a field declared without
    :func:`setting`)."""
    out: dict[str, str] = {}
    if not doc or "Attributes:" not in doc:
        return out
    name = None
    for line in doc.split("Attributes:", 1)[1].splitlines():
        stripped = line.strip()
        head, sep, rest = stripped.partition(": ")
        if sep and head.isidentifier() and len(line) - len(line.lstrip()) <= 8:
            name = head
            out[name] = rest
        elif name and stripped:
            out[name] += " " + stripped
    return out


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return _type_name(args[0]) + " or none"
    if origin is tuple:
        return f"list of {_type_name(typing.get_args(tp)[0])}"
    return getattr(tp, "__name__", str(tp))


def _default_text(v: Any) -> str:
    if v is None:
        return "(none)"
    return f"`{toml_value(v)}`"


def _row(key: str, f: dataclasses.Field, v: Any, tp: Any, attr_docs: dict[str, str]) -> str:
    """One table row: key, default, unit, bounds or choices, meaning."""
    b = field_bounds(f)
    extra = []
    if b.min_len is not None and b.min_len > 1:
        extra.append(f"at least {b.min_len} values")
    if b.allow_inf:
        extra.append("or inf")
    bounds = "; ".join(x for x in [b.describe(), *extra] if x)
    meaning = _md(b.doc or attr_docs.get(f.name, "")) or "(" + _type_name(tp) + ")"
    return f"| {key} | {_default_text(v)} | {b.unit or ''} | {_md(bounds)} | {meaning} |"


_HEADER = ["| key | default | unit | bounds | meaning |", "|---|---|---|---|---|"]


def _user_rows(root: Any) -> list[str]:
    """A row per user setting of every table (``[table] key``)."""
    rows = []
    for path, cfg in iter_tables(root):
        hints, attr_docs = field_types(type(cfg)), _attribute_docs(type(cfg).__doc__)
        for f in dataclasses.fields(cfg):
            v = getattr(cfg, f.name)
            if not dataclasses.is_dataclass(v) and is_user_setting(f):
                key = f"`[{path}] {f.name}`" if path else f"`{f.name}`"
                rows.append(_row(key, f, v, hints[f.name], attr_docs))
    return rows


def _table_section(path: str, cfg: Any) -> list[str]:
    """A table's section: what it is for, its expert constants, its rules and its sub-tables."""
    klass = type(cfg)
    hints, attr_docs = field_types(klass), _attribute_docs(klass.__doc__)
    rows = [_row(f"`{f.name}`", f, getattr(cfg, f.name), hints[f.name], attr_docs) for f in dataclasses.fields(cfg)
            if not dataclasses.is_dataclass(getattr(cfg, f.name)) and not is_user_setting(f)]
    users = [f"`{f.name}`" for f in dataclasses.fields(cfg)
             if not dataclasses.is_dataclass(getattr(cfg, f.name)) and is_user_setting(f)]
    subs = [f"`[{join_path(path, f.name)}]`" for f in dataclasses.fields(cfg)
            if dataclasses.is_dataclass(getattr(cfg, f.name))]
    out = [f"### `[{path}]`" if path else f"### {klass.__name__} (the file's top level)", ""]
    doc = _summary(klass.__doc__)
    if doc and not doc.startswith(klass.__name__ + "("):  # not dataclass's generated signature
        out += [_md(doc), ""]
    if users:
        out += ["User settings (above): " + ", ".join(users) + ".", ""]
    if rows:
        out += [*_HEADER, *rows, ""]
    rules = [(r.__doc__ or r.__name__).strip() for r in check_rules(klass)]
    if rules:
        out += ["Rules:", "", *[f"- {_md(r)}" for r in rules], ""]
    removed = getattr(klass, REMOVED_KEYS_ATTR, {})
    if removed:  # what an older config file may still set: loading it says what replaced the key
        out += ["Removed keys:", "", *[f"- `{key}`: {_md(why)}" for key, why in removed.items()], ""]
    if subs:
        out += ["Tables: " + ", ".join(subs) + ".", ""]
    return out


def reference_markdown(cls: type) -> str:
    """The configuration reference page of config class ``cls`` (Markdown): the user settings of every table
    first, then one section per TOML table with its expert constants and the rules relating its settings."""
    root = cls()
    out = [
        "# Configuration reference",
        "",
        "Generated from the settings' definitions by `make docs` (`python -m surfelslam.tools.gen_docs`); do not edit.",
        "Every setting may be given in a TOML file passed with `--config` or as `--set TABLE.KEY=VALUE`; missing",
        "settings keep the defaults shown. A value of the wrong type or outside its bounds, or a broken rule, stops",
        "the command with one line naming the setting by its table, e.g. `config: [icp] min_inliers must be >= 0,",
        "got -5`. Numbers must be finite (`or inf`: also `inf`); a list's bounds apply to each of its values.",
        "",
        "## User settings",
        "",
        "The choices a run is made of. A run's `config.toml` gives every one of them, the package version, and each",
        "expert constant whose value differs from its default, so that `run SEQ --config RUN/config.toml` repeats",
        "the run.",
        "",
        *_HEADER,
        *_user_rows(root),
        "",
        "## Expert constants, per table",
        "",
        "Tuned values that a run rarely needs to change; they may still be overridden like a user setting.",
        "",
    ]
    for path, cfg in iter_tables(root):
        out += _table_section(path, cfg)
    return "\n".join(out).rstrip() + "\n"
