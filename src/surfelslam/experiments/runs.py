"""The run sections: fusion with ground-truth vs tracked poses (3), the dormant rule (4), every tracker (6)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from surfelslam.experiments.common import (
    REFERENCE_DORMANT_MAX_AGE_FRAMES,
    REFERENCE_DORMANT_MIN_HITS,
    SECTION_TITLES,
    ExperimentOptions,
    ate_of,
    fmt_value,
    run_tracker,
)

# the run figures each section links (the rest would be written for nothing)
_MAPS = ("map_top", "map_camera")
_CAMERA_VIEW = ("map_camera",)


def section_fusion(seq_runs, out_dir: Path, cfg, opts: ExperimentOptions, has_gt: bool):
    lines = [SECTION_TITLES[2], ""]
    intr = seq_runs.intrinsics
    lines.append(f"The first {len(seq_runs)} frames of the selection at {intr.width}x{intr.height}, fused once with "
                 "the ground-truth poses (`run --poses gt`) and once with the dense tracker's poses. Compression = "
                 "map points / (frames x pixels per frame).")
    lines.append("")
    runs: dict[str, dict | None] = {}
    if has_gt:
        runs["ground-truth poses"] = run_tracker(seq_runs, out_dir / "runs" / "gt_poses", cfg, "dense", "gt", opts,
                                                 _MAPS)
    runs["dense tracker poses"] = run_tracker(seq_runs, out_dir / "runs" / "dense", cfg, "dense", None, opts, _MAPS)
    lines += ["| poses | frames fused | map points | compression | ATE RMSE (cm) | maps |", "|---|---|---|---|---|---|"]
    for name, m in runs.items():
        d = "gt_poses" if name.startswith("ground") else "dense"
        ate = ate_of(m) if d == "dense" else None
        lines.append(f"| {name} | {m['frames_processed']} | {m['map_points']} | "
                     f"{100 * m['compression_ratio']:.2f}% | {fmt_value(None if ate is None else 100 * ate)} | "
                     f"[top](runs/{d}/map_top.png), [camera](runs/{d}/map_camera.png) |")
    if not has_gt:
        lines.append("| ground-truth poses | not available: this sequence has no ground truth | | | | |")
    lines.append("")
    for name in runs:
        d = "gt_poses" if name.startswith("ground") else "dense"
        lines += [f"Map with {name} (coloured by normal, confidence, first-seen frame and colour), top view and "
                  f"view from the first camera:", "", f"![{name} top](runs/{d}/map_top.png)", "",
                  f"![{name} camera](runs/{d}/map_camera.png)", ""]
    return lines, runs


def section_dormant(seq_runs, out_dir: Path, cfg, opts: ExperimentOptions, dense_metrics: dict, has_gt: bool):
    lines = [SECTION_TITLES[3], ""]
    f = cfg.fusion
    variants = []
    if f.remove_unstable:
        variants.append((f"on: age > {f.unstable_max_age_frames} frames, hits < {f.stable_min_hits} (configured)",
                         "dense", dense_metrics))
    cfg_off = replace(cfg, fusion=replace(f, remove_unstable=False))
    variants.append(("off", "dormant_off", run_tracker(seq_runs, out_dir / "runs" / "dormant_off", cfg_off, "dense",
                                                       None, opts, _CAMERA_VIEW)))
    cfg_reference = replace(cfg, fusion=replace(f, remove_unstable=True,
                                                unstable_max_age_frames=REFERENCE_DORMANT_MAX_AGE_FRAMES,
                                                stable_min_hits=REFERENCE_DORMANT_MIN_HITS))
    if not (f.remove_unstable and f.unstable_max_age_frames == REFERENCE_DORMANT_MAX_AGE_FRAMES
            and f.stable_min_hits == REFERENCE_DORMANT_MIN_HITS):
        variants.append((f"on: age > {REFERENCE_DORMANT_MAX_AGE_FRAMES} frames, hits < {REFERENCE_DORMANT_MIN_HITS} "
                         "(the reference assignment's values)", "dormant_reference",
                         run_tracker(seq_runs, out_dir / "runs" / "dormant_reference", cfg_reference, "dense", None,
                                     opts, _CAMERA_VIEW)))
    lines.append(f"Dense tracking over the same {len(seq_runs)} frames with `FusionConfig.remove_unstable` on and "
                 "off. The rule removes a surfel older than `unstable_max_age_frames` that was observed in fewer "
                 "than `stable_min_hits` frames (see `mapping/fusion.py`)."
                 + ("" if has_gt else " This sequence has no ground truth: ATE is n/a."))
    lines += ["", "| dormant-point rule | map points | ATE RMSE (cm) | tracking failures | render |",
              "|---|---|---|---|---|"]
    out = {}
    for name, d, m in variants:
        ate = ate_of(m)
        out[name] = {"map_points": m["map_points"], "ate_rmse_m": ate, "run": d}
        lines.append(f"| {name} | {m['map_points']} | {fmt_value(None if ate is None else 100 * ate)} | "
                     f"{m.get('tracking_failures', 0)} | [camera](runs/{d}/map_camera.png) |")
    lines.append("")
    for name, d, _ in variants:
        lines += [f"Dormant rule {name}:", "", f"![dormant {name}](runs/{d}/map_camera.png)", ""]
    return lines, out


# --------------------------------------------------------------------------------------------- section 6


def section_trajectories(seq_runs, out_dir: Path, cfg, opts: ExperimentOptions, dense_metrics: dict,
                         has_gt: bool):
    from surfelslam.eval.metrics import ate
    from surfelslam.io.trajectory import read_tum
    from surfelslam.slam import TRACKERS
    from surfelslam.viz.experiment_figures import plot_trajectories

    lines = [SECTION_TITLES[5], ""]
    if not has_gt:
        lines += ["Not available: this sequence has no ground truth. Trackers: " + ", ".join(TRACKERS) + ".", ""]
        return lines, {}
    lines.append(f"Every tracker (`surfelslam.slam.TRACKERS`) over the same {len(seq_runs)} frames, default "
                 "configuration; ATE after SE(3) alignment (no scale).")
    lines += ["", "| tracker | status | frames | tracking failures | ATE RMSE (cm) | FPS |",
              "|---|---|---|---|---|---|"]
    out: dict[str, dict] = {}
    estimates = {}
    gt_plot = None  # the ground truth over the run's frames (the associated poses)
    for name in TRACKERS:
        d = out_dir / "runs" / name
        try:
            m = dense_metrics if name == "dense" else run_tracker(seq_runs, d, cfg, name, None, opts)
        except Exception as exc:  # noqa: BLE001 - a failing tracker is reported, never dropped
            out[name] = {"status": f"failed: {exc}"}
            lines.append(f"| {name} | failed: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__} "
                         "| | | | |")
            continue
        a = ate_of(m)
        out[name] = {"status": "ran", "ate_rmse_m": a, "frames": m["frames_processed"],
                     "tracking_failures": m.get("tracking_failures", 0), "fps": m["fps"]}
        lines.append(f"| {name} | ran | {m['frames_processed']} | {m.get('tracking_failures', 0)} | "
                     f"{fmt_value(None if a is None else 100 * a)} | {m['fps']:.1f} |")
        try:
            ar = ate(read_tum(d / "trajectory.txt"), seq_runs.ground_truth)
            estimates[f"{name} (ATE {fmt_value(None if a is None else 100 * a)} cm)"] = ar.est_aligned
            gt_plot = ar.gt if gt_plot is None else gt_plot
        except Exception as exc:  # noqa: BLE001 - a trajectory that cannot be aligned is left out of the plot
            out[name]["plot_error"] = str(exc)
    lines.append("")
    if estimates:
        plot_trajectories(out_dir / "trajectories.png", estimates, gt_plot,
                          f"trajectories vs ground truth ({len(seq_runs)} frames)")
        lines += ["![trajectories](trajectories.png)", ""]
    return lines, out
