"""Sparse odometry timings (ms per call, median after warm-up): ORB extract, match, PnP-RANSAC; and the two-nearest
Hamming search of the matching (:mod:`surfelslam.kernels.hamming`) against OpenCV's ``BFMatcher.knnMatch`` on the
same descriptors (why the search is a numba kernel).

Frames: consecutive 7-Scenes redkitchen pairs (i, i+5) from ../shared/data when present, otherwise a
synthetic textured plane (random grey blocks, 2 m away, shifted 3 cm between the two frames). Run at
640x480 and 320x240 (``downsample`` 2). Default FeatureConfig (1000 features at 640x480; 500 at 320x240).

Usage: ``.venv/bin/python -m benchmarks.bench_orb [--quick]``; ``run(quick)`` returns the rows.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import cv2
import numpy as np

from benchmarks.common import REDKITCHEN, median_ms, print_rows
from surfelslam.kernels import hamming
from surfelslam.tracking.features import FeatureConfig, estimate_motion, extract, match
from surfelslam.types import Intrinsics, RGBDFrame


def _synthetic_pairs(intr: Intrinsics, n: int) -> list[tuple[RGBDFrame, RGBDFrame]]:
    rng = np.random.default_rng(0)
    tex = rng.integers(0, 256, (64, 64), dtype=np.uint8)
    v, u = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float64)
    depth = np.full(intr.shape, 2.0, np.float32)
    out = []
    for k in range(n):
        frames = []
        for shift_m in (0.0, 0.03):
            x = (u - intr.cx) / intr.fx * 2.0 + shift_m + 0.01 * k
            y = (v - intr.cy) / intr.fy * 2.0
            g = tex[np.floor(y / 0.04).astype(int) % 64, np.floor(x / 0.04).astype(int) % 64]
            frames.append(RGBDFrame(k, 0.0, np.repeat(g[..., None], 3, axis=2), depth))
        out.append((frames[0], frames[1]))
    return out


def _pairs(downsample: int, n: int) -> tuple[Intrinsics, list[tuple[RGBDFrame, RGBDFrame]], str]:
    full = Intrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)
    if REDKITCHEN.is_dir():
        from surfelslam.datasets import open_sequence
        from surfelslam.datasets.base import DatasetOptions

        seq = open_sequence(REDKITCHEN, DatasetOptions(downsample=downsample))
        idx = np.linspace(0, len(seq) - 6, n).astype(int)
        return seq.intrinsics, [(seq[i], seq[i + 5]) for i in idx], "7scenes"
    intr = full.scaled(downsample)
    return intr, _synthetic_pairs(intr, n), "synthetic"


def _knn_ms(fa, fb) -> tuple[float, float]:
    """Median ms of the two nearest neighbours of every ``fb`` descriptor among ``fa``'s: the numba kernel, then
    OpenCV's brute-force matcher (Hamming norm)."""
    qa, qb = hamming.as_words(fa.descriptors), hamming.as_words(fb.descriptors)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    return (median_ms(lambda: hamming.nearest_two_words(qb, qa), 5),
            median_ms(lambda: bf.knnMatch(fb.descriptors, fa.descriptors, k=2), 5))


def _time_pairs(pairs, intr: Intrinsics, cfg: FeatureConfig):
    ext, mat, pnp, inl, knn = [], [], [], [], []
    for a, b in pairs:
        fa = extract(a.rgb, a.depth_m, intr, cfg)
        fb = extract(b.rgb, b.depth_m, intr, cfg)
        knn.append(_knn_ms(fa, fb))
        ext.append(median_ms(lambda a=a: extract(a.rgb, a.depth_m, intr, cfg), 3))
        mat.append(median_ms(lambda fa=fa, fb=fb: match(fa, fb, cfg), 3))
        # PnP alone: estimate_motion minus its matching
        tot = median_ms(lambda fa=fa, fb=fb: estimate_motion(fa, fb, intr, cfg), 3)
        pnp.append(max(tot - mat[-1], 0.0))
        inl.append(estimate_motion(fa, fb, intr, cfg).n_inliers)
    return ext, mat, pnp, inl, np.array(knn)


def run(quick: bool = False) -> list[dict]:
    rows = []
    n_pairs = 3 if quick else 10
    for downsample, n_feat in ((1, 1000), (2, 500)):
        intr, pairs, source = _pairs(downsample, n_pairs)
        cfg = replace(FeatureConfig(), n_features=n_feat)
        ext, mat, pnp, inl, knn = _time_pairs(pairs, intr, cfg)
        rows.append({
            "resolution": f"{intr.width}x{intr.height}", "source": source, "n_features": n_feat,
            "extract_ms": float(np.median(ext)), "match_ms": float(np.median(mat)),
            "pnp_ms": float(np.median(pnp)), "median_inliers": float(np.median(inl)),
            "knn_numba_ms": float(np.median(knn[:, 0])), "knn_bfmatcher_ms": float(np.median(knn[:, 1])),
        })
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    rows = run(ap.parse_args().quick)
    print_rows(rows, nd=1)


if __name__ == "__main__":
    main()
