"""Keyframe retrieval cost as the keyframe count grows: a query of :class:`DescriptorIndex` (300 descriptors against
every older keyframe's 300) by brute force and through the hash index, at 100, 500, 1000 and 2000 keyframes, how
often the hashed query returns the brute-force best keyframe, and the rows it compares per query descriptor (its
work, :attr:`DescriptorIndex.rows_compared`) without and with the stop-word bound (``hash_bucket_rows`` =
:data:`BUCKET_ROWS`).

Descriptors: synthetic, with unbalanced bits as ORB's (each bit set with its own probability, uniform in [0.05,
0.95]). A walk of ``n`` keyframes sees ``n`` places: a keyframe is its place's descriptors with 6 % of the bits
flipped, and a query is a second view of a random place, so its best keyframe is that place's (one view per place in
the database: several would fail the ratio test together). As on a real floor walk, a fifth of every keyframe's (and
query's) descriptors are views of common appearances (:data:`COMMON` patterns seen everywhere): without the bound
they share buckets with a share of the whole database, so the work per query grows with the map; with it, it levels
off. No data set or camera needed.

Usage: ``.venv/bin/python -m benchmarks.bench_retrieval [--quick]``; ``run(quick)`` returns the rows.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from benchmarks.common import median_ms, print_rows
from surfelslam.backend.place_recognition import DescriptorIndex, RetrievalConfig

PER_KEYFRAME = 300  # descriptors per keyframe (RetrievalConfig.max_descriptors_per_keyframe)
FLIP = 0.06  # share of bits flipped in a view of a place (two views: ~29 bits apart, as ORB matches on a floor walk)
QUERIES = 20
COMMON_SHARE = 0.2  # share of a keyframe's descriptors that are views of common appearances (a floor walk: a fifth)
BUCKET_ROWS = 256  # the stop-word bound compared (RetrievalConfig.hash_bucket_rows; off by default)
COMMON = 50  # common appearances (patterns every place shows: edges, corners of the same texture)


def _views(place: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A view of ``place`` ``(N, 256)`` bits: ``FLIP`` of its bits flipped, packed to ``(N, 32)`` uint8."""
    return np.packbits(place ^ (rng.random(place.shape) < FLIP), axis=1)


def _walk(n_kf: int, seed: int = 0) -> tuple[list[np.ndarray], list[tuple[int, np.ndarray]]]:
    """``n_kf`` keyframes' descriptors (one per place) and ``QUERIES`` queries ``(place, descriptors)``; each view
    includes views of ``COMMON_SHARE x PER_KEYFRAME`` common appearances drawn at random."""
    rng = np.random.default_rng(seed)
    p_one = rng.uniform(0.05, 0.95, 256)
    n_common = int(COMMON_SHARE * PER_KEYFRAME)
    common = (rng.random((COMMON, 256)) < p_one).astype(np.uint8)
    places = [np.concatenate([(rng.random((PER_KEYFRAME - n_common, 256)) < p_one).astype(np.uint8),
                              common[rng.choice(COMMON, n_common)]]) for _ in range(n_kf)]
    keyframes = [_views(p, rng) for p in places]
    queries = [(int(p), _views(places[p], rng)) for p in rng.integers(0, len(places), QUERIES)]
    return keyframes, queries


def _rows_per_descriptor(idx: DescriptorIndex, queries: list[tuple[int, np.ndarray]]) -> float:
    """Rows the hashed ``idx`` compares per query descriptor over ``queries``."""
    before = idx.rows_compared
    for _, q in queries:
        idx.query(q, 3)
    return (idx.rows_compared - before) / (len(queries) * PER_KEYFRAME)


def run(quick: bool = False) -> list[dict]:
    rows = []
    for n_kf in (100, 500) if quick else (100, 500, 1000, 2000):
        keyframes, queries = _walk(n_kf)
        exact = DescriptorIndex(replace(RetrievalConfig(), exact_below_descriptors=1 << 40))
        hashed = DescriptorIndex(replace(RetrievalConfig(), exact_below_descriptors=0))
        bounded = DescriptorIndex(replace(RetrievalConfig(), exact_below_descriptors=0, hash_bucket_rows=BUCKET_ROWS))
        for d in keyframes:
            for idx in (exact, hashed, bounded):
                idx.add(d)
        same = [[k for k, _ in exact.query(q, 1)] == [k for k, _ in hashed.query(q, 1)] == [p] for p, q in queries]
        rows.append({
            "keyframes": n_kf, "descriptors": n_kf * PER_KEYFRAME,
            "exact_ms": float(np.mean([median_ms(lambda q=q, idx=exact: idx.query(q, 3), 3) for _, q in queries])),
            "hashed_ms": float(np.mean([median_ms(lambda q=q, idx=hashed: idx.query(q, 3), 3) for _, q in queries])),
            "bounded_ms": float(np.mean([median_ms(lambda q=q, idx=bounded: idx.query(q, 3), 3) for _, q in queries])),
            "rows_per_desc": _rows_per_descriptor(hashed, queries),
            "bounded_rows_per_desc": _rows_per_descriptor(bounded, queries),
            "same_best": float(np.mean(same)),  # both return the query's place first
        })
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    rows = run(ap.parse_args().quick)
    print_rows(rows, nd=2)


if __name__ == "__main__":
    main()
