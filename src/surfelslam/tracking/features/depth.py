"""Depth of keypoints: nearest pixel or 3x3 median, refined by an inverse-depth plane fit; occluding-contour test."""

from __future__ import annotations

import numpy as np

from surfelslam.tracking.features.config import FeatureConfig


def keypoint_depth(depth_m: np.ndarray, uv: np.ndarray, cfg: FeatureConfig) -> np.ndarray:
    """Depth (m) at each keypoint ``(N,)``; NaN where invalid or out of [min_depth_m, max_depth_m]."""
    h, w = depth_m.shape
    ui = np.clip(np.floor(uv[:, 0] + 0.5).astype(np.int64), 0, w - 1)
    vi = np.clip(np.floor(uv[:, 1] + 0.5).astype(np.int64), 0, h - 1)
    if cfg.depth_median_3x3:
        offs = np.array([-1, 0, 1])
        uu = np.clip(ui[:, None, None] + offs[None, None, :], 0, w - 1)
        vv = np.clip(vi[:, None, None] + offs[None, :, None], 0, h - 1)
        patch = depth_m[vv, uu].reshape(len(uv), 9).astype(np.float64)
        ok = (patch >= cfg.min_depth_m) & (patch <= cfg.max_depth_m)
        patch[~ok] = np.nan
        centre_ok = ok[:, 4]
        # rows without any valid depth stay NaN (no all-NaN median: its warning, and warnings.catch_warnings is
        # not thread-safe while the reader thread extracts features)
        z = np.full(len(uv), np.nan)
        some = ok.any(axis=1)
        z[some] = np.nanmedian(patch[some], axis=1)
        # the centre pixel must itself be valid: a keypoint on a hole has no reliable depth
        z[~centre_ok] = np.nan
        if cfg.depth_plane_radius_px > 0:
            z = _plane_fit_depth(depth_m, uv, ui, vi, z, cfg)
    else:
        z = depth_m[vi, ui].astype(np.float64)
        z[(z < cfg.min_depth_m) | (z > cfg.max_depth_m)] = np.nan
    if cfg.depth_edge_rel > 0:
        z[_on_depth_edge(depth_m, ui, vi, z, cfg)] = np.nan
    return z


def _on_depth_edge(depth_m: np.ndarray, ui: np.ndarray, vi: np.ndarray, z: np.ndarray,
                   cfg: FeatureConfig) -> np.ndarray:
    """``(N,)`` bool: the keypoint's patch holds a valid depth more than ``depth_edge_rel`` away from its depth
    ``z`` (an occluding contour; see :class:`FeatureConfig`)."""
    h, w = depth_m.shape
    offs = np.arange(-cfg.depth_edge_radius_px, cfg.depth_edge_radius_px + 1)
    uu = np.clip(ui[:, None, None] + offs[None, None, :], 0, w - 1)
    vv = np.clip(vi[:, None, None] + offs[None, :, None], 0, h - 1)
    patch = depth_m[vv, uu].reshape(len(ui), -1)
    zc = np.where(np.isfinite(z), z, 0.0)[:, None]
    return ((patch > 0) & (np.abs(patch - zc) > cfg.depth_edge_rel * zc)).any(axis=1) & np.isfinite(z)


def on_occluding_contour(depth_m: np.ndarray, uv: np.ndarray, cfg: FeatureConfig) -> np.ndarray:
    """``(N,)`` bool: pixels ``uv (N, 2)`` whose ``(2 r + 1)^2`` patch of ``depth_m`` (``r = depth_edge_radius_px``)
    holds a valid depth more than ``depth_edge_rel`` away from the nearest pixel's (an occluding contour, see
    :class:`FeatureConfig`); False where that pixel has no depth or ``depth_edge_rel`` is 0."""
    n = len(uv)
    if cfg.depth_edge_rel <= 0 or n == 0:
        return np.zeros(n, bool)
    h, w = depth_m.shape
    ui = np.clip(np.floor(uv[:, 0] + 0.5).astype(np.int64), 0, w - 1)
    vi = np.clip(np.floor(uv[:, 1] + 0.5).astype(np.int64), 0, h - 1)
    z = depth_m[vi, ui].astype(np.float64)
    z[~(z > 0)] = np.nan
    return _on_depth_edge(depth_m, ui, vi, z, cfg)


def _plane_fit_depth(depth_m: np.ndarray, uv: np.ndarray, ui: np.ndarray, vi: np.ndarray, z0: np.ndarray,
                     cfg: FeatureConfig) -> np.ndarray:
    """Depth at each keypoint ``(N,)`` from a plane fit in inverse depth over its patch (see
    :class:`FeatureConfig`); ``z0 (N,)`` is the median depth (NaN = no depth, kept NaN)."""
    h, w = depth_m.shape
    r = cfg.depth_plane_radius_px
    offs = np.arange(-r, r + 1)
    n = len(uv)
    uu, vv = np.broadcast_arrays(ui[:, None, None] + offs[None, None, :], vi[:, None, None] + offs[None, :, None])
    uu, vv = uu.reshape(n, -1), vv.reshape(n, -1)
    inside = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
    patch = depth_m[np.clip(vv, 0, h - 1), np.clip(uu, 0, w - 1)].astype(np.float64)
    du = uu - uv[:, 0:1].astype(np.float64)  # offsets from the sub-pixel keypoint
    dv = vv - uv[:, 1:2].astype(np.float64)
    ok = inside & (patch > 0) & (np.abs(patch - z0[:, None]) <= cfg.depth_plane_gate * z0[:, None])
    wgt = ok.astype(np.float64)
    inv = np.where(ok, 1.0 / np.where(patch > 0, patch, 1.0), 0.0)
    # weighted least squares  1/z = a + b du + c dv  per keypoint: 3x3 normal equations, batched
    M = np.empty((n, 3, 3))
    M[:, 0, 0] = wgt.sum(1)
    M[:, 0, 1] = M[:, 1, 0] = (wgt * du).sum(1)
    M[:, 0, 2] = M[:, 2, 0] = (wgt * dv).sum(1)
    M[:, 1, 1] = (wgt * du * du).sum(1)
    M[:, 1, 2] = M[:, 2, 1] = (wgt * du * dv).sum(1)
    M[:, 2, 2] = (wgt * dv * dv).sum(1)
    rhs = np.stack([inv.sum(1), (inv * du).sum(1), (inv * dv).sum(1)], axis=1)
    fit = (M[:, 0, 0] >= cfg.depth_plane_min_pixels) & np.isfinite(z0)
    z = z0.copy()
    if fit.any():
        Mf = M[fit]
        det = np.linalg.det(Mf)
        good = np.abs(det) > 1e-9 * np.maximum(Mf[:, 0, 0], 1.0) ** 3
        idx = np.flatnonzero(fit)[good]
        a = np.linalg.solve(Mf[good], rhs[fit][good][:, :, None])[:, 0, 0]
        zf = np.where(a > 0, 1.0 / np.where(a > 0, a, 1.0), np.nan)
        keep = np.isfinite(zf) & (np.abs(zf - z0[idx]) <= cfg.depth_plane_gate * z0[idx])
        z[idx[keep]] = zf[keep]
    return z
