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

import compileall
import importlib
import sys
from collections.abc import Iterable
from pathlib import Path

#: what a run imports besides its start: the report's modules (evo, matplotlib), imported while it tracks
RUN_MODULES = ("surfelslam.tools.run", "surfelslam.api", "surfelslam.eval.metrics", "surfelslam.viz.run_report",
               "surfelslam.viz.trajectory_plots", "surfelslam.viz.map_figures")


def module_sources(modules: Iterable) -> list[Path]:
    """The ``.py`` source files of ``modules`` (module objects; built-in and extension modules have none)."""
    files = (getattr(m, "__file__", None) for m in modules)
    return sorted({Path(f) for f in files if isinstance(f, str) and f.endswith(".py")})


def write_bytecode(sources: Iterable[Path]) -> int:
    """Byte-compile each of ``sources`` where the import system reads it, unless its bytecode is fresh (the standard
    library's :func:`compileall.compile_file`: timestamp-checked, as an import writes it); returns how many could not
    be compiled or written (passed over: compiled when imported, as before)."""
    return sum(not compileall.compile_file(str(src), quiet=2) for src in sources)


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
    returns how many could not be written."""
    for name in RUN_MODULES:
        importlib.import_module(name)
    _parse_run_command()
    _load_kernels()
    package = Path(__file__).resolve().parents[1].rglob("*.py")
    return write_bytecode(sorted({*package, *module_sources(list(sys.modules.values()))}))


if __name__ == "__main__":
    write_run_bytecode()
