"""``python -m surfelslam.tools.bytecode`` (``make warmup``): modules without fresh bytecode are found and compiled
where the import system reads them, so that a process with PYTHONDONTWRITEBYTECODE=1 loads them instead of compiling
them again."""

from __future__ import annotations

import importlib
import importlib.machinery
import importlib.util
import sys
from pathlib import Path

import pytest

from surfelslam.tools.bytecode import bytecode_is_fresh, stale_sources, write_bytecode


def _not_from_source(name: str, path: Path):
    """The module's code object as the import system gets it, failing if it had to compile the source."""
    loader = importlib.machinery.SourceFileLoader(name, str(path))

    def compiled(*_args, **_kwargs):
        pytest.fail(f"{path.name} was compiled from source: its bytecode was not taken")

    loader.source_to_code = compiled
    return loader.get_code(name)


def test_stale_modules_are_found_and_their_bytecode_is_taken(tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "dont_write_bytecode", True)  # as under PYTHONDONTWRITEBYTECODE=1
    monkeypatch.syspath_prepend(str(tmp_path))
    src = tmp_path / "ovh_bytecode_probe.py"
    src.write_text("VALUE = 1\n")
    mod = importlib.import_module("ovh_bytecode_probe")
    monkeypatch.delitem(sys.modules, "ovh_bytecode_probe")
    assert not bytecode_is_fresh(src) and stale_sources([mod, sys]) == [src]  # a built-in module has no source

    assert write_bytecode([src, tmp_path / "missing.py"]) == 1  # what cannot be compiled is passed over
    assert bytecode_is_fresh(src) and stale_sources([mod]) == []
    namespace: dict = {}
    exec(_not_from_source("ovh_bytecode_probe", src), namespace)
    assert namespace["VALUE"] == 1

    src.write_text("VALUE = 22\n")  # edited: the bytecode is stale again (its recorded size differs)
    assert stale_sources([mod]) == [src]


def test_make_warmup_writes_the_bytecode():
    recipe = (Path(__file__).parents[2] / "Makefile").read_text().split("\nwarmup:")[1].split("\n\n")[0]
    assert "-m surfelslam.tools.bytecode" in recipe
