"""Rigid 3D consensus among feature matches whose two ends both have depth.

PnP-RANSAC draws minimal samples of 5 matches (EPnP) and needs one sample made only of correct matches. With
an inlier fraction ``w`` that happens with probability ``w^5`` per draw: at ``w = 0.15`` (frames far apart,
little overlap, repeated texture) 300 draws succeed 2 % of the time. When both frames have depth, a rigid
motion preserves the distance between any two points, so correct matches agree with one another pairwise
whatever the motion is, and the wrong ones rarely do. The largest set of mutually agreeing matches is found
without sampling:

1. :func:`pairwise_consistency` (numba, :mod:`surfelslam.kernels.consensus`): ``C[i, j]`` is True when
   matches ``i`` and ``j`` keep their distance within ``abs_tol_m + rel_tol * distance``.
2. :func:`greedy_clique`: from each of the best-connected matches, grow a set in which every two members are
   consistent, adding at each step the candidate consistent with the most remaining candidates.
3. :func:`rigid_fit`: the least-squares rotation and translation of that set (Umeyama, no scale; evo's).

Used by :func:`surfelslam.tracking.features.estimate_motion` when PnP-RANSAC fails or keeps few inliers.
"""

from __future__ import annotations

import numpy as np
from evo.core.geometry import GeometryException, umeyama_alignment

from surfelslam.geometry.se3 import make_T
from surfelslam.kernels import consensus as kc

_MIN_RIGID_POINTS = 3  # a rotation and translation need three non-collinear points


def pairwise_consistency(P_ref: np.ndarray, P_cur: np.ndarray, abs_tol_m: float, rel_tol: float) -> np.ndarray:
    """Which pairs of matches keep their 3D distance.

    Args:
        P_ref: ``(N, 3)`` points of the matches in the reference camera (metres, finite).
        P_cur: ``(N, 3)`` the same matches' points in the current camera.
        abs_tol_m, rel_tol: ``|d_ref - d_cur| <= abs_tol_m + rel_tol * max(d_ref, d_cur)``.

    Returns:
        ``(N, N)`` bool, symmetric, False on the diagonal.
    """
    n = len(P_ref)
    C = np.empty((n, n), np.bool_)
    kc.consistency_matrix(np.ascontiguousarray(P_ref, np.float64), np.ascontiguousarray(P_cur, np.float64),
                          float(abs_tol_m), float(rel_tol), C)
    return C


def greedy_clique(C: np.ndarray, n_seeds: int, min_size: int = 1, stop_at: int = 0) -> np.ndarray:
    """A large set of matches that are all pairwise consistent (an approximate maximum clique of ``C``).

    Args:
        C: ``(N, N)`` symmetric bool consistency, False on the diagonal.
        n_seeds: grow one set from each of this many best-connected matches (ties by index); keep the largest.
        min_size: smallest set worth returning (seeds too poorly connected to reach it are not grown).
        stop_at: when positive, the first set to reach this size is returned as it stands.

    Returns:
        ``(K,)`` int64 sorted indices of the set; empty when no set reaches ``min_size``. Deterministic.
    """
    n = len(C)
    if n == 0:
        return np.zeros(0, np.int64)
    degree = C.sum(axis=1).astype(np.int64)
    seeds = np.argsort(-degree, kind="stable")[: max(n_seeds, 1)].astype(np.int64)
    members = np.empty(n, np.int64)
    k = kc.greedy_clique(np.ascontiguousarray(C), seeds, degree, int(min_size), int(stop_at), members)
    return np.sort(members[:k])


def rigid_fit(P_ref: np.ndarray, P_cur: np.ndarray) -> np.ndarray | None:
    """Least-squares rigid motion ``T_cur_ref (4, 4)`` with ``P_cur ~ R P_ref + t`` (``(N, 3)`` each), or ``None``
    for fewer than 3 points or a degenerate (collinear) set."""
    if len(P_ref) < _MIN_RIGID_POINTS:
        return None
    try:
        R, t, _ = umeyama_alignment(np.asarray(P_ref, np.float64).T, np.asarray(P_cur, np.float64).T, False)
    except GeometryException:
        return None
    T = make_T(R, t)
    return T if np.all(np.isfinite(T)) else None


def rigid_consensus(P_ref: np.ndarray, P_cur: np.ndarray, abs_tol_m: float, rel_tol: float,
                    n_seeds: int, min_size: int = _MIN_RIGID_POINTS) -> tuple[np.ndarray | None, np.ndarray]:
    """The rigid motion of the largest mutually consistent set of matches.

    Args:
        P_ref, P_cur: ``(N, 3)`` the matches' points in the reference and current cameras; rows with a
            non-finite coordinate are ignored.
        abs_tol_m, rel_tol, n_seeds, min_size: see :func:`pairwise_consistency` and :func:`greedy_clique`.

    Returns:
        ``(T_cur_ref, members)``: ``(4, 4)`` or ``None`` (no consistent set of ``max(min_size, 3)`` points, or a
        degenerate one), and the ``(K,)`` indices (into the ``N`` rows) of the consistent set.
    """
    P_ref = np.asarray(P_ref, np.float64)
    P_cur = np.asarray(P_cur, np.float64)
    members = _consistent_members(P_ref, P_cur, abs_tol_m, rel_tol, n_seeds, max(min_size, _MIN_RIGID_POINTS))
    return rigid_fit(P_ref[members], P_cur[members]), members


def _consistent_members(P_ref: np.ndarray, P_cur: np.ndarray, abs_tol_m: float, rel_tol: float, n_seeds: int,
                        min_size: int, stop_at: int = 0) -> np.ndarray:
    """Indices into the ``N`` rows of the greedy consistent set (rows with a non-finite coordinate ignored); see
    :func:`greedy_clique` for ``min_size`` and ``stop_at``."""
    ok = np.flatnonzero(np.all(np.isfinite(P_ref), axis=1) & np.all(np.isfinite(P_cur), axis=1))
    if len(ok) < min_size:
        return np.zeros(0, np.int64)
    C = pairwise_consistency(P_ref[ok], P_cur[ok], abs_tol_m, rel_tol)
    return ok[greedy_clique(C, n_seeds, min_size, stop_at)]


def has_consistent_set(P_ref: np.ndarray, P_cur: np.ndarray, abs_tol_m: float, rel_tol: float, n_seeds: int,
                       size: int) -> bool:
    """Whether the matches ``(N, 3)`` / ``(N, 3)`` (rows with a non-finite coordinate ignored) hold a mutually
    consistent set of ``size`` (see :func:`rigid_consensus`; growth stops once one set is that large)."""
    members = _consistent_members(np.asarray(P_ref, np.float64), np.asarray(P_cur, np.float64), abs_tol_m, rel_tol,
                                  n_seeds, size, stop_at=size)
    return len(members) >= size
