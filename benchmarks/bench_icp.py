"""Dense tracking timings (ms, median after JIT warm-up): depth preprocessing and pyramid ICP.

Frames: 7-Scenes redkitchen pairs (i, i+5) from ../shared/data when present, otherwise synthetic
renders of the ``room`` scene (:mod:`surfelslam.synth`) 5 cm / 2 deg apart. Sizes 320x240 (downsample 2)
and 640x480; numba with 1 thread and with 2 threads. Rows:

* ``preprocess``: depth -> 4-level vertex/normal pyramid into pre-allocated buffers (default settings).
* ``icp 3-level``: :func:`icp` with the first three levels of the defaults (iterations 10/8/10).
* ``icp default``: :func:`icp` with the default :class:`ICPConfig` (4 levels, up to 10/8/10/40 iterations,
  finest-level source stride 2).
* ``icp default stride 1``: the same with every finest-level source pixel.
* ``shape guess (FPFH)``: :func:`surfelslam.tracking.geometric.geometric_guess` on the pyramid level at most
  320 px wide (what ``register --init features`` falls back on, and what dense relocalisation runs), on pairs
  90 frames apart when the frames are 7-Scenes (fewer repetitions: it takes a few hundred ms).

Usage: ``.venv/bin/python -m benchmarks.bench_icp [--quick]``; ``run(quick)`` returns the rows.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numba
import numpy as np

from benchmarks.common import REDKITCHEN, median_ms
from surfelslam.tracking.geometric import geometric_guess
from surfelslam.tracking.icp import ICPConfig, icp
from surfelslam.tracking.preprocess import PreprocessConfig, Preprocessor
from surfelslam.types import Intrinsics

FRAME_GAP = 5
SHAPE_GAP = 90  # frames between the two views of a shape-guess pair (7-Scenes)
SHAPE_REPS = 3


DepthPairs = list[tuple[np.ndarray, np.ndarray]]


def _depth_pairs(downsample: int, n: int, gap: int = FRAME_GAP) -> tuple[Intrinsics, DepthPairs, str]:
    if REDKITCHEN.is_dir():
        from surfelslam.datasets import open_sequence
        from surfelslam.datasets.base import DatasetOptions

        seq = open_sequence(REDKITCHEN, DatasetOptions(downsample=downsample))
        idx = np.linspace(0, len(seq) - 1 - gap, n).astype(int)
        return seq.intrinsics, [(seq[i].depth_m, seq[i + gap].depth_m) for i in idx], "7scenes"
    from surfelslam.geometry import se3
    from surfelslam.synth import make_scene, render
    from surfelslam.synth.trajectories import look_at

    intr = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
    if downsample > 1:
        intr = intr.scaled(downsample)
    scene = make_scene("room")
    pairs = []
    for k in range(n):
        T_w_t = look_at(np.array([2.5, 2.0, 1.4]), np.array([2.5 - 0.3 * k, 0.0, 0.8]))[0]
        step = se3.exp(np.array([0.0, np.radians(2.0), 0.0, 0.05, 0.0, 0.0]))
        pairs.append((render(scene, T_w_t @ step, intr).depth_m.copy(), render(scene, T_w_t, intr).depth_m.copy()))
    return intr, pairs, "synthetic"


def _shape_guess_ms(intr: Intrinsics, pre: Preprocessor, downsample: int, n_pairs: int, reps: int) -> float:
    """Median ms of :func:`geometric_guess` on ``n_pairs`` pairs (90 frames apart on 7-Scenes)."""
    from surfelslam.tracking.registration import guess_level

    _, pairs, _ = _depth_pairs(downsample, n_pairs, SHAPE_GAP)
    times = []
    for ds_m, dt_m in pairs:
        a, b = pre.process(ds_m), pre.process(dt_m)
        la, lb = guess_level(a), guess_level(b)
        geometric_guess(a[la].vertex, a[la].normal, b[lb].vertex, b[lb].normal)  # warm-up
        times.append(median_ms(lambda a=a, b=b, la=la, lb=lb: geometric_guess(
            a[la].vertex, a[la].normal, b[lb].vertex, b[lb].normal), reps))
    return float(np.median(times))


def run(quick: bool = False, n_pairs: int | None = None, reps: int | None = None) -> list[dict]:
    """Rows ``{stage, size, threads, ms, iterations, frames}`` (median ms over pairs x repetitions)."""
    n_pairs = n_pairs or (2 if quick else 4)
    reps = reps or (3 if quick else 10)
    rows: list[dict] = []
    old_threads = numba.get_num_threads()
    cfg4 = ICPConfig()
    cfg4s1 = replace(cfg4, finest_source_stride_px=1)
    d = ICPConfig()
    cfg3 = replace(d, levels=3, iterations=d.iterations[:3], dist_thresh_m=d.dist_thresh_m[:3],
                   angle_thresh_deg=d.angle_thresh_deg[:3])
    try:
        for downsample in (2, 1):
            intr, pairs, source = _depth_pairs(downsample, n_pairs)
            pre = Preprocessor(intr, PreprocessConfig())
            pyr_s, pyr_t = pre.new_pyramid(), pre.new_pyramid()
            size = f"{intr.width}x{intr.height}"
            for threads in sorted({1, min(2, numba.config.NUMBA_NUM_THREADS)}):
                numba.set_num_threads(threads)
                pre.process(pairs[0][0], out=pyr_s)  # warm-up (JIT compile / cache load)
                icp(pyr_s, pre.process(pairs[0][1], out=pyr_t), cfg=cfg4)
                t_pre, t3, t4, t41, it3, it4, it41 = [], [], [], [], [], [], []
                for ds_m, dt_m in pairs:
                    t_pre.append(median_ms(lambda ds_m=ds_m, pre=pre, o=pyr_s: pre.process(ds_m, out=o), reps))
                    pre.process(dt_m, out=pyr_t)
                    for cfg, times, its in ((cfg3, t3, it3), (cfg4, t4, it4), (cfg4s1, t41, it41)):
                        times.append(median_ms(lambda cfg=cfg, a=pyr_s, b=pyr_t: icp(a, b, cfg=cfg), reps))
                        its.append(icp(pyr_s, pyr_t, cfg=cfg).iterations)
                for stage, times, its in (("preprocess", t_pre, [0]), ("icp 3-level", t3, it3),
                                          ("icp default", t4, it4), ("icp default stride 1", t41, it41)):
                    rows.append({"stage": stage, "size": size, "threads": threads,
                                 "ms": float(np.median(times)), "iterations": float(np.mean(its)),
                                 "frames": source})
                rows.append({"stage": "shape guess (FPFH)", "size": size, "threads": threads,
                             "ms": _shape_guess_ms(intr, pre, downsample, n_pairs, min(reps, SHAPE_REPS)),
                             "iterations": 0.0, "frames": source})
    finally:
        numba.set_num_threads(old_threads)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer pairs and repetitions")
    rows = run(ap.parse_args().quick)
    print(f"frames: {rows[0]['frames']} pairs {FRAME_GAP} apart")
    print("| stage | size | threads | ms (median) | mean iterations |")
    print("|---|---|---|---|---|")
    for r in rows:
        its = f"{r['iterations']:.1f}" if r["stage"].startswith("icp") else ""
        print(f"| {r['stage']} | {r['size']} | {r['threads']} | {r['ms']:.2f} | {its} |")


if __name__ == "__main__":
    main()
