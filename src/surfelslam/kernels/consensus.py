"""Pairwise rigid consistency of 3D matches and a greedy clique in it (numba), with numpy references.

Used by :mod:`surfelslam.tracking.consensus` (see there for why). Two matches ``i``, ``j`` with points ``P_i``,
``P_j`` in one camera and ``Q_i``, ``Q_j`` in the other are consistent when a rigid motion could map both:
``|‖P_i - P_j‖ - ‖Q_i - Q_j‖| <= abs_tol + rel_tol * max(‖P_i - P_j‖, ‖Q_i - Q_j‖)``. The clique is grown
from the best-connected matches, each step adding the candidate consistent with the most remaining
candidates (the first such in index order), until no candidate is consistent with every member.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def consistency_matrix(P, Q, abs_tol, rel_tol, out):
    """Fill ``out (N, N)`` bool with the consistency of ``P (N, 3)`` / ``Q (N, 3)`` float64 (False on the diagonal)."""
    n = P.shape[0]
    for i in range(n):
        out[i, i] = False
        for j in range(i + 1, n):
            dp = np.sqrt((P[i, 0] - P[j, 0]) ** 2 + (P[i, 1] - P[j, 1]) ** 2 + (P[i, 2] - P[j, 2]) ** 2)
            dq = np.sqrt((Q[i, 0] - Q[j, 0]) ** 2 + (Q[i, 1] - Q[j, 1]) ** 2 + (Q[i, 2] - Q[j, 2]) ** 2)
            ok = abs(dp - dq) <= abs_tol + rel_tol * max(dp, dq)
            out[i, j] = ok
            out[j, i] = ok


def consistency_matrix_ref(P: np.ndarray, Q: np.ndarray, abs_tol: float, rel_tol: float) -> np.ndarray:
    """Numpy reference of :func:`consistency_matrix`: ``(N, N)`` bool."""
    d_p = np.linalg.norm(P[:, None, :] - P[None, :, :], axis=2)
    d_q = np.linalg.norm(Q[:, None, :] - Q[None, :, :], axis=2)
    C = np.abs(d_p - d_q) <= abs_tol + rel_tol * np.maximum(d_p, d_q)
    np.fill_diagonal(C, False)
    return C


@njit(cache=True, nogil=True)
def greedy_clique(C, seeds, degree, min_size, stop_at, members):
    """Largest greedy clique grown from ``seeds``; returns its size ``K`` (0 if none reaches ``min_size``).

    Each candidate's count of consistent candidates is kept up to date as candidates drop out (``O(N^2)`` per
    seed instead of ``O(N^2)`` per step), which picks exactly what recounting at every step picks.

    Args:
        C: ``(N, N)`` symmetric bool consistency, False on the diagonal.
        seeds: ``(S,)`` int64 start matches, by falling ``degree`` (a seed whose degree cannot beat the best set
            so far, or reach ``min_size``, ends the search).
        degree: ``(N,)`` int64 row sums of ``C``.
        stop_at: when positive, stop as soon as a set has this many members and return it (a test for "is there
            a consistent set this large", not the largest set).
        members: ``(N,)`` int64 output; ``members[:K]`` are the clique's indices in the order they joined.
    """
    n = C.shape[0]
    cand = np.empty(n, np.int64)
    dropped = np.empty(n, np.int64)
    count = np.zeros(n, np.int64)
    grown = np.empty(n, np.int64)
    best = 0
    for s in seeds:
        if degree[s] + 1 <= best or degree[s] + 1 < min_size:
            break
        m = 1
        grown[0] = s
        nc = 0
        for j in range(n):
            if C[s, j]:
                cand[nc] = j
                nc += 1
        for a in range(nc):
            c = 0
            for b in range(nc):
                if C[cand[a], cand[b]]:
                    c += 1
            count[cand[a]] = c
        while nc > 0:
            pick = cand[0]
            for a in range(1, nc):
                if count[cand[a]] > count[pick]:
                    pick = cand[a]
            grown[m] = pick
            m += 1
            if m == stop_at:
                break
            kept = 0
            nd = 0
            for a in range(nc):
                if C[pick, cand[a]]:
                    cand[kept] = cand[a]
                    kept += 1
                else:
                    dropped[nd] = cand[a]  # the pick itself too (no self-consistency)
                    nd += 1
            nc = kept
            for a in range(nc):
                c = 0
                for r in range(nd):
                    if C[cand[a], dropped[r]]:
                        c += 1
                count[cand[a]] -= c
        if m > best and m >= min_size:
            best = m
            for k in range(m):  # not members[:m] = grown[:m]: see icp.copy_pose
                members[k] = grown[k]
            if m == stop_at:
                break
    return best


def greedy_clique_ref(C: np.ndarray, seeds: np.ndarray, degree: np.ndarray, min_size: int,
                      stop_at: int = 0) -> np.ndarray:
    """Numpy reference of :func:`greedy_clique`: the clique's ``(K,)`` indices in joining order."""
    best = np.zeros(0, np.int64)
    for s in seeds:
        if degree[s] + 1 <= len(best) or degree[s] + 1 < min_size:
            break
        grown = [int(s)]
        cand = np.flatnonzero(C[s])
        while cand.size:
            pick = int(cand[np.argmax(C[np.ix_(cand, cand)].sum(axis=1))])
            grown.append(pick)
            if len(grown) == stop_at:
                break
            cand = cand[C[pick, cand]]
        if len(grown) > len(best) and len(grown) >= min_size:
            best = np.array(grown, np.int64)
            if len(grown) == stop_at:
                break
    return best
