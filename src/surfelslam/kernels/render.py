"""Surfel rendering kernels: frustum culling of blocks, splatting z-buffer, attribute fill, index map.

Conventions: pixel centres at integer coordinates, images ``[v, u]``; ``u = fx x / z + cx`` with ``fy``
possibly negative (no sign assumption anywhere). Each kernel has a numpy reference ``<name>_ref``.
Depths in the z-buffers are float64 so that kernel and reference compare identically.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from surfelslam.kernels.threads import dual_njit

_GRAZING_COS = 1e-3  # |n . ray| below this: the splat plane is edge-on, only the centre pixel is drawn
# Rounding slack (metres) of the splat's early outs, which only skip what its exact tests reject anyway: float64 dot
# products of coordinates below 1 km are off by < 1e-12 m, so 1e-9 m leaves a 1000x margin
_EARLY_OUT_SLACK_M = 1e-9
# How much a cube of blocks (:func:`cull_blocks_grouped`) is grown beyond the blocks' margin (metres): its blocks'
# corners then lie inside it by at least this, so that no rounding lets a cube fail a test one of its blocks passes
_GROUP_SLACK_M = 1e-3


# ---------------------------------------------------------------------------------------------------- culling
@njit(cache=True, nogil=True)
def cull_blocks_grouped(group_ijk, group_start, group_blocks, group_edge, n_in_groups, block_ijk, nb, block_size,
                        margin, R, t, fx, fy, cx, cy, umin, umax, vmin, vmax, near, far, reach, visible_out):
    """Frustum test of block boxes: ``visible_out[b] = 1`` unless all 8 corners lie outside one face, or the box's
    bounding sphere lies farther than ``reach`` (metres) from the camera centre (reference: :func:`cull_blocks_ref`).

    The blocks ``0..n_in_groups-1`` are grouped in cubes, and a cube whose box (grown by ``margin`` and
    :data:`_GROUP_SLACK_M`) misses the view rejects all its blocks in one test: their grown boxes lie inside it, so
    each of them would fail the same test. The blocks of the other cubes are tested one by one, as are the blocks
    from ``n_in_groups`` to ``nb``, added since the grouping.

    Args:
        group_ijk: int32 ``(G, 3)`` integer coordinates of the cubes, of edge ``group_edge`` (metres, a multiple of
            ``block_size``); cube ``g`` holds blocks ``group_blocks[group_start[g]:group_start[g + 1]]``.
        block_ijk: int32 ``(>= nb, 3)`` integer block coordinates; block ``b`` spans
            ``[ijk * block_size - margin, (ijk + 1) * block_size + margin]`` (metres, world frame).
        R, t: ``(3, 3)``, ``(3,)`` float64 world-to-camera rotation and translation.
        umin, umax, vmin, vmax: image rectangle (pixels); near, far: depth range (metres).
        reach: the distance from the camera centre within which the frustum lies (:func:`frustum_reach`; ``inf``:
            no distance test). Most blocks of a floor-sized map are far away: one distance per block rejects them,
            instead of 8 corners against 6 faces.
        visible_out: uint8 ``(>= nb,)``.

    The frustum faces are the half-spaces ``z >= near``, ``z <= far``, ``fx x + (cx - umin) z >= 0``,
    ``(umax - cx) z - fx x >= 0`` and the same for ``v`` with ``fy`` (valid for either sign of ``fy``).
    """
    grow = margin + _GROUP_SLACK_M
    for g in range(group_ijk.shape[0]):
        in_view = _box_visible(group_ijk[g, 0], group_ijk[g, 1], group_ijk[g, 2], group_edge, grow, R, t, fx, fy,
                               cx, cy, umin, umax, vmin, vmax, near, far, reach)
        for k in range(group_start[g], group_start[g + 1]):
            b = group_blocks[k]
            visible_out[b] = 0 if in_view == 0 else _box_visible(
                block_ijk[b, 0], block_ijk[b, 1], block_ijk[b, 2], block_size, margin, R, t, fx, fy, cx, cy, umin,
                umax, vmin, vmax, near, far, reach)
    for b in range(n_in_groups, nb):
        visible_out[b] = _box_visible(block_ijk[b, 0], block_ijk[b, 1], block_ijk[b, 2], block_size, margin, R, t,
                                      fx, fy, cx, cy, umin, umax, vmin, vmax, near, far, reach)


@njit(cache=True, nogil=True)
def _box_visible(i, j, k, edge, grow, R, t, fx, fy, cx, cy, umin, umax, vmin, vmax, near, far, reach):
    """1 unless the box ``[(i, j, k) * edge - grow, (i, j, k) * edge + edge + grow]`` (metres) lies outside one face
    of the frustum or its bounding sphere farther than ``reach`` from the camera centre
    (:func:`cull_blocks_grouped`)."""
    half = 0.5 * edge
    sphere = math.sqrt(3.0) * (half + grow)  # bounding-sphere radius of a grown box
    mx = i * edge + half
    my = j * edge + half
    mz = k * edge + half
    dx = R[0, 0] * mx + R[0, 1] * my + R[0, 2] * mz + t[0]
    dy = R[1, 0] * mx + R[1, 1] * my + R[1, 2] * mz + t[1]
    dz = R[2, 0] * mx + R[2, 1] * my + R[2, 2] * mz + t[2]
    if dx * dx + dy * dy + dz * dz > (reach + sphere) * (reach + sphere):
        return 0
    o0 = o1 = o2 = o3 = o4 = o5 = 0
    for c in range(8):
        wx = (i + (c & 1)) * edge + (grow if (c & 1) else -grow)
        wy = (j + ((c >> 1) & 1)) * edge + (grow if ((c >> 1) & 1) else -grow)
        wz = (k + ((c >> 2) & 1)) * edge + (grow if ((c >> 2) & 1) else -grow)
        x = R[0, 0] * wx + R[0, 1] * wy + R[0, 2] * wz + t[0]
        y = R[1, 0] * wx + R[1, 1] * wy + R[1, 2] * wz + t[1]
        z = R[2, 0] * wx + R[2, 1] * wy + R[2, 2] * wz + t[2]
        o0 += z < near
        o1 += z > far
        o2 += fx * x + (cx - umin) * z < 0
        o3 += (umax - cx) * z - fx * x < 0
        o4 += fy * y + (cy - vmin) * z < 0
        o5 += (vmax - cy) * z - fy * y < 0
    return 0 if o0 == 8 or o1 == 8 or o2 == 8 or o3 == 8 or o4 == 8 or o5 == 8 else 1


@njit(cache=True, nogil=True)
def lod_strides(visible, nb, block_ijk, count, block_size, R, t, fx, fy, per_px, max_stride):
    """Level of detail: for each visible block ``b < nb`` (``visible[b] != 0``), the stride at which its surfels are
    drawn, written into ``visible[b]`` (1: all of them, ``k``: one of each ``k`` of its grouped surfels, see
    :func:`surfelslam.kernels.surfels.gather_candidates`).

    A block holding ``count[b]`` surfels whose face covers ``A = (block_size |fx| / z) (block_size |fy| / z)`` pixels
    at the camera depth ``z`` of its centre puts about ``count[b] / A`` surfels on each of them (far blocks of a floor:
    several, of which the z-buffer keeps one). The stride is ``floor(count[b] / (A per_px))``, within
    ``[1, max_stride]``. Blocks whose centre lies within ``block_size`` of the camera plane keep stride 1.

    Args:
        visible: uint8 ``(>= nb,)`` from :func:`cull_blocks_grouped`, modified in place.
        count: int32 ``(>= nb,)`` surfels grouped in each block.
        R, t: float64 world-to-camera rotation and translation.
        per_px: surfels per pixel kept (> 0).
    """
    half = 0.5 * block_size
    area_z2 = block_size * block_size * abs(fx) * abs(fy)  # the face's pixel area times z^2
    for b in range(nb):
        if visible[b] == 0:
            continue
        mx = block_ijk[b, 0] * block_size + half
        my = block_ijk[b, 1] * block_size + half
        mz = block_ijk[b, 2] * block_size + half
        z = R[2, 0] * mx + R[2, 1] * my + R[2, 2] * mz + t[2]
        if z <= block_size:
            continue
        k = count[b] * z * z / (area_z2 * per_px)
        visible[b] = int(min(max(k, 1.0), max_stride))


def lod_strides_ref(visible, nb, block_ijk, count, block_size, R, t, fx, fy, per_px, max_stride):
    """Numpy reference of :func:`lod_strides`; returns the new ``visible[:nb]``."""
    centre = block_ijk[:nb].astype(np.float64) * block_size + 0.5 * block_size
    z = R[2, 0] * centre[:, 0] + R[2, 1] * centre[:, 1] + R[2, 2] * centre[:, 2] + t[2]
    k = count[:nb] * z * z / (block_size * block_size * abs(fx) * abs(fy) * per_px)
    stride = np.minimum(np.maximum(k, 1.0), max_stride).astype(np.uint8)
    return np.where((visible[:nb] != 0) & (z > block_size), stride, visible[:nb]).astype(np.uint8)


def frustum_reach(fx, fy, cx, cy, umin, umax, vmin, vmax, far):
    """Distance (metres) from the camera centre of the farthest point of the frustum (image rectangle ``[umin, umax]
    x [vmin, vmax]`` pixels, depth up to ``far``): a far-plane corner's."""
    tx = max(abs((umin - cx) / fx), abs((umax - cx) / fx))
    ty = max(abs((vmin - cy) / fy), abs((vmax - cy) / fy))
    return far * math.sqrt(1.0 + tx * tx + ty * ty)


def cull_blocks_ref(block_ijk, nb, block_size, margin, R, t, fx, fy, cx, cy, umin, umax, vmin, vmax, near, far,
                    reach=math.inf):
    """Numpy reference of :func:`cull_blocks_grouped` (block by block); returns uint8 ``(nb,)``."""
    bits = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.float64)  # (8, 3)
    lo = block_ijk[:nb].astype(np.float64)[:, None, :] * block_size - margin
    corners = lo + bits[None] * (block_size + 2 * margin)  # (nb, 8, 3)
    centre = block_ijk[:nb].astype(np.float64) * block_size + 0.5 * block_size
    dist = np.linalg.norm(centre @ R.T + t, axis=1)
    cam = corners @ R.T + t
    x, y, z = cam[..., 0], cam[..., 1], cam[..., 2]
    faces = [
        z < near, z > far, fx * x + (cx - umin) * z < 0, (umax - cx) * z - fx * x < 0,
        fy * y + (cy - vmin) * z < 0, (vmax - cy) * z - fy * y < 0,
    ]
    culled = dist > reach + math.sqrt(3.0) * (0.5 * block_size + margin)
    for f in faces:
        culled |= f.all(axis=1)
    return (~culled).astype(np.uint8)


# ---------------------------------------------------------------------------------------------------- splats
@njit(cache=True, nogil=True)
def splat_zbuffer(cand, m, pos, nrm, rad, conf, first_seen, min_conf, young_from_frame, R, t, fx, fy, cx, cy,
                  max_splat_px, near, far, cull_back, band_rel, depth_buf, index_buf):
    """Z-buffer of surfel discs (camera-frame depth of the ray/disc intersection) into ``(H, W)`` buffers.

    Args:
        cand: int32 ``(>= m,)`` surfel indices to draw, in this order (ties keep the earlier one).
        pos, nrm: float32 ``(N, 3)`` world frame; rad: float32 ``(N,)`` metres; conf: float32 ``(N,)``.
        first_seen: int32 ``(N,)``; a surfel is drawn when ``conf >= min_conf`` or
            ``first_seen >= young_from_frame`` (young surfels are drawn while they gather confidence).
        R, t: float64 world-to-camera rotation ``(3, 3)`` and translation ``(3,)``.
        max_splat_px: cap of the footprint radius in pixels.
        near, far: depth range in metres; cull_back: skip surfels whose normal faces away from the camera.
        band_rel: with ``band_rel > 0``, a second pass: among the discs whose depth at a pixel lies within
            ``(1 + band_rel)`` times the nearest one's, the most confident is drawn (ties: the earlier in ``cand``).
            The nearest of several noisy surfels over one surface lies in front of it; the most confident one is
            the best-averaged. 0: the nearest wins.
        depth_buf: float64 ``(H, W)`` initialised to +inf; index_buf: int32 ``(H, W)`` initialised to -1.
    """
    # the z-test (zmin and best unused: depth_buf stands in for them)
    _splat_pass(cand, m, pos, nrm, rad, conf, first_seen, min_conf, young_from_frame, R, t, fx, fy, cx, cy,
                max_splat_px, near, far, cull_back, 0.0, depth_buf, depth_buf, depth_buf, index_buf)
    if band_rel > 0.0:
        best = np.full(depth_buf.shape, -1.0)
        _splat_pass(cand, m, pos, nrm, rad, conf, first_seen, min_conf, young_from_frame, R, t, fx, fy, cx, cy,
                    max_splat_px, near, far, cull_back, band_rel, depth_buf.copy(), best, depth_buf, index_buf)


@njit(cache=True, nogil=True)
def _splat_pass(cand, m, pos, nrm, rad, conf, first_seen, min_conf, young_from_frame, R, t, fx, fy, cx, cy,
                max_splat_px, near, far, cull_back, band_rel, zmin, best, depth_buf, index_buf):
    """One pass of :func:`splat_zbuffer`: the z-test (``band_rel == 0``), or the most confident disc within
    ``(1 + band_rel) zmin`` (``best``: the drawn disc's confidence per pixel, -1 where none yet)."""
    H, W = depth_buf.shape
    afx = abs(fx)
    afy = abs(fy)
    ifx = 1.0 / fx
    ify = 1.0 / fy
    # the camera centre in the world frame: n . (p - c) is the camera-frame n . p without rotating anything, so a
    # surfel facing away is dropped before its transform (the exact camera-frame test follows for the others)
    c0 = -(R[0, 0] * t[0] + R[1, 0] * t[1] + R[2, 0] * t[2])
    c1 = -(R[0, 1] * t[0] + R[1, 1] * t[1] + R[2, 1] * t[2])
    c2 = -(R[0, 2] * t[0] + R[1, 2] * t[1] + R[2, 2] * t[2])
    ztest = band_rel == 0.0
    for k in range(m):
        i = cand[k]
        if conf[i] < min_conf and first_seen[i] < young_from_frame:
            continue
        if cull_back and (nrm[i, 0] * (pos[i, 0] - c0) + nrm[i, 1] * (pos[i, 1] - c1)
                          + nrm[i, 2] * (pos[i, 2] - c2)) > _EARLY_OUT_SLACK_M:
            continue
        px = R[0, 0] * pos[i, 0] + R[0, 1] * pos[i, 1] + R[0, 2] * pos[i, 2] + t[0]
        py = R[1, 0] * pos[i, 0] + R[1, 1] * pos[i, 1] + R[1, 2] * pos[i, 2] + t[1]
        pz = R[2, 0] * pos[i, 0] + R[2, 1] * pos[i, 1] + R[2, 2] * pos[i, 2] + t[2]
        if pz < near or pz > far:
            continue
        nx = R[0, 0] * nrm[i, 0] + R[0, 1] * nrm[i, 1] + R[0, 2] * nrm[i, 2]
        ny = R[1, 0] * nrm[i, 0] + R[1, 1] * nrm[i, 1] + R[1, 2] * nrm[i, 2]
        nz = R[2, 0] * nrm[i, 0] + R[2, 1] * nrm[i, 1] + R[2, 2] * nrm[i, 2]
        npd = nx * px + ny * py + nz * pz
        if cull_back and npd >= 0.0:
            continue
        u = fx * px / pz + cx
        v = fy * py / pz + cy
        ui = int(math.floor(u + 0.5))
        vi = int(math.floor(v + 0.5))
        r = rad[i]
        rx = min(r * afx / pz, max_splat_px)
        ry = min(r * afy / pz, max_splat_px)
        u0 = min(int(math.ceil(u - rx)), ui)
        u1 = max(int(math.floor(u + rx)), ui)
        v0 = min(int(math.ceil(v - ry)), vi)
        v1 = max(int(math.floor(v + ry)), vi)
        if u1 < 0 or v1 < 0 or u0 >= W or v0 >= H:
            continue
        u0 = max(u0, 0)
        v0 = max(v0, 0)
        u1 = min(u1, W - 1)
        v1 = min(v1, H - 1)
        r2 = float(r) * float(r)
        zlow = pz - r - _EARLY_OUT_SLACK_M  # every depth this disc draws is at least pz - r
        for pv in range(v0, v1 + 1):
            dy = (pv - cy) * ify
            for pu in range(u0, u1 + 1):
                if ztest and depth_buf[pv, pu] <= zlow:  # already nearer: the z-test below cannot pass
                    continue
                dx = (pu - cx) * ifx
                centre = pu == ui and pv == vi
                nd = nx * dx + ny * dy + nz
                depth = pz
                ok = False
                if abs(nd) >= _GRAZING_COS:
                    d = npd / nd
                    ex = d * dx - px
                    ey = d * dy - py
                    ez = d - pz
                    if d >= near and ex * ex + ey * ey + ez * ez <= r2:
                        depth = d
                        ok = True
                    elif centre:  # the ray misses the disc: plane depth, kept within r of the centre's
                        depth = min(max(d, pz - r), pz + r)
                        ok = True
                elif centre:
                    ok = True
                if not ok:
                    continue
                if band_rel == 0.0:
                    if depth < depth_buf[pv, pu]:
                        depth_buf[pv, pu] = depth
                        index_buf[pv, pu] = i
                elif depth <= zmin[pv, pu] * (1.0 + band_rel) and conf[i] > best[pv, pu]:
                    best[pv, pu] = conf[i]
                    depth_buf[pv, pu] = depth
                    index_buf[pv, pu] = i


def splat_zbuffer_ref(cand, m, pos, nrm, rad, conf, first_seen, min_conf, young_from_frame, R, t, fx, fy, cx, cy,
                      max_splat_px, near, far, cull_back, band_rel, shape):
    """Numpy reference of :func:`splat_zbuffer`; returns ``(depth (H, W) float64, index (H, W) int32)``."""
    H, W = shape
    idx = cand[:m].astype(np.int64)
    keep = (conf[idx] >= min_conf) | (first_seen[idx] >= young_from_frame)
    k_order = np.arange(m)[keep]
    idx = idx[keep]
    P = pos[idx].astype(np.float64)
    N = nrm[idx].astype(np.float64)
    px = R[0, 0] * P[:, 0] + R[0, 1] * P[:, 1] + R[0, 2] * P[:, 2] + t[0]
    py = R[1, 0] * P[:, 0] + R[1, 1] * P[:, 1] + R[1, 2] * P[:, 2] + t[1]
    pz = R[2, 0] * P[:, 0] + R[2, 1] * P[:, 1] + R[2, 2] * P[:, 2] + t[2]
    nx = R[0, 0] * N[:, 0] + R[0, 1] * N[:, 1] + R[0, 2] * N[:, 2]
    ny = R[1, 0] * N[:, 0] + R[1, 1] * N[:, 1] + R[1, 2] * N[:, 2]
    nz = R[2, 0] * N[:, 0] + R[2, 1] * N[:, 1] + R[2, 2] * N[:, 2]
    npd = nx * px + ny * py + nz * pz
    ok = (pz >= near) & (pz <= far)
    if cull_back:
        ok &= npd < 0
    sel = np.flatnonzero(ok)
    idx, k_order = idx[sel], k_order[sel]
    px, py, pz, nx, ny, nz, npd = (a[sel] for a in (px, py, pz, nx, ny, nz, npd))
    u = fx * px / pz + cx
    v = fy * py / pz + cy
    ui = np.floor(u + 0.5).astype(np.int64)
    vi = np.floor(v + 0.5).astype(np.int64)
    r = rad[idx]
    rx = np.minimum(r * abs(fx) / pz, max_splat_px)
    ry = np.minimum(r * abs(fy) / pz, max_splat_px)
    u0 = np.minimum(np.ceil(u - rx).astype(np.int64), ui)
    v0 = np.minimum(np.ceil(v - ry).astype(np.int64), vi)
    u1 = np.maximum(np.floor(u + rx).astype(np.int64), ui)
    v1 = np.maximum(np.floor(v + ry).astype(np.int64), vi)
    span = int(math.ceil(max_splat_px)) + 1
    offs = np.arange(-span, span + 1)
    ou, ov = np.meshgrid(offs, offs)
    pu = ui[:, None] + ou.reshape(1, -1)
    pv = vi[:, None] + ov.reshape(1, -1)
    inbox = (pu >= u0[:, None]) & (pu <= u1[:, None]) & (pv >= v0[:, None]) & (pv <= v1[:, None])
    inbox &= (pu >= 0) & (pu < W) & (pv >= 0) & (pv < H)
    dx = (pu - cx) * (1.0 / fx)
    dy = (pv - cy) * (1.0 / fy)
    nd = nx[:, None] * dx + ny[:, None] * dy + nz[:, None]
    good = np.abs(nd) >= _GRAZING_COS
    d = np.where(good, npd[:, None] / np.where(good, nd, 1.0), 0.0)
    ex = d * dx - px[:, None]
    ey = d * dy - py[:, None]
    ez = d - pz[:, None]
    r2 = (r.astype(np.float64) ** 2)[:, None]
    hit = good & (d >= near) & (ex * ex + ey * ey + ez * ez <= r2)
    centre = (pu == ui[:, None]) & (pv == vi[:, None])
    rr = r.astype(np.float64)[:, None]
    clamped = np.minimum(np.maximum(d, pz[:, None] - rr), pz[:, None] + rr)
    depth = np.where(hit, d, np.where(good, clamped, pz[:, None]))
    ok = inbox & (hit | centre)
    ci, oi = np.nonzero(ok)
    pix = pv[ci, oi] * W + pu[ci, oi]
    dep = depth[ci, oi]
    korder = k_order[ci]
    srt = np.lexsort((korder, dep, pix))
    pix, dep, win, korder = pix[srt], dep[srt], idx[ci[srt]], korder[srt]
    depth_buf = np.full(H * W, np.inf)
    index_buf = np.full(H * W, -1, np.int32)
    _draw_first_per_pixel(pix, dep, win, depth_buf, index_buf)
    if band_rel > 0:  # the most confident within the band of the nearest, ties by candidate order
        band = dep <= depth_buf[pix] * (1.0 + band_rel)
        pix, dep, win, korder = pix[band], dep[band], win[band], korder[band]
        srt = np.lexsort((korder, -conf[win].astype(np.float64), pix))
        _draw_first_per_pixel(pix[srt], dep[srt], win[srt], depth_buf, index_buf)
    return depth_buf.reshape(H, W), index_buf.reshape(H, W)


def _draw_first_per_pixel(pix, dep, win, depth_buf, index_buf) -> None:
    """Reference helper: for entries sorted by pixel (winner first), write each pixel's first depth and surfel."""
    first = np.ones(len(pix), bool)
    first[1:] = pix[1:] != pix[:-1]
    depth_buf[pix[first]] = dep[first]
    index_buf[pix[first]] = win[first]


# ---------------------------------------------------------------------------------------------------- fill
@dual_njit()
def fill_view(index_buf, depth_buf, pos, nrm, col, conf, R, t, fx, fy, cx, cy, use_centre, vertex_out, normal_out,
              colour_out, conf_out):
    """Per pixel: camera-frame vertex, camera-frame normal, colour, confidence.

    The vertex is the winning surfel's centre ``R p + t`` when ``use_centre`` (unbiased on curved surfaces:
    a neighbour's tangent disc lies in front of a convex surface), else the disc point on the pixel ray
    (``depth_buf`` along the ray).

    Rows are independent (parallel over rows, deterministic). Empty pixels (index -1) get zeros.
    ``colour_out`` uint8 ``(H, W, 3)`` is the rounded, clipped surfel colour.
    """
    H, W = index_buf.shape
    for v in prange(H):
        dy = (v - cy) / fy
        for u in range(W):
            i = index_buf[v, u]
            if i < 0:
                for c in range(3):
                    vertex_out[v, u, c] = 0.0
                    normal_out[v, u, c] = 0.0
                    colour_out[v, u, c] = 0
                conf_out[v, u] = 0.0
                continue
            if use_centre:
                for c in range(3):
                    vertex_out[v, u, c] = R[c, 0] * pos[i, 0] + R[c, 1] * pos[i, 1] + R[c, 2] * pos[i, 2] + t[c]
            else:
                d = depth_buf[v, u]
                vertex_out[v, u, 0] = d * (u - cx) / fx
                vertex_out[v, u, 1] = d * dy
                vertex_out[v, u, 2] = d
            for c in range(3):
                normal_out[v, u, c] = R[c, 0] * nrm[i, 0] + R[c, 1] * nrm[i, 1] + R[c, 2] * nrm[i, 2]
                x = int(col[i, c] + 0.5)  # colours are averages of uint8 values: within [0, 255]
                colour_out[v, u, c] = np.uint8(x if x < 255 else 255)
            conf_out[v, u] = conf[i]


@dual_njit()
def fill_geometry(index_buf, depth_buf, pos, nrm, R, t, fx, fy, cx, cy, use_centre, vertex_out, normal_out):
    """The vertex and normal maps of :func:`fill_view` only (no colour / confidence): what ICP needs.

    Outputs are identical to :func:`fill_view`'s ``vertex_out`` / ``normal_out`` (reference: the first two
    results of :func:`fill_view_ref`).
    """
    H, W = index_buf.shape
    for v in prange(H):
        dy = (v - cy) / fy
        for u in range(W):
            i = index_buf[v, u]
            if i < 0:
                for c in range(3):
                    vertex_out[v, u, c] = 0.0
                    normal_out[v, u, c] = 0.0
                continue
            if use_centre:
                for c in range(3):
                    vertex_out[v, u, c] = R[c, 0] * pos[i, 0] + R[c, 1] * pos[i, 1] + R[c, 2] * pos[i, 2] + t[c]
            else:
                d = depth_buf[v, u]
                vertex_out[v, u, 0] = d * (u - cx) / fx
                vertex_out[v, u, 1] = d * dy
                vertex_out[v, u, 2] = d
            for c in range(3):
                normal_out[v, u, c] = R[c, 0] * nrm[i, 0] + R[c, 1] * nrm[i, 1] + R[c, 2] * nrm[i, 2]


def fill_view_ref(index_buf, depth_buf, pos, nrm, col, conf, R, t, fx, fy, cx, cy, use_centre):
    """Numpy reference of :func:`fill_view`; returns ``(vertex, normal, colour, confidence)``."""
    H, W = index_buf.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    valid = index_buf >= 0
    i = np.where(valid, index_buf, 0)
    if use_centre:
        vertex = (pos[i].astype(np.float64) @ R.T + t).astype(np.float32)
        vertex[~valid] = 0
    else:
        d = np.where(valid, depth_buf, 0.0)
        vertex = np.stack([d * (u - cx) / fx, d * ((v - cy) / fy), d], axis=-1).astype(np.float32)
    n = nrm[i].astype(np.float64)
    normal = np.einsum("ij,hwj->hwi", R, n).astype(np.float32)
    normal[~valid] = 0
    colour = np.minimum((col[i] + 0.5).astype(np.int64), 255).astype(np.uint8)
    colour[~valid] = 0
    confidence = np.where(valid, conf[i], 0).astype(np.float32)
    return vertex, normal, colour, confidence


# ---------------------------------------------------------------------------------------------------- index map
@njit(cache=True, nogil=True)
def index_zbuffer(cand, m, pos, nrm, R, t, fx, fy, cx, cy, scale, near, far, cull_back, depth_buf, index_buf):
    """Supersampled index map: each surfel centre lands in ONE cell of an ``(H*scale, W*scale)`` grid.

    Cell ``(su, sv)`` belongs to pixel ``(su // scale, sv // scale)``; ``su = floor((u + 0.5) * scale)``.
    Nearest surfel (camera z) wins, ties keep the earlier candidate. ``depth_buf`` float64 +inf,
    ``index_buf`` int32 -1 on entry. Other arguments as in :func:`splat_zbuffer`.
    """
    SH, SW = depth_buf.shape
    for k in range(m):
        i = cand[k]
        px = R[0, 0] * pos[i, 0] + R[0, 1] * pos[i, 1] + R[0, 2] * pos[i, 2] + t[0]
        py = R[1, 0] * pos[i, 0] + R[1, 1] * pos[i, 1] + R[1, 2] * pos[i, 2] + t[1]
        pz = R[2, 0] * pos[i, 0] + R[2, 1] * pos[i, 1] + R[2, 2] * pos[i, 2] + t[2]
        if pz < near or pz > far:
            continue
        if cull_back:
            nx = R[0, 0] * nrm[i, 0] + R[0, 1] * nrm[i, 1] + R[0, 2] * nrm[i, 2]
            ny = R[1, 0] * nrm[i, 0] + R[1, 1] * nrm[i, 1] + R[1, 2] * nrm[i, 2]
            nz = R[2, 0] * nrm[i, 0] + R[2, 1] * nrm[i, 1] + R[2, 2] * nrm[i, 2]
            if nx * px + ny * py + nz * pz >= 0.0:
                continue
        su = int(math.floor((fx * px / pz + cx + 0.5) * scale))
        sv = int(math.floor((fy * py / pz + cy + 0.5) * scale))
        if su < 0 or sv < 0 or su >= SW or sv >= SH:
            continue
        if pz < depth_buf[sv, su]:
            depth_buf[sv, su] = pz
            index_buf[sv, su] = i


def candidates_in_camera_ref(cand, m, pos, nrm, R, t, near, far, cull_back):
    """Numpy: the first ``m`` candidate surfels in the camera frame.

    Returns ``(idx (m,) int64, px, py, pz (m,) float64, ok (m,) bool)``: ``ok`` is inside ``[near, far]`` and,
    with ``cull_back``, facing the camera. Shared by the references of the index-map and bucket kernels.
    """
    idx = cand[:m].astype(np.int64)
    P = pos[idx].astype(np.float64)
    N = nrm[idx].astype(np.float64)
    # written out component by component: the same operation order as the kernels, so results match bitwise
    px = R[0, 0] * P[:, 0] + R[0, 1] * P[:, 1] + R[0, 2] * P[:, 2] + t[0]
    py = R[1, 0] * P[:, 0] + R[1, 1] * P[:, 1] + R[1, 2] * P[:, 2] + t[1]
    pz = R[2, 0] * P[:, 0] + R[2, 1] * P[:, 1] + R[2, 2] * P[:, 2] + t[2]
    ok = (pz >= near) & (pz <= far)
    if cull_back:
        nx = R[0, 0] * N[:, 0] + R[0, 1] * N[:, 1] + R[0, 2] * N[:, 2]
        ny = R[1, 0] * N[:, 0] + R[1, 1] * N[:, 1] + R[1, 2] * N[:, 2]
        nz = R[2, 0] * N[:, 0] + R[2, 1] * N[:, 1] + R[2, 2] * N[:, 2]
        ok &= nx * px + ny * py + nz * pz < 0
    return idx, px, py, pz, ok


def index_zbuffer_ref(cand, m, pos, nrm, R, t, fx, fy, cx, cy, scale, near, far, cull_back, shape_s):
    """Numpy reference of :func:`index_zbuffer`; returns ``(depth, index)`` of shape ``shape_s``."""
    SH, SW = shape_s
    idx, px, py, pz, ok = candidates_in_camera_ref(cand, m, pos, nrm, R, t, near, far, cull_back)
    pzs = np.where(ok, pz, 1.0)
    su = np.floor((fx * px / pzs + cx + 0.5) * scale).astype(np.int64)
    sv = np.floor((fy * py / pzs + cy + 0.5) * scale).astype(np.int64)
    ok &= (su >= 0) & (sv >= 0) & (su < SW) & (sv < SH)
    k = np.flatnonzero(ok)
    pix = sv[k] * SW + su[k]
    srt = np.lexsort((k, pz[k], pix))
    pix, kk = pix[srt], k[srt]
    first = np.ones(len(pix), bool)
    first[1:] = pix[1:] != pix[:-1]
    depth = np.full(SH * SW, np.inf)
    index = np.full(SH * SW, -1, np.int32)
    depth[pix[first]] = pz[kk[first]]
    index[pix[first]] = idx[kk[first]]
    return depth.reshape(SH, SW), index.reshape(SH, SW)
