"""Shared pieces of the commands: error handling, dataset options, console output."""

from __future__ import annotations

import contextlib
import functools
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape

from surfelslam.cli import (
    EXIT_INTERNAL_ERROR,
    EXIT_INTERRUPTED,
    debug_enabled,
    force_exit_on_interrupt,
    internal_error_message,
)
from surfelslam.datasets.base import DatasetOptions
from surfelslam.errors import ConfigError, SurfelSlamError

try:  # typer >= 0.20 vendors click
    from typer._click.exceptions import ClickException
except ImportError:  # pragma: no cover - older typer on click
    from click.exceptions import ClickException

console = Console()
err_console = Console(stderr=True)

EXIT_BAD_INPUT = 2
#: typer's own control flow (exit codes, usage errors), passed through untouched
_CONTROL = (typer.Exit, typer.Abort, ClickException)

F = TypeVar("F", bound=Callable[..., Any])


def _stderr_lock():
    """The image reader's lock while it redirects fd 2 (so that our line is not taken for decoder chatter)."""
    images = sys.modules.get("surfelslam.io.images")
    lock = getattr(images, "stderr_lock", None)
    return contextlib.nullcontext() if lock is None else lock


def print_error(message: object) -> None:
    """``error: <message>`` on stderr, on one line, the message printed as it is (rich markup would eat
    ``[section]`` names and bracketed paths)."""
    text = re.sub(r"\s*[\r\n]+\s*", " ", str(message)).strip()
    with _stderr_lock():
        err_console.print(f"[bold red]error:[/] {escape(text)}", highlight=False, soft_wrap=True)


def handle_errors(fn: F) -> F:
    """Wrap a command so that it never ends in a traceback:

    * ``SurfelSlamError`` and OS-level file errors: one line on stderr, exit 2;
    * Ctrl-C: ``interrupted``, exit 130 (a second Ctrl-C during clean-up exits at once);
    * anything else: ``error: internal error: <type>: <message> (please report ...)``, exit 1, unless
      ``SURFELSLAM_DEBUG=1`` (then the exception propagates with its traceback).
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except _CONTROL:
            raise
        except SurfelSlamError as exc:
            print_error(exc)
            raise typer.Exit(EXIT_BAD_INPUT) from None
        except OSError as exc:
            where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
            print_error(f"{where}{exc.strerror or exc}")
            raise typer.Exit(EXIT_BAD_INPUT) from None
        except KeyboardInterrupt:
            force_exit_on_interrupt()
            with _stderr_lock():
                err_console.print("[yellow]interrupted[/]")
            raise typer.Exit(EXIT_INTERRUPTED) from None
        except Exception as exc:
            if debug_enabled():
                raise
            print_error(internal_error_message(exc))
            raise typer.Exit(EXIT_INTERNAL_ERROR) from None

    return wrapper  # type: ignore[return-value]


# Dataset options, shared by every command that reads a sequence.
SeqArg = Annotated[Path, typer.Argument(help="Sequence folder (TUM, ICL-NUIM, 7-Scenes or plain rgb/ + depth/).")]
IntrinsicsOpt = Annotated[
    str | None, typer.Option("--intrinsics", help="fx,fy,cx,cy at full resolution (overrides the layout's default).")
]
DepthScaleOpt = Annotated[
    float | None, typer.Option("--depth-scale", help="Raw depth units per metre (TUM 5000, millimetres 1000).")
]
StartOpt = Annotated[int, typer.Option("--start", help="First frame position (0-based).")]
EndOpt = Annotated[int | None, typer.Option("--end", help="One past the last frame position.")]
StrideOpt = Annotated[int, typer.Option("--stride", help="Keep every N-th frame.")]
DownsampleOpt = Annotated[int, typer.Option("--downsample", help="Sample images [::N, ::N] (intrinsics / N).")]


def parse_intrinsics(text: str | None) -> tuple[float, float, float, float] | None:
    if text is None:
        return None
    try:
        vals = tuple(float(x) for x in text.replace(" ", "").split(","))
    except ValueError:
        raise ConfigError(f"--intrinsics must be four numbers fx,fy,cx,cy, got {text!r}") from None
    if len(vals) != 4:
        raise ConfigError(f"--intrinsics must be four numbers fx,fy,cx,cy, got {text!r}")
    return vals  # type: ignore[return-value]


def dataset_options(
    intrinsics: str | None = None,
    depth_scale: float | None = None,
    start: int = 0,
    end: int | None = None,
    stride: int = 1,
    downsample: int = 1,
) -> DatasetOptions:
    return DatasetOptions(parse_intrinsics(intrinsics), depth_scale, start, end, stride, downsample)
