"""Point-feature histograms over neighbour pairs (numba), with numpy references.

Used by :func:`surfelslam.tracking.geometric.fpfh` (see there for the descriptor). Each kernel is one pass over the
``M`` neighbour pairs ``(i[k], j[k])``:

* :func:`spfh_accumulate`: the three pair angles (:func:`pair_features_ref` defines them) binned into both ends'
  histograms, and each point's neighbour count;
* :func:`neighbour_sum`: each point's inverse-distance-weighted sum of its neighbours' histograms and the sum
  of the weights.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_EPS_DIST = 1e-12  # m: coincident points get a zero line (and zero angles)
_EPS_CROSS = 1e-9  # |d x n| below this: the line is parallel to the normal, the angles are set to 0
_MIN_WEIGHT_DIST_M = 1e-6  # inverse-distance weights are capped at 1 / this


def pair_features_ref(p: np.ndarray, n: np.ndarray, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, ...]:
    """The three FPFH angles of point pairs ``(i, j)``, independent of which end comes first (numpy).

    Args:
        p, n: ``(N, 3)`` points and unit normals.
        i, j: ``(M,)`` pair indices.

    Returns:
        ``(twist, cos_nv, cos_nd)`` ``(M,)``: with ``s`` the end whose normal is closer to the line joining
        them, ``d`` the unit line from ``s`` to the other end ``t``, ``u = n_s``, ``v = d x u / |d x u|``,
        ``w = u x v``: ``twist = atan2(w . n_t, u . n_t)`` in ``[-pi, pi]``, ``cos_nv = v . n_t`` and
        ``cos_nd = u . d`` in ``[-1, 1]``. Pairs whose line is parallel to the normal get zeros.
    """
    d = p[j] - p[i]
    dist = np.linalg.norm(d, axis=1)
    d = d / np.maximum(dist, _EPS_DIST)[:, None]
    ci = np.einsum("ij,ij->i", n[i], d)
    cj = np.einsum("ij,ij->i", n[j], d)
    swap = np.abs(ci) < np.abs(cj)  # the end whose normal is closer to the line is the source
    u = np.where(swap[:, None], n[j], n[i])
    nt = np.where(swap[:, None], n[i], n[j])
    d = np.where(swap[:, None], -d, d)
    cos_nd = np.where(swap, -cj, ci)
    v = np.cross(d, u)
    vn = np.linalg.norm(v, axis=1)
    ok = vn > _EPS_CROSS
    v = v / np.where(ok, vn, 1.0)[:, None]
    w = np.cross(u, v)
    twist = np.arctan2(np.einsum("ij,ij->i", w, nt), np.einsum("ij,ij->i", u, nt))
    cos_nv = np.einsum("ij,ij->i", v, nt)
    zero = np.zeros_like(twist)
    return np.where(ok, twist, zero), np.where(ok, cos_nv, zero), np.where(ok, cos_nd, zero)


def feature_bins_ref(twist: np.ndarray, cos_nv: np.ndarray, cos_nd: np.ndarray, bins: int) -> np.ndarray:
    """``(M, 3)`` int64 histogram columns of the three angles, in ``[0, bins)``, ``[bins, 2 bins)`` and
    ``[2 bins, 3 bins)``."""
    b0 = np.clip(((twist + np.pi) / (2 * np.pi) * bins).astype(np.int64), 0, bins - 1)
    b1 = np.clip(((cos_nv + 1) / 2 * bins).astype(np.int64), 0, bins - 1) + bins
    b2 = np.clip(((cos_nd + 1) / 2 * bins).astype(np.int64), 0, bins - 1) + 2 * bins
    return np.stack([b0, b1, b2], axis=1)


def spfh_accumulate_ref(p: np.ndarray, n: np.ndarray, i: np.ndarray, j: np.ndarray,
                        bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Numpy reference of :func:`spfh_accumulate`: ``(counts (N, 3 bins) float64, degree (N,) int64)``."""
    n_pts, width = len(p), 3 * bins
    cols = feature_bins_ref(*pair_features_ref(p, n, i, j), bins)
    ends = np.concatenate([i, j])
    counts = np.zeros(n_pts * width)
    for c in range(3):  # each pair counts towards both of its ends' histograms (the angles are symmetric)
        counts += np.bincount(ends * width + np.concatenate([cols[:, c], cols[:, c]]), minlength=n_pts * width)
    return counts.reshape(n_pts, width), np.bincount(ends, minlength=n_pts).astype(np.int64)


@njit(cache=True, nogil=True)
def spfh_accumulate(p, n, i, j, bins, counts, degree):
    """Add each pair's three binned angles to both ends' rows of ``counts (N, 3 bins)`` float64 and 1 to both
    ends' ``degree (N,)`` int64 (both zeroed by the caller). ``p``, ``n`` ``(N, 3)`` float64; ``i``, ``j``
    ``(M,)`` int64."""
    for k in range(i.shape[0]):
        a = i[k]
        b = j[k]
        dx = p[b, 0] - p[a, 0]
        dy = p[b, 1] - p[a, 1]
        dz = p[b, 2] - p[a, 2]
        dist = max(math.sqrt(dx * dx + dy * dy + dz * dz), _EPS_DIST)
        dx /= dist
        dy /= dist
        dz /= dist
        ci = n[a, 0] * dx + n[a, 1] * dy + n[a, 2] * dz
        cj = n[b, 0] * dx + n[b, 1] * dy + n[b, 2] * dz
        s, t = a, b
        cos_nd = ci
        if abs(ci) < abs(cj):
            s, t = b, a
            dx, dy, dz = -dx, -dy, -dz
            cos_nd = -cj
        ux, uy, uz = n[s, 0], n[s, 1], n[s, 2]
        vx = dy * uz - dz * uy
        vy = dz * ux - dx * uz
        vz = dx * uy - dy * ux
        vn = math.sqrt(vx * vx + vy * vy + vz * vz)
        twist = 0.0
        cos_nv = 0.0
        if vn > _EPS_CROSS:
            vx /= vn
            vy /= vn
            vz /= vn
            wx = uy * vz - uz * vy
            wy = uz * vx - ux * vz
            wz = ux * vy - uy * vx
            tx, ty, tz = n[t, 0], n[t, 1], n[t, 2]
            twist = math.atan2(wx * tx + wy * ty + wz * tz, ux * tx + uy * ty + uz * tz)
            cos_nv = vx * tx + vy * ty + vz * tz
        else:
            cos_nd = 0.0
        b0 = min(max(int((twist + math.pi) / (2 * math.pi) * bins), 0), bins - 1)
        b1 = min(max(int((cos_nv + 1.0) / 2.0 * bins), 0), bins - 1) + bins
        b2 = min(max(int((cos_nd + 1.0) / 2.0 * bins), 0), bins - 1) + 2 * bins
        for e in (a, b):
            counts[e, b0] += 1.0
            counts[e, b1] += 1.0
            counts[e, b2] += 1.0
            degree[e] += 1


def neighbour_sum_ref(p: np.ndarray, i: np.ndarray, j: np.ndarray, spfh: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Numpy reference of :func:`neighbour_sum`: ``(weighted sum (N, D), weight sum (N,))``."""
    from scipy import sparse

    n_pts = len(p)
    wgt = 1.0 / np.maximum(np.linalg.norm(p[i] - p[j], axis=1), _MIN_WEIGHT_DIST_M)
    W = sparse.coo_matrix((np.concatenate([wgt, wgt]), (np.concatenate([i, j]), np.concatenate([j, i]))),
                          shape=(n_pts, n_pts)).tocsr()
    return np.asarray(W @ spfh), np.asarray(W.sum(axis=1)).ravel()


@njit(cache=True, nogil=True)
def neighbour_sum(p, i, j, spfh, acc, wsum):
    """``acc[a] += w spfh[b]``, ``acc[b] += w spfh[a]``, ``wsum[a] += w``, ``wsum[b] += w`` over the pairs, with
    ``w = 1 / max(|p_a - p_b|, 1e-6 m)``. ``acc (N, D)``, ``wsum (N,)`` float64, zeroed by the caller."""
    width = spfh.shape[1]
    for k in range(i.shape[0]):
        a = i[k]
        b = j[k]
        d = math.sqrt((p[a, 0] - p[b, 0]) ** 2 + (p[a, 1] - p[b, 1]) ** 2 + (p[a, 2] - p[b, 2]) ** 2)
        w = 1.0 / max(d, _MIN_WEIGHT_DIST_M)
        for c in range(width):
            acc[a, c] += w * spfh[b, c]
            acc[b, c] += w * spfh[a, c]
        wsum[a] += w
        wsum[b] += w
