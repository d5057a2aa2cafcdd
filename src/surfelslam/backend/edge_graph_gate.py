"""Chi-square gate of a far keyframe edge against the graph of the edges accepted so far (false-loop-closure guard).

The odometry chain (:mod:`surfelslam.backend.loop_consistency`) judges an edge ``i -> j`` by the odometry alone; over
a long path its random-walk drift model allows metres of error, so a look-alike place metres off can pass it. Once
loops have been closed on the way, the accepted edges (odometry, loop and nearby ones) join ``i`` and ``j`` by a much
shorter chain of measurements. This gate finds the path of least total variance between the two keyframes through
the accepted edges (Dijkstra on each edge's covariance trace, searching no further than the odometry chain's own
cost), composes the measured relative poses along it with their covariances (propagated by the adjoints, as the
chain does), and applies the same chi-square test. After a long excursion with no loop on the way, the path is the
odometry chain itself and the gate is as wide as the chain's.
"""

from __future__ import annotations

import numpy as np

from surfelslam.geometry.se3 import adjoint, invert, log
from surfelslam.kernels.graph_search import NO_NODE, shortest_path
from surfelslam.types import GrowingRows

# Dijkstra weight (m^2 + rad^2) added to every edge: a still camera's odometry step has zero drift variance (kept from
# the scipy search, which dropped zero-weight entries of its sparse matrix: the same costs, the same paths)
_MIN_WEIGHT = 1e-12
_INITIAL_NODES = 64  # the node array's first capacity (doubled when full)


class EdgeGraph:
    """Keyframes joined by the accepted edges, each a measured ``T_a_b`` with its ``(6, 6)`` covariance (right
    perturbation at ``b``, ``(omega, v)``); between two keyframes only the edge of least variance is kept.

    The edges are kept as linked adjacency lists (:mod:`surfelslam.kernels.graph_search`): adding one is O(1), and a
    path search visits only the keyframes nearer (in variance) than its end, whatever the graph's size."""

    def __init__(self) -> None:
        self._index: dict[tuple[int, int], int] = {}  # (a, b), a < b -> row of the arrays below
        self._ends = GrowingRows((2,), np.int64)  # (a, b) per row
        self._w = GrowingRows((), np.float64, np.inf)  # Dijkstra weight (covariance trace) per row; inf: removed
        self._T: list[np.ndarray] = []  # measured T_a_b per row
        self._cov: list[np.ndarray] = []  # its (6, 6) covariance (right perturbation at b)
        self._head = GrowingRows((), np.int64, NO_NODE, _INITIAL_NODES)  # per keyframe: newest half-edge leaving it
        # per row, its two half-edges (half 2 row: leaving a, 2 row + 1: leaving b): the next (older) half-edge
        # leaving the same keyframe
        self._next_half = GrowingRows((2,), np.int64, NO_NODE)

    def __len__(self) -> int:
        return len(self._head)

    def add_node(self) -> int:
        """Add a keyframe; returns its id."""
        return self._head.append(NO_NODE)

    def add_edge(self, i: int, j: int, T_i_j: np.ndarray, cov: np.ndarray) -> None:
        """Add the measured ``T_i_j`` ``(4, 4)`` with its ``(6, 6)`` covariance (kept if the pair has none, or a
        larger one)."""
        T_i_j, cov = np.asarray(T_i_j, np.float64), np.asarray(cov, np.float64)
        if i > j:  # store as (min, max): the inverse, its perturbation moved to the other end by the adjoint
            A = adjoint(T_i_j)
            i, j, T_i_j, cov = j, i, invert(T_i_j), A @ cov @ A.T
        w = float(np.trace(cov)) + _MIN_WEIGHT
        row = self._index.get((i, j))
        if row is None:
            row = self._index[(i, j)] = self._ends.append((i, j))
            self._w.append(w)
            self._next_half.append((NO_NODE, NO_NODE))
            head, next_half = self._head.rows, self._next_half.rows
            for end, node in enumerate((i, j)):  # each end's list gets the half-edge leaving it
                next_half[row, end] = head[node]
                head[node] = 2 * row + end
            self._T.append(T_i_j.copy())
            self._cov.append(cov.copy())
        elif w < self._w.rows[row]:
            self._T[row], self._cov[row] = T_i_j.copy(), cov.copy()
            self._w.rows[row] = w

    def remove_edge(self, i: int, j: int) -> None:
        """Drop the edge between ``i`` and ``j`` (if any)."""
        row = self._index.pop((min(i, j), max(i, j)), None)
        if row is not None:
            self._w.rows[row] = np.inf  # the row stays, unused (its half-edges stay in the lists, never taken)

    def path(self, i: int, j: int, limit: float = np.inf) -> list[int] | None:
        """Keyframes ``[i, ..., j]`` on the path of least total variance (``None``: none cheaper than ``limit``)."""
        if i == j:
            return [i]
        pred = np.empty(len(self._head), np.int64)
        if not np.isfinite(shortest_path(self._head.rows, self._next_half.rows.reshape(-1), self._ends.rows,
                                         self._w.rows, i, j, float(limit), pred)):
            return None
        out = [j]
        while out[-1] != i:
            out.append(int(pred[out[-1]]))
        return out[::-1]

    def relative(self, path: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """``T_i_j`` ``(4, 4)`` composed of the measured edges along ``path`` (``[i, ..., j]``) and its ``(6, 6)``
        covariance (right perturbation at ``j``)."""
        P = [np.eye(4)]  # poses of the path's keyframes in the frame of i
        ends, covs = [], []  # per edge: the index in path of its stored end b, its covariance there
        for m, (a, b) in enumerate(zip(path[:-1], path[1:], strict=True)):
            row = self._index[(min(a, b), max(a, b))]
            T, cov = self._T[row], self._cov[row]
            P.append(P[-1] @ (T if a < b else invert(T)))
            ends.append(m + 1 if a < b else m)
            covs.append(cov)
        if not covs:
            return np.eye(4), np.zeros((6, 6))
        P = np.stack(P)
        A = adjoint(invert(P[-1])[None] @ P[np.array(ends)])  # T_j_b: moves each edge's perturbation to j
        return P[-1], np.einsum("nab,nbc,ndc->ad", A, np.stack(covs), A)

    def mahalanobis2(self, i: int, j: int, T_i_j: np.ndarray, cov_edge: np.ndarray,
                     limit: float = np.inf) -> float | None:
        """Squared Mahalanobis distance of the edge ``T_i_j`` ``(4, 4)`` with covariance ``cov_edge`` ``(6, 6)``
        from the path of least variance through the graph (``None``: no path cheaper than ``limit``)."""
        p = self.path(i, j, limit)
        if p is None:
            return None
        T_path, cov = self.relative(p)
        r = log(invert(np.asarray(T_i_j, np.float64)) @ T_path)
        return float(r @ np.linalg.solve(cov + cov_edge, r))
