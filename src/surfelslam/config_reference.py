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

from surfelslam.config import check_rules, field_bounds, field_types, iter_tables, join_path, toml_value


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


def reference_markdown(cls: type) -> str:
    """The configuration reference page of config class ``cls`` (Markdown): one section per TOML table with its
    settings (key, default, unit, bounds or choices, meaning) and the rules relating them."""
    root = cls()
    out = [
        "# Configuration reference",
        "",
        "Generated from the settings' definitions by `make docs` (`python -m surfelslam.tools.gen_docs`); do not edit.",
        "Every setting may be given in a TOML file passed with `--config`; missing settings keep the defaults shown.",
        "A value of the wrong type or outside its bounds, or a broken rule, stops the command with one line naming",
        "the setting by its table, e.g. `config: [icp] min_inliers must be >= 0, got -5`. Numbers must be finite",
        "(`or inf`: also `inf`); a list's bounds apply to each of its values.",
        "",
    ]
    for path, cfg in iter_tables(root):
        klass = type(cfg)
        hints = field_types(klass)
        attr_docs = _attribute_docs(klass.__doc__)
        rows = []
        for f in dataclasses.fields(cfg):
            v = getattr(cfg, f.name)
            if dataclasses.is_dataclass(v):
                continue
            b = field_bounds(f)
            bounds = b.describe()
            extra = []
            if b.min_len is not None and b.min_len > 1:
                extra.append(f"at least {b.min_len} values")
            if b.allow_inf:
                extra.append("or inf")
            bounds = "; ".join(x for x in [bounds, *extra] if x)
            rows.append(f"| `{f.name}` | {_default_text(v)} | {b.unit or ''} | {_md(bounds)} | "
                        f"{_md(b.doc or attr_docs.get(f.name, '')) or '(' + _type_name(hints[f.name]) + ')'} |")
        subs = [f"`[{join_path(path, f.name)}]`" for f in dataclasses.fields(cfg)
                if dataclasses.is_dataclass(getattr(cfg, f.name))]
        out.append(f"## `[{path}]`" if path else f"## {klass.__name__} (the file's top level)")
        out.append("")
        doc = _summary(klass.__doc__)
        if doc and not doc.startswith(klass.__name__ + "("):  # not dataclass's generated signature
            out += [_md(doc), ""]
        if rows:
            out += ["| key | default | unit | bounds | meaning |", "|---|---|---|---|---|", *rows, ""]
        rules = [(r.__doc__ or r.__name__).strip() for r in check_rules(klass)]
        if rules:
            out += ["Rules:", "", *[f"- {_md(r)}" for r in rules], ""]
        if subs:
            out += ["Tables: " + ", ".join(subs) + ".", ""]
    return "\n".join(out).rstrip() + "\n"
