"""Accuracy (ATE, RPE) and FPS of ``surfelslam run`` on real and synthetic sequences; Open3D side by side.

* Real sequences: every folder of ``../shared/data`` that opens as a sequence; those with fewer than
  ``min_frames`` frames (the 4-5 frame samples) are listed as too short to track, not silently skipped.
* Synthetic sequences (room scene, Kinect-like noise, written to a temporary folder in TUM layout and read back
  through the dataset reader like real data): ``slow`` (orbit across the room), ``walking loop`` (one lap round
  the room), ``fast`` (the ``slow`` path at 3x speed: a third of the frames over the same path).
* Every run is ``python -m surfelslam run`` in a child process (background reading, warm-up excluded from FPS,
  ``metrics.json`` with the per-stage breakdown, ATE/RPE against the ground truth), timed from outside (the whole
  process: what a user waits) with the child's own CPU time and peak memory; the rest of the row is built from
  the ``metrics.json`` written by the run.
* Open3D side by side (:mod:`benchmarks.open3d_slam`): the first ``n`` frames of a sequence through Open3D's
  ``t.pipelines.slam`` and through ``surfelslam run`` on exactly the same frames; ratios ours / theirs.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from benchmarks.common import child_run, cli_tracker_args
from surfelslam.datasets import DatasetOptions, open_sequence
from surfelslam.errors import SurfelSlamError
from surfelslam.synth.writer import generate_sequence

SYNTH_SCENE = "room"
SYNTH_NOISE = "kinect"
FAST_FACTOR = 3  # "fast" = the "slow" path at this many times the speed (TrajectoryConfig.fast_factor)


def shared_sequences(root: Path, min_frames: int) -> tuple[list[tuple[str, Path]], list[dict]]:
    """``([(name, path)] long enough to track, [notes on the others])`` for the folders of ``root``."""
    long, notes = [], []
    if not root.is_dir():
        return long, [{"sequence": str(root), "frames": 0, "reason": "folder absent: no real data"}]
    for path in sorted(p for p in root.iterdir() if p.is_dir()):
        try:
            seq = open_sequence(path, DatasetOptions())
        except SurfelSlamError as exc:
            notes.append({"sequence": path.name, "frames": 0, "reason": f"not a sequence ({type(exc).__name__})"})
            continue
        if seq.ground_truth is None:
            notes.append({"sequence": path.name, "frames": len(seq), "reason": "no ground truth"})
        elif len(seq) < min_frames:
            notes.append({"sequence": path.name, "frames": len(seq),
                          "reason": f"too short to track (fewer than {min_frames} frames)"})
        else:
            long.append((path.name, path))
    return long, notes


def synthetic_sequences(tmp: Path, width: int, n_slow: int, n_loop: int, seed: int = 0) -> list[tuple[str, Path]]:
    """Generate ``slow`` (n_slow frames), ``walking loop`` (one lap of n_loop) and ``fast`` (n_slow / 3 frames)."""
    height = width * 3 // 4
    out = []
    for name, style, n in (("synthetic slow", "slow", n_slow), ("synthetic walking loop", "loop", n_loop),
                           ("synthetic fast (slow x3)", "fast", max(n_slow // FAST_FACTOR, 1))):
        path = generate_sequence(tmp / style, scene=SYNTH_SCENE, style=style, n_frames=n, noise=SYNTH_NOISE,
                                 seed=seed, width=width, height=height)
        out.append((name, path))
    return out


def run_tracker(name: str, path: Path, tracker: str, downsample: int, out_dir: Path, end: int | None = None) -> dict:
    """``python -m surfelslam run`` on ``path`` (frames ``[0, end)``) in a child process, as a user runs it (no
    figures): the row from its ``metrics.json``, with the whole process's wall time timed from outside
    (``wall_s``), its CPU time (``cpu_s``, ``cpu_ms_per_frame``: the child's rusage, every thread, start-up and
    warm-up included) and peak memory (``peak_mb``), :func:`benchmarks.common.child_run`."""
    args = ["run", str(path), "--out", str(out_dir), "--downsample", str(downsample), "--no-figures",
            "--no-progress", "--overwrite", *cli_tracker_args(tracker)]
    child = child_run(args + ([] if end is None else ["--end", str(end)]))
    if child["returncode"] != 0:
        raise RuntimeError(f"surfelslam run --tracker {tracker} on {name} exited {child['returncode']}: "
                           f"{child['stderr']}")
    m = json.loads((out_dir / "metrics.json").read_text())
    row = row_from_metrics(name, tracker, m, child["cpu_s"])
    row.update({"wall_s": round(child["wall_s"], 2), "peak_mb": child["peak_mb"],
                "cpu_ms_per_frame": round(1e3 * child["cpu_s"] / max(row["frames"], 1), 2)})
    return row


def row_from_metrics(name: str, tracker: str, m: dict, cpu_s: float | None = None) -> dict:
    """One accuracy row (units in the keys) from a run's ``metrics.json``."""
    e = m.get("eval") or {}
    row = {
        "sequence": name, "resolution": "x".join(str(v) for v in m["resolution"]), "frames": m["frames_processed"],
        "tracker": tracker,
        "ate_rmse_cm": _r(e.get("ate_rmse_m"), 100), "ate_max_cm": _r(e.get("ate_max_m"), 100),
        "rpe_trans_mm_per_frame": _r(e.get("rpe_trans_rmse_m_per_frame"), 1000),
        "rpe_rot_deg_per_frame": _r(e.get("rpe_rot_rmse_deg_per_frame"), 1, 3),
        "failures": m.get("tracking_failures", 0), "fps": round(m["fps"], 2),
        "ms_per_frame": round(m["ms_per_frame"]["mean"], 2),
        "stage_ms": {k: round(v["mean"], 2) for k, v in m["stage_ms"].items()},
        "warmup_s": round(m["warmup_s"], 2),
        "startup_s": _r(m.get("startup_s"), 1), "shutdown_s": _r(m.get("shutdown_s"), 1),
    }
    if cpu_s is not None:
        row["cpu_s"] = round(cpu_s, 1)
    if "eval_error" in m:
        row["eval_error"] = m["eval_error"]
    return row


def _r(v, scale: float, nd: int = 2):
    return None if v is None else round(v * scale, nd)


def open3d_side_by_side(name: str, path: Path, downsample: int, n_frames: int, out_dir: Path,
                        ours: dict | None = None) -> dict:
    """Open3D and ``surfelslam run`` (dense) on the first ``n_frames`` frames; ratios ours / theirs.

    ``ours``: an accuracy row of a dense run on exactly these frames, reused instead of running again.
    """
    from benchmarks import open3d_slam
    from surfelslam.eval.metrics import evaluate

    seq = open_sequence(path, DatasetOptions(downsample=downsample, end=n_frames))
    if ours is None:
        ours = run_tracker(name, path, "dense", downsample, out_dir, end=n_frames)
    c0 = time.process_time()
    o3 = open3d_slam.run_open3d_slam(seq)
    o3_cpu = time.process_time() - c0
    theirs_ate = evaluate(o3["trajectory"], seq.ground_truth)["ate_rmse_m"] * 100
    row = {
        "sequence": name, "resolution": f"{seq.intrinsics.width}x{seq.intrinsics.height}", "frames": len(seq),
        "ours_fps": ours["fps"], "open3d_fps": round(o3["fps"], 2),
        "fps_ratio": round(ours["fps"] / max(o3["fps"], 1e-9), 2),
        "ours_ate_cm": ours["ate_rmse_cm"], "open3d_ate_cm": round(theirs_ate, 2),
        "ate_ratio": None if ours["ate_rmse_cm"] is None else round(ours["ate_rmse_cm"] / max(theirs_ate, 1e-9), 2),
        "ours_failures": ours["failures"], "open3d_failures": o3["failed"],
        "ours_cpu_s": ours.get("cpu_s"), "open3d_cpu_s": round(o3_cpu, 1),
    }
    return row


def prefix_row(name: str, path: Path, downsample: int, run_dir: Path, n_frames: int) -> dict:
    """Accuracy of the first ``n_frames`` poses of a dense run (the dense tracker is causal and deterministic:
    these are the poses a run on those frames alone gives), to compare with trackers run on fewer frames.

    FPS and timings are not measured for the prefix (``None``).
    """
    from surfelslam.eval.metrics import evaluate
    from surfelslam.io.trajectory import read_tum

    seq = open_sequence(path, DatasetOptions(downsample=downsample, end=n_frames))
    est = read_tum(run_dir / "trajectory.txt").subset(slice(0, n_frames))
    e = evaluate(est, seq.ground_truth)
    m = json.loads((run_dir / "metrics.json").read_text())
    return {
        "sequence": name, "resolution": f"{seq.intrinsics.width}x{seq.intrinsics.height}", "frames": len(est),
        "tracker": "dense", "ate_rmse_cm": _r(e["ate_rmse_m"], 100), "ate_max_cm": _r(e["ate_max_m"], 100),
        "rpe_trans_mm_per_frame": _r(e["rpe_trans_rmse_m_per_frame"], 1000),
        "rpe_rot_deg_per_frame": _r(e["rpe_rot_rmse_deg_per_frame"], 1, 3),
        "failures": None, "fps": None, "from": f"first {len(est)} poses of the {m['frames_processed']}-frame run",
    }
