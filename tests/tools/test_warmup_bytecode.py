"""``python -m surfelslam.tools.bytecode`` (``make warmup``): modules without fresh bytecode are found and compiled
where the import system reads them, so that a process with PYTHONDONTWRITEBYTECODE=1 loads them instead of compiling
them again."""

from __future__ import annotations

import importlib
import importlib.machinery
import importlib.util
import os
import sys
from pathlib import Path

import pytest

from surfelslam.tools.bytecode import module_sources, write_bytecode


def _not_from_source(name: str, path: Path):
    """The module's code object as the import system gets it, failing if it had to compile the source."""
    loader = importlib.machinery.SourceFileLoader(name, str(path))

    def compiled(*_args, **_kwargs):
        pytest.fail(f"{path.name} was compiled from source: its bytecode was not taken")

    loader.source_to_code = compiled
    return loader.get_code(name)


def test_modules_bytecode_is_written_and_taken(tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "dont_write_bytecode", True)  # as under PYTHONDONTWRITEBYTECODE=1
    monkeypatch.syspath_prepend(str(tmp_path))
    src = tmp_path / "ovh_bytecode_probe.py"
    src.write_text("VALUE = 1\n")
    mod = importlib.import_module("ovh_bytecode_probe")
    monkeypatch.delitem(sys.modules, "ovh_bytecode_probe")
    pyc = Path(importlib.util.cache_from_source(str(src)))
    assert module_sources([mod, sys]) == [src] and not pyc.exists()  # a built-in module has no source

    broken = tmp_path / "ovh_broken.py"
    broken.write_text("def (:\n")
    assert write_bytecode([src, broken]) == 1  # what cannot be compiled is passed over, and counted
    namespace: dict = {}
    exec(_not_from_source("ovh_bytecode_probe", src), namespace)
    assert namespace["VALUE"] == 1
    written = pyc.stat().st_mtime_ns
    assert write_bytecode([src]) == 0 and pyc.stat().st_mtime_ns == written  # fresh: left alone

    src.write_text("VALUE = 22\n")  # edited (a later mtime): stale, written again, and the new code taken
    os.utime(src, ns=(src.stat().st_atime_ns, src.stat().st_mtime_ns + 2_000_000_000))
    assert write_bytecode([src]) == 0
    namespace = {}
    exec(_not_from_source("ovh_bytecode_probe", src), namespace)
    assert namespace["VALUE"] == 22


def test_make_warmup_writes_the_bytecode():
    recipe = (Path(__file__).parents[2] / "Makefile").read_text().split("\nwarmup:")[1].split("\n\n")[0]
    assert "-m surfelslam.tools.bytecode" in recipe
