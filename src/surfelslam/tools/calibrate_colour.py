"""``surfelslam calibrate-colour SEQ``: fit a separate colour camera to a sequence whose colour is not registered.

Prints the fit (``geometry.colour_fit``) and the two ``INFO.txt`` lines that make every command use it.
"""

from __future__ import annotations

import json
from typing import Annotated

import typer
from rich.table import Table

from surfelslam.tools.common import DatasetOptionsArgs, SeqArg, console, handle_errors, with_dataset_options


def info_lines(fx: float, fy: float, cx: float, cy: float, t: tuple[float, float, float]) -> list[str]:
    """The ``INFO.txt`` lines of a colour camera (full-resolution values)."""
    return [f"colour intrinsics : fx={fx:.2f} fy={fy:.2f} cx={cx:.2f} cy={cy:.2f}",
            f"colour translation : {t[0]:.4f} {t[1]:.4f} {t[2]:.4f}"]


def register(app: typer.Typer) -> None:
    @app.command("calibrate-colour")
    @handle_errors
    @with_dataset_options
    def calibrate_colour(
        seq: SeqArg,
        dataset: DatasetOptionsArgs,
        frames: Annotated[int, typer.Option(help="Frames used, evenly spread over the selection.", min=1)] = 20,
        json_out: Annotated[bool, typer.Option("--json", help="Print the result as JSON.")] = False,
    ) -> None:
        """Fit the colour camera (intrinsics + sideways offset) so that colour edges fall on depth edges."""
        import numpy as np

        from surfelslam.datasets import open_sequence
        from surfelslam.geometry.colour_fit import fit_colour_camera

        sq = open_sequence(seq, dataset.resolve())
        picks = np.unique(np.linspace(0, len(sq) - 1, min(frames, len(sq))).round().astype(int))
        fit = fit_colour_camera([sq[int(i)] for i in picks], sq.intrinsics)
        ci, f = fit.camera.intrinsics, sq.options.downsample
        full = (ci.fx * f, ci.fy * f, ci.cx * f, ci.cy * f)  # INFO.txt values are at the files' resolution
        lines = info_lines(*full, fit.camera.t_colour_depth_m)
        result = {"colour_intrinsics_full_resolution": dict(zip(("fx", "fy", "cx", "cy"), full, strict=True)),
                  "t_colour_depth_m": list(fit.camera.t_colour_depth_m),
                  "edge_distance_px": fit.edge_distance_px,
                  "edge_distance_same_pixel_px": fit.edge_distance_same_pixel_px,
                  "frames": fit.n_frames, "edge_pixels": fit.n_edge_pixels, "info_lines": lines}
        if json_out:
            typer.echo(json.dumps(result, indent=2))
            return
        table = Table(title="colour camera fit", show_header=False)
        table.add_column("field", style="bold")
        table.add_column("value")
        table.add_row("colour intrinsics", "fx={:.2f} fy={:.2f} cx={:.2f} cy={:.2f} (files' resolution)".format(*full))
        table.add_row("t_colour_depth", "({:.4f}, {:.4f}, {:.4f}) m".format(*fit.camera.t_colour_depth_m))
        table.add_row("depth edge -> colour edge", f"{fit.edge_distance_same_pixel_px:.2f} px same pixel, "
                                                   f"{fit.edge_distance_px:.2f} px through the fit")
        table.add_row("used", f"{fit.n_frames} frames, {fit.n_edge_pixels} depth-edge pixels")
        console.print(table)
        typer.echo(f"Add to {sq.root / 'INFO.txt'} (the maps' colours are then sampled through this camera):")
        for line in lines:
            typer.echo(f"  {line}")
