"""The ``surfelslam`` command line. Each command lives in :mod:`surfelslam.tools`.

A command's module (and with it numba, OpenCV, matplotlib, evo) is imported only when that command runs:
``surfelslam --help`` lists the commands from :data:`COMMANDS`, whose one-line help texts are copied from the
commands' docstrings (a test keeps them equal).

Start-up guarantees (:func:`main`):

* numba caches compiled kernels next to their sources, else in ``~/.cache/numba``; when neither is writable
  (read-only install, no writable HOME) ``NUMBA_CACHE_DIR`` is pointed at a temp folder before numba is imported
  (:func:`surfelslam.numba_cache.numba_cache_fallback`); a user-set ``NUMBA_CACHE_DIR`` is kept.
* Ctrl-C at any moment prints ``interrupted`` on stderr and exits with 130, without a traceback (from the moment
  this module runs: the ``surfelslam`` package's own imports come before it). The process ends with
  ``os._exit`` after the exit handlers, skipping the interpreter's slow module teardown.
* An unexpected exception prints ``error: internal error: <type>: <message> (please report)`` and exits with 1;
  ``SURFELSLAM_DEBUG=1`` shows the traceback instead.
"""

from __future__ import annotations

import atexit
import contextlib
import importlib
import os
import sys
from typing import Any

from surfelslam.numba_cache import configure_numba_cache
from surfelslam.tools.exits import (
    EXIT_INTERNAL_ERROR,
    EXIT_INTERRUPTED,
    catch_interrupts,
    debug_enabled,
    force_exit_on_interrupt,
    internal_error_message,
    interrupt_requested,
)

#: command name -> (module in surfelslam.tools, its docstring's first paragraph: the listing's help text)
COMMANDS: dict[str, tuple[str, str]] = {
    "info": ("info", "Show the detected layout, frames, resolution, intrinsics, depth scale and ground-truth "
                     "coverage."),
    "synth": ("synth", "Render a textured indoor scene along a camera trajectory; write rgb/, depth/, "
                       "groundtruth.txt."),
    "eval": ("eval", "ATE (SE(3)-aligned, TUM protocol) and RPE per frame and per second, computed with evo."),
    "run": ("run", "Track and fuse a sequence; writes trajectory.txt, map.ply, config.toml, metrics.json and "
                   "figures."),
    "register": ("register", "Register frame SOURCE onto frame TARGET; print and save the pose, inliers, RMSE and "
                             "GT error."),
    "experiments": ("experiments", "The reference assignment's experiments (ICP pairs, solvers, fusion, dormant "
                                   "rule, features, trackers) -> report.md."),
    "calibrate-colour": ("calibrate_colour", "Fit the colour camera (intrinsics + sideways offset) so that colour "
                                             "edges fall on depth edges."),
    "mesh": ("mesh", "Write a run's triangle mesh (mesh.ply, colours and normals) by TSDF fusion or Poisson."),
    "batch": ("batch", "Run sequences x trackers x configurations (a spec file, or SEQ... with --tracker/--set "
                       "sweeps) as Ray tasks; one results table."),
    "rerun": ("export_rerun", "Write a run as a Rerun recording (map, estimate vs ground truth, loops, camera and "
                              "images over time)."),
}
#: One module per command, each with ``register(app)``.
COMMAND_MODULES = [module for module, _ in COMMANDS.values()]

APP_HELP = "Dense RGB-D SLAM: projective ICP + point-based fusion, with a sparse ORB back end."


# ------------------------------------------------------------------------------------------------ messages
def _stderr_line(text: str) -> None:
    try:
        sys.stderr.write(text + "\n")
        sys.stderr.flush()
    except (OSError, ValueError):
        pass


def report_interrupt() -> None:
    """``interrupted`` on stderr; a second Ctrl-C exits at once."""
    force_exit_on_interrupt()
    _stderr_line("interrupted")


# ------------------------------------------------------------------------------------------------ the app
def _build_app() -> Any:
    import typer

    def show_version(value: bool) -> None:
        if value:
            from surfelslam import __version__

            typer.echo(f"surfelslam {__version__}")
            raise typer.Exit(0)

    app = typer.Typer(
        name="surfelslam",
        help=APP_HELP,
        cls=_lazy_command_group(),
        no_args_is_help=True,
        add_completion=False,
        pretty_exceptions_enable=False,
        rich_markup_mode=None,  # help texts hold literal brackets: 'surfelslam[viz]', units like [s]
    )

    @app.callback()
    def _root(
        version: bool = typer.Option(False, "--version", help="Print the version and exit.", is_eager=True,
                                     callback=show_version),
    ) -> None:
        pass

    return app


def _lazy_command_group() -> type:
    """The app's command group class (built on first use: defining it imports typer)."""
    import typer
    from typer.core import TyperGroup

    try:  # typer >= 0.20 vendors click
        from typer._click.exceptions import UsageError
    except ImportError:  # pragma: no cover - older typer on click
        from click.exceptions import UsageError

    class LazyCommandGroup(TyperGroup):
        """Imports a command's module on first use; lists unloaded commands from :data:`COMMANDS`."""

        def get_help_option(self, ctx):
            return _help_flag_off_by_default(super().get_help_option(ctx))

        def list_commands(self, ctx) -> list[str]:
            return [*self.commands, *(name for name in COMMANDS if name not in self.commands)]

        def get_command(self, ctx, cmd_name: str):
            if cmd_name not in self.commands and cmd_name in COMMANDS:
                self.commands[cmd_name] = _load_command(cmd_name)
            return self.commands.get(cmd_name)

        def format_commands(self, ctx, formatter) -> None:
            _list_commands(self.commands, self.list_commands(ctx), formatter)

        # typer turns a KeyboardInterrupt into a silent exit 130: report it where start-up takes time
        def make_context(self, *args, **kwargs):
            try:  # parsing imports typer's value coercion (pydantic): about 0.1 s
                return super().make_context(*args, **kwargs)
            except KeyboardInterrupt:
                report_interrupt()
                raise typer.Exit(EXIT_INTERRUPTED) from None

        def invoke(self, ctx):
            try:  # importing the command's module takes about a second
                return super().invoke(ctx)
            except KeyboardInterrupt:
                report_interrupt()
                raise typer.Exit(EXIT_INTERRUPTED) from None

        def resolve_command(self, ctx, args):
            try:
                return self._click_resolve_command(ctx, args)
            except UsageError as exc:
                if self.suggest_commands and args:
                    _suggest_commands(exc, args[0], self.list_commands(ctx))
                raise

    return LazyCommandGroup


def _list_commands(loaded: dict, names: list[str], formatter: Any) -> None:
    """The "Commands" section of the help: the ``loaded`` commands' own help, the others' from :data:`COMMANDS`."""
    from typer.core import TyperCommand

    names = [n for n in names if not (n in loaded and loaded[n].hidden)]
    if not names:
        return
    limit = formatter.width - 6 - max(len(n) for n in names)
    rows = []
    for name in names:
        cmd = loaded.get(name) or TyperCommand(name, help=COMMANDS[name][1])
        rows.append((name, cmd.get_short_help_str(limit)))
    with formatter.section("Commands"):
        formatter.write_dl(rows)


def _help_flag_off_by_default(option: Any) -> Any:
    """The group's ``--help`` option with the default ``False``, not ``None``: typer skips its value coercion for a
    bool, whose first use imports pydantic (about 0.3 s) that ``surfelslam COMMAND --help`` would otherwise pay for
    the group's ``--help``, which was not given."""
    if option is not None and option.default is None:
        option.default = False
    return option


def _suggest_commands(exc: Any, word: str, names: list[str]) -> None:
    """Append "Did you mean ...?" with the commands close to ``word`` to the usage error ``exc``."""
    import difflib

    matches = difflib.get_close_matches(word, names)
    if matches:
        exc.message = exc.message.rstrip(".") + ". Did you mean " + ", ".join(repr(m) for m in matches) + "?"


def _load_command(name: str) -> Any:
    """Import ``surfelslam.tools.<module>`` and build its click command."""
    import typer

    module = importlib.import_module(f"surfelslam.tools.{COMMANDS[name][0]}")
    sub = typer.Typer(rich_markup_mode=None, pretty_exceptions_enable=False, add_completion=False)
    module.register(sub)
    return typer.main.get_group(sub).commands[name]


_APP = None


def get_app() -> Any:
    """The typer application (built once; building imports typer but no command module)."""
    global _APP
    if _APP is None:
        configure_numba_cache()
        _APP = _build_app()
    return _APP


def __getattr__(name: str) -> Any:  # ``from surfelslam.cli import app`` builds it on demand
    if name == "app":
        return get_app()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def run_cli(argv: list[str] | None = None) -> int:
    """Run the command line and return its exit code (never raises, except with ``SURFELSLAM_DEBUG=1``)."""
    try:
        get_app()(args=argv, prog_name="surfelslam")
        return 0
    except SystemExit as exc:
        if exc.code is None or isinstance(exc.code, int):
            return exc.code or 0
        _stderr_line(str(exc.code))
        return EXIT_INTERNAL_ERROR
    except KeyboardInterrupt:
        report_interrupt()
        return EXIT_INTERRUPTED
    except Exception as exc:
        if interrupt_requested():  # a failure the Ctrl-C caused (e.g. a compilation it broke)
            report_interrupt()
            return EXIT_INTERRUPTED
        if debug_enabled():
            raise
        _stderr_line(f"error: {internal_error_message(exc)}")
        return EXIT_INTERNAL_ERROR


def _end_process(code: int) -> None:
    """Exit without the interpreter's teardown of every module (numba / LLVM: about 0.4 s), during which a Ctrl-C
    would kill the process without a word: exit handlers run, the output streams are flushed, then ``os._exit``."""
    with contextlib.suppress(Exception):
        atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


def main(argv: list[str] | None = None) -> None:
    """Entry point of the ``surfelslam`` script and ``python -m surfelslam`` (module docstring).

    Called without ``argv`` (as the process's entry point) it ends the process itself (:func:`_end_process`);
    with ``argv`` it raises SystemExit like any click program.
    """
    catch_interrupts()
    code = run_cli(argv)
    force_exit_on_interrupt()  # from here on a Ctrl-C ends the process at once, with a word
    if argv is None and hasattr(atexit, "_run_exitfuncs"):
        _end_process(code)
    sys.exit(code)


if __name__ == "__main__":
    main()
