"""A finished run folder as a Rerun recording: :func:`export_run` is ``surfelslam rerun`` without its printing.

The run is read with :func:`~surfelslam.slam.run_reader.open_run`; its sequence (for the images and the ground
truth) is reopened with the run's dataset options when it is found, else the recording has the poses and the map
alone and a note says why.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from surfelslam.errors import InputError
from surfelslam.slam.run_reader import FinishedRun, open_run
from surfelslam.viz.rerun_export import ExportSummary, build_scene, require_rerun, write_recording

#: Largest difference (s) between a trajectory stamp and a frame stamp for the frame's images to be logged.
FRAME_MATCH_S = 1e-4


def export_run(run_dir: Path, out: Path | None = None, seq_dir: Path | None = None, images_every: int = 10,
               images: bool = True, intrinsics: Sequence[float] | None = None, depth_scale: float | None = None,
               downsample: int | None = None, seq=None) -> tuple[ExportSummary, list[str]]:
    """Write ``run_dir``'s outputs (and, when the sequence is found, its ground truth and images) as a Rerun
    recording. The sequence is ``seq`` (already open), else ``seq_dir``, else the one ``metrics.json`` names, opened
    with the run's dataset options (:func:`~surfelslam.slam.run_reader.open_run`) unless ``intrinsics`` /
    ``depth_scale`` / ``downsample`` are given. Returns ``(ExportSummary, notes)``: notes say what was left out
    and why."""
    require_rerun()
    run = open_run(run_dir)
    est, metrics, vertices, notes = run.trajectory(), run.metrics, run.map_vertices(), []
    if vertices is None:
        notes.append(f"no map: {run.map_path} is missing")
    seq, seq_dir = _run_sequence(run, notes, seq, seq_dir, intrinsics, depth_scale, downsample)
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


def _run_sequence(run: FinishedRun, notes: list[str], seq, seq_dir: Path | None, intrinsics: Sequence[float] | None,
                  depth_scale: float | None, downsample: int | None):
    """``(sequence or None, its folder or None)``: ``seq`` as given, else ``seq_dir`` or the run's sequence opened
    with the run's dataset options (overridden by those given); a note says why there is none."""
    if seq is not None:
        return seq, seq.root
    try:
        path = run.sequence_path(seq_dir, "--seq")
    except InputError as exc:
        notes.append(f"no images or ground truth: {exc}")
        return None, None
    fx_fy_cx_cy = None if intrinsics is None else tuple(float(v) for v in intrinsics)
    seq = run.open_sequence(path, intrinsics=fx_fy_cx_cy, depth_scale=depth_scale, downsample=downsample)
    return seq, path


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
