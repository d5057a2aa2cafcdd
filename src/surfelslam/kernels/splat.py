"""Z-buffer splatting of screen-space discs, for map figures (not the tracking path).

The caller projects the surfels (perspective or orthographic) in numpy; this kernel only does the per-pixel
work. A disc covers the pixels within ``radius_px`` of its centre, plus always the pixel its centre falls in.
Its depth varies across the disc with the surfel's plane (``dz_du``, ``dz_dv`` metres per pixel, clamped to
``+-dz_max_m``), so two overlapping surfels of one surface do not fight. Pixel centres are at integer
coordinates, images ``[v, u]``. :func:`splat_discs_ref` is the brute-force numpy reference.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def splat_discs(u_px, v_px, depth_m, radius_px, dz_du, dz_dv, dz_max_m, depth_buf, index_buf):
    """Draw discs nearest-first per pixel into ``depth_buf`` / ``index_buf`` (ties keep the earlier disc).

    Args:
        u_px, v_px, depth_m, radius_px, dz_du, dz_dv, dz_max_m: float64 ``(N,)`` disc centres (pixels), centre
            depth (metres, smaller is nearer), radius (pixels), depth slope (metres per pixel) and its clamp.
        depth_buf: float64 ``(H, W)`` initialised to +inf; index_buf: int32 ``(H, W)`` initialised to -1.
    """
    H, W = depth_buf.shape
    for i in range(u_px.shape[0]):
        u = u_px[i]
        v = v_px[i]
        r = radius_px[i]
        ui = int(math.floor(u + 0.5))
        vi = int(math.floor(v + 0.5))
        u0 = min(int(math.ceil(u - r)), ui)
        u1 = max(int(math.floor(u + r)), ui)
        v0 = min(int(math.ceil(v - r)), vi)
        v1 = max(int(math.floor(v + r)), vi)
        if u1 < 0 or v1 < 0 or u0 >= W or v0 >= H:
            continue
        u0 = max(u0, 0)
        v0 = max(v0, 0)
        u1 = min(u1, W - 1)
        v1 = min(v1, H - 1)
        r2 = r * r
        z0 = depth_m[i]
        su = dz_du[i]
        sv = dz_dv[i]
        zmax = dz_max_m[i]
        for pv in range(v0, v1 + 1):
            dv = pv - v
            for pu in range(u0, u1 + 1):
                du = pu - u
                if du * du + dv * dv > r2 and not (pu == ui and pv == vi):
                    continue
                z = z0 + min(max(su * du + sv * dv, -zmax), zmax)
                if z < depth_buf[pv, pu]:
                    depth_buf[pv, pu] = z
                    index_buf[pv, pu] = i


def splat_discs_ref(u_px, v_px, depth_m, radius_px, dz_du, dz_dv, dz_max_m, shape):
    """Brute-force reference of :func:`splat_discs`: every disc against every pixel, argmin of depth.

    Returns ``(depth (H, W) float64, index (H, W) int32)``; memory is ``N * H * W``, so tiny inputs only.
    """
    H, W = shape
    pv, pu = np.mgrid[0:H, 0:W]
    du = pu[None] - u_px[:, None, None]
    dv = pv[None] - v_px[:, None, None]
    centre = (pu[None] == np.floor(u_px + 0.5)[:, None, None]) & (pv[None] == np.floor(v_px + 0.5)[:, None, None])
    cover = (du * du + dv * dv <= (radius_px * radius_px)[:, None, None]) | centre
    zmax = dz_max_m[:, None, None]
    z = depth_m[:, None, None] + np.minimum(np.maximum(dz_du[:, None, None] * du + dz_dv[:, None, None] * dv,
                                                       -zmax), zmax)
    z = np.where(cover, z, np.inf)
    index = np.argmin(z, axis=0).astype(np.int32)  # first minimum: the earlier disc on ties
    depth = np.take_along_axis(z, index[None].astype(np.int64), axis=0)[0]
    index[~np.isfinite(depth)] = -1
    return depth, index
