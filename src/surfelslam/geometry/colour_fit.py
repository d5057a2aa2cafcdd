"""Fit a separate colour camera to a sequence: colour edges should fall on depth discontinuities.

For colour not registered to depth (two cameras, no calibration given), the model of
:class:`~surfelslam.types.ColourCamera` (pinhole intrinsics + translation, axes parallel) is estimated from the
frames themselves. Every depth discontinuity (a relative jump above ``depth_edge_jump`` between neighbours) is a
silhouette, and a silhouette is an edge in the colour image too. Each discontinuity pixel, lifted at its near
(foreground) depth, is projected into the colour image with the candidate camera; the cost is the mean distance
(capped at ``max_edge_distance_px``) to the nearest colour edge (Canny), looked up in a distance transform.

The search: a grid over the focal-length ratio (colour / depth, the same for x and y) and the principal-point
offset, then Nelder-Mead over ``fx, fy, cx, cy`` and the horizontal offset ``tx`` (a Kinect-style rig: the colour
camera sits beside the depth camera along x; ``ty = tz = 0``). Vectorised numpy + OpenCV; no I/O.

The built-in 7-Scenes model (:data:`surfelslam.datasets.sevenscenes.SEVENSCENES_COLOUR_CAMERA`) came from this
criterion; ``surfelslam calibrate-colour`` fits other sequences.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from surfelslam.config import Config, ordered, setting
from surfelslam.errors import ConfigError
from surfelslam.types import ColourCamera, Intrinsics, RGBDFrame


@dataclass(frozen=True)
class ColourFitConfig(Config):
    """Settings of :func:`fit_colour_camera`: a grid search aligning depth discontinuities with colour edges."""

    depth_edge_jump: float = setting(0.05, unit="fraction", gt=0, le=10,
                                     doc="relative depth difference between neighbours that marks a discontinuity")
    canny_low: int = setting(30, unit="grey levels", ge=0, le=1000, doc="lower Canny threshold of the colour edges")
    canny_high: int = setting(80, unit="grey levels", ge=0, le=1000, doc="upper Canny threshold")
    blur_sigma_px: float = setting(1.2, unit="px", ge=0, le=50, doc="Gaussian blur before Canny")
    max_edge_distance_px: float = setting(8.0, unit="px", gt=0, le=1000,
                                          doc="distances to the nearest colour edge are capped here")
    max_points_per_frame: int = setting(4000, unit="pixels", ge=1, le=10_000_000,
                                        doc="discontinuity pixels kept per frame (evenly strided)")
    ratio_min: float = setting(0.8, gt=0, le=100, doc="smallest colour / depth focal-length ratio tried")
    ratio_max: float = setting(1.2, gt=0, le=100, doc="largest ratio tried")
    ratio_step: float = setting(0.02, gt=0, le=100, doc="step of the ratio grid")
    offset_max_px: float = setting(16.0, unit="px", ge=0, le=1000, doc="largest principal-point offset tried (both "
                                   "axes)")
    offset_step_px: float = setting(4.0, unit="px", gt=0, le=1000, doc="step of the offset grid")
    fit_translation: bool = setting(True, doc="also fit the colour camera's offset along the depth camera's x axis")

    _ratio_range = ordered("ratio_min", "ratio_max")


@dataclass(frozen=True)
class ColourFit:
    """Result of :func:`fit_colour_camera`.

    Attributes:
        camera: the fitted colour camera (on the frames' pixel grid).
        edge_distance_px: mean capped distance from a depth discontinuity to the nearest colour edge, fitted.
        edge_distance_same_pixel_px: the same with colour pixel = depth pixel (registered colour scores lowest
            there already).
        n_frames: frames used; n_edge_pixels: discontinuity pixels used.
    """

    camera: ColourCamera
    edge_distance_px: float
    edge_distance_same_pixel_px: float
    n_frames: int
    n_edge_pixels: int


def depth_discontinuities(depth_m: np.ndarray, jump: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels next to a relative depth jump above ``jump``: ``(u, v, z_near)``, each ``(M,)`` float64, with
    ``z_near`` the nearer of the pixel and its left / upper neighbour (the silhouette's depth)."""
    d = np.where(np.isfinite(depth_m) & (depth_m > 0), depth_m, np.nan).astype(np.float64)
    near = d.copy()
    edge = np.zeros(d.shape, bool)
    with np.errstate(invalid="ignore"):
        jx = np.abs(d[:, 1:] - d[:, :-1]) > jump * np.fmin(d[:, 1:], d[:, :-1])
        jy = np.abs(d[1:, :] - d[:-1, :]) > jump * np.fmin(d[1:, :], d[:-1, :])
    edge[:, 1:] |= jx
    edge[1:, :] |= jy
    near[:, 1:] = np.where(jx, np.fmin(d[:, 1:], d[:, :-1]), near[:, 1:])
    near[1:, :] = np.where(jy, np.fmin(near[1:, :], d[:-1, :]), near[1:, :])
    v, u = np.nonzero(edge)
    z = near[v, u]
    ok = np.isfinite(z)
    return u[ok].astype(np.float64), v[ok].astype(np.float64), z[ok]


def colour_edge_distance(rgb: np.ndarray, cfg: ColourFitConfig) -> np.ndarray:
    """``(H, W)`` float32 distance (px) from each pixel to the nearest Canny edge of the colour image."""
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    edges = cv2.Canny(cv2.GaussianBlur(grey, (0, 0), cfg.blur_sigma_px), cfg.canny_low, cfg.canny_high) > 0
    return cv2.distanceTransform((~edges).astype(np.uint8), cv2.DIST_L2, 5)


def fit_colour_camera(frames: Sequence[RGBDFrame], intr: Intrinsics, cfg: ColourFitConfig | None = None
                      ) -> ColourFit:
    """Estimate the colour camera of ``frames`` (see the module docstring).

    Args:
        frames: RGB-D frames (colour not registered to depth); varied views with depth edges help.
        intr: depth camera intrinsics of the frames.

    Raises:
        ConfigError: no depth discontinuities in the frames (nothing to align).
    """
    cfg = cfg or ColourFitConfig()
    us, vs, zs, dts, owner = [], [], [], [], []
    for k, f in enumerate(frames):
        u, v, z = depth_discontinuities(f.depth_m, cfg.depth_edge_jump)
        step = max(1, int(np.ceil(len(u) / cfg.max_points_per_frame)))
        us.append(u[::step])
        vs.append(v[::step])
        zs.append(z[::step])
        owner.append(np.full(len(us[-1]), k))
        dts.append(colour_edge_distance(f.rgb, cfg))
    if not frames or sum(len(u) for u in us) == 0:
        raise ConfigError("colour fit: no depth discontinuities in the frames (nothing to align colour with)")
    u, v, inv_z, who = np.concatenate(us), np.concatenate(vs), 1.0 / np.concatenate(zs), np.concatenate(owner)
    h, w = intr.shape
    # the distance maps stacked vertically: frame k's pixel (x, y) is row y + k h (clipped per frame below)
    flat = np.vstack(dts).astype(np.float64).ravel()
    row0 = (who * h).astype(np.float64)
    xn, yn = (u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy

    def cost(fx: float, fy: float, cx: float, cy: float, tx: float) -> float:
        uc = fx * (xn + tx * inv_z) + cx
        vc = fy * yn + cy
        inside = (uc >= 0) & (uc < w - 1) & (vc >= 0) & (vc < h - 1)
        d = np.full(len(u), cfg.max_edge_distance_px, np.float64)
        x, y = uc[inside], vc[inside]
        x0, y0 = np.floor(x), np.floor(y)
        ax, ay = x - x0, y - y0
        i = (y0 + row0[inside]).astype(np.int64) * w + x0.astype(np.int64)  # bilinear in the stacked maps
        d[inside] = ((1 - ay) * ((1 - ax) * flat[i] + ax * flat[i + 1])
                     + ay * ((1 - ax) * flat[i + w] + ax * flat[i + w + 1]))
        return float(np.minimum(d, cfg.max_edge_distance_px).mean())

    same = cost(intr.fx, intr.fy, intr.cx, intr.cy, 0.0)
    best = (same, 1.0, 0.0, 0.0)
    offsets = np.arange(-cfg.offset_max_px, cfg.offset_max_px + 1e-9, cfg.offset_step_px)
    for ratio in np.arange(cfg.ratio_min, cfg.ratio_max + 1e-9, cfg.ratio_step):
        for ox in offsets:
            for oy in offsets:
                c = cost(ratio * intr.fx, ratio * intr.fy, intr.cx + ox, intr.cy + oy, 0.0)
                if c < best[0]:
                    best = (c, float(ratio), float(ox), float(oy))
    _, ratio, ox, oy = best
    x0 = np.array([ratio * intr.fx, ratio * intr.fy, intr.cx + ox, intr.cy + oy, 0.0])
    # simplex steps: 1 % of the focal lengths, the grid's offset step, 1 cm
    steps = np.array([0.01 * abs(intr.fx), 0.01 * abs(intr.fy), cfg.offset_step_px, cfg.offset_step_px, 0.01])
    n = 5 if cfg.fit_translation else 4
    simplex = np.vstack([x0[:n]] + [x0[:n] + np.diag(steps[:n])[i] for i in range(n)])

    def f(x: np.ndarray) -> float:
        return cost(*x, *([0.0] * (5 - n)))

    from scipy.optimize import minimize  # here: importing scipy.optimize costs a run's start-up about 0.3 s

    res = minimize(f, x0[:n], method="Nelder-Mead",
                   options={"initial_simplex": simplex, "xatol": 1e-3, "fatol": 1e-5, "maxiter": 2000})
    x = np.concatenate([res.x, np.zeros(5 - n)])
    fit_cost = float(res.fun)
    if fit_cost > best[0]:  # never worse than the grid's best
        x, fit_cost = x0, best[0]
    cam = ColourCamera(Intrinsics(float(x[0]), float(x[1]), float(x[2]), float(x[3]), w, h), (float(x[4]), 0.0, 0.0))
    return ColourFit(cam, fit_cost, same, len(frames), len(u))


#: Image width that :func:`fit_says_unregistered`'s pixel bound is given for.
GAIN_REFERENCE_WIDTH_PX = 640


def fit_says_unregistered(fit: ColourFit, width_px: int, min_gain_px: float, min_gain_fraction: float) -> bool:
    """Whether a fitted colour camera lines colour edges up with depth edges so much better than the same pixel
    that colour cannot be registered to depth: the mean edge distance drops by at least ``min_gain_px`` (given
    for 640-pixel-wide images, scaled with ``width_px``) and by ``min_gain_fraction`` of the same-pixel one
    (measured distances on real datasets: docs/datasets.md).
    """
    gain = fit.edge_distance_same_pixel_px - fit.edge_distance_px
    return bool(gain >= min_gain_px * width_px / GAIN_REFERENCE_WIDTH_PX
                and gain >= min_gain_fraction * fit.edge_distance_same_pixel_px)
