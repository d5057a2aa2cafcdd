"""TSDF kernels: a sparse grid of 8^3-voxel blocks, projective integration of depth images, marching cubes.

Storage (:class:`surfelslam.mapping.mesh.TsdfVolume` owns the arrays): block ``b`` holds the voxels
``coords[b] * 8 + (i, j, k)``, ``i, j, k`` in ``[0, 8)``, stored at ``i + 8 j + 64 k``; voxel ``(x, y, z)`` sits at
``(x, y, z) * voxel_m`` in the world. Blocks are found through an open-addressing hash (linear probing) of their
packed coordinates (:func:`block_key`, 21 bits per axis): ``keys`` (``-1`` = empty slot, at most half full) and
``vals`` (the block index). Per voxel: ``tsdf`` float32 (signed distance / ``trunc_m``, positive in front of the
surface; in ``[-1, 1]`` near the sensor, up to ``trunc_max / trunc_m`` where the truncation widens with the depth
noise), ``weight`` float32 (the sum of the measurements' weights; 0 = never observed), ``count`` uint16 (frames that
updated it), colour as ``uint16`` fixed point (value x 256, a running average that does not stall as uint8 averages
do) with its own ``uint16`` weight (colour is taken only within the truncation band).

Per frame: :func:`allocate` walks every valid pixel's ray through ``depth +- trunc(depth)`` and inserts the blocks
it crosses (serial: it writes the hash) and lists them; :func:`integrate` updates every voxel of those blocks
(``prange`` over blocks): projective distance ``sdf = depth(u, v) - z`` at the pixel the voxel projects to (nearest),
skipped when ``sdf < -trunc(depth)``, ``min(trunc(depth), sdf) / trunc_m`` averaged with the measurement's weight.
Noise-aware fusion: a depth ``z`` of axial noise ``sigma(z)`` (a Kinect-like model, growing with ``z^2``) weighs
``1 / sigma(z)^2`` (so far, noisy depth refines nothing that near depth saw, yet fills what only it saw) and its
truncation widens to a few sigmas (:func:`truncation`, so that the noise is averaged rather than clipped).

Extraction: marching cubes with a triangle table built here (:func:`build_triangle_table`, the classic 256-case
table's topology with ambiguous faces split so that inside corners are separated: crack-free; no triangle diagonal
lies in a cube face, so the surface is edge-manifold and consistently oriented), over every cube whose 8 corners
were observed (``count >= min_weight``: the extraction kernels take the count array as their ``weight``) and whose
values do not jump across 0 by more than :data:`MAX_CROSSING_JUMP` (the edge of a truncation band). Vertices
are shared: the vertex on the edge from voxel ``v`` along axis ``a`` is owned by ``v`` (key ``3 v + a`` within its
block; a block's vertices are written in key order, so a triangle finds it by a binary search), so the mesh is
welded. Normals: the TSDF gradient (central differences) interpolated along the edge; colours interpolated
likewise. Two passes each (count, prefix sum, fill) so that the parallel kernels write disjoint slices and the
output order is fixed.

Meshing is an offline job with no frame-reading thread to leave a core to, so the block loops always run in
parallel (``prange``): they have no serial twins (:mod:`surfelslam.kernels.threads`), and the results do not depend
on the thread count.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

BLOCK = 8  # voxels per block edge
BLOCK_VOXELS = BLOCK**3
_OFF = 1 << 20  # block coordinate offset in the packed key (21 bits per axis)
EMPTY = -1
#: colour fixed point: stored value = colour x COLOUR_SCALE
COLOUR_SCALE = 256.0
_U16_MAX = 65535
#: a vertex lies at least this fraction of its voxel edge from the edge's ends, so that the vertices of the edges
#: meeting at a voxel whose TSDF is exactly 0 do not coincide (duplicated positions, zero-area triangles)
EDGE_T_MIN = 1e-3
#: a cube whose TSDF values (in units of trunc_m) on either side of 0 differ by more than this is no surface: a
#: surface changes the signed distance by at most a voxel per voxel (0.25 at trunc_m = 4 voxels, 1.2 seen at 78 deg
#: by the projective distance), while free space (+1) next to the back of another surface's band jumps by more
MAX_CROSSING_JUMP = 1.5
#: allocation samples each ray's truncation band this many voxels apart (a third of a block: every block the band
#: crosses is met)
ALLOCATE_STEP_VOXELS = BLOCK / 3.0


# ---------------------------------------------------------------------------------------------- triangle table
def _cube_edges() -> list[tuple[int, int]]:
    """The 12 cube edges as ``(lower corner, axis)``; corner ``c`` is at ``(c & 1, c >> 1 & 1, c >> 2 & 1)``."""
    return [(c, a) for a in range(3) for c in range(8) if not (c >> a) & 1]


def _face_cycles() -> list[list[int]]:
    """The 6 faces' corners in counter-clockwise order seen from outside the cube."""
    cycles = []
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3  # e_b x e_c = e_a
        for side in (0, 1):
            ring = [(0, 0), (1, 0), (1, 1), (0, 1)]
            if side == 0:  # outward normal -e_a: the other way round
                ring = ring[::-1]
            cycles.append([(side << a) | (p << b) | (q << c) for p, q in ring])
    return cycles


def _faces_of_edge(edge: tuple[int, int]) -> set[tuple[int, int]]:
    """The two cube faces ``(axis, side)`` that contain the cube edge ``(lower corner, axis)``."""
    c, a = edge
    return {(b, (c >> b) & 1) for b in range(3) if b != a}


def _triangulations(loop: list[int]):
    """Every triangulation of the polygon ``loop`` (vertices in loop order, so each triangle keeps its winding), as
    lists of ``(i, j, k)`` triples; the fans come first, from each start in turn."""
    n = len(loop)
    for s in range(n):
        yield [(loop[s], loop[(s + i) % n], loop[(s + i + 1) % n]) for i in range(1, n - 1)]
    if n < 5:
        return

    def rec(poly: list[int]):
        if len(poly) < 3:
            yield []
            return
        a, b = poly[0], poly[-1]
        for m in range(1, len(poly) - 1):
            for left in rec(poly[: m + 1]):
                for right in rec(poly[m:]):
                    yield [*left, (a, poly[m], b), *right]

    yield from rec(loop)


def _triangulate_loop(loop: list[int], edges: list[tuple[int, int]]) -> list[int]:
    """A triangulation of one loop of cut edges whose inner diagonals never join two edges of the same cube face.

    Such a diagonal lies in the face, which the neighbouring cube shares: where that face is ambiguous (4 cut
    edges) the neighbour may use the same diagonal (an edge of 4 triangles) or even the same triangle, reversed.
    Diagonals through the cube's interior are shared by nothing else, so the surface stays edge-manifold.
    """
    n = len(loop)
    for tris in _triangulations(loop):
        diagonals = {frozenset(p) for t in tris for p in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
        diagonals -= {frozenset((loop[i], loop[(i + 1) % n])) for i in range(n)}
        if all(not (_faces_of_edge(edges[e]) & _faces_of_edge(edges[f])) for e, f in diagonals):
            return [e for t in tris for e in t]
    raise AssertionError(f"no triangulation of the marching cubes loop {loop} avoids the cube's faces")


def build_triangle_table() -> tuple[np.ndarray, np.ndarray]:
    """``(table (256, 3 * T) int8, count (256,) int8)``: per corner configuration (bit ``c`` set when corner ``c``
    is inside, ``tsdf < 0``), the triangles as edge indices into :func:`_cube_edges`, ``-1`` padded.

    Each face's cut edges are paired into segments from an edge where the face's counter-clockwise walk enters the
    inside to the next edge where it leaves (a face with two inside corners on a diagonal gets two segments, each
    cutting one inside corner off: neighbouring cubes agree, so the surface has no cracks). Every cut edge starts
    one segment and ends another, so the segments form loops; each loop is triangulated
    (:func:`_triangulate_loop`), wound counter-clockwise seen from the outside (positive) side.
    """
    edges = _cube_edges()
    edge_of = {}
    for e, (c, a) in enumerate(edges):
        edge_of[(c, c | (1 << a))] = edge_of[(c | (1 << a), c)] = e
    cycles = _face_cycles()
    rows: list[list[int]] = []
    for config in range(256):
        nxt: dict[int, int] = {}
        for ring in cycles:
            inside = [(config >> c) & 1 for c in ring]
            for k in range(4):
                if inside[k] or not inside[(k + 1) % 4]:
                    continue  # not an entering edge
                m = (k + 1) % 4
                while inside[(m + 1) % 4]:
                    m = (m + 1) % 4
                nxt[edge_of[(ring[k], ring[(k + 1) % 4])]] = edge_of[(ring[m], ring[(m + 1) % 4])]
        tris: list[int] = []
        seen: set[int] = set()
        for start in sorted(nxt):
            if start in seen:
                continue
            loop = [start]
            while nxt[loop[-1]] != start:
                loop.append(nxt[loop[-1]])
            seen.update(loop)
            tris += _triangulate_loop(loop, edges)
        rows.append(tris)
    width = max(len(r) for r in rows)
    table = np.full((256, width), -1, np.int8)
    for i, r in enumerate(rows):
        table[i, : len(r)] = r
    return table, np.array([len(r) // 3 for r in rows], np.int8)


TRI_TABLE, TRI_COUNT = build_triangle_table()
EDGE_CORNER = np.array([c for c, _ in _cube_edges()], np.int64)
EDGE_AXIS = np.array([a for _, a in _cube_edges()], np.int64)


# ---------------------------------------------------------------------------------------------- block hash
@njit(cache=True, nogil=True)
def block_key(bx: int, by: int, bz: int) -> int:
    return ((bx + _OFF) << 42) | ((by + _OFF) << 21) | (bz + _OFF)


@njit(cache=True, nogil=True)
def _slot(key: int, mask: int) -> int:
    h = np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)
    return np.int64((h >> np.uint64(32)) & np.uint64(mask))


@njit(cache=True, nogil=True)
def hash_find(keys: np.ndarray, vals: np.ndarray, key: int) -> int:
    """Block index of ``key``, or -1."""
    mask = keys.shape[0] - 1
    s = _slot(key, mask)
    while True:
        k = keys[s]
        if k == key:
            return vals[s]
        if k == EMPTY:
            return -1
        s = (s + 1) & mask


@njit(cache=True, nogil=True)
def _hash_put(keys: np.ndarray, vals: np.ndarray, key: int, value: int) -> None:
    mask = keys.shape[0] - 1
    s = _slot(key, mask)
    while keys[s] != EMPTY:
        s = (s + 1) & mask
    keys[s] = key
    vals[s] = value


@njit(cache=True, nogil=True)
def rehash(coords: np.ndarray, n_blocks: int, keys: np.ndarray, vals: np.ndarray) -> None:
    """Fill the empty hash ``keys`` / ``vals`` with blocks ``0 .. n_blocks - 1``."""
    for b in range(n_blocks):
        _hash_put(keys, vals, block_key(coords[b, 0], coords[b, 1], coords[b, 2]), b)


# ---------------------------------------------------------------------------------------------- integration
#: layout of the ``noise`` array the integration kernels take (:func:`depth_sigma`, :func:`truncation`,
#: :func:`measurement_weight`): axial depth noise ``sigma(z) = base + quad (z - offset)^2`` (m), the truncation
#: ``clip(trunc_sigmas sigma(z), trunc_m, trunc_max_m)`` and the weight ``ref_var / sigma(z)^2``
NOISE_BASE, NOISE_QUAD, NOISE_OFFSET, NOISE_TRUNC_SIGMAS, NOISE_TRUNC_MAX, NOISE_REF_VAR = range(6)


@njit(cache=True, nogil=True)
def depth_sigma(d, noise):
    """Axial noise (m, one sigma) of a depth ``d`` (m)."""
    return noise[NOISE_BASE] + noise[NOISE_QUAD] * (d - noise[NOISE_OFFSET]) ** 2


@njit(cache=True, nogil=True)
def truncation(d, trunc_m, noise):
    """Truncation (m) of a depth ``d``: ``trunc_m``, widened to ``trunc_sigmas`` noise sigmas, at most
    ``trunc_max``."""
    return min(max(trunc_m, noise[NOISE_TRUNC_SIGMAS] * depth_sigma(d, noise)), max(trunc_m, noise[NOISE_TRUNC_MAX]))


@njit(cache=True, nogil=True)
def measurement_weight(d, noise):
    """Fusion weight of a depth ``d``: inverse noise variance, 1 where the variance is ``ref_var``."""
    s = depth_sigma(d, noise)
    return noise[NOISE_REF_VAR] / (s * s)


@njit(cache=True, nogil=True)
def _touch(bx, by, bz, keys, vals, coords, n_blocks, stamp, stamps, visible, n_vis):
    """Insert block ``(bx, by, bz)`` if new and list it in ``visible`` once per ``stamp``. Returns ``(n_blocks,
    n_vis, full)``; ``full``: the block is new and does not fit."""
    key = block_key(bx, by, bz)
    b = hash_find(keys, vals, key)
    if b < 0:
        if n_blocks >= coords.shape[0] or n_blocks >= keys.shape[0] // 2:
            return n_blocks, n_vis, True
        b = n_blocks
        coords[b, 0] = bx
        coords[b, 1] = by
        coords[b, 2] = bz
        _hash_put(keys, vals, key, b)
        n_blocks += 1
    if stamps[b] != stamp:
        stamps[b] = stamp
        visible[n_vis] = b
        n_vis += 1
    return n_blocks, n_vis, False


@njit(cache=True, nogil=True)
def allocate(depth, fx, fy, cx, cy, T_world_cam, min_depth, max_depth, trunc_m, noise, voxel_m, keys, vals, coords,
             n_blocks, stamp, stamps, visible):
    """Insert the blocks that every valid pixel's ray crosses within the truncation (:func:`truncation`) of its
    depth, sampled :data:`ALLOCATE_STEP_VOXELS` apart, and list the blocks this frame touches in ``visible`` (each
    once: ``stamps[b] == stamp``).

    Returns ``(n_blocks, n_visible, full)``; ``full``: a new block did not fit (``coords`` full or the hash
    half full); the caller grows the arrays and calls again (with a new ``stamp``).
    """
    H, W = depth.shape
    inv_v = 1.0 / voxel_m
    inv_b = inv_v / BLOCK
    n_vis = 0
    for v in range(H):
        for u in range(W):
            d = depth[v, u]
            if not (d >= min_depth and d <= max_depth):
                continue
            xr = (u - cx) / fx
            yr = (v - cy) / fy
            ray_len = np.sqrt(xr * xr + yr * yr + 1.0)
            tr = truncation(d, trunc_m, noise)
            z0 = max(d - tr, 1e-3)
            z1 = d + tr
            n = int(np.ceil((z1 - z0) * ray_len * inv_v / ALLOCATE_STEP_VOXELS)) + 1
            lx = ly = lz = -(1 << 40)
            for s in range(n):
                z = z0 + (z1 - z0) * s / (n - 1)
                xc, yc = xr * z, yr * z
                px = T_world_cam[0, 0] * xc + T_world_cam[0, 1] * yc + T_world_cam[0, 2] * z + T_world_cam[0, 3]
                py = T_world_cam[1, 0] * xc + T_world_cam[1, 1] * yc + T_world_cam[1, 2] * z + T_world_cam[1, 3]
                pz = T_world_cam[2, 0] * xc + T_world_cam[2, 1] * yc + T_world_cam[2, 2] * z + T_world_cam[2, 3]
                bx = int(np.floor(px * inv_b))
                by = int(np.floor(py * inv_b))
                bz = int(np.floor(pz * inv_b))
                if bx == lx and by == ly and bz == lz:
                    continue
                lx, ly, lz = bx, by, bz
                n_blocks, n_vis, full = _touch(bx, by, bz, keys, vals, coords, n_blocks, stamp, stamps, visible,
                                               n_vis)
                if full:
                    return n_blocks, n_vis, True
    return n_blocks, n_vis, False


@njit(cache=True, nogil=True)
def _integrate_block(depth, rgb, fx, fy, cx, cy, T_cam_world, min_depth, max_depth, trunc_m, noise, voxel_m, visible,
                     coords, tsdf, weight, count, colour, colour_weight, max_weight, q):
    """Item ``q`` of :func:`integrate`'s parallel loop, a function of its own: numba's parallel pass then
    handles a loop of one call (see ``icp._normal_equations_chunk``)."""
    H, W = depth.shape
    inv_t = 1.0 / trunc_m
    c_max = 255.0 * COLOUR_SCALE
    cw_max = min(max_weight, _U16_MAX)
    # camera-frame steps of one voxel along world x, y, z
    ax, ay, az = T_cam_world[0, 0] * voxel_m, T_cam_world[1, 0] * voxel_m, T_cam_world[2, 0] * voxel_m
    bx, by, bz = T_cam_world[0, 1] * voxel_m, T_cam_world[1, 1] * voxel_m, T_cam_world[2, 1] * voxel_m
    cx_, cy_, cz_ = T_cam_world[0, 2] * voxel_m, T_cam_world[1, 2] * voxel_m, T_cam_world[2, 2] * voxel_m
    b = visible[q]
    gx, gy, gz = coords[b, 0] * BLOCK, coords[b, 1] * BLOCK, coords[b, 2] * BLOCK
    ox = ax * gx + bx * gy + cx_ * gz + T_cam_world[0, 3]
    oy = ay * gx + by * gy + cy_ * gz + T_cam_world[1, 3]
    oz = az * gx + bz * gy + cz_ * gz + T_cam_world[2, 3]
    for kz in range(BLOCK):
        for ky in range(BLOCK):
            rx = ox + bx * ky + cx_ * kz
            ry = oy + by * ky + cy_ * kz
            rz = oz + bz * ky + cz_ * kz
            for kx in range(BLOCK):
                zc = rz + az * kx
                if zc <= 1e-6:
                    continue
                inv_z = 1.0 / zc
                uf = fx * (rx + ax * kx) * inv_z + cx + 0.5
                vf = fy * (ry + ay * kx) * inv_z + cy + 0.5
                if not (uf >= 0.0 and vf >= 0.0 and uf < W and vf < H):
                    continue
                u = int(uf)
                v = int(vf)
                d = depth[v, u]
                if not (d >= min_depth and d <= max_depth):
                    continue
                sdf = d - zc
                tr = truncation(d, trunc_m, noise)
                if sdf < -tr:
                    continue
                k = kx + BLOCK * ky + BLOCK * BLOCK * kz
                w0 = weight[b, k]
                w = measurement_weight(d, noise)
                tsdf[b, k] = (tsdf[b, k] * w0 + min(tr, sdf) * inv_t * w) / (w0 + w)
                weight[b, k] = min(w0 + w, max_weight)
                count[b, k] = min(count[b, k] + 1, _U16_MAX)
                if sdf < tr:
                    cw = np.float64(colour_weight[b, k])
                    inv_w = 1.0 / (cw + 1.0)
                    for c in range(3):
                        val = (colour[b, k, c] * cw + rgb[v, u, c] * COLOUR_SCALE) * inv_w + 0.5
                        colour[b, k, c] = np.uint16(min(val, c_max))
                    colour_weight[b, k] = np.uint16(min(cw + 1.0, cw_max))


@njit(cache=True, nogil=True, parallel=True)
def integrate(depth, rgb, fx, fy, cx, cy, T_cam_world, min_depth, max_depth, trunc_m, noise, voxel_m, visible,
              coords, tsdf, weight, count, colour, colour_weight, max_weight):
    """Projective TSDF update of every voxel of the blocks ``visible`` with one frame.

    ``depth`` ``(H, W)`` float32 metres (0 / NaN / out of range: no measurement); ``rgb`` ``(H, W, 3)`` uint8, the
    colour of each depth pixel; ``T_cam_world`` ``(4, 4)``. A voxel whose projective distance ``sdf = d - z`` is
    ``>= -tr`` (``tr``: :func:`truncation` of ``d``) gets ``min(tr, sdf) / trunc_m`` averaged in with the weight
    :func:`measurement_weight` of ``d`` (the weight saturates at ``max_weight``, so old frames fade) and its
    ``count`` of frames goes up by one; within ``|sdf| < tr`` its colour is averaged too.
    """
    for q in prange(visible.shape[0]):
        _integrate_block(depth, rgb, fx, fy, cx, cy, T_cam_world, min_depth, max_depth, trunc_m, noise, voxel_m,
                         visible, coords, tsdf, weight, count, colour, colour_weight, max_weight, np.int64(q))


# ---------------------------------------------------------------------------------------------- extraction
@njit(cache=True, nogil=True)
def neighbour_table(coords, n_blocks, keys, vals):
    """``(n_blocks, 27)`` int32: the block at offset ``(dx, dy, dz)`` in ``{-1, 0, 1}^3`` (column
    ``(dx + 1) + 3 (dy + 1) + 9 (dz + 1)``), or -1."""
    out = np.full((n_blocks, 27), -1, np.int32)
    for b in range(n_blocks):
        for n in range(27):
            key = block_key(coords[b, 0] + n % 3 - 1, coords[b, 1] + (n // 3) % 3 - 1, coords[b, 2] + n // 9 - 1)
            out[b, n] = hash_find(keys, vals, key)
    return out


@njit(cache=True, nogil=True)
def _voxel(nbr, b, i, j, k):
    """``(block, index in block)`` of the voxel ``(i, j, k)`` relative to block ``b`` (each in ``[-8, 16)``);
    block -1 when it is not allocated."""
    nb = nbr[b, ((i >> 3) + 1) + 3 * ((j >> 3) + 1) + 9 * ((k >> 3) + 1)]
    return nb, (i & 7) + 8 * (j & 7) + 64 * (k & 7)


@njit(cache=True, nogil=True)
def _observed(nbr, weight, min_weight, b, i, j, k):
    nb, nk = _voxel(nbr, b, i, j, k)
    return nb >= 0 and weight[nb, nk] >= min_weight


@njit(cache=True, nogil=True)
def _gradient(nbr, tsdf, weight, min_weight, b, i, j, k):
    """TSDF gradient at voxel ``(i, j, k)`` of block ``b``: central differences, one-sided where a neighbour is
    unobserved, 0 where both are."""
    nb0, nk0 = _voxel(nbr, b, i, j, k)
    f0 = tsdf[nb0, nk0]
    g = np.zeros(3)
    for a in range(3):
        di = 1 if a == 0 else 0
        dj = 1 if a == 1 else 0
        dk = 1 if a == 2 else 0
        bp, kp = _voxel(nbr, b, i + di, j + dj, k + dk)
        bm, km = _voxel(nbr, b, i - di, j - dj, k - dk)
        okp = bp >= 0 and weight[bp, kp] >= min_weight
        okm = bm >= 0 and weight[bm, km] >= min_weight
        if okp and okm:
            g[a] = 0.5 * (tsdf[bp, kp] - tsdf[bm, km])
        elif okp:
            g[a] = tsdf[bp, kp] - f0
        elif okm:
            g[a] = f0 - tsdf[bm, km]
    return g


@njit(cache=True, nogil=True)
def _count_vertices_block(nbr, tsdf, weight, min_weight, counts, b):
    """Item ``b`` of :func:`count_vertices`'s parallel loop, a function of its own: numba's parallel pass then
    handles a loop of one call (see ``icp._normal_equations_chunk``)."""
    c = 0
    for k in range(BLOCK_VOXELS):
        if weight[b, k] < min_weight:
            continue
        i, j, l = k & 7, (k >> 3) & 7, k >> 6
        neg = tsdf[b, k] < 0
        for a in range(3):
            nb, nk = _voxel(nbr, b, i + int(a == 0), j + int(a == 1), l + int(a == 2))
            if nb >= 0 and weight[nb, nk] >= min_weight and (tsdf[nb, nk] < 0) != neg:
                c += 1
    counts[b] = c


@njit(cache=True, nogil=True, parallel=True)
def count_vertices(nbr, tsdf, weight, min_weight, counts):
    """``counts[b]``: the surface crossings on the edges owned by block ``b``'s voxels (both ends observed)."""
    for b in prange(counts.shape[0]):
        _count_vertices_block(nbr, tsdf, weight, min_weight, counts, np.int64(b))


@njit(cache=True, nogil=True)
def _fill_vertices_block(nbr, coords, tsdf, weight, colour, colour_weight, min_weight, voxel_m, start, vkey, verts,
                         normals, rgb, b):
    """Item ``b`` of :func:`fill_vertices`'s parallel loop, a function of its own: numba's parallel pass then
    handles a loop of one call (see ``icp._normal_equations_chunk``)."""
    n = start[b]
    ox = coords[b, 0] * BLOCK
    oy = coords[b, 1] * BLOCK
    oz = coords[b, 2] * BLOCK
    for k in range(BLOCK_VOXELS):
        if weight[b, k] < min_weight:
            continue
        i, j, l = k & 7, (k >> 3) & 7, k >> 6
        f0 = tsdf[b, k]
        for a in range(3):
            di, dj, dl = int(a == 0), int(a == 1), int(a == 2)
            nb, nk = _voxel(nbr, b, i + di, j + dj, l + dl)
            if nb < 0 or weight[nb, nk] < min_weight:
                continue
            f1 = tsdf[nb, nk]
            if (f1 < 0) == (f0 < 0):
                continue
            t = min(max(f0 / (f0 - f1), EDGE_T_MIN), 1.0 - EDGE_T_MIN)
            verts[n, 0] = (ox + i + t * di) * voxel_m
            verts[n, 1] = (oy + j + t * dj) * voxel_m
            verts[n, 2] = (oz + l + t * dl) * voxel_m
            g0 = _gradient(nbr, tsdf, weight, min_weight, b, i, j, l)
            g1 = _gradient(nbr, tsdf, weight, min_weight, b, i + di, j + dj, l + dl)
            gx = (1 - t) * g0[0] + t * g1[0]
            gy = (1 - t) * g0[1] + t * g1[1]
            gz = (1 - t) * g0[2] + t * g1[2]
            norm = np.sqrt(gx * gx + gy * gy + gz * gz)
            if norm > 0:
                normals[n, 0] = gx / norm
                normals[n, 1] = gy / norm
                normals[n, 2] = gz / norm
            else:
                normals[n, 0] = normals[n, 1] = normals[n, 2] = 0.0
            w0 = (1.0 - t) if colour_weight[b, k] > 0 else 0.0
            w1 = t if colour_weight[nb, nk] > 0 else 0.0
            if w0 + w1 <= 0.0:
                w0 = w1 = 0.0
            else:
                s = 1.0 / ((w0 + w1) * COLOUR_SCALE)
                w0 *= s
                w1 *= s
            for c in range(3):
                rgb[n, c] = np.uint8(min(w0 * colour[b, k, c] + w1 * colour[nb, nk, c] + 0.5, 255.0))
            vkey[n] = 3 * k + a
            n += 1


@njit(cache=True, nogil=True, parallel=True)
def fill_vertices(nbr, coords, tsdf, weight, colour, colour_weight, min_weight, voxel_m, start, vkey, verts,
                  normals, rgb):
    """Write the vertices counted by :func:`count_vertices` from ``start[b]`` on: position (linear interpolation of
    the zero crossing), normal (interpolated TSDF gradient, unit length, towards the free side), colour
    (interpolated between the ends that have one); and each one's key within its block into ``vkey`` ``(V,)`` int16
    (``3 voxel + axis`` < 3 x 512; increasing within a block). No per-voxel table: 2 bytes per vertex instead of 3 x
    2 bytes per voxel of every block."""
    for b in prange(coords.shape[0]):
        _fill_vertices_block(nbr, coords, tsdf, weight, colour, colour_weight, min_weight, voxel_m, start, vkey,
                             verts, normals, rgb, np.int64(b))


@njit(cache=True, nogil=True)
def _vertex_index(vkey, lo, hi, key):
    """Index of ``key`` among ``vkey[lo:hi]`` (increasing; the key is there: a cube's crossing edge has its
    vertex)."""
    while lo < hi:
        mid = (lo + hi) >> 1
        if vkey[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True, nogil=True)
def _cube_case(nbr, tsdf, weight, min_weight, b, i, j, l):
    """The cube's configuration (bit c: corner c inside), or -1 when a corner is unobserved or the sign change along
    one of its edges is a jump no surface makes (:data:`MAX_CROSSING_JUMP`)."""
    case = 0
    lo = np.inf
    hi = -np.inf
    for c in range(8):
        nb, nk = _voxel(nbr, b, i + (c & 1), j + ((c >> 1) & 1), l + (c >> 2))
        if nb < 0 or weight[nb, nk] < min_weight:
            return -1
        f = tsdf[nb, nk]
        if f < 0:
            case |= 1 << c
            lo = min(lo, f)
        else:
            hi = max(hi, f)
    if hi - lo > MAX_CROSSING_JUMP:
        return -1
    return case


@njit(cache=True, nogil=True)
def _count_triangles_block(nbr, tsdf, weight, min_weight, tri_count, counts, b):
    """Item ``b`` of :func:`count_triangles`'s parallel loop, a function of its own: numba's parallel pass then
    handles a loop of one call (see ``icp._normal_equations_chunk``)."""
    c = 0
    for k in range(BLOCK_VOXELS):
        if weight[b, k] < min_weight:
            continue
        case = _cube_case(nbr, tsdf, weight, min_weight, b, k & 7, (k >> 3) & 7, k >> 6)
        if case > 0:
            c += np.int64(tri_count[case])  # int64 as numba types it (plain Python would add in int8)
    counts[b] = c


@njit(cache=True, nogil=True, parallel=True)
def count_triangles(nbr, tsdf, weight, min_weight, tri_count, counts):
    """``counts[b]``: triangles of the cubes whose lowest corner is a voxel of block ``b``."""
    for b in prange(counts.shape[0]):
        _count_triangles_block(nbr, tsdf, weight, min_weight, tri_count, counts, np.int64(b))


@njit(cache=True, nogil=True)
def _fill_triangles_block(nbr, tsdf, weight, min_weight, tri_table, tri_count, edge_corner, edge_axis, vkey,
                          vstart, start, faces, b):
    """Item ``b`` of :func:`fill_triangles`'s parallel loop, a function of its own: numba's parallel pass then
    handles a loop of one call (see ``icp._normal_equations_chunk``)."""
    n = start[b]
    for k in range(BLOCK_VOXELS):
        if weight[b, k] < min_weight:
            continue
        i, j, l = k & 7, (k >> 3) & 7, k >> 6
        case = _cube_case(nbr, tsdf, weight, min_weight, b, i, j, l)
        if case <= 0:
            continue
        for t in range(tri_count[case]):
            for m in range(3):
                e = tri_table[case, 3 * t + m]
                c = edge_corner[e]
                nb, nk = _voxel(nbr, b, i + (c & 1), j + ((c >> 1) & 1), l + (c >> 2))
                faces[n, m] = _vertex_index(vkey, vstart[nb], vstart[nb + 1], 3 * nk + edge_axis[e])
            n += 1


@njit(cache=True, nogil=True, parallel=True)
def fill_triangles(nbr, tsdf, weight, min_weight, tri_table, tri_count, edge_corner, edge_axis, vkey, vstart, start,
                   faces):
    """Write the triangles counted by :func:`count_triangles` from ``start[b]`` on, their vertices found by key in
    :func:`fill_vertices`'s ``vkey``: block ``b``'s vertices are ``vstart[b]`` to ``vstart[b + 1]`` (``(B + 1,)``)."""
    for b in prange(start.shape[0]):
        _fill_triangles_block(nbr, tsdf, weight, min_weight, tri_table, tri_count, edge_corner, edge_axis, vkey,
                              vstart, start, faces, np.int64(b))
