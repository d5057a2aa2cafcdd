"""Joint RGB-D refinement of a PnP pose in one kernel: Gauss-Newton over reprojection and inverse-depth residuals.

The numpy reference is :func:`surfelslam.tracking.features.refine.refine_rgbd_ref`. It runs on every frame's PnP
match in the hybrid and on every keyframe edge check, on a few hundred points, where numpy's per-call overhead, not
the arithmetic, was the cost. Results agree with the reference to float rounding (the sums run in another order
than BLAS's).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from surfelslam.kernels.icp import cholesky_solve6, copy_pose, se3_exp_left_update

_MAD_TO_SIGMA = 1.4826  # median absolute deviation -> standard deviation of a Gaussian (as robust_sigma)


@njit(cache=True, nogil=True)
def median(v):
    """``np.median`` of ``v (N,)`` float64, to the bit (NaN when empty or when ``v`` holds a NaN), by quickselect on a
    copy: numba's own ``np.median`` takes seconds to compile in every cold start, this a fraction of one."""
    n = v.shape[0]
    if n == 0:
        return np.nan
    a = v.copy()
    for i in range(n):
        if a[i] != a[i]:
            return np.nan
    half = n >> 1
    lo, hi = 0, n - 1
    while lo < hi:  # Hoare's selection: a[half] ends as the half-th smallest, everything before it no larger
        pivot = a[(lo + hi) >> 1]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if half <= j:
            hi = j
        elif half >= i:
            lo = i
        else:
            break
    upper = a[half]
    if n & 1:
        return upper
    lower = a[0]
    for i in range(1, half):
        lower = max(lower, a[i])
    return (lower + upper) / 2


@njit(cache=True, nogil=True)
def _robust_sigma(v):
    """``1.4826 * median(|v - median(v)|)`` of ``v (N,)``."""
    return _MAD_TO_SIGMA * median(np.abs(v - median(v)))


@njit(cache=True, nogil=True)
def _to_cam(T, P, i):
    """Point ``P[i]`` in the camera frame of ``T``: ``(x, y, z)``."""
    x = T[0, 0] * P[i, 0] + T[0, 1] * P[i, 1] + T[0, 2] * P[i, 2] + T[0, 3]
    y = T[1, 0] * P[i, 0] + T[1, 1] * P[i, 1] + T[1, 2] * P[i, 2] + T[1, 3]
    z = T[2, 0] * P[i, 0] + T[2, 1] * P[i, 1] + T[2, 2] * P[i, 2] + T[2, 3]
    return x, y, z


@njit(cache=True, nogil=True)
def _sigmas(T, P, uv, q, w_inv, fx, fy, cx, cy, min_points_pixel, default_pixel_sigma, min_pixel_sigma,
            min_points_depth, model_inv_sigma):
    """The pixel and inverse-depth sigmas at ``T``: the data's robust spreads, bounded below (as the reference's
    ``pixel_sigma`` and ``spread``)."""
    n = P.shape[0]
    if n < min_points_pixel:
        sp = default_pixel_sigma
    else:
        res = np.empty(2 * n)
        k = 0
        for i in range(n):
            x, y, z = _to_cam(T, P, i)
            if z > 0:
                res[k] = fx * x / z + cx - uv[i, 0]
                k += 1
        m = k
        for i in range(n):
            _, y, z = _to_cam(T, P, i)
            if z > 0:
                res[k] = fy * y / z + cy - uv[i, 1]
                k += 1
        spread = 0.0 if m < min_points_pixel else _robust_sigma(res[:k])
        sp = max(min_pixel_sigma, spread)
    n_depth = 0
    for i in range(n):
        if w_inv[i]:
            n_depth += 1
    if n_depth < min_points_depth:
        return sp, model_inv_sigma
    d = np.empty(n_depth)
    k = 0
    for i in range(n):
        if w_inv[i]:
            z = _to_cam(T, P, i)[2]
            d[k] = 1.0 / z - q[i]
            k += 1
    return sp, max(model_inv_sigma, _robust_sigma(d))


@njit(cache=True, nogil=True)
def _normal_equations(T, P, uv, q, w_inv, sp, si, fx, fy, cx, cy, huber, H, g):
    """Huber-weighted ``H (6, 6)``, ``g (6,)`` at ``T`` for a left update ``exp(xi) T``, ``xi = (omega, v)``;
    False if a point is behind the camera."""
    H[:, :] = 0.0
    g[:] = 0.0
    J = np.empty((3, 6))
    r = np.empty(3)
    for i in range(P.shape[0]):
        x, y, z = _to_cam(T, P, i)
        if z <= 0:
            return False
        iz = 1.0 / z
        # d(point)/d(xi) = [-[X]x | I]; projection and inverse-depth derivatives on top
        a_u, c_u = fx * iz, -fx * x * iz * iz
        b_v, c_v = fy * iz, -fy * y * iz * iz
        c_d = -iz * iz
        # rows: u, v, 1/z; columns: omega (3), v (3)
        J[0, 0] = c_u * y
        J[0, 1] = a_u * z - c_u * x
        J[0, 2] = -a_u * y
        J[0, 3] = a_u
        J[0, 4] = 0.0
        J[0, 5] = c_u
        J[1, 0] = -b_v * z + c_v * y
        J[1, 1] = -c_v * x
        J[1, 2] = b_v * x
        J[1, 3] = 0.0
        J[1, 4] = b_v
        J[1, 5] = c_v
        J[2, 0] = c_d * y
        J[2, 1] = -c_d * x
        J[2, 2] = 0.0
        J[2, 3] = 0.0
        J[2, 4] = 0.0
        J[2, 5] = c_d
        r[0] = (fx * x * iz + cx - uv[i, 0]) / sp
        r[1] = (fy * y * iz + cy - uv[i, 1]) / sp
        n_rows = 3 if w_inv[i] else 2
        r[2] = (iz - q[i]) / si if w_inv[i] else 0.0
        for a in range(n_rows):
            s = sp if a < 2 else si
            ra = abs(r[a])
            w = 1.0 if ra <= huber else huber / max(ra, 1e-12)
            for c in range(6):
                jc = J[a, c] / s
                g[c] += w * jc * r[a]
                for e in range(c, 6):
                    H[c, e] += w * jc * (J[a, e] / s)
    for c in range(6):
        for e in range(c):
            H[c, e] = H[e, c]
    return True


@njit(cache=True, nogil=True)
def _all_finite(A):
    """Whether every entry of the 2-D ``A`` is finite."""
    for i in range(A.shape[0]):
        for j in range(A.shape[1]):
            if not np.isfinite(A[i, j]):
                return False
    return True


@njit(cache=True, nogil=True)
def _any_behind(T, P):
    """Whether a point of ``P`` is not in front of the camera of ``T``."""
    for i in range(P.shape[0]):
        if _to_cam(T, P, i)[2] <= 0:
            return True
    return False


@njit(cache=True, nogil=True)
def rgbd_refine(T0, P, uv, q, w_inv, fx, fy, cx, cy, iterations, huber, min_points_pixel, default_pixel_sigma,
                min_pixel_sigma, min_points_depth, model_inv_sigma, converged, with_information, T_out, H_out):
    """Refine ``T0 (4, 4)`` (``T_cur_ref``) on ``P (N, 3)`` reference points, ``uv (N, 2)`` their current pixels and
    ``q (N,)`` the measured inverse depths (used where ``w_inv (N,)`` bool). Writes ``T_out (4, 4)``; with
    ``with_information``, the Hessian at ``T_out`` into ``H_out (6, 6)``. Returns whether ``H_out`` holds one.
    """
    T = T0.copy()
    T_next = np.empty((4, 4))
    H = np.empty((6, 6))
    g = np.empty(6)
    rhs = np.empty(6)
    xi = np.empty(6)
    for _ in range(iterations):
        if _any_behind(T, P):
            break
        sp, si = _sigmas(T, P, uv, q, w_inv, fx, fy, cx, cy, min_points_pixel, default_pixel_sigma,
                         min_pixel_sigma, min_points_depth, model_inv_sigma)
        if not _normal_equations(T, P, uv, q, w_inv, sp, si, fx, fy, cx, cy, huber, H, g):
            break
        if not _all_finite(H):
            break
        for c in range(6):
            rhs[c] = -g[c]
        if not cholesky_solve6(H, rhs, xi):  # H is J^T W J: singular or not positive definite, no step
            break
        se3_exp_left_update(xi, T, T_next)
        copy_pose(T_next, T)
        if np.sqrt(np.sum(xi * xi)) < converged:
            break
    copy_pose(T, T_out)
    if not with_information or not _all_finite(T):
        return False
    if _any_behind(T, P):
        return False
    sp, si = _sigmas(T, P, uv, q, w_inv, fx, fy, cx, cy, min_points_pixel, default_pixel_sigma, min_pixel_sigma,
                     min_points_depth, model_inv_sigma)
    if not _normal_equations(T, P, uv, q, w_inv, sp, si, fx, fy, cx, cy, huber, H_out, g):
        return False
    return _all_finite(H_out)
