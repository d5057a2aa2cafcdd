"""Descriptor matching: Hamming nearest neighbours (cross-check or ratio test) and the good-match filter."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from surfelslam.kernels import hamming
from surfelslam.tracking.features.config import FeatureConfig
from surfelslam.tracking.features.extract import Features


@dataclass
class MatchResult:
    """Good matches between a reference and a current :class:`Features`.

    Attributes:
        pairs: ``(M, 2)`` int64 ``(ref_index, cur_index)`` of the good matches, ordered by ref index.
        distances: ``(M,)`` float32 Hamming distances (bits).
        n_raw: matches before the distance filter.
        n_good: ``M``.
        min_dist, max_dist: smallest / largest raw match distance (bits; 0 when there is none).
    """

    pairs: np.ndarray
    distances: np.ndarray
    n_raw: int
    n_good: int
    min_dist: float
    max_dist: float


def match(ref: Features, cur: Features, cfg: FeatureConfig, pred_uv: np.ndarray | None = None,
          image_size: tuple[int, int] | None = None) -> MatchResult:
    """Match ``ref`` descriptors to ``cur`` descriptors and keep the good matches.

    Good matches: Hamming distance ``< good_match_k * max(min_dist, good_match_floor_bits)`` where
    ``min_dist`` is the smallest distance of all raw matches (the reference assignment's rule).

    ``pred_uv``: ``(N, 2)`` predicted pixels of the reference keypoints in the current image (non-finite: not
    matched) and ``image_size`` ``(W, H)``: guided matching within ``cfg.guided_radius_px`` of them (ORB only,
    always mutual nearest neighbours) instead of brute force.
    """
    empty = MatchResult(np.zeros((0, 2), np.int64), np.zeros(0, np.float32), 0, 0, 0.0, 0.0)
    if len(ref) == 0 or len(cur) == 0:
        return empty
    if ref.descriptors.dtype != np.uint8 or cur.descriptors.dtype != np.uint8:
        return _match_float(ref, cur, cfg)
    ref_w, cur_w = hamming.as_words(ref.descriptors), hamming.as_words(cur.descriptors)
    if pred_uv is not None and image_size is not None and cfg.guided_radius_px > 0:
        d12, j12, i21 = hamming.nearest_mutual_within_words(ref_w, pred_uv, cur_w, cur.keypoints_uv,
                                                            cfg.guided_radius_px, *image_size)
        keep = (j12 >= 0) & (i21[np.maximum(j12, 0)] == np.arange(len(ref)))
    elif cfg.matching == "crosscheck":  # brute force, numba (see kernels.hamming); both directions in one pass
        d12, d12_second, j12, i21 = hamming.nearest_two_mutual_words(ref_w, cur_w)
        keep = i21[j12] == np.arange(len(ref))  # mutual nearest neighbours
    else:
        d12, d12_second, j12 = hamming.nearest_two_words(ref_w, cur_w)
        keep = (d12_second != hamming.NO_MATCH) & (d12 < cfg.ratio * d12_second)
    if not keep.any():
        return empty
    q = np.nonzero(keep)[0]  # ordered by ref index
    d = d12[q].astype(np.float64)
    min_d, max_d = float(d.min()), float(d.max())
    thresh = cfg.good_match_k * max(min_d, cfg.good_match_floor_bits)
    good = d < thresh
    pairs = np.column_stack([q[good], j12[q[good]]]).astype(np.int64)
    return MatchResult(pairs, d[good].astype(np.float32), len(q), int(good.sum()), min_d, max_d)


def _match_float(ref: Features, cur: Features, cfg: FeatureConfig) -> MatchResult:
    """SIFT descriptors: L2 nearest neighbours (OpenCV brute force) kept by Lowe's ratio test at ``cfg.ratio``;
    with ``crosscheck`` matching they must also be mutual. No good-match distance filter."""
    if ref.descriptors.dtype != cur.descriptors.dtype or ref.descriptors.shape[1] != cur.descriptors.shape[1]:
        raise ValueError("reference and current descriptors are of different kinds (ORB and SIFT?)")
    empty = MatchResult(np.zeros((0, 2), np.int64), np.zeros(0, np.float32), 0, 0, 0.0, 0.0)
    bf = cv2.BFMatcher(cv2.NORM_L2)
    knn = bf.knnMatch(ref.descriptors, cur.descriptors, k=2)
    rows = [(m[0].queryIdx, m[0].trainIdx, m[0].distance) for m in knn
            if len(m) == 2 and m[0].distance < cfg.ratio * m[1].distance]
    if not rows:
        return empty
    q = np.array([r[0] for r in rows], np.int64)
    j = np.array([r[1] for r in rows], np.int64)
    d = np.array([r[2] for r in rows], np.float32)
    if cfg.matching == "crosscheck":
        back = np.array([m[0].trainIdx for m in bf.knnMatch(cur.descriptors, ref.descriptors, k=1)], np.int64)
        keep = back[j] == q
        q, j, d = q[keep], j[keep], d[keep]
    if len(q) == 0:
        return empty
    return MatchResult(np.column_stack([q, j]), d, len(knn), len(q), float(d.min()), float(d.max()))
