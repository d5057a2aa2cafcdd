"""The run loop: a sequence through a tracker into a run folder.

:func:`run_sequence` reads frames (decoded, and prepared by the tracker, in a background thread), tracks them,
streams the trajectory to ``trajectory.txt`` and writes ``config.toml``, ``metrics.json``, ``map.ply`` and the
figures. It is what ``surfelslam run``, the experiments and the benchmarks call; it prints nothing.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from surfelslam.config import dumps_toml, load_toml
from surfelslam.errors import ConfigError
from surfelslam.io.atomic import write_text_atomic
from surfelslam.io.jsonio import json_default
from surfelslam.io.prefetch import prefetch_frames
from surfelslam.io.trajectory import TumAppender
from surfelslam.kernels.threads import concurrent_launch_safe, parallel_enabled
from surfelslam.slam import SlamConfig, build_slam, poses_for_mapping


def load_config(path: Path | None) -> SlamConfig:
    return SlamConfig() if path is None else load_toml(SlamConfig, path)


def run_sequence(seq, out_dir: Path, cfg: SlamConfig, tracker: str, poses: str | None = None,
                 progress: bool = True, figures: bool = True) -> dict:
    """Run the pipeline on an opened sequence and write every output into ``out_dir``.

    Returns the metrics dict (also written as ``metrics.json``).
    """
    if len(seq) == 0:
        raise ConfigError(f"{seq.root}: the selection has no frames (check --start/--end/--stride)")
    out_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out_dir / "config.toml", dumps_toml(cfg))

    given = poses_for_mapping(seq, poses, cfg) if poses is not None else None
    slam = build_slam(seq.intrinsics, cfg, tracker if given is None else "given",
                      colour_registered=getattr(seq, "colour_registered", True),
                      colour_camera=getattr(seq, "colour_camera", None))
    t_warm = time.perf_counter()
    slam.warmup()
    warmup_s = time.perf_counter() - t_warm
    # the warm-up ran the kernels, so numba's threading layer is known: with parallel kernels on a layer that
    # cannot launch from two threads at once, frames are prepared in the main thread (same results, slower)
    prepare_in_reader = cfg.io.prepare_in_reader and concurrent_launch_safe()

    skipped: list[dict] = []
    stage_ms: dict[str, list[float]] = {"read": []}
    frame_ms: list[float] = []
    n_done = 0
    bar = tqdm(total=len(seq), unit="frame", disable=not progress, dynamic_ncols=True, leave=False)
    t_start = time.perf_counter()
    try:
        with TumAppender(out_dir / "trajectory.txt") as traj_out:
            prepare = slam.prepare if prepare_in_reader else None
            for item in prefetch_frames(seq, ahead=cfg.io.prefetch_frames, prepare=prepare):
                t0 = time.perf_counter()
                if item.error is not None:
                    skipped.append({"position": item.position, "reason": str(item.error)})
                    bar.update(1)
                    continue
                frame = item.frame
                if given is not None:
                    T_given = given.get(item.position)
                    if T_given is None:
                        slam.discard(item.prepared)  # its pyramid back to the pool
                        skipped.append({"position": item.position, "reason": "no pose within max_dt"})
                        bar.update(1)
                        continue
                    res = slam.process(frame, T_world_cam=T_given, prepared=item.prepared)
                else:
                    res = slam.process(frame, prepared=item.prepared)
                traj_out.append(frame.timestamp, res.T_world_cam)
                n_done += 1
                stage_ms["read"].append(item.read_ms)
                for k, v in res.timings_ms.items():
                    stage_ms.setdefault(k, []).append(v)
                frame_ms.append((time.perf_counter() - t0) * 1e3)
                bar.update(1)
                if n_done % 10 == 0:
                    el = time.perf_counter() - t_start
                    bar.set_postfix(fps=f"{n_done / max(el, 1e-9):.1f}", pts=f"{res.map_points:,}")
    finally:
        bar.close()
    wall_s = time.perf_counter() - t_start
    result = slam.finish()
    if result.trajectory_override is not None:
        # A back end (pose graph) corrected the poses: the written trajectory is the optimised one.
        result.trajectory_override.write_tum(out_dir / "trajectory.txt")

    metrics = {
        "sequence": str(seq.root),
        "layout": seq.layout,
        "tracker": tracker if given is None else f"given:{poses}",
        "frames": len(seq),
        "frames_processed": n_done,
        "frames_skipped": len(skipped),
        "skipped": skipped,
        "resolution": [seq.intrinsics.width, seq.intrinsics.height],
        "downsample": seq.options.downsample,
        "dataset_options": asdict(seq.options),
        "fps": n_done / wall_s if wall_s > 0 else 0.0,
        "wall_s": wall_s,
        "warmup_s": warmup_s,
        "parallel_kernels": parallel_enabled(),
        "prepare_in_reader": bool(prepare_in_reader and cfg.io.prefetch_frames > 0),
        "ms_per_frame": _stats(frame_ms),
        "stage_ms": {k: _stats(v) for k, v in stage_ms.items()},
        "map_points": result.map_points,
        "compression_ratio": result.map_points / max(n_done * seq.intrinsics.width * seq.intrinsics.height, 1),
        **result.metrics,
    }
    if result.loop_stamps:
        # keyframe timestamps (s) of each accepted loop edge, for viewers (`surfelslam rerun`)
        metrics["loop_edges"] = [[float(a), float(b)] for a, b in result.loop_stamps]
    if seq.ground_truth is not None and n_done >= 3:
        from surfelslam.eval.metrics import evaluate
        from surfelslam.types import Trajectory

        est = Trajectory.read_tum(out_dir / "trajectory.txt")
        try:
            metrics["eval"] = evaluate(est, seq.ground_truth)
        except Exception as exc:  # noqa: BLE001 - evaluation problems must not lose the run's outputs
            metrics["eval_error"] = str(exc)
    write_text_atomic(out_dir / "metrics.json", json.dumps(metrics, indent=2, default=json_default) + "\n")
    result.write_map(out_dir / "map.ply")
    if figures:
        _write_figures(out_dir, seq, result, metrics)
    return metrics


def _stats(v: list[float]) -> dict:
    if not v:
        return {"mean": 0.0, "median": 0.0, "p95": 0.0}
    a = np.asarray(v)
    return {"mean": float(a.mean()), "median": float(np.median(a)), "p95": float(np.percentile(a, 95))}


def _write_figures(out_dir: Path, seq, result, metrics: dict) -> None:
    from surfelslam.types import Trajectory
    from surfelslam.viz.map_figures import save_map_figures

    est = Trajectory.read_tum(out_dir / "trajectory.txt")
    if "eval" in metrics:
        from surfelslam.eval.metrics import ate
        from surfelslam.viz.trajectory_plots import plot_errors, plot_trajectory

        a = ate(est, seq.ground_truth)
        plot_trajectory(out_dir / "trajectory.png", a.est_aligned, a.gt,
                        title=f"{metrics['tracker']}: ATE RMSE {a.rmse_m * 100:.2f} cm", loops=result.loop_stamps)
        plot_errors(out_dir / "ate_errors.png", a)
    cloud = result.map_arrays()
    if cloud is not None and len(cloud["position"]):
        save_map_figures(out_dir, cloud["position"], cloud["normal"], cloud["colour"], cloud["confidence"],
                         cloud["first_seen"], est.T_world_cam[0], title=f"{metrics['tracker']} map")
