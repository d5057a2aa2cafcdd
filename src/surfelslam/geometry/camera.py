"""Pinhole projection and back-projection (vectorised numpy).

Pixel centres are at integer coordinates; images are indexed ``[v, u]``.
"""

from __future__ import annotations

import numpy as np

from surfelslam.types import Intrinsics


def pixel_grid(intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """``(u, v)`` float32 arrays of shape ``(H, W)`` holding each pixel's column and row."""
    v, u = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float32)
    return u, v


def backproject(depth_m: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Depth ``(H, W)`` -> vertex map ``(H, W, 3)`` float32 in the camera frame; invalid depth gives 0."""
    u, v = pixel_grid(intr)
    z = depth_m.astype(np.float32)
    x = (u - intr.cx) / intr.fx * z
    y = (v - intr.cy) / intr.fy * z
    return np.stack([x, y, z], axis=-1)


def project(points_cam: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points ``(..., 3)`` in the camera frame -> ``(u, v, z)`` float arrays (sub-pixel).

    Points with ``z <= 0`` get ``u = v = -1`` so that they fail any in-image test.
    """
    z = points_cam[..., 2]
    safe = z > 0
    zs = np.where(safe, z, 1.0)
    u = np.where(safe, intr.fx * points_cam[..., 0] / zs + intr.cx, -1.0)
    v = np.where(safe, intr.fy * points_cam[..., 1] / zs + intr.cy, -1.0)
    return u, v, z


def round_in_image(u: np.ndarray, v: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest pixel ``(ui, vi)`` (int64) and a mask of those inside the image."""
    ui = np.floor(u + 0.5).astype(np.int64)
    vi = np.floor(v + 0.5).astype(np.int64)
    inside = (ui >= 0) & (ui < intr.width) & (vi >= 0) & (vi < intr.height)
    return ui, vi, inside
