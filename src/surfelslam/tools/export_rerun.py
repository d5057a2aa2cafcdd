"""``surfelslam rerun RUN_DIR``: a finished run as a Rerun recording (``run.rrd``), with the sequence's images."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from surfelslam.errors import ConfigError, InputError
from surfelslam.io.run_folder import read_run_metrics, read_run_trajectory
from surfelslam.tools.common import DepthScaleOpt, IntrinsicsOpt, console, handle_errors, parse_intrinsics

#: Largest difference (s) between a trajectory stamp and a frame stamp for the frame's images to be logged.
FRAME_MATCH_S = 1e-4




def export_run(run_dir: Path, out: Path | None = None, seq_dir: Path | None = None, images_every: int = 10,
               images: bool = True, intrinsics: str | None = None, depth_scale: float | None = None,
               downsample: int | None = None, seq=None):
    """Write ``run_dir``'s outputs (and, when the sequence is found, its ground truth and images) as a Rerun
    recording. The sequence is ``seq`` (already open), else ``seq_dir``, else the one ``metrics.json`` names, opened
    with the run's dataset options (``metrics.json``) unless ``intrinsics`` / ``depth_scale`` / ``downsample`` are
    given. Returns ``(ExportSummary, notes)``: notes say what was left out and why."""
    from surfelslam.viz.rerun_export import build_scene, require_rerun, write_recording

    require_rerun()
    est, metrics, vertices, notes = _read_run(run_dir)
    seq, seq_dir = _run_sequence(metrics, notes, seq, seq_dir, intrinsics, depth_scale, downsample)
    gt = None if seq is None else seq.ground_truth
    scene = build_scene(est, vertices, metrics.get("loop_edges", []), gt)
    if scene.alignment == "origin":
        notes.append("the SE(3) alignment to the ground truth is degenerate (the estimate does not move): the first "
                     "poses are aligned instead")
    elif gt is not None and scene.ground_truth is None:
        notes.append("no ground truth shown: fewer than 3 poses have a ground-truth pose")
    frame_at = _frame_lookup(est, seq, seq_dir, notes) if seq is not None and images and len(seq) else None
    out = run_dir / "run.rrd" if out is None else out
    summary = write_recording(out, scene, None if seq is None else seq.intrinsics, frame_at, images_every)
    return summary, notes


def _read_run(run_dir: Path):
    """``(trajectory, metrics, map vertices or None, notes)`` of a run folder; InputError when it is not one."""
    from surfelslam.io.ply import read_ply

    if not run_dir.is_dir():
        raise InputError(run_dir, "not a folder (expected the --out folder of `surfelslam run`)")
    est = read_run_trajectory(run_dir)
    metrics = read_run_metrics(run_dir)
    notes: list[str] = []
    map_path = run_dir / "map.ply"
    vertices = read_ply(map_path) if map_path.is_file() else None
    if vertices is None:
        notes.append(f"no map: {map_path} is missing")
    return est, metrics, vertices, notes


def _run_sequence(metrics: dict, notes: list[str], seq, seq_dir: Path | None, intrinsics: str | None,
                  depth_scale: float | None, downsample: int | None):
    """``(sequence or None, its folder or None)``: ``seq`` as given, else ``seq_dir`` or the run's sequence opened
    with the run's dataset options (overridden by those given); a note says why there is none."""
    if seq is not None:
        return seq, seq.root
    if seq_dir is None and metrics.get("sequence"):
        seq_dir = Path(metrics["sequence"])
        if not seq_dir.is_dir():
            notes.append(f"no images or ground truth: the run's sequence {seq_dir} is not here (pass --seq)")
            seq_dir = None
    if seq_dir is None:
        if not metrics.get("sequence"):
            notes.append("no images or ground truth: metrics.json names no sequence (pass --seq)")
        return None, None
    from surfelslam.datasets import open_sequence
    from surfelslam.datasets.base import DatasetOptions

    run_opts = metrics.get("dataset_options") or {}
    fx_fy_cx_cy = parse_intrinsics(intrinsics) if intrinsics is not None else run_opts.get("intrinsics")
    opts = DatasetOptions(
        intrinsics=None if fx_fy_cx_cy is None else tuple(float(v) for v in fx_fy_cx_cy),
        depth_scale=depth_scale if depth_scale is not None else run_opts.get("depth_scale"),
        downsample=downsample if downsample is not None else int(metrics.get("downsample", 1)))
    seq = open_sequence(seq_dir, opts)
    res = metrics.get("resolution")
    if res is not None and [seq.intrinsics.width, seq.intrinsics.height] != list(res):
        raise ConfigError(f"{seq_dir} opens at {seq.intrinsics.width}x{seq.intrinsics.height}, the run was "
                          f"{res[0]}x{res[1]}: pass the run's --downsample")
    return seq, seq_dir


def _frame_lookup(est, seq, seq_dir: Path | None, notes: list[str]):
    """``frame_at(k)``: the sequence frame with the ``k``-th pose's timestamp, or None."""
    from surfelslam.datasets.tum import associate

    pose_k, frame_pos, _ = associate(est.timestamps, seq.timestamps, FRAME_MATCH_S)
    position_of = dict(zip(pose_k.tolist(), frame_pos.tolist(), strict=True))

    def frame_at(k: int):
        return seq[position_of[k]] if k in position_of else None

    if not position_of:
        notes.append(f"no images: no frame of {seq_dir} has the trajectory's timestamps")
    return frame_at


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
        print_export(*export_run(run_dir, out, seq, images_every, not no_images, intrinsics, depth_scale,
                                 downsample))

