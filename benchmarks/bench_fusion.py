"""Render + fuse timings (ms per call, after warm-up) at 320x240 and 640x480.

Scene: an analytic corridor (a long box, 4 m x 3 m x 80 m) ray-cast from a camera that walks along it
while panning, with 2 mm depth noise; normals from central differences. The map grows frame after frame
(new wall keeps coming into view) while the view stays alike, which also shows whether the per-frame cost
follows what is in view (culling) or the map size: the table gives the first and last windows of frames.
Vertex/normal maps are prepared before timing; only ``render`` (at the previous pose) and ``fuse`` are timed.

Usage: ``.venv/bin/python -m benchmarks.bench_fusion [--quick]``; ``run(quick)`` returns the rows.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from benchmarks.common import print_rows
from surfelslam.geometry.camera import backproject
from surfelslam.geometry.se3 import make_T, so3_exp
from surfelslam.mapping import FusionConfig, SurfelMap, fuse, render
from surfelslam.types import Intrinsics

LO = np.array([-2.0, -1.5, -1.0])
HI = np.array([2.0, 1.5, 80.0])


def _frame(T: np.ndarray, intr: Intrinsics, rng: np.random.Generator):
    H, W = intr.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    d_cam = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], -1)
    R, c = T[:3, :3], T[:3, 3]
    d_w = d_cam @ R.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t_axis = np.where(d_w > 0, (HI - c) / d_w, np.where(d_w < 0, (LO - c) / d_w, np.inf))
    t = t_axis.min(-1)
    p = c + t[..., None] * d_w
    depth = (t + rng.normal(0, 0.002, t.shape)).astype(np.float32)
    vertex = backproject(depth, intr)
    dx = np.zeros_like(vertex)
    dy = np.zeros_like(vertex)
    dx[:, 1:-1] = vertex[:, 2:] - vertex[:, :-2]
    dy[1:-1] = vertex[2:] - vertex[:-2]
    n = np.cross(dx, dy)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(norm > 0, n / np.where(norm > 0, norm, 1.0), 0.0)
    n = np.where((n * vertex).sum(-1, keepdims=True) > 0, -n, n).astype(np.float32)
    tile = (np.floor(p * 3).sum(-1) % 2).astype(np.uint8)
    rgb = np.stack([tile * 180 + 40, tile * 60 + 90, np.full_like(tile, 120)], -1).astype(np.uint8)
    return vertex, n, rgb


def _pose(i: int) -> np.ndarray:
    return make_T(so3_exp([0.05 * math.sin(i / 17), 0.5 * math.sin(i / 40), 0.0]),
                  [0.6 * math.sin(i / 25), 0.2 * math.sin(i / 31), 0.02 * i])


def bench(width: int, n_frames: int, window: int) -> dict:
    scale = width / 640
    intr = Intrinsics(525.0 * scale, 525.0 * scale, (width - 1) / 2, (480 * scale - 1) / 2, width, int(480 * scale))
    rng = np.random.default_rng(0)
    m = SurfelMap()
    cfg = FusionConfig()
    t_render, t_fuse, sizes, cands = [], [], [], []
    # warm-up (numba compilation) on a throw-away map
    V, N, C = _frame(_pose(0), intr, rng)
    warm = SurfelMap()
    fuse(warm, V, N, C, _pose(0), intr, 0, cfg)
    render(warm, _pose(0), intr)
    for i in range(n_frames):
        T = _pose(i)
        V, N, C = _frame(T, intr, rng)
        t0 = time.perf_counter()
        view = render(m, _pose(max(i - 1, 0)), intr)
        t1 = time.perf_counter()
        stats = fuse(m, V, N, C, T, intr, i, cfg)
        t2 = time.perf_counter()
        t_render.append(t1 - t0)
        t_fuse.append(t2 - t1)
        sizes.append(m.n_alive)
        cands.append(view.n_candidates)
        del stats
    tr = np.array(t_render[1:]) * 1e3  # frame 0 renders an empty map
    tf = np.array(t_fuse[1:]) * 1e3
    w = min(window, len(tr) // 2)
    return {
        "resolution": f"{intr.width}x{intr.height}", "frames": n_frames,
        "render_ms": float(np.median(tr)), "fuse_ms": float(np.median(tf)),
        "render_first_ms": float(np.median(tr[:w])), "render_last_ms": float(np.median(tr[-w:])),
        "fuse_first_ms": float(np.median(tf[:w])), "fuse_last_ms": float(np.median(tf[-w:])),
        "map_surfels": int(sizes[-1]), "candidates_last": int(cands[-1]),
    }


def run(quick: bool = False) -> list[dict]:
    n = 40 if quick else 300
    window = 10 if quick else 50
    return [bench(320, n, window), bench(640, n, window)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="40 frames instead of 300")
    rows = run(ap.parse_args().quick)
    cols = ["resolution", "frames", "render_ms", "fuse_ms", "render_first_ms", "render_last_ms", "fuse_first_ms",
            "fuse_last_ms", "map_surfels", "candidates_last"]
    print_rows(rows, cols)


if __name__ == "__main__":
    main()
