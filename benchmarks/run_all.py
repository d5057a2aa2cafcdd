"""`make bench`: stage timings, whole-pipeline throughput and accuracy, side by side with Open3D when installed.

Writes benchmarks/results/latest.json and latest.md (a markdown table). Usage: python benchmarks/run_all.py [--quick]
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import bench_fusion  # noqa: E402
import bench_icp  # noqa: E402
import bench_orb  # noqa: E402
import bench_pipeline  # noqa: E402
import open3d_slam  # noqa: E402
from surfelslam.datasets import DatasetOptions, open_sequence  # noqa: E402
from surfelslam.pipeline import SlamConfig  # noqa: E402
from surfelslam.synth.writer import generate_sequence  # noqa: E402
from surfelslam.tools.run import run_sequence  # noqa: E402

SHARED = HERE.parent.parent / "shared" / "data"


def pipeline_rows(quick: bool) -> list[dict]:
    """Whole dense loop (read, preprocess, render, ICP, fuse) on synthetic and shared sequences."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        n = 60 if quick else 150
        for style in ("slow", "handheld", "fast", "loop"):
            seq_dir = Path(tmp) / style
            generate_sequence(seq_dir, scene="room", style=style, n_frames=n, noise="kinect", seed=0)
            for ds in (2, 1):
                rows.append(_run(f"synthetic room/{style}", seq_dir, ds, Path(tmp) / f"{style}_{ds}"))
        seven = SHARED / "7scenes_redkitchen_0000_0499"
        if seven.is_dir():
            for ds in (2, 1):
                rows.append(_run("7-Scenes redkitchen 0-199", seven, ds, Path(tmp) / f"7s_{ds}", end=200))
    return rows


def _run(name: str, path: Path, downsample: int, out: Path, end: int | None = None) -> dict:
    seq = open_sequence(path, DatasetOptions(downsample=downsample, end=end))
    m = run_sequence(seq, out, SlamConfig(), "dense", progress=False, figures=False)
    row = {
        "sequence": name, "resolution": f"{seq.intrinsics.width}x{seq.intrinsics.height}", "frames": len(seq),
        "fps": round(m["fps"], 1), "ate_cm": round(m["eval"]["ate_rmse_m"] * 100, 2) if "eval" in m else None,
        "failures": m.get("tracking_failures", 0), "warmup_s": round(m["warmup_s"], 1),
        **{f"{k}_ms": round(v["mean"], 1) for k, v in m["stage_ms"].items()},
    }
    if open3d_slam.available() and downsample == 2:  # Open3D runs ~1-3 FPS: side by side at 320x240 only
        o3 = open3d_slam.run_open3d_slam(seq)
        from surfelslam.eval.metrics import evaluate

        row["open3d_fps"] = round(o3["fps"], 2)
        row["open3d_ate_cm"] = round(evaluate(o3["trajectory"], seq.ground_truth)["ate_rmse_m"] * 100, 2)
        row["fps_ratio"] = round(row["fps"] / max(o3["fps"], 1e-9), 1)
    return row


def markdown(title: str, rows: list[dict]) -> str:
    if not rows:
        return f"### {title}\n\n(no rows)\n"
    keys = list(dict.fromkeys(k for r in rows for k in r))
    lines = [f"### {title}", "", "| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(str(r.get(k, "")) for k in keys) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    t0 = time.time()
    sections = {
        "ICP and preprocessing (ms)": bench_icp.run(args.quick),
        "Fusion and rendering (ms)": bench_fusion.run(args.quick),
        "ORB front end (ms)": bench_orb.run(args.quick),
        "Per-frame cost over a long run (flat-cost check)": bench_pipeline.run(args.quick),
        "Whole dense pipeline": pipeline_rows(args.quick),
    }
    meta = {"date": datetime.date.today().isoformat(), "machine": f"{platform.machine()}, {platform.processor()}",
            "python": platform.python_version(), "seconds": round(time.time() - t0, 1),
            "open3d": open3d_slam.available()}
    md = f"Benchmarks of {meta['date']} on {meta['machine']} ({meta['seconds']} s)\n\n"
    md += "\n".join(markdown(k, v) for k, v in sections.items())
    out = HERE / "results"
    out.mkdir(exist_ok=True)
    (out / "latest.json").write_text(json.dumps({"meta": meta, **sections}, indent=2) + "\n")
    (out / "latest.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
