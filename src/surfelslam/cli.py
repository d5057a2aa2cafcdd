"""The ``surfelslam`` command line. Each command lives in :mod:`surfelslam.tools`."""

from __future__ import annotations

import importlib

import typer

app = typer.Typer(
    name="surfelslam",
    help="Dense RGB-D SLAM: projective ICP + point-based fusion, with a sparse ORB back end.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

# One module per command, each with register(app).
COMMAND_MODULES = [
    "info",
    "synth",
    "eval",
    "run",
    "register",
    "experiments",
    "calibrate_colour",
    "export_rerun",
]

for _name in COMMAND_MODULES:
    importlib.import_module(f"surfelslam.tools.{_name}").register(app)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
