"""Numba kernels of the mesh clean-up (:func:`surfelslam.mapping.mesh_topology.clean_faces`) in little memory.

Faces are ``(F, 3)`` vertex indices; half-edge ``h = 3 t + k`` runs from corner ``k`` of triangle ``t`` to corner
``k + 1``, and corner ``h`` is vertex ``faces[t, k]`` of triangle ``t``. ``keep`` ``(F,)`` bool marks the faces
still in the mesh (the kernels ignore the others and clear entries of the ones they remove).

Instead of sorting int64 edge keys and building sparse graphs (hundreds of bytes per face), the half-edges are
bucketed by their lower vertex (:func:`edge_buckets`, a CSR: the half-edges of one undirected edge are in one
bucket of a few entries) and pieces are joined with a union-find whose roots are the lowest member, holding minus
the piece's size (``parent`` ``(N,)``: ``parent[r] < 0`` at a root ``r``). About 25 bytes per face in all.
Serial: union-find does not split into independent slices.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def nondegenerate(vertices: np.ndarray, faces: np.ndarray, keep: np.ndarray) -> None:
    """Clear ``keep[t]`` for the triangles with a repeated vertex or zero area (float64 cross product of the edges
    from corner 0). ``vertices`` ``(V, 3)`` float, ``faces`` ``(F, 3)`` int, ``keep`` ``(F,)`` bool."""
    for t in range(faces.shape[0]):
        i, j, k = faces[t, 0], faces[t, 1], faces[t, 2]
        if i == j or j == k or k == i:
            keep[t] = False
            continue
        ax, ay, az = np.float64(vertices[i, 0]), np.float64(vertices[i, 1]), np.float64(vertices[i, 2])
        ux = np.float64(vertices[j, 0]) - ax
        uy = np.float64(vertices[j, 1]) - ay
        uz = np.float64(vertices[j, 2]) - az
        wx = np.float64(vertices[k, 0]) - ax
        wy = np.float64(vertices[k, 1]) - ay
        wz = np.float64(vertices[k, 2]) - az
        cx, cy, cz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
        if not np.sqrt(cx * cx + cy * cy + cz * cz) > 0:
            keep[t] = False


@njit(cache=True, nogil=True)
def _corner(faces, h):
    return faces[h // 3, h % 3]


@njit(cache=True, nogil=True)
def _next(h):
    return h - h % 3 + (h % 3 + 1) % 3


@njit(cache=True, nogil=True)
def edge_buckets(faces: np.ndarray, n_vertices: int, offsets: np.ndarray, halfedges: np.ndarray) -> None:
    """Fill the CSR of half-edges by lower vertex: ``halfedges[offsets[u]:offsets[u + 1]]`` ``(3F,)`` are the
    half-edges whose lower end is vertex ``u``, in increasing order. ``offsets`` ``(V + 1,)`` int64."""
    offsets[:] = 0
    n = 3 * faces.shape[0]
    for h in range(n):
        offsets[min(_corner(faces, h), _corner(faces, _next(h))) + 1] += 1
    for u in range(n_vertices):
        offsets[u + 1] += offsets[u]
    fill = offsets[:-1].copy()
    for h in range(n):
        u = min(_corner(faces, h), _corner(faces, _next(h)))
        halfedges[fill[u]] = h
        fill[u] += 1


@njit(cache=True, nogil=True)
def _find(parent, a):
    while parent[a] >= 0 and parent[parent[a]] >= 0:  # path halving
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a if parent[a] < 0 else parent[a]


@njit(cache=True, nogil=True)
def _union(parent, a, b):
    """Join the pieces of ``a`` and ``b``: the lower root stays, holding minus the summed size."""
    ra, rb = _find(parent, a), _find(parent, b)
    if ra == rb:
        return
    if rb < ra:
        ra, rb = rb, ra
    parent[ra] += parent[rb]
    parent[rb] = ra


@njit(cache=True, nogil=True)
def _other_end(faces, h, u):
    s = _corner(faces, h)
    return _corner(faces, _next(h)) if s == u else s


@njit(cache=True, nogil=True)
def _join_edges(faces, keep, offsets, halfedges, parent, fans):
    """Union over each undirected edge of kept faces: ``fans``: the corners around the edge's vertices (edges of
    exactly two half-edges, the fan graph of :func:`drop_extra_fans`); otherwise the triangles (every edge)."""
    for u in range(offsets.shape[0] - 1):
        lo, hi = offsets[u], offsets[u + 1]
        for a in range(lo, hi):
            h1 = halfedges[a]
            if not keep[h1 // 3]:
                continue
            v = _other_end(faces, h1, u)
            first = True
            for b in range(lo, a):  # an earlier kept half-edge of the same edge: already handled
                h = halfedges[b]
                if keep[h // 3] and _other_end(faces, h, u) == v:
                    first = False
                    break
            if not first:
                continue
            count, h2 = 1, -1
            for b in range(a + 1, hi):
                h = halfedges[b]
                if keep[h // 3] and _other_end(faces, h, u) == v:
                    count += 1
                    if count == 2:
                        h2 = h
                    if not fans:
                        _union(parent, h1 // 3, h // 3)
            if fans and count == 2:
                n1, n2 = _next(h1), _next(h2)
                if _corner(faces, h1) == _corner(faces, h2):  # inconsistent orientation: same direction
                    _union(parent, h1, h2)
                    _union(parent, n1, n2)
                else:
                    _union(parent, h1, n2)
                    _union(parent, n1, h2)


@njit(cache=True, nogil=True)
def drop_extra_fans(faces: np.ndarray, keep: np.ndarray, offsets: np.ndarray, halfedges: np.ndarray,
                    parent: np.ndarray, fans: np.ndarray, best: np.ndarray, best_size: np.ndarray) -> int:
    """One round of fan removal; returns the number of faces removed from ``keep``.

    The corners of a vertex form fans, joined through the edges of exactly two kept triangles; at each vertex with
    several fans, the triangles of all but its largest (ties: the one with the lowest corner) are removed. Work
    arrays: ``parent`` ``(3F,)`` int, ``fans`` ``(V,)`` int, ``best`` ``(V,)`` int, ``best_size`` ``(V,)`` int.
    """
    parent[:] = -1
    fans[:] = 0
    best_size[:] = 0
    _join_edges(faces, keep, offsets, halfedges, parent, True)
    n = parent.shape[0]
    for c in range(n):  # roots in increasing order: the first largest fan of a vertex wins ties
        if parent[c] < 0 and keep[c // 3]:
            u = _corner(faces, c)
            fans[u] += 1
            if -parent[c] > best_size[u]:
                best_size[u] = -parent[c]
                best[u] = c
    dropped = 0
    for c in range(n):
        if keep[c // 3]:
            u = _corner(faces, c)
            if fans[u] > 1 and _find(parent, c) != best[u]:
                keep[c // 3] = False
                dropped += 1
    return dropped


@njit(cache=True, nogil=True)
def drop_small_pieces(faces: np.ndarray, keep: np.ndarray, offsets: np.ndarray, halfedges: np.ndarray,
                      parent: np.ndarray, min_component: int) -> int:
    """Remove from ``keep`` the pieces (kept triangles joined through shared edges, ``parent`` ``(F,)`` int work
    array) of fewer than ``min_component`` triangles; returns the number of faces removed."""
    parent[:] = -1
    _join_edges(faces, keep, offsets, halfedges, parent, False)
    dropped = 0
    for t in range(faces.shape[0]):
        if keep[t] and -parent[_find(parent, t)] < min_component:
            keep[t] = False
            dropped += 1
    return dropped
