"""Per-frame stage timings that a dense run does not measure by itself: frame reading and the ORB front end.

* ``read``: ``seq[i]`` of the dataset reader, synchronously (in ``surfelslam run`` it runs in a background
  thread): decode of the colour and depth files, depth scaling and validation, downsampling. With
  ``downsample`` 2 the reader decodes the full-size files and keeps every second pixel, so reading 320x240
  costs about what reading 640x480 costs.
* ``orb``: :func:`extract` per frame, and matching + PnP-RANSAC (``estimate_motion``) per pair of frames 5 apart,
  with the ORB settings the ``orb``/``hybrid`` trackers use (``SlamConfig().sparse.features``).

The other stages (preprocess, render, ICP, fuse) come from the ``metrics.json`` of a real dense run
(:mod:`benchmarks.bench_accuracy`). Usage: ``.venv/bin/python -m benchmarks.bench_stages SEQUENCE [--downsample 2]``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchmarks.bench_accuracy import run_tracker
from benchmarks.common import median_ms
from surfelslam.datasets import DatasetOptions, open_sequence
from surfelslam.slam import SlamConfig
from surfelslam.tracking.features import estimate_motion, extract

PAIR_GAP = 5  # frames between the two frames of an ORB pair
STAGES = ("read", "preprocess", "render", "icp", "fuse")  # the stage columns of the page (metrics.json names)


def read_ms(path: Path, downsample: int, n_frames: int) -> dict:
    """Mean and median ms of ``seq[i]`` over ``n_frames`` frames spread over the sequence (after one warm read)."""
    seq = open_sequence(path, DatasetOptions(downsample=downsample))
    idx = np.unique(np.linspace(0, len(seq) - 1, n_frames).astype(int))
    seq[int(idx[0])]  # file system cache, decoder libraries
    times = []
    for i in idx:
        t0 = time.perf_counter()
        seq[int(i)]
        times.append((time.perf_counter() - t0) * 1e3)
    return {"read_ms": round(float(np.mean(times)), 2), "read_median_ms": round(float(np.median(times)), 2),
            "read_frames": len(times), "resolution": f"{seq.intrinsics.width}x{seq.intrinsics.height}"}


def orb_ms(path: Path, downsample: int, n_pairs: int, reps: int = 3) -> dict:
    """ORB extract ms per frame and match + PnP ms per pair (medians), tracker settings."""
    seq = open_sequence(path, DatasetOptions(downsample=downsample))
    intr = seq.intrinsics
    cfg = SlamConfig().sparse.features
    gap = min(PAIR_GAP, len(seq) - 1)
    idx = np.unique(np.linspace(0, len(seq) - 1 - gap, n_pairs).astype(int))
    ext, mp, inl = [], [], []
    for i in idx:
        a, b = seq[int(i)], seq[int(i) + gap]
        fa = extract(a.rgb, a.depth_m, intr, cfg)
        fb = extract(b.rgb, b.depth_m, intr, cfg)
        ext.append(median_ms(lambda a=a: extract(a.rgb, a.depth_m, intr, cfg), reps))
        mp.append(median_ms(lambda fa=fa, fb=fb: estimate_motion(fa, fb, intr, cfg), reps))  # matches, then PnP
        inl.append(estimate_motion(fa, fb, intr, cfg).n_inliers)
    return {"orb_extract_ms": round(float(np.median(ext)), 2), "orb_match_pnp_ms": round(float(np.median(mp)), 2),
            "orb_features": cfg.n_features, "orb_pairs": len(idx), "orb_median_inliers": float(np.median(inl))}


def stage_source(fallback_frames: int, real: list[tuple[str, Path]], tmp: Path) -> tuple[str, Path, bool]:
    """The sequence the stage timings run on: the longest real one, else a generated 640x480 one."""
    if real:
        name, path = max(real, key=lambda r: len(open_sequence(r[1], DatasetOptions())))
        return name, path, True
    from surfelslam.synth.writer import generate_sequence

    path = generate_sequence(tmp / "stages", scene="room", style="slow", n_frames=fallback_frames,
                             noise="kinect", width=640, height=480)
    return "synthetic slow 640x480", path, False


def stages(stage_runs, read_frames: int, orb_pairs: int, name: str, path: Path, tmp: Path
           ) -> tuple[list[dict], list[dict]]:
    """Stage rows per ``(downsample, frames)`` of ``stage_runs``, and the accuracy rows of the dense runs they came
    from (``read_frames`` frames read, ``orb_pairs`` pairs matched per resolution)."""
    rows, acc = [], []
    for ds, n in stage_runs:
        read = read_ms(path, ds, read_frames)
        orb = orb_ms(path, ds, orb_pairs)
        run = run_tracker(name, path, "dense", ds, tmp / f"stages_{ds}", end=n)
        acc.append(run)
        sm = run["stage_ms"]
        rows.append({
            "resolution": run["resolution"], "sequence": name, "frames": run["frames"],
            "read_ms": read["read_ms"], **{f"{k}_ms": sm.get(k) for k in STAGES[1:]},
            "loop_ms": run["ms_per_frame"], "fps": run["fps"],
            "orb_extract_ms": orb["orb_extract_ms"], "orb_match_pnp_ms": orb["orb_match_pnp_ms"],
            "read_in_run_ms": sm.get("read"), "read_frames": read["read_frames"], "orb_pairs": orb["orb_pairs"],
            "orb_features": orb["orb_features"], "metrics_json_stages": sorted(sm),
        })
    return rows, acc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--downsample", type=int, default=2)
    ap.add_argument("--frames", type=int, default=40)
    a = ap.parse_args()
    print({**read_ms(a.sequence, a.downsample, a.frames), **orb_ms(a.sequence, a.downsample, 5)})


if __name__ == "__main__":
    main()
