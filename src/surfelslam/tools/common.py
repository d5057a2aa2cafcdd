"""Shared pieces of the commands: error handling, dataset options, console output."""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape

from surfelslam.datasets.base import DatasetOptions
from surfelslam.errors import ConfigError, SurfelSlamError

console = Console()
err_console = Console(stderr=True)

EXIT_BAD_INPUT = 2

F = TypeVar("F", bound=Callable[..., Any])


def print_error(message: object) -> None:
    """``error: <message>`` on stderr, the message printed as it is (rich markup would eat ``[section]`` names and
    bracketed paths)."""
    err_console.print(f"[bold red]error:[/] {escape(str(message))}", highlight=False, soft_wrap=True)


def handle_errors(fn: F) -> F:
    """Turn every ``SurfelSlamError`` (and OS-level file errors) into one line on stderr and exit 2."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except SurfelSlamError as exc:
            print_error(exc)
            raise typer.Exit(EXIT_BAD_INPUT) from None
        except OSError as exc:
            where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
            print_error(f"{where}{exc.strerror or exc}")
            raise typer.Exit(EXIT_BAD_INPUT) from None
        except KeyboardInterrupt:
            err_console.print("[yellow]interrupted[/]")
            raise typer.Exit(130) from None

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
