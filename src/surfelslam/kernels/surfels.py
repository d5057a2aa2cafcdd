"""Surfel-map bookkeeping kernels: stable compaction, block grouping (counting sort), candidate gathering.

Each kernel has a plain-numpy reference ``<name>_ref`` used by the tests.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# level-of-detail offsets (gather_candidates): a 31-bit linear congruential generator with glibc's constants; its low
# bits have short periods, so an offset is drawn from bits 8 and up
_LCG_MUL = 1103515245
_LCG_ADD = 12345
_LCG_MASK = (1 << 31) - 1
_LCG_SHIFT = 8


@njit(cache=True, nogil=True)
def compact_rows(position, normal, colour, confidence, radius, first_seen, last_seen, hits, block_id, dead, size):
    """Stable in-place compaction of the first ``size`` rows, dropping rows with ``dead != 0``.

    Args:
        position, normal, colour: float32 ``(cap, 3)``.
        confidence, radius: float32 ``(cap,)``.
        first_seen, last_seen, hits, block_id: int32 ``(cap,)``.
        dead: uint8 ``(cap,)``; cleared for the kept rows.
        size: number of rows in use.

    Returns:
        The new size (number of kept rows); kept rows keep their relative order.
    """
    j = 0
    for i in range(size):
        if dead[i]:
            continue
        if j != i:
            for k in range(3):
                position[j, k] = position[i, k]
                normal[j, k] = normal[i, k]
                colour[j, k] = colour[i, k]
            confidence[j] = confidence[i]
            radius[j] = radius[i]
            first_seen[j] = first_seen[i]
            last_seen[j] = last_seen[i]
            hits[j] = hits[i]
            block_id[j] = block_id[i]
        j += 1
    for i in range(size):
        dead[i] = 0
    return j


def compact_rows_ref(arrays, dead, size):
    """Numpy reference: the compacted copies of each ``a[:size]`` in ``arrays`` (no in-place update)."""
    keep = dead[:size] == 0
    return [a[:size][keep] for a in arrays]


@njit(cache=True, nogil=True)
def group_by_block(block_id, n, n_blocks, order_out, start_out, count_out):
    """Stable counting sort of surfels ``0..n-1`` by ``block_id``.

    Args:
        block_id: int32 ``(>= n,)`` block of each surfel, in ``[0, n_blocks)``.
        order_out: int32 ``(>= n,)`` receives surfel indices grouped by block (ascending within a block).
        start_out, count_out: int32 ``(>= n_blocks,)`` receive each block's segment in ``order_out``.
    """
    for b in range(n_blocks):
        count_out[b] = 0
    for i in range(n):
        count_out[block_id[i]] += 1
    acc = 0
    for b in range(n_blocks):
        start_out[b] = acc
        acc += count_out[b]
    # count_out doubles as the fill cursor of each segment (ends equal to the count again)
    for b in range(n_blocks):
        count_out[b] = 0
    for i in range(n):
        b = block_id[i]
        order_out[start_out[b] + count_out[b]] = i
        count_out[b] += 1


def group_by_block_ref(block_id, n, n_blocks):
    """Numpy reference: ``(order, start, count)``."""
    ids = block_id[:n]
    order = np.argsort(ids, kind="stable").astype(np.int32)
    count = np.bincount(ids, minlength=n_blocks).astype(np.int32)
    start = (np.cumsum(count) - count).astype(np.int32)
    return order, start, count


@njit(cache=True, nogil=True)
def gather_candidates(visible, order, start, count, n_blocks_sorted, block_id, n_sorted, size, dead, out):
    """Surfel indices that may be in view: those of visible blocks (grouped part) + the visible tail.

    Args:
        visible: uint8 ``(n_blocks,)`` 0 where the block's box misses the view frustum, else the stride at which its
            grouped surfels are taken (1: all; ``k``: one of each run of ``k`` in the block's order, at a
            pseudo-random offset drawn per run from a generator seeded with the block's number, so that a block whose
            surfels were fused in raster order is not thinned in stripes; see
            :func:`surfelslam.kernels.render.lod_strides`). The tail is taken whole.
        order, start, count: the grouping of surfels ``0..n_sorted-1`` (see :func:`group_by_block`), covering
            blocks ``0..n_blocks_sorted-1``.
        block_id: int32 ``(>= size,)``; used for the ungrouped tail ``n_sorted..size-1``.
        dead: uint8 ``(>= size,)`` removed-but-not-compacted surfels, skipped.
        out: int32 ``(>= size,)`` receives the candidates.

    Returns:
        Number of candidates written (order: visible blocks ascending, then the tail ascending).
    """
    m = 0
    for b in range(n_blocks_sorted):
        st = visible[b]
        if st == 0:
            continue
        s = start[b]
        e = s + count[b]
        h = b  # offsets seeded by the block's number: deterministic, and neighbouring blocks draw different ones
        for k0 in range(s, e, st):
            k = k0
            if st > 1:
                h = (h * _LCG_MUL + _LCG_ADD) & _LCG_MASK
                k = k0 + (h >> _LCG_SHIFT) % st
                if k >= e:
                    continue
            i = order[k]
            if not dead[i]:
                out[m] = i
                m += 1
    for i in range(n_sorted, size):
        if visible[block_id[i]] and not dead[i]:
            out[m] = i
            m += 1
    return m


def gather_candidates_ref(visible, order, start, count, n_blocks_sorted, block_id, n_sorted, size, dead):
    """Numpy reference of :func:`gather_candidates` (returns the array)."""
    parts = []
    for b in np.flatnonzero(visible[:n_blocks_sorted]):
        st, s, e = int(visible[b]), int(start[b]), int(start[b] + count[b])
        k = np.arange(s, e, st)
        if st > 1:
            h, off = int(b), []
            for _ in k:
                h = (h * _LCG_MUL + _LCG_ADD) & _LCG_MASK
                off.append((h >> _LCG_SHIFT) % st)
            k = k + np.array(off, np.int64)
            k = k[k < e]
        parts.append(order[k])
    grouped = np.concatenate(parts) if parts else np.zeros(0, np.int32)
    grouped = grouped[dead[grouped] == 0]
    tail = np.arange(n_sorted, size)
    tail = tail[(visible[block_id[tail]] != 0) & (dead[tail] == 0)]
    return np.concatenate([grouped, tail]).astype(np.int32)


@njit(cache=True, nogil=True)
def transform_rows(position, normal, rows, group, R, t):
    """Move rows ``rows`` ``(m,)`` in place by the rigid transform of their group ``group`` ``(m,)``:
    ``position = R[g] p + t[g]``, ``normal = R[g] n`` (``R`` ``(G, 3, 3)``, ``t`` ``(G, 3)`` float32; ``position``,
    ``normal`` float32 ``(cap, 3)``). A map correction per keyframe without a ``(m, 3, 3)`` array per surfel."""
    for j in range(rows.shape[0]):
        i = rows[j]
        g = group[j]
        p0, p1, p2 = position[i, 0], position[i, 1], position[i, 2]
        n0, n1, n2 = normal[i, 0], normal[i, 1], normal[i, 2]
        for r in range(3):
            position[i, r] = R[g, r, 0] * p0 + R[g, r, 1] * p1 + R[g, r, 2] * p2 + t[g, r]
            normal[i, r] = R[g, r, 0] * n0 + R[g, r, 1] * n1 + R[g, r, 2] * n2


@njit(cache=True, nogil=True)
def rows_off_block(position, rows, block_id, block_ijk, inv_block):
    """Which of ``rows`` ``(m,)`` lie outside their culling block: ``(k,)`` int64 positions ``j`` into ``rows``
    (ascending) where ``floor(position[rows[j]] * inv_block)`` differs from ``block_ijk[block_id[rows[j]]]``
    (``position`` float32 ``(cap, 3)``, ``inv_block`` float32: the product rounds to float32 like numpy's). One
    pass, no ``(m, 3)`` temporaries: a map correction moves millions of surfels, most within their block."""
    out = np.empty(rows.shape[0], np.int64)
    k = 0
    for j in range(rows.shape[0]):
        i = rows[j]
        b = block_id[i]
        for r in range(3):
            if np.int32(np.floor(position[i, r] * inv_block)) != block_ijk[b, r]:
                out[k] = j
                k += 1
                break
    return out[:k]


def rows_off_block_ref(position, rows, block_id, block_ijk, inv_block):
    """Numpy reference of :func:`rows_off_block`."""
    ijk = np.floor(position[rows] * inv_block).astype(np.int32)
    return np.flatnonzero(np.any(ijk != block_ijk[block_id[rows]], axis=1))


def transform_rows_ref(position, normal, rows, group, R, t):
    """Reference of :func:`transform_rows` (returns the moved rows' positions and normals)."""
    return (np.einsum("nij,nj->ni", R[group], position[rows]) + t[group],
            np.einsum("nij,nj->ni", R[group], normal[rows]))
