"""Depth of keypoints (numba), with numpy references.

Every keypoint reads a few small depth patches: the 3x3 median, an inverse-depth plane fit over a
``(2 r + 1)^2`` patch and an occluding-contour test over another. Vectorised numpy builds ``(N, patch)`` arrays
for each step and a masked median: 1.6-3 ms per frame for 1000 keypoints in the reader thread, against 0.55 ms
here (half of it the batched LAPACK solve, kept so that the results stay those of numpy). The kernels add in
numpy's pairwise order, so their results equal the references bit for bit (tested) and trajectories do not move.

Shared arguments: ``depth_m (H, W)`` float32 metres (0 = invalid); ``ui, vi (N,)`` int64 nearest pixels (clipped
to the image); ``u, v (N,)`` float64 sub-pixel keypoint coordinates.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: A plane fit whose 3x3 normal matrix has a determinant below this times ``max(pixels, 1)^3`` is ill conditioned
#: (the gated pixels lie on a line): the median depth is kept.
MIN_DET_REL = 1e-9


@njit(cache=True, nogil=True)
def _median_3x3(depth_m, ui, vi, min_depth_m, max_depth_m, z):
    """``z[k]`` = median of the valid (in range) depths of the 3x3 patch around ``(ui[k], vi[k])`` (clipped), NaN
    where the centre pixel itself is not valid."""
    h, w = depth_m.shape
    vals = np.empty(9, np.float64)
    for k in range(ui.shape[0]):
        z[k] = np.nan
        c = np.float64(depth_m[vi[k], ui[k]])
        if not (c >= min_depth_m and c <= max_depth_m):
            continue
        n = 0
        for dv in range(-1, 2):
            y = min(max(vi[k] + dv, 0), h - 1)
            for du in range(-1, 2):
                x = min(max(ui[k] + du, 0), w - 1)
                p = np.float64(depth_m[y, x])
                if p >= min_depth_m and p <= max_depth_m:
                    # insertion sort: at most 9 values
                    j = n
                    while j > 0 and vals[j - 1] > p:
                        vals[j] = vals[j - 1]
                        j -= 1
                    vals[j] = p
                    n += 1
        z[k] = vals[n // 2] if n % 2 == 1 else (vals[n // 2 - 1] + vals[n // 2]) / 2.0


_PAIRWISE_BLOCK = 128  # numpy's PW_BLOCKSIZE: sums of at most this many values are not split further
_MAX_SPLITS = 64  # stack depth of the pairwise split: enough for any array that fits in memory


@njit(cache=True, nogil=True)
def _block_sum(a, start, n):
    """numpy's sum of ``n <= 128`` values: sequential below 8, else eight interleaved partial sums, combined in
    pairs, then the rest."""
    if n < 8:
        res = 0.0
        for i in range(start, start + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[start], a[start + 1], a[start + 2], a[start + 3]
    r4, r5, r6, r7 = a[start + 4], a[start + 5], a[start + 6], a[start + 7]
    i = 8
    while i < n - n % 8:
        j = start + i
        r0 += a[j]
        r1 += a[j + 1]
        r2 += a[j + 2]
        r3 += a[j + 3]
        r4 += a[j + 4]
        r5 += a[j + 5]
        r6 += a[j + 6]
        r7 += a[j + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[start + i]
        i += 1
    return res


@njit(cache=True, nogil=True)
def _pairwise_sum(a, n):
    """Sum of ``a[:n]`` in numpy's pairwise order (halves, cut at multiples of 8, down to blocks of 128), so that
    the kernel's sums equal numpy's ``sum`` bit for bit. Iterative: numba's cache cannot reload recursion."""
    if n <= _PAIRWISE_BLOCK:
        return _block_sum(a, np.int64(0), n)  # not the literal 0, which would compile a second signature
    todo_start = np.empty(_MAX_SPLITS * 3, np.int64)
    todo_n = np.empty(_MAX_SPLITS * 3, np.int64)
    todo_join = np.empty(_MAX_SPLITS * 3, np.bool_)
    values = np.empty(_MAX_SPLITS, np.float64)
    top, n_values = 1, 0
    todo_start[0], todo_n[0], todo_join[0] = 0, n, False
    while top > 0:
        top -= 1
        s, m = todo_start[top], todo_n[top]
        if todo_join[top]:  # both halves are done: left + right, in that order
            values[n_values - 2] = values[n_values - 2] + values[n_values - 1]
            n_values -= 1
        elif m <= _PAIRWISE_BLOCK:
            values[n_values] = _block_sum(a, s, m)
            n_values += 1
        else:
            m2 = m // 2
            m2 -= m2 % 8
            todo_join[top] = True
            todo_start[top + 1], todo_n[top + 1], todo_join[top + 1] = s + m2, m - m2, False
            todo_start[top + 2], todo_n[top + 2], todo_join[top + 2] = s, m2, False
            top += 3
    return values[0]


@njit(cache=True, nogil=True)
def plane_fit_sums(depth_m, ui, vi, u, v, z0, radius_px, gate, min_pixels):
    """Normal equations of the weighted least-squares plane ``1/z = a + b du + c dv`` of every keypoint whose
    median depth ``z0`` is finite, over the pixels of its ``(2 r + 1)^2`` patch (inside the image) within
    ``gate * z0`` of it; ``du, dv`` are offsets from the sub-pixel keypoint ``(u, v)``.

    Returns:
        ``(M (N, 3, 3), rhs (N, 3), fit (N,) bool)``; ``fit``: ``z0`` is finite and at least ``min_pixels``
        pixels enter the fit (``M``, ``rhs`` are only filled there).
    """
    h, w = depth_m.shape
    n = ui.shape[0]
    side = 2 * radius_px + 1
    size = side * side
    M = np.zeros((n, 3, 3), np.float64)
    rhs = np.zeros((n, 3), np.float64)
    fit = np.zeros(n, np.bool_)
    terms = np.empty((9, size), np.float64)  # per pixel: w, w du, w dv, w du du, w du dv, w dv dv, i, i du, i dv
    for k in range(n):
        zk = z0[k]
        if not np.isfinite(zk):
            continue
        for iy in range(side):
            y = vi[k] + iy - radius_px
            yc = min(max(y, 0), h - 1)
            dv = y - v[k]
            for ix in range(side):
                x = ui[k] + ix - radius_px
                p = np.float64(depth_m[yc, min(max(x, 0), w - 1)])
                ok = 0 <= x < w and 0 <= y < h and p > 0 and abs(p - zk) <= gate * zk
                wgt = 1.0 if ok else 0.0
                inv = 1.0 / p if ok else 0.0
                du = x - u[k]
                j = iy * side + ix
                terms[0, j] = wgt
                terms[1, j] = wgt * du
                terms[2, j] = wgt * dv
                terms[3, j] = wgt * du * du
                terms[4, j] = wgt * du * dv
                terms[5, j] = wgt * dv * dv
                terms[6, j] = inv
                terms[7, j] = inv * du
                terms[8, j] = inv * dv
        s0 = _pairwise_sum(terms[0], size)
        if not s0 >= min_pixels:
            continue
        fit[k] = True
        su, sv = _pairwise_sum(terms[1], size), _pairwise_sum(terms[2], size)
        M[k, 0, 0] = s0
        M[k, 0, 1] = M[k, 1, 0] = su
        M[k, 0, 2] = M[k, 2, 0] = sv
        M[k, 1, 1] = _pairwise_sum(terms[3], size)
        M[k, 1, 2] = M[k, 2, 1] = _pairwise_sum(terms[4], size)
        M[k, 2, 2] = _pairwise_sum(terms[5], size)
        for c in range(3):
            rhs[k, c] = _pairwise_sum(terms[6 + c], size)
    return M, rhs, fit


def solve_plane_depth(M: np.ndarray, rhs: np.ndarray, fit: np.ndarray, z0: np.ndarray, gate: float) -> np.ndarray:
    """Depth ``(N,)`` at each keypoint from :func:`plane_fit_sums`' systems (batched LAPACK): the plane's where
    ``fit``, the system is well conditioned and its depth lies within ``gate * z0``; ``z0`` elsewhere."""
    z = z0.copy()
    if fit.any():
        Mf = M[fit]
        det = np.linalg.det(Mf)
        good = np.abs(det) > MIN_DET_REL * np.maximum(Mf[:, 0, 0], 1.0) ** 3
        idx = np.flatnonzero(fit)[good]
        a = np.linalg.solve(Mf[good], rhs[fit][good][:, :, None])[:, 0, 0]
        zf = np.where(a > 0, 1.0 / np.where(a > 0, a, 1.0), np.nan)
        keep = np.isfinite(zf) & (np.abs(zf - z0[idx]) <= gate * z0[idx])
        z[idx[keep]] = zf[keep]
    return z


@njit(cache=True, nogil=True)
def depth_edge_flags(depth_m, ui, vi, z, rel, radius_px):
    """``(N,)`` bool: ``z[k]`` is finite and the ``(2 r + 1)^2`` patch (clipped) around ``(ui[k], vi[k])`` holds a
    valid depth more than ``rel * z[k]`` away from it (an occluding contour)."""
    h, w = depth_m.shape
    out = np.zeros(ui.shape[0], np.bool_)
    for k in range(ui.shape[0]):
        zc = z[k]
        if not np.isfinite(zc):
            continue
        lim = rel * zc
        for dy in range(-radius_px, radius_px + 1):
            y = min(max(vi[k] + dy, 0), h - 1)
            for dx in range(-radius_px, radius_px + 1):
                p = np.float64(depth_m[y, min(max(ui[k] + dx, 0), w - 1)])
                if p > 0 and abs(p - zc) > lim:
                    out[k] = True
                    break
            if out[k]:
                break
    return out


@njit(cache=True, nogil=True)
def _nearest_in_range(depth_m, ui, vi, min_depth_m, max_depth_m, z):
    """``z[k]`` = the depth of pixel ``(ui[k], vi[k])``, NaN out of ``[min_depth_m, max_depth_m]``."""
    for k in range(ui.shape[0]):
        p = np.float64(depth_m[vi[k], ui[k]])
        z[k] = p if (p >= min_depth_m and p <= max_depth_m) else np.nan


def keypoint_depths(depth_m, ui, vi, u, v, median_3x3, plane_radius_px, plane_gate, plane_min_pixels,
                    edge_rel, edge_radius_px, min_depth_m, max_depth_m):
    """Depth (m) of each keypoint, ``(N,)`` float64, NaN where it has none (see :class:`FeatureConfig` for the
    steps and their parameters): numba kernels for the patches, batched LAPACK for the plane fits."""
    z = np.empty(len(ui), np.float64)
    if median_3x3:
        _median_3x3(depth_m, ui, vi, min_depth_m, max_depth_m, z)
        if plane_radius_px > 0:
            M, rhs, fit = plane_fit_sums(depth_m, ui, vi, u, v, z, plane_radius_px, plane_gate, plane_min_pixels)
            z = solve_plane_depth(M, rhs, fit, z, plane_gate)
    else:
        _nearest_in_range(depth_m, ui, vi, min_depth_m, max_depth_m, z)
    if edge_rel > 0:
        z[depth_edge_flags(depth_m, ui, vi, z, edge_rel, edge_radius_px)] = np.nan
    return z


def keypoint_depths_ref(depth_m, ui, vi, u, v, median_3x3, plane_radius_px, plane_gate, plane_min_pixels,
                        edge_rel, edge_radius_px, min_depth_m, max_depth_m):
    """Numpy reference of :func:`keypoint_depths`."""
    h, w = depth_m.shape
    if median_3x3:
        offs = np.array([-1, 0, 1])
        uu = np.clip(ui[:, None, None] + offs[None, None, :], 0, w - 1)
        vv = np.clip(vi[:, None, None] + offs[None, :, None], 0, h - 1)
        patch = depth_m[vv, uu].reshape(len(ui), 9).astype(np.float64)
        ok = (patch >= min_depth_m) & (patch <= max_depth_m)
        patch[~ok] = np.nan
        z = np.full(len(ui), np.nan)
        some = ok.any(axis=1)
        z[some] = np.nanmedian(patch[some], axis=1)
        z[~ok[:, 4]] = np.nan  # the centre pixel must itself be valid
        if plane_radius_px > 0:
            M, rhs, fit = plane_fit_sums_ref(depth_m, ui, vi, u, v, z, plane_radius_px, plane_gate, plane_min_pixels)
            z = solve_plane_depth(M, rhs, fit, z, plane_gate)
    else:
        z = depth_m[vi, ui].astype(np.float64)
        z[(z < min_depth_m) | (z > max_depth_m)] = np.nan
    if edge_rel > 0:
        z[depth_edge_flags_ref(depth_m, ui, vi, z, edge_rel, edge_radius_px)] = np.nan
    return z


def depth_edge_flags_ref(depth_m, ui, vi, z, rel, radius_px):
    """Numpy reference of :func:`depth_edge_flags`."""
    h, w = depth_m.shape
    offs = np.arange(-radius_px, radius_px + 1)
    uu = np.clip(ui[:, None, None] + offs[None, None, :], 0, w - 1)
    vv = np.clip(vi[:, None, None] + offs[None, :, None], 0, h - 1)
    patch = depth_m[vv, uu].reshape(len(ui), -1)
    zc = np.where(np.isfinite(z), z, 0.0)[:, None]
    return ((patch > 0) & (np.abs(patch - zc) > rel * zc)).any(axis=1) & np.isfinite(z)


def plane_fit_sums_ref(depth_m, ui, vi, u, v, z0, radius_px, gate, min_pixels):
    """Numpy reference of :func:`plane_fit_sums`."""
    h, w = depth_m.shape
    offs = np.arange(-radius_px, radius_px + 1)
    n = len(ui)
    uu, vv = np.broadcast_arrays(ui[:, None, None] + offs[None, None, :], vi[:, None, None] + offs[None, :, None])
    uu, vv = uu.reshape(n, -1), vv.reshape(n, -1)
    inside = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
    patch = depth_m[np.clip(vv, 0, h - 1), np.clip(uu, 0, w - 1)].astype(np.float64)
    du = uu - u[:, None]
    dv = vv - v[:, None]
    ok = inside & (patch > 0) & (np.abs(patch - z0[:, None]) <= gate * z0[:, None])
    wgt = ok.astype(np.float64)
    inv = np.where(ok, 1.0 / np.where(patch > 0, patch, 1.0), 0.0)
    M = np.empty((n, 3, 3))
    M[:, 0, 0] = wgt.sum(1)
    M[:, 0, 1] = M[:, 1, 0] = (wgt * du).sum(1)
    M[:, 0, 2] = M[:, 2, 0] = (wgt * dv).sum(1)
    M[:, 1, 1] = (wgt * du * du).sum(1)
    M[:, 1, 2] = M[:, 2, 1] = (wgt * du * dv).sum(1)
    M[:, 2, 2] = (wgt * dv * dv).sum(1)
    rhs = np.stack([inv.sum(1), (inv * du).sum(1), (inv * dv).sum(1)], axis=1)
    fit = (M[:, 0, 0] >= min_pixels) & np.isfinite(z0)
    return M, rhs, fit
