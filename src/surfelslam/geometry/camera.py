"""Pinhole projection and back-projection (vectorised numpy).

Pixel centres are at integer coordinates; images are indexed ``[v, u]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from surfelslam.config import Config, setting
from surfelslam.errors import ConfigError
from surfelslam.types import ColourCamera, Intrinsics


def pixel_grid(intr: Intrinsics, dtype: type = np.float32) -> tuple[np.ndarray, np.ndarray]:
    """``(u, v)`` arrays (``dtype``, float32 by default) of shape ``(H, W)`` holding each pixel's column and row."""
    v, u = np.mgrid[0 : intr.height, 0 : intr.width].astype(dtype)
    return u, v


def backproject(depth_m: np.ndarray, intr: Intrinsics, dtype: type = np.float32) -> np.ndarray:
    """Depth ``(H, W)`` -> vertex map ``(H, W, 3)`` (``dtype``, float32 by default) in the camera frame; invalid
    depth gives 0."""
    u, v = pixel_grid(intr, dtype)
    z = depth_m.astype(dtype)
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


@dataclass(frozen=True)
class ColourRegistrationConfig(Config):
    """Colour of each depth pixel when the sequence's colour camera is separate (:class:`ColourCamera`)."""

    enabled: bool = setting(True, user=True,
                            doc="sample each depth pixel's colour through the sequence's colour camera model "
                            "(when its layout has one, e.g. 7-Scenes); false: the colour pixel at the same (u, v)")
    fallback_depth_m: float = setting(2.0, unit="m", gt=0, le=100,
                                      doc="depth assumed where the depth pixel is invalid (sets the parallax of its "
                                          "colour)")
    check: bool = setting(
        True, doc="when the layout takes colour as registered to depth (TUM, ICL-NUIM, plain folders), fit a separate "
                  "colour camera on a few frames first; if it lines colour edges up with depth edges much better, "
                  "colour is taken as not registered (colour terms under auto turn off)", user=True)
    check_frames: int = setting(6, unit="frames", ge=1, le=1000, doc="frames of that check, spread over the selection")
    check_min_gain_px: float = setting(
        1.0, unit="px at 640 wide", gt=0, le=1000,
        doc="the fit must lower the mean edge distance by at least this much (scaled with the image width)")
    check_min_gain_fraction: float = setting(0.35, unit="fraction", gt=0, le=1,
                                             doc="and by at least this fraction of the same-pixel distance")


@lru_cache(maxsize=8)
def _colour_maps_at_infinity(intr: Intrinsics, cam: ColourCamera) -> tuple[np.ndarray, np.ndarray]:
    """Colour pixel ``(u_c, v_c)`` of each depth pixel's ray at infinite depth, ``(H, W)`` float32 each."""
    u, v = pixel_grid(intr)
    ci = cam.intrinsics
    return (ci.fx / intr.fx * (u - intr.cx) + ci.cx).astype(np.float32), \
        (ci.fy / intr.fy * (v - intr.cy) + ci.cy).astype(np.float32)


def colour_at_depth_pixels(rgb: np.ndarray, depth_m: np.ndarray, intr: Intrinsics, cam: ColourCamera,
                           fallback_depth_m: float) -> np.ndarray:
    """Each depth pixel's colour seen by a separate colour camera (registration of colour onto depth).

    Depth pixel ``(u, v)`` with depth ``z`` is the point ``X = z K^-1 (u, v, 1)`` of the depth camera; the colour
    camera sees it at ``project(X + t)``, where the colour image is sampled bilinearly (replicated at its border).
    With parallel axes that pixel is the ray's pixel at infinity plus the parallax ``f_c t_xy / z`` (``t_z`` changes
    the depth: ``z + t_z``).

    Args:
        rgb: ``(Hc, Wc, 3)`` uint8 colour image, ``Hc x Wc`` = ``cam.intrinsics`` size.
        depth_m: ``(H, W)`` depth (m) of the depth camera; 0 or non-finite = invalid (``fallback_depth_m`` used).
        intr: depth camera intrinsics (``H x W``).
        cam: the colour camera.
        fallback_depth_m: depth assumed at invalid pixels.

    Returns:
        ``(H, W, 3)`` uint8: colour registered to the depth pixels.
    """
    ci = cam.intrinsics
    if rgb.shape[:2] != ci.shape:
        raise ConfigError(f"colour image is {rgb.shape[1]}x{rgb.shape[0]}, "
                          f"the colour camera's is {ci.width}x{ci.height}")
    if depth_m.shape != intr.shape:
        raise ConfigError(f"depth image is {depth_m.shape[1]}x{depth_m.shape[0]}, expected {intr.width}x{intr.height}")
    u_inf, v_inf = _colour_maps_at_infinity(intr, cam)
    tx, ty, tz = (float(c) for c in cam.t_colour_depth_m)
    z = np.where(np.isfinite(depth_m) & (depth_m > 0), depth_m, np.float32(fallback_depth_m)).astype(np.float32)
    if tz != 0.0:  # the point's depth in the colour camera; the ray term scales by z / (z + tz)
        zc = z + np.float32(tz)
        scale = z / zc
        map_u = (u_inf - np.float32(ci.cx)) * scale + np.float32(ci.cx) + np.float32(ci.fx * tx) / zc
        map_v = (v_inf - np.float32(ci.cy)) * scale + np.float32(ci.cy) + np.float32(ci.fy * ty) / zc
    else:
        map_u = u_inf + np.float32(ci.fx * tx) / z
        map_v = v_inf + np.float32(ci.fy * ty) / z
    return cv2.remap(rgb, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
