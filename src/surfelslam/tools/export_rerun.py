"""``surfelslam rerun RUN_DIR``: a finished run as a Rerun recording (``run.rrd``), with the sequence's images."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from surfelslam.errors import ConfigError
from surfelslam.tools.common import DepthScaleOpt, IntrinsicsOpt, console, handle_errors, parse_intrinsics


def print_export(summary, notes: list[str]) -> None:
    for n in notes:
        console.print(f"note: {n}", highlight=False, markup=False)
    for s in summary.frames_skipped[:5]:
        console.print(f"skipped frame: {s}", highlight=False, markup=False)
    console.print(f"wrote {summary.path} ({summary.poses} poses, {summary.points:,} map points, "
                  f"{summary.loop_edges} loop edges, {summary.images} image pairs)", highlight=False,
                  markup=False)


def register(app: typer.Typer) -> None:
    @app.command("rerun")
    @handle_errors
    def rerun_cmd(
        run_dir: Annotated[Path, typer.Argument(help="Output folder of `surfelslam run`.")],
        out: Annotated[Path | None, typer.Option("--out", help="Recording to write (default RUN_DIR/run.rrd).")] = None,
        seq: Annotated[Path | None, typer.Option(
            "--sequence", "--seq", help="The run's sequence (default: the one named in metrics.json), for images "
                                        "and ground truth.")] = None,
        images_every: Annotated[int, typer.Option("--images-every", help="Log every N-th frame's colour and "
                                                                         "depth images.")] = 10,
        no_images: Annotated[bool, typer.Option("--no-images", help="Poses, map and trajectories only.")] = False,
        intrinsics: IntrinsicsOpt = None,
        depth_scale: DepthScaleOpt = None,
        downsample: Annotated[int | None, typer.Option(
            "--downsample", help="Image sampling of the run (default: the one in metrics.json).")] = None,
    ) -> None:
        """Write a run as a Rerun recording (map, estimate vs ground truth, loops, camera and images over time).

        Needs the optional rerun-sdk (pip install 'surfelslam[viz]'); view with `rerun RUN_DIR/run.rrd`.
        """
        if images_every < 1:
            raise ConfigError(f"--images-every must be >= 1, got {images_every}")
        from surfelslam.viz.run_export import export_run

        print_export(*export_run(run_dir, out, seq, images_every, not no_images, parse_intrinsics(intrinsics),
                                 depth_scale, downsample))

