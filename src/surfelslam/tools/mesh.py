"""``surfelslam mesh RUN_DIR``: a triangle mesh (``mesh.ply``) of a finished run.

The work is :func:`surfelslam.slam.run_mesh.mesh_run` (TSDF fusion of the run's depth frames at its poses, or
Poisson on its surfels); the command parses its options into a :class:`MeshConfig` and prints what was written.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from surfelslam.errors import ConfigError, ConfigValueError
from surfelslam.tools.common import console, handle_errors

if TYPE_CHECKING:  # the library is imported when the command runs, not for its --help
    from surfelslam.mapping.mesh import MeshConfig

#: MeshConfig fields -> the options that set them (for error messages)
OPTION_OF = {"method": "--method", "voxel_m": "--voxel", "trunc_m": "--trunc", "max_depth_m": "--max-depth",
             "min_depth_m": "the run's [fusion] min_depth_m", "stride": "--stride", "min_weight": "--min-weight",
             "min_component": "--min-component"}


def mesh_config(**given) -> MeshConfig:
    """A :class:`MeshConfig` from the options given (``None``: the default); a bad value names its option."""
    from surfelslam.mapping.mesh import MeshConfig

    try:
        return MeshConfig(**{k: v for k, v in given.items() if v is not None})
    except ConfigValueError as exc:
        text = str(exc).replace("config: [MeshConfig] ", "")
        for field, option in OPTION_OF.items():
            text = re.sub(rf"\b{field}\b", option, text)
        raise ConfigError(text) from None




def register(app: typer.Typer) -> None:
    @app.command("mesh")
    @handle_errors
    def mesh_cmd(
        run_dir: Annotated[Path, typer.Argument(help="Output folder of `surfelslam run`.")],
        method: Annotated[str, typer.Option(
            "--method", help="tsdf: fuse the run's depth frames at its poses, then marching cubes; poisson: "
                             "screened Poisson on map.ply's surfels (needs open3d: pip install "
                             "'surfelslam[bench]').")] = "tsdf",
        voxel: Annotated[float | None, typer.Option("--voxel", help="TSDF voxel size [m]. Default 0.01.")] = None,
        trunc: Annotated[float | None, typer.Option(
            "--trunc", help="TSDF truncation distance [m]. Default 4 voxels.")] = None,
        max_depth: Annotated[float | None, typer.Option(
            "--max-depth", help="Fuse depths up to this [m]. Default 5: a Kinect's range, each depth noise-weighted.")
                                        ] = None,
        stride: Annotated[int | None, typer.Option("--stride", help="Fuse every N-th frame. Default 1.")] = None,
        min_weight: Annotated[float | None, typer.Option(
            "--min-weight", help="Mesh only voxels seen in at least this many frames. Default 1.")] = None,
        min_component: Annotated[int | None, typer.Option(
            "--min-component", help="Remove floating pieces of fewer triangles (0: keep all). Default 100.")] = None,
        out: Annotated[Path | None, typer.Option("--out", help="Mesh file to write (default RUN_DIR/mesh.ply).")
                       ] = None,
        sequence: Annotated[Path | None, typer.Option(
            "--sequence", help="The run's sequence folder (default: the one metrics.json names).")] = None,
        progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Show a progress bar.")] = True,
    ) -> None:
        """Write a run's triangle mesh (mesh.ply, colours and normals) by TSDF fusion or Poisson.

        TSDF (the default) reads the run's sequence again with the run's dataset options and fuses its depth
        frames at the poses of trajectory.txt; Poisson uses the surfels of map.ply.
        """
        from surfelslam.api import tsdf_bar
        from surfelslam.mapping.mesh import METHODS
        from surfelslam.slam.run_mesh import mesh_run

        if method not in METHODS:
            raise ConfigError(f"--method must be one of {', '.join(METHODS)}, got {method!r}")
        cfg = mesh_config(method=method, voxel_m=voxel, trunc_m=trunc, max_depth_m=max_depth, stride=stride,
                          min_weight=min_weight, min_component=min_component)
        res = mesh_run(run_dir, cfg, out, sequence, tsdf_bar if progress else None, run_depth_range=max_depth is None)
        for note in res.notes:
            console.print(f"note: {note}", highlight=False, markup=False, soft_wrap=True)
        detail = (f"{res.frames_fused} frames fused, voxel {cfg.voxel_m * 100:g} cm, TSDF {res.tsdf_mb:,.0f} MiB"
                  if res.method == "tsdf" else "Poisson on map.ply")
        console.print(f"wrote {res.path} ({res.vertices:,} vertices, {res.faces:,} triangles; {detail}; "
                      f"{res.seconds:.1f} s)", highlight=False, markup=False, soft_wrap=True)
