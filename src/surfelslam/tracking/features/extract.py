"""Keypoint extraction: ORB (or SIFT) detection, grid bucketing and lifting to 3D (:class:`Features`)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from surfelslam.tracking.features.config import FeatureConfig
from surfelslam.tracking.features.depth import keypoint_depth
from surfelslam.types import Intrinsics

_DESCRIPTOR_BYTES = 32
_SIFT_DIMS = 128


@dataclass
class Features:
    """Keypoints of one image.

    Attributes:
        keypoints_uv: ``(N, 2)`` float32 pixel coordinates ``(u, v)`` at full resolution.
        descriptors: ``(N, 32)`` uint8 ORB descriptors, or ``(N, 128)`` float32 SIFT ones.
        points_cam: ``(N, 3)`` float32 camera-frame points (metres); NaN where depth is invalid.
        valid: ``(N,)`` bool, True where ``points_cam`` is finite.
        response: ``(N,)`` float32 detector response (for diagnostics).
        grey: ``(H, W)`` uint8 image the keypoints come from (for sub-pixel tracking), or ``None``.
        depth_m: ``(H, W)`` float32 depth of that image (a reference, not a copy), or ``None``.
    """

    keypoints_uv: np.ndarray
    descriptors: np.ndarray
    points_cam: np.ndarray
    valid: np.ndarray
    response: np.ndarray
    grey: np.ndarray | None = None
    depth_m: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.keypoints_uv)


def _detector(cfg: FeatureConfig):
    """The OpenCV detector + descriptor extractor of ``cfg.detector``."""
    n_detect = int(np.ceil(cfg.n_features * cfg.detect_oversample))
    if cfg.detector == "sift":
        return cv2.SIFT_create(nfeatures=n_detect)
    return cv2.ORB_create(
        nfeatures=n_detect,
        scaleFactor=cfg.scale_factor,
        nlevels=cfg.n_levels,
        edgeThreshold=cfg.edge_threshold_px,
        patchSize=cfg.edge_threshold_px,
        fastThreshold=cfg.fast_threshold,
    )


def to_grey(rgb: np.ndarray) -> np.ndarray:
    """The ``(H, W)`` uint8 grey image features are detected and tracked in, of ``rgb (H, W, 3)`` (or grey)."""
    if rgb.ndim == 2:
        return np.ascontiguousarray(rgb, dtype=np.uint8)
    return cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)


def bucket_keypoints(
    uv: np.ndarray, response: np.ndarray, shape: tuple[int, int], cfg: FeatureConfig, n_keep: int | None = None
) -> np.ndarray:
    """Indices of the keypoints kept by grid bucketing (strongest first within each cell).

    Args:
        uv: ``(N, 2)`` pixel coordinates.
        response: ``(N,)`` detector responses.
        shape: image ``(H, W)``.
        n_keep: how many to keep (default ``cfg.n_features``); the grid is ``cfg``'s.

    Returns:
        ``(K,)`` int64 indices into ``uv``, ascending, ``K <= n_keep``. Cells with fewer
        keypoints than their quota leave room that is refilled with the best remaining keypoints.
    """
    n = len(uv)
    n_keep = cfg.n_features if n_keep is None else n_keep
    if n <= n_keep:
        return np.arange(n, dtype=np.int64)
    h, w = shape
    cu = np.clip((uv[:, 0] * cfg.grid_cols / w).astype(np.int64), 0, cfg.grid_cols - 1)
    cv_ = np.clip((uv[:, 1] * cfg.grid_rows / h).astype(np.int64), 0, cfg.grid_rows - 1)
    cell = cv_ * cfg.grid_cols + cu
    # stable sort by (cell, -response, index): deterministic ranks within each cell
    order = np.lexsort((np.arange(n), -response, cell))
    cell_sorted = cell[order]
    first = np.searchsorted(cell_sorted, cell_sorted, side="left")
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n) - first
    quota = int(np.ceil(n_keep / (cfg.grid_cols * cfg.grid_rows)))
    # global order: by rank within the cell first, then by response -> fill evenly, then the strongest
    global_order = np.lexsort((np.arange(n), -response, np.minimum(rank, quota)))
    keep = global_order[:n_keep]
    return np.sort(keep)


def extract(rgb: np.ndarray, depth_m: np.ndarray, intr: Intrinsics, cfg: FeatureConfig) -> Features:
    """Detect ORB keypoints, compute descriptors and lift them to 3D.

    Args:
        rgb: ``(H, W, 3)`` uint8 RGB (or ``(H, W)`` grey).
        depth_m: ``(H, W)`` float32 metres, 0 = invalid.
        intr: intrinsics of these images.

    Returns:
        :class:`Features`; ``points_cam`` rows are NaN where the depth is invalid.
    """
    grey = to_grey(rgb)
    if grey.shape != depth_m.shape:
        raise ValueError(f"rgb {grey.shape} and depth {depth_m.shape} sizes differ")
    kps, desc = _detector(cfg).detectAndCompute(grey, None)
    if desc is None or len(kps) == 0:
        empty2 = np.zeros((0, 2), np.float32)
        no_desc = np.zeros((0, _SIFT_DIMS), np.float32) if cfg.detector == "sift" else \
            np.zeros((0, _DESCRIPTOR_BYTES), np.uint8)
        return Features(
            empty2, no_desc, np.zeros((0, 3), np.float32),
            np.zeros(0, bool), np.zeros(0, np.float32), grey, depth_m,
        )
    uv = cv2.KeyPoint_convert(kps).astype(np.float32, copy=False).reshape(-1, 2)  # C++: no Python loop
    response = np.array([kp.response for kp in kps], dtype=np.float32)
    keep = bucket_keypoints(uv, response, grey.shape, cfg)
    uv, response, desc = uv[keep], response[keep], np.ascontiguousarray(desc[keep])
    z = keypoint_depth(depth_m, uv, cfg)
    x = (uv[:, 0] - intr.cx) / intr.fx * z
    y = (uv[:, 1] - intr.cy) / intr.fy * z
    pts = np.column_stack([x, y, z]).astype(np.float32)
    return Features(uv, desc, pts, np.isfinite(z), response, grey, depth_m)
