"""Topology of triangle meshes: the checks mesh tools make (manifold edges and vertices, orientation, duplicates,
connected pieces), and the clean-up that gives ``surfelslam mesh`` meshes that pass them.

A mesh is *edge-manifold* when every edge has one triangle (a border) or two; *consistently oriented* when the two
triangles of every inner edge run along it in opposite directions; *vertex-manifold* when the triangles around each
vertex form a single fan (joined through the vertex's edges), not several that touch at the vertex only. Faces are
``(F, 3)`` vertex indices; everything here is vectorised numpy and scipy's connected components.

Marching cubes with :mod:`surfelslam.kernels.tsdf`'s table gives edge-manifold, oriented surfaces by construction;
where the observed region ends, several fans may still meet at one vertex, and noise leaves small floating pieces:
:func:`clean_faces` removes both.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from surfelslam.kernels import mesh_topology as kmt

#: rounds of fan removal at most (each round can leave a new non-manifold vertex next to the fans it removed;
#: in practice two rounds suffice)
MAX_FAN_ROUNDS = 20


def _half_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(start (3F,), end (3F,), triangle (3F,))``: the directed edges of the faces, edge ``k`` of triangle ``t``
    at ``3 t + k`` (from corner ``k`` to corner ``k + 1``)."""
    f = np.asarray(faces, np.int64)
    start = f.reshape(-1)
    end = f[:, [1, 2, 0]].reshape(-1)
    return start, end, np.repeat(np.arange(len(f)), 3)


def _edge_groups(start: np.ndarray, end: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(order, group (3F,), count (G,))``: half-edges sorted by their undirected edge, the edge index of each
    (in that order), and how many half-edges each edge has."""
    lo, hi = np.minimum(start, end), np.maximum(start, end)
    key = lo * (int(hi.max(initial=0)) + 1) + hi  # one int64 per undirected edge (V^2 fits for V < 3e9)
    order = np.argsort(key, kind="stable")
    key = key[order]
    new = np.ones(len(order), bool)
    new[1:] = key[1:] != key[:-1]
    group = np.cumsum(new) - 1
    count = np.bincount(group) if len(group) else np.zeros(0, np.int64)
    return order, group, count


def _pairs(faces: np.ndarray):
    """The inner edges with exactly two half-edges: ``(h1, h2)`` arrays of their half-edge indices, plus the
    per-edge counts (for the statistics)."""
    start, end, _ = _half_edges(faces)
    order, group, count = _edge_groups(start, end)
    first = np.flatnonzero(np.r_[True, group[1:] != group[:-1]]) if len(group) else np.zeros(0, np.int64)
    two = count == 2
    h1 = order[first[two]]
    h2 = order[first[two] + 1]
    return start, end, h1, h2, count


def fan_labels(faces: np.ndarray) -> np.ndarray:
    """``(3F,)`` label of each triangle corner (``3 t + k``): corners of one vertex get one label per fan, the
    triangles around the vertex joined through the edges they share (edges of two triangles only)."""
    start, end, h1, h2, _ = _pairs(faces)
    n = len(start)
    if n == 0:
        return np.zeros(0, np.int64)
    # half-edge h runs from corner h to corner next(h) of its triangle
    nxt = np.arange(n) - np.arange(n) % 3 + (np.arange(n) % 3 + 1) % 3
    same = start[h1] == start[h2]  # inconsistent orientation: the edges run the same way
    a1, b1 = h1, nxt[h1]
    a2 = np.where(same, h2, nxt[h2])
    b2 = np.where(same, nxt[h2], h2)
    rows = np.concatenate([a1, b1])
    cols = np.concatenate([a2, b2])
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def _fans_per_vertex(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(fans (V,), corner vertex (3F,), corner fan label (3F,))``."""
    labels = fan_labels(faces)
    vert = np.asarray(faces, np.int64).reshape(-1)
    _, first = np.unique(labels, return_index=True)  # a label belongs to the corners of one vertex
    fans = np.bincount(vert[first], minlength=n_vertices)
    return fans, vert, labels


def triangle_components(faces: np.ndarray) -> np.ndarray:
    """``(F,)`` component label of each triangle, triangles joined through shared edges."""
    start, end, tri = _half_edges(faces)
    if len(start) == 0:
        return np.zeros(0, np.int64)
    order, group, _ = _edge_groups(start, end)
    link = np.flatnonzero(group[1:] == group[:-1])  # consecutive half-edges of one edge
    a, b = tri[order[link]], tri[order[link + 1]]
    graph = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(len(faces), len(faces)))
    return connected_components(graph, directed=False)[1]


def _duplicate_rows(a: np.ndarray) -> int:
    """Rows of ``a`` ``(N, 3)`` equal to an earlier row."""
    if len(a) == 0:
        return 0
    order = np.lexsort((a[:, 2], a[:, 1], a[:, 0]))
    s = a[order]
    return int(np.all(s[1:] == s[:-1], axis=1).sum())


def topology_report(vertices: np.ndarray, faces: np.ndarray) -> dict:
    """The counts mesh tools check: duplicated vertices (same position) and triangles (same vertex set), degenerate
    triangles (a repeated vertex or zero area), border / non-manifold (3+ triangles) / inconsistently oriented
    edges, non-manifold vertices (more than one fan), connected components; ``manifold``: all of those 0."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    sorted_f = np.sort(f, axis=1)
    dup_tri = _duplicate_rows(sorted_f)
    dup_vert = _duplicate_rows(v)
    repeated = (sorted_f[:, 0] == sorted_f[:, 1]) | (sorted_f[:, 1] == sorted_f[:, 2])
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    zero_area = np.linalg.norm(np.cross(b - a, c - a), axis=1) <= 0
    start, end, h1, h2, count = _pairs(f)
    fans, _, _ = _fans_per_vertex(f, len(v))
    comps = triangle_components(f)
    report = {
        "vertices": len(v), "faces": len(f),
        "duplicated_vertices": int(dup_vert), "duplicated_triangles": int(dup_tri),
        "degenerate_triangles": int((repeated | zero_area).sum()),
        "border_edges": int((count == 1).sum()), "non_manifold_edges": int((count > 2).sum()),
        "misoriented_edges": int((start[h1] == start[h2]).sum()),
        "non_manifold_vertices": int((fans > 1).sum()),
        "unreferenced_vertices": int((np.bincount(f.reshape(-1), minlength=len(v)) == 0).sum()),
        "components": int(comps.max() + 1) if len(comps) else 0,
    }
    report["manifold"] = all(report[k] == 0 for k in ("duplicated_vertices", "duplicated_triangles",
                                                      "degenerate_triangles", "non_manifold_edges",
                                                      "misoriented_edges", "non_manifold_vertices"))
    return report


def _drop_extra_fans(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """``(F,)`` keep mask: at each vertex with several fans, the triangles of all but its largest fan go."""
    fans, vert, labels = _fans_per_vertex(faces, n_vertices)
    keep = np.ones(len(faces), bool)
    bad = fans[vert] > 1
    if not bad.any():
        return keep
    corners = np.flatnonzero(bad)
    size = np.bincount(labels[corners], minlength=labels.max() + 1)  # corners of each fan = its triangles
    # per vertex, the fan with the most triangles (ties: the lowest label, so the result is deterministic)
    order = np.lexsort((labels[corners], -size[labels[corners]], vert[corners]))
    c = corners[order]
    first = np.r_[True, vert[c][1:] != vert[c][:-1]]
    best = np.repeat(labels[c][first], np.diff(np.r_[np.flatnonzero(first), len(c)]))
    drop = c[labels[c] != best]
    keep[drop // 3] = False
    return keep


def _index_dtype(n: int):
    """int32 where ``n`` indices fit (half the memory), else int64."""
    return np.int32 if n < np.iinfo(np.int32).max else np.int64


def clean_faces(vertices: np.ndarray, faces: np.ndarray, min_component: int) -> np.ndarray:
    """``(F,)`` keep mask of the faces that make the mesh tool-friendly: no degenerate triangles (repeated vertex,
    zero area), one fan per vertex (the largest; :data:`MAX_FAN_ROUNDS` rounds), no piece of fewer than
    ``min_component`` triangles (0: keep all).

    The numba kernels of :mod:`surfelslam.kernels.mesh_topology` (about 25 bytes per face); the same mask as
    :func:`clean_faces_reference`."""
    v = np.ascontiguousarray(vertices)
    f = np.ascontiguousarray(np.asarray(faces).reshape(-1, 3))
    n_v = len(v)
    keep = np.ones(len(f), bool)
    if len(f) == 0:
        return keep
    kmt.nondegenerate(v, f, keep)
    idx = _index_dtype(3 * len(f))
    offsets = np.empty(n_v + 1, np.int64)
    halfedges = np.empty(3 * len(f), idx)
    kmt.edge_buckets(f, n_v, offsets, halfedges)
    parent = np.empty(3 * len(f), idx)
    fans, best_size = np.empty(n_v, np.int32), np.empty(n_v, idx)
    best = np.empty(n_v, idx)
    for _ in range(MAX_FAN_ROUNDS):
        if kmt.drop_extra_fans(f, keep, offsets, halfedges, parent, fans, best, best_size) == 0:
            break
    del fans, best, best_size
    if min_component > 1:
        kmt.drop_small_pieces(f, keep, offsets, halfedges, parent[: len(f)], min_component)
    return keep


def clean_faces_reference(vertices: np.ndarray, faces: np.ndarray, min_component: int) -> np.ndarray:
    """:func:`clean_faces` by numpy sorts and scipy's connected components (a few hundred bytes per face): the
    reference the kernels are tested against."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    keep = np.linalg.norm(np.cross(b - a, c - a), axis=1) > 0
    keep &= (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
    for _ in range(MAX_FAN_ROUNDS):
        idx = np.flatnonzero(keep)
        sub = _drop_extra_fans(f[idx], len(v))
        if sub.all():
            break
        keep[idx[~sub]] = False
    if min_component > 1:
        idx = np.flatnonzero(keep)
        comp = triangle_components(f[idx])
        if len(comp):
            keep[idx[np.bincount(comp)[comp] < min_component]] = False
    return keep
