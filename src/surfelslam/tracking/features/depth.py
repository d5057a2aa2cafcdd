"""Depth of keypoints: nearest pixel or 3x3 median, refined by an inverse-depth plane fit; occluding-contour test."""

from __future__ import annotations

import numpy as np

from surfelslam.kernels.keypoint_depth import depth_edge_flags, keypoint_depths
from surfelslam.tracking.features.config import FeatureConfig


def _nearest_pixels(uv: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``(ui, vi)``: the nearest pixel of each ``uv (N, 2)`` row, clipped to an image of ``shape (H, W)``, int64."""
    h, w = shape
    ui = np.clip(np.floor(uv[:, 0] + 0.5).astype(np.int64), 0, w - 1)
    vi = np.clip(np.floor(uv[:, 1] + 0.5).astype(np.int64), 0, h - 1)
    return ui, vi


def keypoint_depth(depth_m: np.ndarray, uv: np.ndarray, cfg: FeatureConfig) -> np.ndarray:
    """Depth (m) at each keypoint ``(N,)``; NaN where invalid or out of [min_depth_m, max_depth_m].

    Args:
        depth_m: ``(H, W)`` float32 metres, 0 = invalid.
        uv: ``(N, 2)`` pixel coordinates (float32 or float64).
    """
    ui, vi = _nearest_pixels(uv, depth_m.shape)
    uv64 = uv.astype(np.float64)
    return keypoint_depths(
        np.ascontiguousarray(depth_m), ui, vi, np.ascontiguousarray(uv64[:, 0]), np.ascontiguousarray(uv64[:, 1]),
        bool(cfg.depth_median_3x3), int(cfg.depth_plane_radius_px), float(cfg.depth_plane_gate),
        float(cfg.depth_plane_min_pixels), float(cfg.depth_edge_rel), int(cfg.depth_edge_radius_px),
        float(cfg.min_depth_m), float(cfg.max_depth_m))


def on_occluding_contour(depth_m: np.ndarray, uv: np.ndarray, cfg: FeatureConfig) -> np.ndarray:
    """``(N,)`` bool: pixels ``uv (N, 2)`` whose ``(2 r + 1)^2`` patch of ``depth_m`` (``r = depth_edge_radius_px``)
    holds a valid depth more than ``depth_edge_rel`` away from the nearest pixel's (an occluding contour, see
    :class:`FeatureConfig`); False where that pixel has no depth or ``depth_edge_rel`` is 0."""
    n = len(uv)
    if cfg.depth_edge_rel <= 0 or n == 0:
        return np.zeros(n, bool)
    ui, vi = _nearest_pixels(uv, depth_m.shape)
    z = depth_m[vi, ui].astype(np.float64)
    z[~(z > 0)] = np.nan
    return depth_edge_flags(np.ascontiguousarray(depth_m), ui, vi, z, float(cfg.depth_edge_rel),
                            int(cfg.depth_edge_radius_px))
