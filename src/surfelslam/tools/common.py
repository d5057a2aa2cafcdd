"""Shared pieces of the commands: error handling, dataset options, console output."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import inspect
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape

from surfelslam.errors import ConfigError, SurfelSlamError, one_line
from surfelslam.tools.exits import (
    EXIT_INTERNAL_ERROR,
    EXIT_INTERRUPTED,
    debug_enabled,
    force_exit_on_interrupt,
    internal_error_message,
    interrupt_requested,
)

if TYPE_CHECKING:  # the dataset layer (numpy, scipy) is imported when a command runs, not for its --help
    from surfelslam.datasets.base import DatasetOptions

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
    text = one_line(re.sub(r"\s*[\r\n]+\s*", " ", str(message)).strip())
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
            if interrupt_requested():  # a failure the Ctrl-C caused (e.g. a JIT compilation it broke)
                force_exit_on_interrupt()
                with _stderr_lock():
                    err_console.print("[yellow]interrupted[/]")
                raise typer.Exit(EXIT_INTERRUPTED) from None
            if debug_enabled():
                raise
            print_error(internal_error_message(exc))
            raise typer.Exit(EXIT_INTERNAL_ERROR) from None

    return wrapper  # type: ignore[return-value]


# Dataset options, shared by every command that reads a sequence: one definition (the ``...Opt`` annotations) and one
# way to declare them (:func:`with_dataset_options`, which hands the command one :class:`DatasetOptionsArgs`).
SeqArg = Annotated[Path, typer.Argument(help="Sequence folder (TUM, ICL-NUIM, 7-Scenes or plain rgb/ + depth/), "
                                              "or a ROS bag: .bag, .mcap, or a ROS 2 bag folder.")]
IntrinsicsOpt = Annotated[
    str | None, typer.Option("--intrinsics", help="fx,fy,cx,cy at full resolution (overrides the layout's default).")
]
DepthScaleOpt = Annotated[
    float | None, typer.Option("--depth-scale", help="Raw depth units per metre (TUM 5000, millimetres 1000).")
]
StartOpt = Annotated[int | None, typer.Option("--start", help="First frame position (0-based). Default 0.")]
EndOpt = Annotated[int | None, typer.Option("--end", help="One past the last frame position. Default: the end.")]
StrideOpt = Annotated[int | None, typer.Option("--stride", help="Keep every N-th frame. Default 1.")]
DownsampleOpt = Annotated[
    int | None, typer.Option("--downsample", help="Sample images [::N, ::N] (intrinsics / N). Default 1.")
]
RgbTopicOpt = Annotated[str | None, typer.Option(
    "--rgb-topic", help="ROS bags: the colour image topic (default: found by type and name).")]
DepthTopicOpt = Annotated[str | None, typer.Option(
    "--depth-topic", help="ROS bags: the depth image topic (default: found by type and name).")]
CameraInfoTopicOpt = Annotated[str | None, typer.Option(
    "--camera-info-topic", help="ROS bags: the CameraInfo topic giving the intrinsics (default: the one beside "
                                "the depth topic).")]
GtOpt = Annotated[str | None, typer.Option(
    "--gt", help="Ground truth replacing the sequence's own: a TUM trajectory file (or a bag's pose topic).")]


@dataclasses.dataclass(frozen=True)
class DatasetOptionsArgs:
    """The dataset options as typed on the command line; ``None``: not given (the default, or a config file's
    ``[dataset]`` value, applies: :meth:`resolve`)."""

    intrinsics: str | None = None
    depth_scale: float | None = None
    start: int | None = None
    end: int | None = None
    stride: int | None = None
    downsample: int | None = None
    rgb_topic: str | None = None
    depth_topic: str | None = None
    camera_info_topic: str | None = None
    gt: str | None = None

    def given(self) -> dict[str, Any]:
        """The options given, as :class:`DatasetOptions` fields (``--intrinsics`` parsed)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if getattr(self, f.name) is not None}
        if "intrinsics" in out:
            out["intrinsics"] = parse_intrinsics(out["intrinsics"])
        return out

    def resolve(self, base: DatasetOptions | None = None) -> DatasetOptions:
        """The options given override ``base`` (e.g. a config file's ``[dataset]``; default: the defaults)."""
        from surfelslam.datasets.base import DatasetOptions

        return dataclasses.replace(DatasetOptions() if base is None else base, **self.given())


_DATASET_PARAMS = tuple(
    inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=None, annotation=annotation)
    for name, annotation in (("intrinsics", IntrinsicsOpt), ("depth_scale", DepthScaleOpt), ("start", StartOpt),
                             ("end", EndOpt), ("stride", StrideOpt), ("downsample", DownsampleOpt),
                             ("rgb_topic", RgbTopicOpt), ("depth_topic", DepthTopicOpt),
                             ("camera_info_topic", CameraInfoTopicOpt), ("gt", GtOpt))
)


def with_dataset_options(fn: F) -> F:
    """Give command ``fn`` the dataset options ``--intrinsics --depth-scale --start --end --stride --downsample``
    and ``--rgb-topic --depth-topic --camera-info-topic --gt`` (the same names, help and defaults in every command);
    ``fn`` receives them as one ``dataset: DatasetOptionsArgs`` argument. Apply below ``@handle_errors``."""
    sig = inspect.signature(fn, eval_str=True)
    if "dataset" not in sig.parameters:
        raise TypeError(f"{fn.__name__} needs a 'dataset: DatasetOptionsArgs' parameter")
    params = [p for p in sig.parameters.values() if p.name != "dataset"] + list(_DATASET_PARAMS)
    names = [p.name for p in _DATASET_PARAMS]

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        given = {name: kwargs.pop(name, None) for name in names}
        return fn(*args, dataset=DatasetOptionsArgs(**given), **kwargs)

    new_sig = sig.replace(parameters=params)
    wrapper.__signature__ = new_sig  # type: ignore[attr-defined]
    wrapper.__annotations__ = {p.name: p.annotation for p in params}
    return wrapper  # type: ignore[return-value]


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

