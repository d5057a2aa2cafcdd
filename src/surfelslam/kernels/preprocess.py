"""Numba kernels for depth preprocessing: bilateral filter, back-projection, normals, pyramid.

Every kernel writes into a caller-provided output array (no allocation in the hot path) and has a
plain-numpy reference ``<kernel>_ref`` beside it that returns a new array with identical values
(up to float rounding). The kernels parallelise over image rows with ``prange``; each output pixel
depends only on the input, so the result does not depend on the thread count.

Conventions: images ``[v, u]``; vertex / normal maps are ``(H, W, 3)`` float32 in the camera frame;
an invalid pixel has depth 0, vertex ``(0, 0, 0)`` and normal ``(0, 0, 0)``.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from surfelslam.kernels.threads import dual_njit

# Only fused multiply-add contraction (no reassociation): results differ from the numpy references
# by float rounding only.
_FASTMATH = {"contract"}

# ----------------------------------------------------------------------------------------------
# Bilateral filter
# ----------------------------------------------------------------------------------------------


def bilateral_tables(radius_px: int, sigma_px: float, sigma_depth_m: float, lut_size: int = 256):
    """Spatial weights ``(2r+1, 2r+1)`` and a range-weight lookup table.

    The range weight ``exp(-d^2 / (2 sigma_depth^2))`` is tabulated for ``|d|`` in
    ``[0, 3 sigma_depth)`` in ``lut_size`` steps; depth differences beyond ``3 sigma_depth`` get weight 0.

    Returns:
        ``(spatial (2r+1, 2r+1) float64, range_lut (lut_size,) float64, lut_step_m float)``.
    """
    d = np.arange(-radius_px, radius_px + 1, dtype=np.float64)
    spatial = np.exp(-(d[:, None] ** 2 + d[None, :] ** 2) / (2.0 * sigma_px**2))
    step = 3.0 * sigma_depth_m / lut_size
    centres = (np.arange(lut_size) + 0.5) * step
    lut = np.exp(-(centres**2) / (2.0 * sigma_depth_m**2))
    return spatial, lut, step


@dual_njit(fastmath=_FASTMATH, error_model="numpy")
def bilateral_filter(depth_m, min_depth_m, max_depth_m, spatial, range_lut, lut_step_m, out):
    """Edge-preserving depth smoothing that ignores invalid pixels.

    Args:
        depth_m: ``(H, W)`` float32 metres; pixels outside ``[min_depth_m, max_depth_m]`` are invalid.
        spatial: ``(2r+1, 2r+1)`` spatial weights; range_lut / lut_step_m: see :func:`bilateral_tables`.
        out: ``(H, W)`` float32, receives the filtered depth; invalid pixels (of the input) stay 0.
    """
    H, W = depth_m.shape
    r = spatial.shape[0] // 2
    nlut = range_lut.shape[0]
    inv_step = 1.0 / lut_step_m
    for v in prange(H):
        for u in range(W):
            z0 = np.float64(depth_m[v, u])
            if not (z0 >= min_depth_m and z0 <= max_depth_m):
                out[v, u] = 0.0
                continue
            sw = 0.0
            sz = 0.0
            for dv in range(-r, r + 1):
                vv = v + dv
                if vv < 0 or vv >= H:
                    continue
                for du in range(-r, r + 1):
                    uu = u + du
                    if uu < 0 or uu >= W:
                        continue
                    z = np.float64(depth_m[vv, uu])
                    if not (z >= min_depth_m and z <= max_depth_m):
                        continue
                    k = int(abs(z - z0) * inv_step)
                    if k >= nlut:
                        continue
                    w = spatial[dv + r, du + r] * range_lut[k]
                    sw += w
                    sz += w * z
            out[v, u] = sz / sw


def bilateral_filter_ref(depth_m, min_depth_m, max_depth_m, spatial, range_lut, lut_step_m):
    """Numpy reference of :func:`bilateral_filter`; returns a new ``(H, W)`` float32 array."""
    H, W = depth_m.shape
    r = spatial.shape[0] // 2
    z0 = depth_m.astype(np.float64)
    valid0 = (z0 >= min_depth_m) & (z0 <= max_depth_m)
    pad = np.pad(np.where(valid0, z0, np.nan), r, constant_values=np.nan)
    sw = np.zeros((H, W))
    sz = np.zeros((H, W))
    for dv in range(-r, r + 1):  # loops over the (2r+1)^2 window offsets, not over pixels
        for du in range(-r, r + 1):
            z = pad[r + dv : r + dv + H, r + du : r + du + W]
            k = np.floor(np.abs(np.nan_to_num(z, nan=np.inf) - z0) * (1.0 / lut_step_m))
            ok = np.isfinite(z) & (k < len(range_lut))
            w = np.where(ok, spatial[dv + r, du + r] * range_lut[np.where(ok, k, 0).astype(np.int64)], 0.0)
            sw += w
            sz += w * np.nan_to_num(z)
    out = np.where(valid0, sz / np.where(sw > 0, sw, 1.0), 0.0)
    return out.astype(np.float32)


# ----------------------------------------------------------------------------------------------
# Back-projection
# ----------------------------------------------------------------------------------------------


@dual_njit(fastmath=_FASTMATH, error_model="numpy")
def depth_to_vertex(depth_m, fx, fy, cx, cy, min_depth_m, max_depth_m, out):
    """Depth ``(H, W)`` -> vertex map ``out (H, W, 3)`` float32; depth outside the range gives 0.

    ``x = (u - cx) / fx * z``, ``y = (v - cy) / fy * z`` (``fy`` may be negative).
    """
    H, W = depth_m.shape
    for v in prange(H):
        for u in range(W):
            z = depth_m[v, u]
            if z >= min_depth_m and z <= max_depth_m:
                out[v, u, 0] = (u - cx) / fx * z
                out[v, u, 1] = (v - cy) / fy * z
                out[v, u, 2] = z
            else:
                out[v, u, 0] = 0.0
                out[v, u, 1] = 0.0
                out[v, u, 2] = 0.0


def depth_to_vertex_ref(depth_m, fx, fy, cx, cy, min_depth_m, max_depth_m):
    """Numpy reference of :func:`depth_to_vertex`; returns ``(H, W, 3)`` float32."""
    H, W = depth_m.shape
    v, u = np.mgrid[0:H, 0:W]
    z = depth_m.astype(np.float64)
    ok = (z >= min_depth_m) & (z <= max_depth_m)
    z = np.where(ok, z, 0.0)
    return np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=-1).astype(np.float32)


# ----------------------------------------------------------------------------------------------
# Normals
# ----------------------------------------------------------------------------------------------


@dual_njit(fastmath=_FASTMATH, error_model="numpy")
def vertex_normals(vertex, max_depth_jump_m, out, step=1):
    """Normal map from central differences of a vertex map, ``step`` pixels either side.

    ``n = (V[v, u+s] - V[v, u-s]) x (V[v+s, u] - V[v-s, u])`` (``s = step``), normalised and flipped so that
    ``n . p < 0`` (it faces the camera, whatever the sign of ``fy``). The normal is invalid (zeros) within ``s``
    pixels of the image border, when the pixel or any of its 4 neighbours is invalid (``z <= 0``), or when a
    neighbour's depth differs from the pixel's by more than ``s * max_depth_jump_m``.

    Why a step: a structured-light sensor quantises disparity, so a slanted surface comes out as a staircase of
    constant-depth treads a few pixels wide; 1-pixel differences give the treads' normal (the optical axis), which
    fuses into the map and pins the camera's motion along its axis. Differences across ``s = 2`` pixels span the
    risers too.

    Args:
        vertex: ``(H, W, 3)`` float32 camera-frame points, ``z <= 0`` = invalid.
        out: ``(H, W, 3)`` float32 unit normals.
        step: ``s``, pixels (>= 1).
    """
    H, W = vertex.shape[0], vertex.shape[1]
    s = step
    jump = max_depth_jump_m * s
    for v in prange(H):
        for u in range(W):
            out[v, u, 0] = 0.0
            out[v, u, 1] = 0.0
            out[v, u, 2] = 0.0
            if v < s or v >= H - s or u < s or u >= W - s:
                continue
            z = vertex[v, u, 2]
            if z <= 0.0:
                continue
            zl = vertex[v, u - s, 2]
            zr = vertex[v, u + s, 2]
            zu = vertex[v - s, u, 2]
            zd = vertex[v + s, u, 2]
            if zl <= 0.0 or zr <= 0.0 or zu <= 0.0 or zd <= 0.0:
                continue
            if abs(zl - z) > jump or abs(zr - z) > jump or abs(zu - z) > jump or abs(zd - z) > jump:
                continue
            ax = np.float64(vertex[v, u + s, 0]) - vertex[v, u - s, 0]
            ay = np.float64(vertex[v, u + s, 1]) - vertex[v, u - s, 1]
            az = np.float64(zr) - zl
            bx = np.float64(vertex[v + s, u, 0]) - vertex[v - s, u, 0]
            by = np.float64(vertex[v + s, u, 1]) - vertex[v - s, u, 1]
            bz = np.float64(zd) - zu
            nx = ay * bz - az * by
            ny = az * bx - ax * bz
            nz = ax * by - ay * bx
            norm = np.sqrt(nx * nx + ny * ny + nz * nz)
            if norm <= 0.0:
                continue
            inv = 1.0 / norm
            if nx * vertex[v, u, 0] + ny * vertex[v, u, 1] + nz * z > 0.0:
                inv = -inv
            out[v, u, 0] = nx * inv
            out[v, u, 1] = ny * inv
            out[v, u, 2] = nz * inv


def vertex_normals_ref(vertex, max_depth_jump_m, step=1):
    """Numpy reference of :func:`vertex_normals`; returns ``(H, W, 3)`` float32."""
    V = vertex.astype(np.float64)
    H, W = V.shape[:2]
    s = step
    out = np.zeros((H, W, 3))
    c = V[s:-s, s:-s]
    left, right, up, down = V[s:-s, : -2 * s], V[s:-s, 2 * s :], V[: -2 * s, s:-s], V[2 * s :, s:-s]
    ok = c[..., 2] > 0
    for nb in (left, right, up, down):
        ok &= (nb[..., 2] > 0) & (np.abs(nb[..., 2] - c[..., 2]) <= max_depth_jump_m * s)
    n = np.cross(right - left, down - up)
    norm = np.linalg.norm(n, axis=-1)
    ok &= norm > 0
    sign = np.where(np.sum(n * c, axis=-1) > 0, -1.0, 1.0)
    n = n * (sign / np.where(ok, norm, 1.0))[..., None]
    out[s:-s, s:-s] = np.where(ok[..., None], n, 0.0)
    return out.astype(np.float32)


# ----------------------------------------------------------------------------------------------
# Pyramid (2x2 block averaging)
# ----------------------------------------------------------------------------------------------


@njit(cache=True, nogil=True, fastmath=_FASTMATH, error_model="numpy")
def _block_sum(vertex, values, vo, uo, max_depth_diff_m):
    """Sum of ``values`` over the 2x2 block ``(vo, uo)``'s valid points within ``max_depth_diff_m`` of the
    block's nearest valid depth; returns ``(sx, sy, sz, count)`` (``count == 0``: no valid point)."""
    zmin = np.inf
    for dv in range(2):
        for du in range(2):
            z = vertex[2 * vo + dv, 2 * uo + du, 2]
            if z > 0.0 and z < zmin:
                zmin = z
    sx = 0.0
    sy = 0.0
    sz = 0.0
    cnt = 0
    if zmin < np.inf:
        for dv in range(2):
            for du in range(2):
                z = vertex[2 * vo + dv, 2 * uo + du, 2]
                if z > 0.0 and z - zmin <= max_depth_diff_m:
                    sx += values[2 * vo + dv, 2 * uo + du, 0]
                    sy += values[2 * vo + dv, 2 * uo + du, 1]
                    sz += values[2 * vo + dv, 2 * uo + du, 2]
                    cnt += 1
    return sx, sy, sz, cnt


@dual_njit(fastmath=_FASTMATH, error_model="numpy")
def downsample_vertex(vertex, max_depth_diff_m, out):
    """Halve a vertex map by averaging 2x2 blocks of camera-frame points.

    Output pixel ``(u', v')`` covers input pixels ``2u'..2u'+1`` x ``2v'..2v'+1``; it is the mean of
    the block's valid points whose depth is within ``max_depth_diff_m`` of the block's smallest valid
    depth (so foreground and background are never mixed). A block without valid points is invalid.
    A full valid block on a plane gives the point seen at the block centre ``(2u'+0.5, 2v'+0.5)``.

    Args:
        vertex: ``(H, W, 3)`` float32. out: ``(H // 2, W // 2, 3)`` float32.
    """
    Ho, Wo = out.shape[0], out.shape[1]
    for vo in prange(Ho):
        for uo in range(Wo):
            sx, sy, sz, cnt = _block_sum(vertex, vertex, vo, uo, max_depth_diff_m)
            if cnt > 0:
                out[vo, uo, 0] = sx / cnt
                out[vo, uo, 1] = sy / cnt
                out[vo, uo, 2] = sz / cnt
            else:
                out[vo, uo, 0] = 0.0
                out[vo, uo, 1] = 0.0
                out[vo, uo, 2] = 0.0


@dual_njit(fastmath=_FASTMATH, error_model="numpy")
def downsample_depth(depth_m, min_depth_m, max_depth_m, max_depth_diff_m, out):
    """Halve a raw depth image by averaging 2x2 blocks.

    Output pixel ``(u', v')`` is the mean of the block's valid depths (in ``[min_depth_m, max_depth_m]``)
    within ``max_depth_diff_m`` of the block's *reference* depth, its first valid pixel in the order top-left,
    top-right, bottom-left, bottom-right; 0 when the block has none. Foreground and background are never mixed.
    Back-projected with the halved intrinsics (:func:`surfelslam.tracking.preprocess.halve_intrinsics`) it
    gives the block-centre point of a fronto-parallel surface.

    The reference is a pixel chosen by position, not by value, so that the window is centred on a random draw
    of the noise and the mean is unbiased. Referencing the block's *smallest* depth (as
    :func:`downsample_vertex` does on filtered maps) cuts off the far tail of raw Kinect noise (sigma 2.6 cm at
    4 m, against the 5 cm window) and pulls distant surfaces towards the camera, which biases keyframe-to-keyframe
    ICP on such depth by millimetres.

    Args:
        depth_m: ``(H, W)`` float32 metres. out: ``(H // 2, W // 2)`` float32.
    """
    Ho, Wo = out.shape
    for vo in prange(Ho):
        for uo in range(Wo):
            zref = -1.0
            for dv in range(2):
                for du in range(2):
                    z = depth_m[2 * vo + dv, 2 * uo + du]
                    if zref < 0.0 and z >= min_depth_m and z <= max_depth_m:
                        zref = z
            s = 0.0
            cnt = 0
            if zref > 0.0:
                for dv in range(2):
                    for du in range(2):
                        z = depth_m[2 * vo + dv, 2 * uo + du]
                        if z >= min_depth_m and z <= max_depth_m and abs(z - zref) <= max_depth_diff_m:
                            s += z
                            cnt += 1
            out[vo, uo] = s / cnt if cnt > 0 else 0.0


def downsample_depth_ref(depth_m, min_depth_m, max_depth_m, max_depth_diff_m):
    """Numpy reference of :func:`downsample_depth`; returns ``(H // 2, W // 2)`` float32."""
    H, W = depth_m.shape[0] // 2 * 2, depth_m.shape[1] // 2 * 2
    z = depth_m[:H, :W].astype(np.float64)
    blocks = z.reshape(H // 2, 2, W // 2, 2).transpose(0, 2, 1, 3).reshape(H // 2, W // 2, 4)
    valid = (blocks >= min_depth_m) & (blocks <= max_depth_m)
    zref = np.take_along_axis(blocks, np.argmax(valid, axis=-1)[..., None], axis=-1)  # first valid (or any: unused)
    sel = valid & (np.abs(blocks - zref) <= max_depth_diff_m)
    cnt = sel.sum(axis=-1)
    s = np.sum(np.where(sel, blocks, 0.0), axis=-1)
    return np.where(cnt > 0, s / np.maximum(cnt, 1), 0.0).astype(np.float32)


def _block_selection_ref(vertex, max_depth_diff_m):
    H, W = vertex.shape[0] // 2 * 2, vertex.shape[1] // 2 * 2
    V = vertex[:H, :W].astype(np.float64)
    blocks = V.reshape(H // 2, 2, W // 2, 2, 3).transpose(0, 2, 1, 3, 4).reshape(H // 2, W // 2, 4, 3)
    z = blocks[..., 2]
    valid = z > 0
    zmin = np.min(np.where(valid, z, np.inf), axis=-1, keepdims=True)
    sel = valid & (z - zmin <= max_depth_diff_m)
    return blocks, sel


def downsample_vertex_ref(vertex, max_depth_diff_m):
    """Numpy reference of :func:`downsample_vertex`; returns ``(H // 2, W // 2, 3)`` float32."""
    blocks, sel = _block_selection_ref(vertex, max_depth_diff_m)
    cnt = sel.sum(axis=-1)
    s = np.sum(np.where(sel[..., None], blocks, 0.0), axis=-2)
    return np.where(cnt[..., None] > 0, s / np.maximum(cnt, 1)[..., None], 0.0).astype(np.float32)


@dual_njit(fastmath=_FASTMATH, error_model="numpy")
def downsample_normal(vertex, normal, max_depth_diff_m, out):
    """Halve a normal map with the same block selection as :func:`downsample_vertex`.

    The selected normals (those with a non-zero normal among the block's selected points) are summed
    and renormalised; a block whose selection has no valid normal gets ``(0, 0, 0)``.

    Args:
        vertex, normal: ``(H, W, 3)`` float32. out: ``(H // 2, W // 2, 3)`` float32.
    """
    Ho, Wo = out.shape[0], out.shape[1]
    for vo in prange(Ho):
        for uo in range(Wo):
            sx, sy, sz, _ = _block_sum(vertex, normal, vo, uo, max_depth_diff_m)
            norm = np.sqrt(sx * sx + sy * sy + sz * sz)
            if norm > 0.0:
                out[vo, uo, 0] = sx / norm
                out[vo, uo, 1] = sy / norm
                out[vo, uo, 2] = sz / norm
            else:
                out[vo, uo, 0] = 0.0
                out[vo, uo, 1] = 0.0
                out[vo, uo, 2] = 0.0


def downsample_normal_ref(vertex, normal, max_depth_diff_m):
    """Numpy reference of :func:`downsample_normal`; returns ``(H // 2, W // 2, 3)`` float32."""
    _, sel = _block_selection_ref(vertex, max_depth_diff_m)
    H, W = sel.shape[0] * 2, sel.shape[1] * 2
    N = normal[:H, :W].astype(np.float64)
    nb = N.reshape(H // 2, 2, W // 2, 2, 3).transpose(0, 2, 1, 3, 4).reshape(H // 2, W // 2, 4, 3)
    s = np.sum(np.where(sel[..., None], nb, 0.0), axis=-2)
    norm = np.linalg.norm(s, axis=-1, keepdims=True)
    return np.where(norm > 0, s / np.where(norm > 0, norm, 1.0), 0.0).astype(np.float32)


@dual_njit(fastmath=_FASTMATH, error_model="numpy")
def downsample_vertex_normal(vertex, normal, max_depth_diff_m, vertex_out, normal_out):
    """:func:`downsample_vertex` and :func:`downsample_normal` in one pass (the block selection is made once).

    Args:
        vertex, normal: ``(H, W, 3)`` float32. vertex_out, normal_out: ``(H // 2, W // 2, 3)`` float32.
    The outputs are identical to those of the two separate kernels (references: their ``_ref``).
    """
    Ho, Wo = vertex_out.shape[0], vertex_out.shape[1]
    for vo in prange(Ho):
        for uo in range(Wo):
            zmin = np.inf
            for dv in range(2):
                for du in range(2):
                    z = vertex[2 * vo + dv, 2 * uo + du, 2]
                    if z > 0.0 and z < zmin:
                        zmin = z
            sx = 0.0
            sy = 0.0
            sz = 0.0
            nx = 0.0
            ny = 0.0
            nz = 0.0
            cnt = 0
            if zmin < np.inf:
                for dv in range(2):
                    for du in range(2):
                        z = vertex[2 * vo + dv, 2 * uo + du, 2]
                        if z > 0.0 and z - zmin <= max_depth_diff_m:
                            sx += vertex[2 * vo + dv, 2 * uo + du, 0]
                            sy += vertex[2 * vo + dv, 2 * uo + du, 1]
                            sz += vertex[2 * vo + dv, 2 * uo + du, 2]
                            nx += normal[2 * vo + dv, 2 * uo + du, 0]
                            ny += normal[2 * vo + dv, 2 * uo + du, 1]
                            nz += normal[2 * vo + dv, 2 * uo + du, 2]
                            cnt += 1
            if cnt > 0:
                vertex_out[vo, uo, 0] = sx / cnt
                vertex_out[vo, uo, 1] = sy / cnt
                vertex_out[vo, uo, 2] = sz / cnt
            else:
                vertex_out[vo, uo, 0] = 0.0
                vertex_out[vo, uo, 1] = 0.0
                vertex_out[vo, uo, 2] = 0.0
            norm = np.sqrt(nx * nx + ny * ny + nz * nz)
            if norm > 0.0:
                normal_out[vo, uo, 0] = nx / norm
                normal_out[vo, uo, 1] = ny / norm
                normal_out[vo, uo, 2] = nz / norm
            else:
                normal_out[vo, uo, 0] = 0.0
                normal_out[vo, uo, 1] = 0.0
                normal_out[vo, uo, 2] = 0.0
