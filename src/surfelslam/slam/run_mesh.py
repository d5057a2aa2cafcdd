"""The triangle mesh of a finished run: :func:`mesh_run` is ``surfelslam mesh`` without its printing.

``tsdf`` (default) reads the run's sequence again (:func:`~surfelslam.slam.run_reader.open_run`: the folder
``metrics.json`` names, with the run's dataset options from ``config.toml``), fuses its depth frames at the poses
of ``trajectory.txt`` into a TSDF and extracts the surface by marching cubes (:mod:`surfelslam.mapping.mesh`).
``poisson`` reconstructs from the surfels of ``map.ply`` with Open3D (optional).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np

from surfelslam.errors import FrameError, InputError
from surfelslam.mapping.mesh import Mesh, MeshConfig
from surfelslam.slam.run_reader import NOT_A_RUN, open_run

#: ``progress(positions)``: iterates over the frame positions to fuse, showing progress (e.g. a tqdm bar).
ProgressWrap = Callable[[Sequence[int]], Iterable[int]]

MESH_FILE = "mesh.ply"
#: Largest difference (s) between a trajectory stamp and a frame stamp for the frame to be fused at that pose.
FRAME_MATCH_S = 1e-4

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


def _tsdf_mesh(run_dir: Path, cfg: MeshConfig, sequence: Path | None, progress: ProgressWrap | None,
               run_depth_range: bool) -> tuple[Mesh, MeshResult]:
    from surfelslam.mapping.mesh import TsdfVolume
    from surfelslam.slam.mapper import frame_colour_at_depth

    run = open_run(run_dir)
    est = run.trajectory()
    run_cfg = run.config
    if run_depth_range:  # the near limit the run fused its map with (farther than its far limit: noise-weighted)
        cfg = dataclasses.replace(cfg, min_depth_m=run_cfg.fusion.min_depth_m)
    seq = run.open_sequence(sequence)
    T, has_pose = est.lookup(seq.timestamps, FRAME_MATCH_S)
    positions = np.flatnonzero(has_pose)[:: cfg.stride]
    if len(positions) == 0:
        raise InputError(run_dir / "trajectory.txt",
                         f"no pose has the timestamp of a frame of {seq.root}: is it the run's sequence?")
    colour_cam = getattr(seq, "colour_camera", None)
    vol = TsdfVolume.from_config(cfg)
    skipped = 0
    t0 = time.perf_counter()
    for i in positions if progress is None else progress(positions):
        try:
            frame = seq[int(i)]
        except FrameError:
            skipped += 1
            continue
        rgb = frame_colour_at_depth(frame, seq.intrinsics, colour_cam, run_cfg.colour_registration)
        vol.integrate(frame.depth_m, rgb, seq.intrinsics, T[i])
    tsdf_mb = vol.memory_mb(vol.n_blocks)
    mesh = vol.extract_mesh(cfg.min_weight, release=True)
    result = MeshResult(Path(), "tsdf", mesh.n_vertices, mesh.n_faces, vol.frames, skipped, tsdf_mb,
                        time.perf_counter() - t0)
    if skipped:
        result.notes.append(f"{skipped} unreadable frames left out")
    missing = int((~has_pose).sum())
    if missing:
        result.notes.append(f"{missing} frames of the sequence have no pose in trajectory.txt (left out)")
    return mesh, result


def _poisson_mesh(run_dir: Path, cfg: MeshConfig) -> tuple[Mesh, MeshResult]:
    from surfelslam.mapping.mesh import poisson_mesh, require_open3d

    require_open3d()  # before reading anything
    run = open_run(run_dir)
    map_path, v = run.map_path, run.map_vertices()
    if v is None:
        raise InputError(map_path, "missing: not the output folder of `surfelslam run`")
    if not {"nx", "ny", "nz"} <= v.keys():
        raise InputError(map_path, "the map has no normals (nx ny nz): poisson needs oriented points")
    t0 = time.perf_counter()
    xyz = np.stack([v["x"], v["y"], v["z"]], 1)
    nrm = np.stack([v["nx"], v["ny"], v["nz"]], 1)
    rgb = np.stack([v["red"], v["green"], v["blue"]], 1) if "red" in v else np.full((len(xyz), 3), 200)
    mesh = poisson_mesh(xyz, nrm, rgb, cfg)
    return mesh, MeshResult(Path(), "poisson", mesh.n_vertices, mesh.n_faces, seconds=time.perf_counter() - t0)


def mesh_run(run_dir: Path, cfg: MeshConfig, out: Path | None = None, sequence: Path | None = None,
             progress: ProgressWrap | None = None, run_depth_range: bool = False) -> MeshResult:
    """Write the mesh of the run in ``run_dir`` to ``out`` (default ``run_dir/mesh.ply``).

    ``sequence``: the run's sequence folder when it is not where ``metrics.json`` says. ``run_depth_range``: fuse
    from the run's ``[fusion] min_depth_m`` on instead of ``cfg``'s (up to ``cfg.max_depth_m``).
    """
    from surfelslam.io.ply import write_mesh_ply

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(run_dir, NOT_A_RUN)
    if cfg.method == "poisson":
        mesh, result = _poisson_mesh(run_dir, cfg)
    else:
        mesh, result = _tsdf_mesh(run_dir, cfg, sequence, progress, run_depth_range)
    if mesh.n_faces == 0:
        result.notes.append("the mesh is empty (no surface observed with enough weight)")
    result.path = run_dir / MESH_FILE if out is None else Path(out)
    write_mesh_ply(result.path, mesh.vertices, mesh.faces, mesh.normals, mesh.colours)
    return result
