"""The driver: every section in turn, written up as ``report.md`` and ``results.json``."""

from __future__ import annotations

import json
import time
from pathlib import Path

from surfelslam.experiments.common import ExperimentOptions, ate_of, choose_pairs
from surfelslam.experiments.pairs import section_features, section_icp_pairs, section_solvers
from surfelslam.experiments.runs import section_dormant, section_fusion, section_trajectories
from surfelslam.io.atomic import write_text_atomic
from surfelslam.io.jsonio import json_default


def run_experiments(seq, seq_runs, out_dir: Path, cfg, opts: ExperimentOptions) -> dict:
    """Run every section; write ``out_dir/report.md``, ``out_dir/results.json`` and the PNGs.

    Args:
        seq: the whole selection (frame pairs are taken from it).
        seq_runs: its first ``opts.frames`` frames (fusion, dormant rule and trajectory sections).

    Returns:
        the results dict (also written as ``results.json``).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    has_gt = seq.ground_truth is not None and bool(seq.gt_poses()[1].any())
    t_all = time.perf_counter()
    times: dict[str, float] = {}
    results: dict = {"sequence": str(seq.root), "frames_in_selection": len(seq), "frames_run": len(seq_runs),
                     "resolution": [seq.intrinsics.width, seq.intrinsics.height],
                     "downsample": seq.options.downsample, "has_ground_truth": has_gt}
    pairs, scaled = choose_pairs(len(seq), opts.pair_start, opts.pair_gaps)
    results["pairs"] = [list(p) for p in pairs]
    body: list[str] = []

    def timed(key, fn, *a):
        t0 = time.perf_counter()
        r = fn(*a)
        times[key] = time.perf_counter() - t0
        return r

    lines, results["icp_pairs"], pyramids = timed("icp_pairs", section_icp_pairs, seq, out_dir, pairs, scaled, opts)
    body += lines
    lines, results["solvers"] = timed("solvers", section_solvers, pyramids, pairs)
    body += lines
    lines, runs = timed("fusion", section_fusion, seq_runs, out_dir, cfg, opts, has_gt)
    body += lines
    results["fusion"] = {k: {"frames": m["frames_processed"], "map_points": m["map_points"],
                             "compression_ratio": m["compression_ratio"], "ate_rmse_m": ate_of(m)}
                         for k, m in runs.items()}
    dense_metrics = runs["dense tracker poses"]
    lines, results["dormant"] = timed("dormant", section_dormant, seq_runs, out_dir, cfg, opts, dense_metrics, has_gt)
    body += lines
    lines, results["features"] = timed("features", section_features, seq, out_dir, pairs, cfg)
    body += lines
    lines, results["trackers"] = timed("trackers", section_trajectories, seq_runs, out_dir, cfg, opts,
                                       dense_metrics, has_gt)
    body += lines
    total = time.perf_counter() - t_all
    results["seconds"] = {**times, "total": total}

    intr = seq.intrinsics
    head = ["# surfelslam experiments", "",
            f"Sequence `{seq.root}` ({seq.layout}), {len(seq)} frames selected at {intr.width}x{intr.height} "
            f"(downsample {seq.options.downsample}); sections 3, 4 and 6 use the first {len(seq_runs)} frames. "
            + ("Ground truth: yes." if has_gt else "Ground truth: none (sections needing it say so)."),
            f"Run time {total:.0f} s ("
            + ", ".join(f"{k.replace('_', ' ')} {v:.0f} s" for k, v in times.items()) + ").", ""]
    write_text_atomic(out_dir / "report.md", "\n".join(head + body).rstrip() + "\n")
    write_text_atomic(out_dir / "results.json", json.dumps(results, indent=2, default=json_default) + "\n")
    return results
