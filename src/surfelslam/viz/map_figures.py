"""Figures of a fused map: point renders coloured by normal, confidence and time.

These are for pictures only (not the tracking path): a vectorised numpy z-buffer splat of every
point, with a top view and a view from the first camera.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib import colormaps

from surfelslam.viz.save import new_figure, save_figure

COLOUR_MODES = ("normal", "confidence", "time", "rgb")


def _zbuffer(u: np.ndarray, v: np.ndarray, depth: np.ndarray, width: int,
             height: int) -> tuple[np.ndarray, np.ndarray]:
    """Nearest point per pixel. Returns ``(pixel_flat_index (K,), point_index (K,))``."""
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height) & (depth > 0)
    idx = np.flatnonzero(inside)
    pix = v[idx] * width + u[idx]
    order = np.lexsort((depth[idx], pix))
    pix_sorted = pix[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = pix_sorted[1:] != pix_sorted[:-1]
    return pix_sorted[first], idx[order[first]]


def point_colours(mode: str, normal: np.ndarray, confidence: np.ndarray, first_seen: np.ndarray,
                  rgb: np.ndarray) -> tuple[np.ndarray, str | None]:
    """``(N, 3)`` float colours in [0, 1] for a colour mode, plus a colour-bar label (or None)."""
    if mode == "normal":
        return np.clip((normal + 1.0) * 0.5, 0, 1), None
    if mode == "rgb":
        return rgb.astype(np.float32) / 255.0, None
    if mode == "confidence":
        hi = float(np.percentile(confidence, 98)) if len(confidence) else 1.0
        return colormaps["viridis"](np.clip(confidence / max(hi, 1e-9), 0, 1))[:, :3], "confidence"
    if mode == "time":
        span = max(int(first_seen.max()) if len(first_seen) else 1, 1)
        return colormaps["plasma"](first_seen / span)[:, :3], "first seen (frame)"
    raise ValueError(f"unknown colour mode {mode!r}; known: {COLOUR_MODES}")


def render_points(xyz_cam: np.ndarray, colours: np.ndarray, fx: float, cx: float, cy: float, width: int,
                  height: int, orthographic_scale: float | None = None) -> np.ndarray:
    """Splat camera-frame points ``(N, 3)`` into an ``(H, W, 3)`` float image (white background).

    Perspective with focal ``fx`` unless ``orthographic_scale`` (pixels per metre) is given.
    """
    z = xyz_cam[:, 2]
    if orthographic_scale is None:
        zs = np.where(z > 0, z, 1.0)
        u = np.floor(fx * xyz_cam[:, 0] / zs + cx + 0.5).astype(np.int64)
        v = np.floor(fx * xyz_cam[:, 1] / zs + cy + 0.5).astype(np.int64)
        depth = z
    else:
        u = np.floor(orthographic_scale * xyz_cam[:, 0] + cx + 0.5).astype(np.int64)
        v = np.floor(orthographic_scale * xyz_cam[:, 1] + cy + 0.5).astype(np.int64)
        depth = z - z.min() + 1.0
    img = np.ones((height * width, 3), dtype=np.float32)
    pix, pts = _zbuffer(u, v, depth, width, height)
    img[pix] = colours[pts]
    return img.reshape(height, width, 3)


def view_top(xyz_world: np.ndarray, T_world_cam0: np.ndarray, size_px: int = 800) -> tuple[np.ndarray, dict]:
    """Points in a 'top' camera looking down the first camera's up axis (camera y is down, so up = -y0).

    Returns camera-frame points and the orthographic projection parameters.
    """
    R0 = T_world_cam0[:3, :3]
    down = R0[:, 1]                     # first camera's y axis (pointing down in the world)
    right = R0[:, 0]
    fwd = np.cross(down, right)          # completes a right-handed frame: x=right, y=fwd-ish, z=down
    R_world_top = np.column_stack([right, -fwd, down])
    centre = np.median(xyz_world, axis=0) if len(xyz_world) else np.zeros(3)
    pts = (xyz_world - centre) @ R_world_top
    extent = np.percentile(np.abs(pts[:, :2]), 99, axis=0).max() if len(pts) else 1.0
    scale = 0.45 * size_px / max(extent, 1e-3)
    return pts, {"orthographic_scale": scale, "cx": size_px / 2, "cy": size_px / 2, "fx": 0.0}


def view_first_camera(xyz_world: np.ndarray, T_world_cam0: np.ndarray, width: int = 640,
                      height: int = 480, pull_back_m: float = 0.5) -> tuple[np.ndarray, dict]:
    """Points in the first camera, pulled back along its optical axis to show more of the map."""
    T = T_world_cam0.copy()
    T[:3, 3] -= pull_back_m * T[:3, 2]
    R, t = T[:3, :3], T[:3, 3]
    pts = (xyz_world - t) @ R
    return pts, {"fx": 0.8 * width * 0.5, "cx": width / 2, "cy": height / 2, "orthographic_scale": None}


def save_map_figures(out_dir: str | Path, xyz: np.ndarray, normal: np.ndarray, rgb: np.ndarray,
                     confidence: np.ndarray, first_seen: np.ndarray, T_world_cam0: np.ndarray,
                     prefix: str = "map", title: str = "") -> list[Path]:
    """Write ``{prefix}_{top,camera}.png``: one row per view, one panel per colour mode."""
    out_dir = Path(out_dir)
    written = []
    views = {
        "top": view_top(xyz, T_world_cam0),
        "camera": view_first_camera(xyz, T_world_cam0),
    }
    modes = ("normal", "confidence", "time", "rgb")
    for view_name, (pts, p) in views.items():
        w = h = 800 if view_name == "top" else None
        if view_name == "camera":
            w, h = 640, 480
        fig = new_figure((4.2 * len(modes), 4.2 * h / w + 0.6))
        for k, mode in enumerate(modes):
            cols, label = point_colours(mode, normal, confidence, first_seen, rgb)
            img = render_points(pts, cols, p["fx"], p["cx"], p["cy"], w, h, p["orthographic_scale"])
            ax = fig.add_subplot(1, len(modes), k + 1)
            ax.imshow(img, interpolation="nearest")
            ax.set_title(f"{view_name} view, coloured by {mode}", fontsize=9)
            ax.set_axis_off()
        fig.suptitle(f"{title} ({len(xyz):,} points)" if title else f"{len(xyz):,} points", fontsize=10)
        fig.tight_layout()
        path = out_dir / f"{prefix}_{view_name}.png"
        save_figure(fig, path)
        written.append(path)
    return written
