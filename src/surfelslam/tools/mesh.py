"""``surfelslam mesh RUN_DIR``: a triangle mesh (``mesh.ply``) of a finished run.

``--method tsdf`` (default) reads the run's sequence again (the folder ``metrics.json`` names, with the run's
dataset options from ``config.toml``), fuses its depth frames at the poses of ``trajectory.txt`` into a TSDF and
extracts the surface by marching cubes (:mod:`surfelslam.mapping.mesh`). ``--method poisson`` reconstructs from the
surfels of ``map.ply`` with Open3D (optional). :func:`mesh_run` is the command without its printing.
"""

from __future__ import annotations

import dataclasses
import re
import time
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from surfelslam.errors import ConfigError, ConfigValueError, FrameError, InputError
from surfelslam.io.run_folder import read_run_metrics, read_run_trajectory
from surfelslam.mapping.mesh import METHODS, Mesh, MeshConfig
from surfelslam.tools.common import console, handle_errors

MESH_FILE = "mesh.ply"
#: Largest difference (s) between a trajectory stamp and a frame stamp for the frame to be fused at that pose.
FRAME_MATCH_S = 1e-4
#: MeshConfig fields -> the options that set them (for error messages)
OPTION_OF = {"method": "--method", "voxel_m": "--voxel", "trunc_m": "--trunc", "max_depth_m": "--max-depth",
             "min_depth_m": "the run's [fusion] min_depth_m", "stride": "--stride", "min_weight": "--min-weight",
             "min_component": "--min-component"}


@dataclasses.dataclass
class MeshResult:
    """What :func:`mesh_run` did."""

    path: Path
    method: str
    vertices: int
    faces: int
    frames_fused: int = 0
    frames_skipped: int = 0
    tsdf_mb: float = 0.0
    seconds: float = 0.0
    notes: list[str] = dataclasses.field(default_factory=list)


def mesh_config(**given) -> MeshConfig:
    """A :class:`MeshConfig` from the options given (``None``: the default); a bad value names its option."""
    try:
        return MeshConfig(**{k: v for k, v in given.items() if v is not None})
    except ConfigValueError as exc:
        text = str(exc).replace("config: [MeshConfig] ", "")
        for field, option in OPTION_OF.items():
            text = re.sub(rf"\b{field}\b", option, text)
        raise ConfigError(text) from None




def _run_config(run_dir: Path, metrics: dict):
    """The run's :class:`SlamConfig` (its ``config.toml``; else the defaults with ``metrics.json``'s dataset
    options)."""
    from surfelslam.config import load_toml
    from surfelslam.datasets.base import DatasetOptions
    from surfelslam.slam.config import SlamConfig

    path = run_dir / "config.toml"
    if path.is_file():
        return load_toml(SlamConfig, path)
    opts = dict(metrics.get("dataset_options") or {})
    if opts.get("intrinsics") is not None:
        opts["intrinsics"] = tuple(float(v) for v in opts["intrinsics"])
    known = {f.name for f in dataclasses.fields(DatasetOptions)}
    return SlamConfig(dataset=DatasetOptions(**{k: v for k, v in opts.items() if k in known}))


def _open_run_sequence(run_dir: Path, metrics: dict, run_cfg, sequence: Path | None):
    from surfelslam.datasets import open_sequence

    if sequence is None:
        named = metrics.get("sequence")
        if not named:
            raise InputError(run_dir, "metrics.json names no sequence (is it a complete run?): pass --sequence PATH")
        sequence = Path(named)
        if not sequence.is_dir():
            raise InputError(sequence, "the run's sequence (named in metrics.json) is not here: pass --sequence PATH")
    seq = open_sequence(sequence, run_cfg.dataset)
    res = metrics.get("resolution")
    if res is not None and [seq.intrinsics.width, seq.intrinsics.height] != list(res):
        raise ConfigError(f"{sequence} opens at {seq.intrinsics.width}x{seq.intrinsics.height}, the run was "
                          f"{res[0]}x{res[1]}: is it the run's sequence?")
    return seq


def _tsdf_mesh(run_dir: Path, cfg: MeshConfig, sequence: Path | None, progress: bool,
               run_depth_range: bool) -> tuple[Mesh, MeshResult]:
    from tqdm import tqdm

    from surfelslam.mapping.mesh import TsdfVolume
    from surfelslam.slam.mapper import frame_colour_at_depth

    est = read_run_trajectory(run_dir)
    metrics = read_run_metrics(run_dir)
    run_cfg = _run_config(run_dir, metrics)
    if run_depth_range:  # the near limit the run fused its map with (farther than its far limit: noise-weighted)
        cfg = dataclasses.replace(cfg, min_depth_m=run_cfg.fusion.min_depth_m)
    seq = _open_run_sequence(run_dir, metrics, run_cfg, sequence)
    T, has_pose = est.lookup(seq.timestamps, FRAME_MATCH_S)
    positions = np.flatnonzero(has_pose)[:: cfg.stride]
    if len(positions) == 0:
        raise InputError(run_dir / "trajectory.txt",
                         f"no pose has the timestamp of a frame of {seq.root}: is it the run's sequence?")
    colour_cam = getattr(seq, "colour_camera", None)
    vol = TsdfVolume.from_config(cfg)
    skipped = 0
    t0 = time.perf_counter()
    for i in tqdm(positions, unit="frame", disable=not progress, leave=False, desc="tsdf"):
        try:
            frame = seq[int(i)]
        except FrameError:
            skipped += 1
            continue
        rgb = frame_colour_at_depth(frame, seq.intrinsics, colour_cam, run_cfg.colour_registration)
        vol.integrate(frame.depth_m, rgb, seq.intrinsics, T[i])
    mesh = vol.extract_mesh(cfg.min_weight)
    result = MeshResult(Path(), "tsdf", mesh.n_vertices, mesh.n_faces, vol.frames, skipped,
                        vol.memory_mb(vol.n_blocks), time.perf_counter() - t0)
    if skipped:
        result.notes.append(f"{skipped} unreadable frames left out")
    missing = int((~has_pose).sum())
    if missing:
        result.notes.append(f"{missing} frames of the sequence have no pose in trajectory.txt (left out)")
    return mesh, result


def _poisson_mesh(run_dir: Path, cfg: MeshConfig) -> tuple[Mesh, MeshResult]:
    from surfelslam.io.ply import read_ply
    from surfelslam.mapping.mesh import poisson_mesh, require_open3d

    require_open3d()  # before reading anything
    map_path = run_dir / "map.ply"
    if not map_path.is_file():
        raise InputError(map_path, "missing: not the output folder of `surfelslam run`")
    v = read_ply(map_path)
    if not {"nx", "ny", "nz"} <= v.keys():
        raise InputError(map_path, "the map has no normals (nx ny nz): poisson needs oriented points")
    t0 = time.perf_counter()
    xyz = np.stack([v["x"], v["y"], v["z"]], 1)
    nrm = np.stack([v["nx"], v["ny"], v["nz"]], 1)
    rgb = np.stack([v["red"], v["green"], v["blue"]], 1) if "red" in v else np.full((len(xyz), 3), 200)
    mesh = poisson_mesh(xyz, nrm, rgb, cfg)
    return mesh, MeshResult(Path(), "poisson", mesh.n_vertices, mesh.n_faces, seconds=time.perf_counter() - t0)


def mesh_run(run_dir: Path, cfg: MeshConfig, out: Path | None = None, sequence: Path | None = None,
             progress: bool = False, run_depth_range: bool = False) -> MeshResult:
    """Write the mesh of the run in ``run_dir`` to ``out`` (default ``run_dir/mesh.ply``).

    ``sequence``: the run's sequence folder when it is not where ``metrics.json`` says. ``run_depth_range``: fuse
    from the run's ``[fusion] min_depth_m`` on instead of ``cfg``'s (up to ``cfg.max_depth_m``).
    """
    from surfelslam.io.ply import write_mesh_ply

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(run_dir, "not a folder (expected the --out folder of `surfelslam run`)")
    if cfg.method == "poisson":
        mesh, result = _poisson_mesh(run_dir, cfg)
    else:
        mesh, result = _tsdf_mesh(run_dir, cfg, sequence, progress, run_depth_range)
    if mesh.n_faces == 0:
        result.notes.append("the mesh is empty (no surface observed with enough weight)")
    result.path = run_dir / MESH_FILE if out is None else Path(out)
    write_mesh_ply(result.path, mesh.vertices, mesh.faces, mesh.normals, mesh.colours)
    return result


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
        if method not in METHODS:
            raise ConfigError(f"--method must be one of {', '.join(METHODS)}, got {method!r}")
        cfg = mesh_config(method=method, voxel_m=voxel, trunc_m=trunc, max_depth_m=max_depth, stride=stride,
                          min_weight=min_weight, min_component=min_component)
        res = mesh_run(run_dir, cfg, out, sequence, progress, run_depth_range=max_depth is None)
        for note in res.notes:
            console.print(f"note: {note}", highlight=False, markup=False, soft_wrap=True)
        detail = (f"{res.frames_fused} frames fused, voxel {cfg.voxel_m * 100:g} cm, TSDF {res.tsdf_mb:,.0f} MiB"
                  if res.method == "tsdf" else "Poisson on map.ply")
        console.print(f"wrote {res.path} ({res.vertices:,} vertices, {res.faces:,} triangles; {detail}; "
                      f"{res.seconds:.1f} s)", highlight=False, markup=False, soft_wrap=True)
