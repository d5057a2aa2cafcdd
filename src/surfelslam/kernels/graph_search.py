"""Least-cost path between two nodes of an undirected weighted graph kept as linked adjacency lists (numba).

The graph grows one edge at a time (the accepted edges of the keyframe graph): each edge ``e`` is two half-edges,
``2 e`` (leaving its first end) and ``2 e + 1`` (leaving its second), and every node holds a linked list of the
half-edges that leave it (``head[node]``, then ``next_half[h]``, newest first), so adding an edge is O(1) and no
matrix is rebuilt. A removed edge keeps its half-edges with an infinite weight: the search never takes it.

:func:`shortest_path` is Dijkstra's search from ``src`` (a binary heap with lazy deletion) that stops as soon as
``dst`` is settled and never reaches a node farther than ``limit``: its cost is that of the nodes nearer than ``dst``,
not of the whole graph. A node's predecessor changes only on a strictly shorter distance, as in
``scipy.sparse.csgraph.dijkstra``; the paths agree with it except where two paths cost exactly the same.
"""

from __future__ import annotations

import numpy as np
from numba import njit

NO_NODE = -1  # no predecessor: the source, or a node not reached


@njit(cache=True, nogil=True)
def _push(heap_d, heap_n, size, d, n):
    """Push ``(d, n)`` on the binary min-heap of ``size`` entries; returns the new size."""
    k = size
    while k > 0:
        parent = (k - 1) // 2
        if heap_d[parent] <= d:
            break
        heap_d[k], heap_n[k] = heap_d[parent], heap_n[parent]
        k = parent
    heap_d[k], heap_n[k] = d, n
    return size + 1


@njit(cache=True, nogil=True)
def _pop(heap_d, heap_n, size):
    """Remove the smallest entry of the heap of ``size`` entries (its root, read before); returns the new size."""
    size -= 1
    d, n = heap_d[size], heap_n[size]
    k = 0
    while True:
        c = 2 * k + 1
        if c >= size:
            break
        if c + 1 < size and heap_d[c + 1] < heap_d[c]:
            c += 1
        if d <= heap_d[c]:
            break
        heap_d[k], heap_n[k] = heap_d[c], heap_n[c]
        k = c
    if size > 0:
        heap_d[k], heap_n[k] = d, n
    return size


@njit(cache=True, nogil=True)
def shortest_path(head, next_half, ends, weight, src, dst, limit, pred):
    """Dijkstra from ``src`` until ``dst`` is settled, through nodes no farther than ``limit``.

    Args:
        head: ``(V,)`` int64 newest half-edge leaving each node (``NO_NODE``: none).
        next_half: ``(>= 2 E,)`` int64 the next (older) half-edge leaving the same node.
        ends: ``(>= E, 2)`` int64 the two nodes of each edge; weight: ``(>= E,)`` float64 its cost (``inf``: removed).
        src, dst: the two nodes; limit: the largest path cost searched.
        pred: ``(V,)`` int64 output, each reached node's predecessor (``NO_NODE`` elsewhere).

    Returns:
        the cost of the path to ``dst``, ``inf`` when it is farther than ``limit`` or not connected.
    """
    n = head.shape[0]
    dist = np.full(n, np.inf)
    done = np.zeros(n, np.bool_)
    pred[:] = NO_NODE
    cap = 2 * next_half.shape[0] + 1  # a node enters the heap once per improvement, at most once per half-edge
    heap_d = np.empty(cap)
    heap_n = np.empty(cap, np.int64)
    dist[src] = 0.0
    size = _push(heap_d, heap_n, 0, 0.0, src)
    while size > 0:
        d, u = heap_d[0], heap_n[0]
        size = _pop(heap_d, heap_n, size)
        if done[u]:
            continue
        done[u] = True
        if u == dst:
            return d
        h = head[u]
        while h != NO_NODE:
            e = h // 2
            v = ends[e, 1 - h % 2]
            nd = d + weight[e]
            if nd <= limit and nd < dist[v] and not done[v]:
                dist[v] = nd
                pred[v] = u
                size = _push(heap_d, heap_n, size, nd, v)
            h = next_half[h]
    return np.inf
