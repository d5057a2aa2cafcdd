"""Fuzzing the configuration: a mutated or random ``config.toml`` (``--config``) and random ``--set KEY=VALUE`` items.
A valid result is a checked :class:`SlamConfig` that survives the round trip a run makes: written as ``config.toml``
(:func:`dumps_toml`) and read back, it is the same config."""

from __future__ import annotations

import dataclasses
import json
import math

from fuzzkit import NASTY_TOKENS, example_dir, is_error, mutated_text, outcome, text_or_bytes, unchanged
from hypothesis import example, given
from hypothesis import strategies as st

from surfelslam.config import dumps_toml, iter_tables, validate
from surfelslam.slam import SlamConfig
from surfelslam.slam.runner import apply_sets, load_config

DEFAULT_TOML = dumps_toml(SlamConfig())
#: every setting's dotted path (``icp.min_inliers``), and every table's
LEAF_KEYS = sorted(f"{path}.{f.name}".lstrip(".") for path, cfg in iter_tables(SlamConfig())
                   for f in dataclasses.fields(cfg) if not dataclasses.is_dataclass(getattr(cfg, f.name)))
TABLE_KEYS = sorted(path for path, _ in iter_tables(SlamConfig()) if path)
#: TOML values (and things that are not TOML) for --set
SET_VALUES = st.one_of(
    st.sampled_from(NASTY_TOKENS),
    st.sampled_from(("true", "false", "[]", "[1, 2]", "[nan]", "[1, \"a\"]", "{a = 1}", "\"\"", "\"a\\nb\"",
                     "'x'", "1979-05-27", "0.5", "-0.5", "300", "1e6", "-inf", "[[1]]", "\"\\u0000\"")),
    st.integers(-(2**70), 2**70).map(str),
    st.floats().map(repr),
    st.text(max_size=20),
)


def check_config(cfg: SlamConfig, where) -> None:
    """A valid config: it validates, and ``config.toml`` written from it reads back as the same config."""
    assert isinstance(cfg, SlamConfig)
    validate(cfg)
    path = example_dir(where) / "config.toml"
    path.write_text(dumps_toml(cfg))
    back = outcome(lambda: load_config(path))
    assert not is_error(back), f"the config.toml written for this config does not read back: {back}"
    assert _same(back, cfg), "config.toml does not read back as the same config"


def _same(a, b) -> bool:
    """Equal configs, NaN-free by validation; floats compared exactly (TOML keeps them)."""
    if dataclasses.is_dataclass(a):
        return all(_same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a))
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a):
        return math.isnan(b)
    return a == b


@given(content=text_or_bytes(DEFAULT_TOML))
def test_mutated_config_file(tmp_path, content):
    path = example_dir(tmp_path) / "config.toml"
    path.write_bytes(content)
    with unchanged(path.parent):
        cfg = outcome(lambda: load_config(path))
    if not is_error(cfg):
        check_config(cfg, tmp_path)


@given(key=st.sampled_from(LEAF_KEYS), value=SET_VALUES, extra=st.lists(st.sampled_from(LEAF_KEYS + TABLE_KEYS),
                                                                         max_size=2))
def test_toml_value_of_any_setting(tmp_path, key, value, extra):
    """A config file giving one setting any value (in its table), sometimes with other keys or tables set too."""
    table, _, name = key.rpartition(".")
    lines = [f"[{table}]" if table else "", f"{name} = {value}"] + [f"{k.rpartition('.')[2]} = 1" for k in extra]
    path = example_dir(tmp_path) / "config.toml"
    path.write_text("\n".join(lines) + "\n")
    cfg = outcome(lambda: load_config(path))
    if not is_error(cfg):
        check_config(cfg, tmp_path)


@given(items=st.lists(st.one_of(
    st.tuples(st.sampled_from(LEAF_KEYS + TABLE_KEYS), SET_VALUES).map(lambda kv: f"{kv[0]}={kv[1]}"),
    st.text(max_size=30),
    st.sampled_from(LEAF_KEYS).map(lambda k: k.upper()),
    st.sampled_from(LEAF_KEYS).map(lambda k: f"{k}"),
), min_size=1, max_size=3))
@example(items=["icp.robust_kernel=\n"])  # found: the error message quoted the item with its line break
@example(items=["icp.no\nsuch=1", "dataset.end=0,1"])
def test_set_items(tmp_path, items):
    """``--set`` items: known and unknown keys, tables, any value, no ``=``."""
    cfg = outcome(lambda: apply_sets(SlamConfig(), items))
    if not is_error(cfg):
        check_config(cfg, tmp_path)


@given(text=mutated_text("[icp]\nmin_inliers = 300\n[dataset]\nend = 5\ngt = \"gt.txt\"\n"))
def test_small_config_files(tmp_path, text):
    path = example_dir(tmp_path) / "small.toml"
    path.write_text(text, errors="surrogatepass")
    cfg = outcome(lambda: load_config(path))
    if not is_error(cfg):
        check_config(cfg, tmp_path)


#: the settings that hold strings (free text such as dataset.gt, or one of a setting's choices)
STRING_KEYS = sorted(f"{path}.{f.name}".lstrip(".") for path, cfg in iter_tables(SlamConfig())
                     for f in dataclasses.fields(cfg)
                     if "str" in str(f.type) and not dataclasses.is_dataclass(getattr(cfg, f.name)))


@given(key=st.sampled_from(STRING_KEYS), text=st.text(max_size=20))
@example(key="dataset.gt", text="gt\n.txt")  # found: a newline was written raw, config.toml did not read back
@example(key="dataset.rgb_topic", text="\x00\x7f\\\"")
def test_any_text_in_a_string_setting(tmp_path, key, text):
    """Any text (control characters, quotes, backslashes, non-ASCII) given to a string setting as a TOML string."""
    quoted = json.dumps(text, ensure_ascii=False)  # a TOML basic string too, but for the characters JSON leaves raw
    cfg = outcome(lambda: apply_sets(SlamConfig(), [f"{key}={quoted}"]))
    if not is_error(cfg):
        check_config(cfg, tmp_path)
