"""``python -m surfelslam.tools.bytecode``: write the Python bytecode of every module a ``surfelslam run`` imports,
where it is missing or stale (``make warmup`` runs it after the kernels' parts).

A process started with PYTHONDONTWRITEBYTECODE=1 compiles every module that has no bytecode from source, and keeps
nothing: with a venv uv installed (uv compiles nothing) that is about 270 modules at every command's start (the
package, typer, pydantic, rich, evo), a second of CPU. Written once here, they are loaded instead. The bytecode goes
where the import system reads it (``__pycache__`` beside the source, or ``sys.pycache_prefix``), timestamp-checked as
an import writes it; a folder that cannot be written is passed over (its modules are compiled when imported, as
before).
"""

from __future__ import annotations

import importlib
import importlib.util
import py_compile
import sys
from collections.abc import Iterable
from pathlib import Path

#: what a run imports besides its start: the report's modules (evo, matplotlib), imported while it tracks
RUN_MODULES = ("surfelslam.tools.run", "surfelslam.api", "surfelslam.eval.metrics", "surfelslam.viz.run_report",
               "surfelslam.viz.trajectory_plots", "surfelslam.viz.map_figures")
_PYC_HEADER_BYTES = 16  # magic number, flags, source mtime, source size (PEP 552)
_HASH_BASED = 1  # the flags' bit of a hash-checked file


def bytecode_is_fresh(source: Path) -> bool:
    """Whether ``source`` has bytecode the import system takes: this Python's magic number and, for a
    timestamp-checked file, the source's mtime and size (a hash-checked file is taken as it is)."""
    try:
        with open(importlib.util.cache_from_source(str(source)), "rb") as fh:
            head = fh.read(_PYC_HEADER_BYTES)
        st = source.stat()
    except OSError:
        return False
    if len(head) < _PYC_HEADER_BYTES or head[:4] != importlib.util.MAGIC_NUMBER:
        return False
    if int.from_bytes(head[4:8], "little") & _HASH_BASED:
        return True
    mtime, size = int.from_bytes(head[8:12], "little"), int.from_bytes(head[12:16], "little")
    return mtime == int(st.st_mtime) & 0xFFFFFFFF and size == st.st_size & 0xFFFFFFFF


def stale_sources(modules: Iterable) -> list[Path]:
    """The source files of ``modules`` (module objects) without fresh bytecode (:func:`bytecode_is_fresh`)."""
    files = {Path(f) for m in modules if isinstance(f := getattr(m, "__file__", None), str) and f.endswith(".py")}
    return sorted(f for f in files if not bytecode_is_fresh(f))


def write_bytecode(sources: Iterable[Path]) -> int:
    """Byte-compile each of ``sources`` where the import system reads it; returns how many were written (a source
    that cannot be compiled, or whose folder cannot be written, is passed over)."""
    written = 0
    for src in sources:
        try:
            py_compile.compile(str(src), cfile=importlib.util.cache_from_source(str(src)), doraise=True,
                               invalidation_mode=py_compile.PycInvalidationMode.TIMESTAMP)
            written += 1
        except (OSError, py_compile.PyCompileError):
            continue
    return written


def _parse_run_command() -> None:
    """Parse a ``surfelslam run`` command line as the command does (typer's value coercion, whose first use imports
    pydantic), without running it."""
    import typer

    from surfelslam.tools import run

    app = typer.Typer(add_completion=False)
    run.register(app)
    typer.main.get_command(app).make_context("run", ["SEQ", "--out", "OUT"])


def _load_kernels() -> None:
    """The dense tracker's kernels on two tiny frames: numba imports much of itself only when it first loads a kernel
    (from its cache, after ``make warmup``'s parts)."""
    from surfelslam.slam.config import SlamConfig
    from surfelslam.slam.warmup import warm_up_dense

    warm_up_dense(SlamConfig())


def write_run_bytecode() -> int:
    """The bytecode of every module of the package and of every other module a ``surfelslam run`` imports (its
    command line's parsing, the library, the kernels' loading, the report's modules) where it is missing or stale;
    returns how many files were written."""
    for name in RUN_MODULES:
        importlib.import_module(name)
    _parse_run_command()
    _load_kernels()
    package = sorted(Path(__file__).resolve().parents[1].rglob("*.py"))
    return write_bytecode([*(f for f in package if not bytecode_is_fresh(f)),
                           *stale_sources(list(sys.modules.values()))])


if __name__ == "__main__":
    write_run_bytecode()
