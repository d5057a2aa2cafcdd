"""Projective data association and point-to-plane normal equations (numba), with numpy references.

For every valid source pixel ``p`` (camera frame of the source) with normal ``n_p``:

    p' = R p + t                      (current estimate of T_target_source)
    (u, v) = nearest pixel of p' in the target image
    q, n_q = target vertex / normal at (u, v)

The pair is an inlier when ``(u, v)`` is inside the image, ``q_z > 0``, ``n_q != 0``,
``|p' - q| < dist_thresh_m`` and ``(R n_p) . n_q >= cos(angle_thresh)``. Each inlier contributes

    A_i = n_q^T [-[p']x  I] = [ (p' x n_q)^T , n_q^T ]        (1 x 6, twist xi = (omega, t))
    b_i = n_q^T (p' - q)                                        (signed point-to-plane residual, m)

with robust weight ``w_i = rho'(b_i) / b_i`` (optionally depth-scaled: ``w_i = w(b_i / s_i) / s_i^2`` with
``s_i = (p'_z / depth_ref_m)^2``) to ``A^T W A`` and ``A^T W b``; the Gauss-Newton step solves
``(A^T W A) xi = -A^T W b`` and updates ``T <- exp(xi) T``.

Layout of the accumulated vector (``N_STATS`` float64 values):
    [0:21]  upper triangle of A^T W A, row-major ((0,0), (0,1), ..., (0,5), (1,1), ..., (5,5))
    [21:27] A^T W b
    [27]    sum w_i b_i^2          [28] sum b_i^2 (unweighted)
    [29]    inlier count           [30] sum of inlier source depths p_z (m)
    [31]    number of valid source points (z > 0 and normal != 0)
    [32]    of those, the points that land on a valid target pixel (the overlap with the model: the others see
            space the target does not hold, e.g. a room seen for the first time through a doorway)

Determinism: source rows are split into ``N_CHUNKS`` fixed chunks (independent of the thread count);
each chunk accumulates its own partial sums in row-major pixel order and the chunks are added in
chunk order, so the result is bit-identical for any number of threads.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from surfelslam.kernels.threads import dual_njit

N_CHUNKS = 8

# Only fused multiply-add contraction: no reassociation, so the per-chunk summation order (and the
# result) stays fixed; results differ from the numpy references by float rounding only.
_FASTMATH = {"contract"}
N_STATS = 33

ROBUST_NONE = 0
ROBUST_HUBER = 1
ROBUST_TUKEY = 2
ROBUST_KINDS = {"none": ROBUST_NONE, "huber": ROBUST_HUBER, "tukey": ROBUST_TUKEY}


@njit(cache=True, nogil=True)
def _robust_weight(r, kind, scale):
    if kind == ROBUST_HUBER:
        a = abs(r)
        return 1.0 if a <= scale else scale / a
    if kind == ROBUST_TUKEY:
        x = r / scale
        if abs(x) >= 1.0:
            return 0.0
        y = 1.0 - x * x
        return y * y
    return 1.0


def robust_weight_ref(r: np.ndarray, kind: int, scale: float) -> np.ndarray:
    """Numpy reference of the per-residual robust weight."""
    r = np.asarray(r, dtype=np.float64)
    if kind == ROBUST_HUBER:
        a = np.abs(r)
        return np.where(a <= scale, 1.0, scale / np.where(a > 0, a, 1.0))
    if kind == ROBUST_TUKEY:
        x = r / scale
        return np.where(np.abs(x) < 1.0, (1.0 - x * x) ** 2, 0.0)
    return np.ones_like(r)


@njit(cache=True, nogil=True, fastmath=_FASTMATH, error_model="numpy")
def _normal_equations_chunk(src_vertex, src_normal, tgt_vertex, tgt_normal, T, fx, fy, cx, cy, dist_thresh_m,
                            cos_angle_thresh, robust_kind, robust_scale_m, src_stride, depth_ref_m, c, pc):
    """Chunk ``c`` of :func:`accumulate_normal_equations` (its source rows), sums into ``pc (N_STATS,)``.

    A function of its own, called from the ``prange`` loop: numba's parallel pass then handles a loop of one call
    instead of this body, which cuts the parallel twin's compile time several-fold (same code, same results).
    """
    H, W = src_vertex.shape[0], src_vertex.shape[1]
    Ht, Wt = tgt_vertex.shape[0], tgt_vertex.shape[1]
    r00, r01, r02, t0 = T[0, 0], T[0, 1], T[0, 2], T[0, 3]
    r10, r11, r12, t1 = T[1, 0], T[1, 1], T[1, 2], T[1, 3]
    r20, r21, r22, t2 = T[2, 0], T[2, 1], T[2, 2], T[2, 3]
    d2max = dist_thresh_m * dist_thresh_m
    zref2 = depth_ref_m * depth_ref_m if depth_ref_m > 0.0 else 0.0
    # scalar accumulators (kept in registers): s0..s20 AtA, s21..s26 Atb, then the counters
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = s8 = s9 = s10 = 0.0
    s11 = s12 = s13 = s14 = s15 = s16 = s17 = s18 = s19 = s20 = 0.0
    s21 = s22 = s23 = s24 = s25 = s26 = 0.0
    s27 = s28 = s29 = s30 = s31 = s32 = 0.0
    row0 = (c * H) // N_CHUNKS
    row1 = ((c + 1) * H) // N_CHUNKS
    for v in range(row0, row1):
        if v % src_stride != 0:
            continue
        for u in range(0, W, src_stride):
            pz0 = np.float64(src_vertex[v, u, 2])
            if pz0 <= 0.0:
                continue
            nx0 = np.float64(src_normal[v, u, 0])
            ny0 = np.float64(src_normal[v, u, 1])
            nz0 = np.float64(src_normal[v, u, 2])
            if nx0 == 0.0 and ny0 == 0.0 and nz0 == 0.0:
                continue
            s31 += 1.0
            px0 = np.float64(src_vertex[v, u, 0])
            py0 = np.float64(src_vertex[v, u, 1])
            px = r00 * px0 + r01 * py0 + r02 * pz0 + t0
            py = r10 * px0 + r11 * py0 + r12 * pz0 + t1
            pz = r20 * px0 + r21 * py0 + r22 * pz0 + t2
            if pz <= 0.0:
                continue
            iz = 1.0 / pz
            uf = fx * px * iz + cx + 0.5  # nearest pixel = floor(uf)
            vf = fy * py * iz + cy + 0.5
            if uf < 0.0 or uf >= Wt or vf < 0.0 or vf >= Ht:
                continue
            ui = int(uf)
            vi = int(vf)
            qz = np.float64(tgt_vertex[vi, ui, 2])
            if qz <= 0.0:
                continue
            s32 += 1.0
            dx = px - tgt_vertex[vi, ui, 0]
            dy = py - tgt_vertex[vi, ui, 1]
            dz = pz - qz
            if dx * dx + dy * dy + dz * dz >= d2max:
                continue
            mx = np.float64(tgt_normal[vi, ui, 0])
            my = np.float64(tgt_normal[vi, ui, 1])
            mz = np.float64(tgt_normal[vi, ui, 2])
            rnx = r00 * nx0 + r01 * ny0 + r02 * nz0
            rny = r10 * nx0 + r11 * ny0 + r12 * nz0
            rnz = r20 * nx0 + r21 * ny0 + r22 * nz0
            if rnx * mx + rny * my + rnz * mz < cos_angle_thresh:
                continue
            b = mx * dx + my * dy + mz * dz
            if zref2 > 0.0:
                isz = zref2 * iz * iz  # 1 / s with s = (p'_z / depth_ref_m)^2 (iz = 1 / p'_z, from above)
                w = _robust_weight(b * isz, robust_kind, robust_scale_m) * (isz * isz)
            else:
                w = _robust_weight(b, robust_kind, robust_scale_m)
            a0 = py * mz - pz * my
            a1 = pz * mx - px * mz
            a2 = px * my - py * mx
            wa0 = w * a0
            wa1 = w * a1
            wa2 = w * a2
            wa3 = w * mx
            wa4 = w * my
            wa5 = w * mz
            s0 += wa0 * a0
            s1 += wa0 * a1
            s2 += wa0 * a2
            s3 += wa0 * mx
            s4 += wa0 * my
            s5 += wa0 * mz
            s6 += wa1 * a1
            s7 += wa1 * a2
            s8 += wa1 * mx
            s9 += wa1 * my
            s10 += wa1 * mz
            s11 += wa2 * a2
            s12 += wa2 * mx
            s13 += wa2 * my
            s14 += wa2 * mz
            s15 += wa3 * mx
            s16 += wa3 * my
            s17 += wa3 * mz
            s18 += wa4 * my
            s19 += wa4 * mz
            s20 += wa5 * mz
            s21 += wa0 * b
            s22 += wa1 * b
            s23 += wa2 * b
            s24 += wa3 * b
            s25 += wa4 * b
            s26 += wa5 * b
            s27 += w * b * b
            s28 += b * b
            s29 += 1.0
            s30 += pz0
    pc[0] = s0
    pc[1] = s1
    pc[2] = s2
    pc[3] = s3
    pc[4] = s4
    pc[5] = s5
    pc[6] = s6
    pc[7] = s7
    pc[8] = s8
    pc[9] = s9
    pc[10] = s10
    pc[11] = s11
    pc[12] = s12
    pc[13] = s13
    pc[14] = s14
    pc[15] = s15
    pc[16] = s16
    pc[17] = s17
    pc[18] = s18
    pc[19] = s19
    pc[20] = s20
    pc[21] = s21
    pc[22] = s22
    pc[23] = s23
    pc[24] = s24
    pc[25] = s25
    pc[26] = s26
    pc[27] = s27
    pc[28] = s28
    pc[29] = s29
    pc[30] = s30
    pc[31] = s31
    pc[32] = s32


@dual_njit(fastmath=_FASTMATH, error_model="numpy")
def accumulate_normal_equations(src_vertex, src_normal, tgt_vertex, tgt_normal, T, fx, fy, cx, cy,
                                dist_thresh_m, cos_angle_thresh, robust_kind, robust_scale_m, out,
                                src_stride=1, depth_ref_m=0.0):
    """One association pass + accumulation of the weighted normal equations.

    Args:
        src_vertex, src_normal: ``(H, W, 3)`` float32 source camera frame (invalid: ``z <= 0`` / zero normal).
        tgt_vertex, tgt_normal: ``(H', W', 3)`` float32 target camera frame.
        T: ``(4, 4)`` float64 current ``T_target_source``.
        fx, fy, cx, cy: target intrinsics (``fy`` may be negative).
        dist_thresh_m: maximum ``|p' - q|``; cos_angle_thresh: minimum ``(R n_p) . n_q``.
        robust_kind: ``ROBUST_NONE | ROBUST_HUBER | ROBUST_TUKEY``; robust_scale_m: kernel scale (m).
        out: ``(N_STATS,)`` float64, receives the sums (layout in the module docstring).
        src_stride: use only source pixels ``[::src_stride, ::src_stride]`` (1 = all).
        depth_ref_m: depth-dependent weighting (0 = off): the residual's noise scale is
            ``s = (p'_z / depth_ref_m)^2`` (Kinect axial noise grows with z^2; ``p'_z`` = depth of the
            transformed source point in the target camera, within the distance gate of ``q_z``), the robust
            weight is taken of ``b / s`` and the pair's weight is divided by ``s^2``.
    """
    partial = np.zeros((N_CHUNKS, N_STATS))
    for c in prange(N_CHUNKS):
        _normal_equations_chunk(src_vertex, src_normal, tgt_vertex, tgt_normal, T, fx, fy, cx, cy, dist_thresh_m,
                                cos_angle_thresh, robust_kind, robust_scale_m, src_stride, depth_ref_m, np.int64(c),
                                partial[c])
    for k in range(N_STATS):
        s = 0.0
        for c in range(N_CHUNKS):
            s += partial[c, k]
        out[k] = s


def build_linear_system_ref(src_vertex, src_normal, tgt_vertex, tgt_normal, T, fx, fy, cx, cy,
                            dist_thresh_m, cos_angle_thresh, robust_kind=ROBUST_NONE, robust_scale_m=1.0,
                            src_stride=1, depth_ref_m=0.0):
    """Numpy reference: the explicit system of :func:`accumulate_normal_equations`.

    Returns:
        ``(A (N, 6), b (N,), w (N,), src_z (N,), n_valid_source)`` for the N inliers, in row-major
        source-pixel order; ``A^T diag(w) A`` and ``A^T diag(w) b`` are the normal equations.
    """
    P0 = src_vertex[::src_stride, ::src_stride].reshape(-1, 3).astype(np.float64)
    N0 = src_normal[::src_stride, ::src_stride].reshape(-1, 3).astype(np.float64)
    ok = (P0[:, 2] > 0) & np.any(N0 != 0, axis=1)
    n_valid = int(ok.sum())
    P0, N0 = P0[ok], N0[ok]
    R, t = np.asarray(T[:3, :3], np.float64), np.asarray(T[:3, 3], np.float64)
    P = P0 @ R.T + t
    Nr = N0 @ R.T
    Ht, Wt = tgt_vertex.shape[:2]
    front = P[:, 2] > 0
    iz = 1.0 / np.where(front, P[:, 2], 1.0)
    uf = fx * P[:, 0] * iz + cx + 0.5  # nearest pixel = floor(uf), as in the kernel
    vf = fy * P[:, 1] * iz + cy + 0.5
    inside = front & (uf >= 0) & (uf < Wt) & (vf >= 0) & (vf < Ht)
    ui = np.where(inside, np.floor(uf), 0).astype(np.int64)
    vi = np.where(inside, np.floor(vf), 0).astype(np.int64)
    Q = tgt_vertex[vi, ui].astype(np.float64)
    M = tgt_normal[vi, ui].astype(np.float64)
    D = P - Q
    keep = inside & (Q[:, 2] > 0)
    keep &= np.sum(D * D, axis=1) < dist_thresh_m**2
    keep &= np.sum(Nr * M, axis=1) >= cos_angle_thresh
    P, M, D, z = P[keep], M[keep], D[keep], P0[keep, 2]
    A = np.concatenate([np.cross(P, M), M], axis=1)
    b = np.sum(M * D, axis=1)
    if depth_ref_m > 0:
        sz = (P[:, 2] / depth_ref_m) ** 2
        w = robust_weight_ref(b / sz, robust_kind, robust_scale_m) / sz**2
    else:
        w = robust_weight_ref(b, robust_kind, robust_scale_m)
    return A, b, w, z, n_valid


def normal_equations_ref(A: np.ndarray, b: np.ndarray, w: np.ndarray | None = None):
    """``(A^T W A (6, 6), A^T W b (6,))`` from the explicit system."""
    if w is None:
        w = np.ones(len(b))
    Aw = A * w[:, None]
    return Aw.T @ A, Aw.T @ b


def unpack_normal_equations(stats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Accumulated vector -> ``(AtA (6, 6) symmetric, Atb (6,))``."""
    H = np.empty((6, 6))
    iu = np.triu_indices(6)
    H[iu] = stats[:21]
    H.T[iu] = stats[:21]
    return H, stats[21:27].copy()


@njit(cache=True, nogil=True)
def _unpack_lower(stats, H):
    """Upper triangle of ``A^T W A`` from ``stats`` into the lower triangle of ``H (6, 6)`` (column j, rows >= j)."""
    k = 0
    for i in range(6):
        for j in range(i, 6):
            H[j, i] = stats[k]
            k += 1


@njit(cache=True, nogil=True)
def cholesky_solve6(L, rhs, x):
    """Solve ``A x = rhs`` for a symmetric positive definite ``A (6, 6)`` given by its lower triangle in ``L``.

    ``L`` is factorised in place (``A = L L^T``); ``x (6,)`` receives the solution. Returns ``False`` (``x``
    untouched) when ``A`` is not positive definite. A hand-written 6x6 Cholesky: numba's LAPACK-backed
    ``np.linalg.solve`` costs seconds of compile time per kernel that uses it.
    """
    for j in range(6):
        d = L[j, j]
        for m in range(j):
            d -= L[j, m] * L[j, m]
        if not d > 0.0:
            return False
        d = np.sqrt(d)
        L[j, j] = d
        for i in range(j + 1, 6):
            s = L[i, j]
            for m in range(j):
                s -= L[i, m] * L[j, m]
            L[i, j] = s / d
    # forward (L y = rhs) and backward (L^T x = y) substitution
    for i in range(6):
        s = rhs[i]
        for m in range(i):
            s -= L[i, m] * x[m]
        x[i] = s / L[i, i]
    for i in range(5, -1, -1):
        s = x[i]
        for m in range(i + 1, 6):
            s -= L[m, i] * x[m]
        x[i] = s / L[i, i]
    return True


@njit(cache=True, nogil=True)
def gauss_newton_step(stats, T, T_out):
    """Cholesky solve of the accumulated normal equations and the update ``T_out = exp(xi) T``.

    Args:
        stats: ``(N_STATS,)`` from :func:`accumulate_normal_equations`.
        T: ``(4, 4)`` float64 current pose. T_out: ``(4, 4)`` float64, receives the updated pose.

    Returns:
        the twist norm ``|xi|``, or ``-1.0`` when ``A^T W A`` is not positive definite (``T_out = T``).
    """
    L = np.zeros((6, 6))
    _unpack_lower(stats, L)
    rhs = np.empty(6)
    for i in range(6):
        rhs[i] = -stats[21 + i]
    xi = np.empty(6)
    if not cholesky_solve6(L, rhs, xi):
        copy_pose(T, T_out)
        return -1.0
    se3_exp_left_update(xi, T, T_out)
    return np.sqrt(np.sum(xi * xi))


@njit(cache=True, nogil=True)
def copy_pose(T, T_out):
    """``T_out[:, :] = T`` for ``(4, 4)`` poses, as a loop: numba's array-to-array slice assignment compiles its
    shape-mismatch error message, seconds of compile time for a 16-element copy."""
    for i in range(4):
        for j in range(4):
            T_out[i, j] = T[i, j]


@njit(cache=True, nogil=True)
def se3_exp_left_update(xi, T, T_out):
    """``T_out = exp(xi) @ T`` for a twist ``xi = (omega, v)`` (closed-form SE(3) exponential).

    The small products go through numba's BLAS bindings, as they always have: a scalar rewrite compiles faster
    but rounds differently, and every tracker's poses would move in the last bits.
    """
    wx, wy, wz = xi[0], xi[1], xi[2]
    th2 = wx * wx + wy * wy + wz * wz
    th = np.sqrt(th2)
    if th < 1e-8:
        a = 1.0 - th2 / 6.0
        b = 0.5 - th2 / 24.0
        c = 1.0 / 6.0 - th2 / 120.0
    else:
        a = np.sin(th) / th
        b = (1.0 - np.cos(th)) / th2
        c = (th - np.sin(th)) / (th2 * th)
    W = np.empty((3, 3))
    W[0, 0], W[0, 1], W[0, 2] = 0.0, -wz, wy
    W[1, 0], W[1, 1], W[1, 2] = wz, 0.0, -wx
    W[2, 0], W[2, 1], W[2, 2] = -wy, wx, 0.0
    W2 = W @ W
    # R = I + a W + b W2 and V = I + b W + c W2, element by element (the same roundings as the array expressions)
    E = np.zeros((4, 4))
    V = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            eye = 1.0 if i == j else 0.0
            E[i, j] = (eye + a * W[i, j]) + b * W2[i, j]
            V[i, j] = (eye + b * W[i, j]) + c * W2[i, j]
    t = V @ xi[3:]
    for i in range(3):
        E[i, 3] = t[i]
    E[3, 3] = 1.0
    copy_pose(E @ T, T_out)


_JACOBI_MAX_SWEEPS = 50  # cyclic Jacobi converges quadratically: a 6x6 needs about 6-10 sweeps
_JACOBI_OFF_REL = 1e-30  # converged: squared off-diagonal norm below this times the squared diagonal (1e-15 relative)
_JACOBI_THETA_MAX = 1e150  # beyond it theta^2 overflows; the rotation's tangent is then 1 / (2 theta)


@njit(cache=True, nogil=True)
def jacobi_eigh6(A, lam, V):
    """Eigen-decomposition of a symmetric ``A (6, 6)`` (destroyed) by cyclic Jacobi rotations: ``lam (6,)``
    ascending, ``V (6, 6)`` the unit eigenvectors as columns. Hand-written, as :func:`cholesky_solve6`: numba's
    LAPACK-backed ``np.linalg.eigh`` cost 2 s more of compile time; Jacobi also keeps the small eigenvalues of a
    graded (near-degenerate) matrix to high relative accuracy, and a non-finite matrix comes back as its diagonal
    instead of raising."""
    n = 6
    for i in range(n):
        for j in range(n):
            V[i, j] = 1.0 if i == j else 0.0
    for _ in range(_JACOBI_MAX_SWEEPS):
        off = 0.0
        diag = 0.0
        for i in range(n):
            diag += A[i, i] * A[i, i]
            for j in range(i + 1, n):
                off += A[i, j] * A[i, j]
        if not off > _JACOBI_OFF_REL * diag:  # converged (also stops on a zero or non-finite matrix)
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = A[p, q]
                if apq == 0.0:
                    continue
                theta = (A[q, q] - A[p, p]) / (2.0 * apq)
                if abs(theta) > _JACOBI_THETA_MAX:
                    t = 0.5 / theta
                else:
                    t = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0))
                    if theta < 0.0:
                        t = -t
                c = 1.0 / np.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):  # A <- A J (columns p, q)
                    akp = A[k, p]
                    akq = A[k, q]
                    A[k, p] = c * akp - s * akq
                    A[k, q] = s * akp + c * akq
                for k in range(n):  # A <- J^T A (rows p, q)
                    apk = A[p, k]
                    aqk = A[q, k]
                    A[p, k] = c * apk - s * aqk
                    A[q, k] = s * apk + c * aqk
                for k in range(n):
                    vkp = V[k, p]
                    vkq = V[k, q]
                    V[k, p] = c * vkp - s * vkq
                    V[k, q] = s * vkp + c * vkq
    for i in range(n):
        lam[i] = A[i, i]
    for i in range(1, n):  # insertion sort, ascending, columns of V alongside
        j = i
        while j > 0 and lam[j - 1] > lam[j]:
            lam[j - 1], lam[j] = lam[j], lam[j - 1]
            for k in range(n):
                V[k, j - 1], V[k, j] = V[k, j], V[k, j - 1]
            j -= 1


@njit(cache=True, nogil=True)
def remapped_gauss_newton_step(stats, mean_depth_m, max_ratio, T, T_out):
    """Solution remapping (numpy reference: :func:`remapped_step_ref`) and the update.

    Eigen-decomposes ``S AtA S`` (``S = diag(1/d, 1/d, 1/d, 1, 1, 1)``, ``d = mean_depth_m``); when some
    eigenvalue is below the largest divided by ``max_ratio``, solves in the other directions only and sets
    ``T_out = exp(xi) T``.

    Returns:
        ``(n_frozen, |xi|)``; ``n_frozen = 0`` means nothing is weak and ``T_out`` is untouched (the caller
        takes the ordinary step).
    """
    H = np.empty((6, 6))
    _unpack_lower(stats, H)
    for i in range(6):
        for j in range(i + 1, 6):
            H[i, j] = H[j, i]
    d = max(mean_depth_m, 1e-6)
    s = np.ones(6)
    s[0] = 1.0 / d
    s[1] = 1.0 / d
    s[2] = 1.0 / d
    for i in range(6):
        for j in range(6):
            H[i, j] *= s[i] * s[j]
    lam = np.empty(6)
    V = np.empty((6, 6))
    jacobi_eigh6(H, lam, V)
    if not lam[5] > 0.0:
        return 0, 0.0
    n_frozen = 0
    for i in range(6):
        if lam[i] * max_ratio < lam[5]:
            n_frozen += 1
    if n_frozen == 0:
        return 0, 0.0
    g = np.empty(6)
    for i in range(6):
        g[i] = s[i] * stats[21 + i]
    xi = np.zeros(6)
    for kk in range(n_frozen, 6):  # eigenvalues ascending: the frozen ones come first
        c = 0.0
        for i in range(6):
            c += V[i, kk] * g[i]
        c /= lam[kk]
        for i in range(6):
            xi[i] -= V[i, kk] * c
    for i in range(6):
        xi[i] *= s[i]
    se3_exp_left_update(xi, T, T_out)
    return n_frozen, np.sqrt(np.sum(xi * xi))


def remapped_step_ref(AtA: np.ndarray, Atb: np.ndarray, mean_depth_m: float, max_ratio: float
                      ) -> tuple[np.ndarray | None, int]:
    """Numpy reference of :func:`remapped_gauss_newton_step`: the Gauss-Newton step restricted to the
    well-constrained directions.

    With ``S = diag(1/d, 1/d, 1/d, 1, 1, 1)`` (``d`` = mean depth) and ``S AtA S = V diag(lam) V^T``,
    directions with ``lam_k < lam_max / max_ratio`` are dropped: ``xi = -S sum_{k kept} v_k v_k^T S Atb / lam_k``.

    Returns:
        ``(xi (6,), n_frozen)``; ``xi`` is ``None`` when no direction is weak (use the ordinary solve) or the
        matrix has no positive eigenvalue.
    """
    d = max(mean_depth_m, 1e-6)
    s = np.array([1 / d, 1 / d, 1 / d, 1.0, 1.0, 1.0])
    lam, V = np.linalg.eigh(AtA * s[:, None] * s[None, :])
    if not lam[-1] > 0:
        return None, 0
    keep = lam * max_ratio >= lam[-1]
    n_frozen = int(6 - np.count_nonzero(keep))
    if n_frozen == 0:
        return None, 0
    Vk = V[:, keep]
    xi_s = -(Vk @ ((Vk.T @ (s * Atb)) / lam[keep]))
    return s * xi_s, n_frozen


@njit(cache=True, nogil=True, fastmath=_FASTMATH)
def accumulate_reprojection(pts_target, uv_source, T, fx, fy, cx, cy, sigma_px, huber, weight, out):
    """Add sparse reprojection terms to the normal equations ``out`` (layout above), in place.

    Each point ``X_t = pts_target[i]`` (target camera frame, m) is observed at pixel ``uv_source[i]`` in the
    source image. With ``T = T_target_source`` and the left update ``T <- exp(xi) T``, the source point is
    ``X_s = R^T (X_t - t)`` and ``dX_s/dxi = R^T [[X_t]x  -I]``; the residual ``e = (pi(X_s) - uv) / sigma_px``
    (2,) gets the Huber weight ``h = min(1, huber / |e|)`` of its norm. The term adds
    ``weight h J^T J`` to ``[0:21]``, ``weight h J^T e`` to ``[21:27]`` and ``weight h |e|^2`` to ``[27]``
    (``J = de/dxi``, 2 x 6); inlier counts ``[28:32]`` are left to the dense pairs. Points with
    ``X_s_z <= 0`` are skipped. ``weight`` converts one squared unit residual into the units of ``out``.

    Args:
        pts_target: ``(M, 3)`` float64; uv_source: ``(M, 2)`` float64 pixels of the camera ``fx, fy, cx, cy``.
        T: ``(4, 4)`` float64. out: ``(N_STATS,)`` float64.
    """
    r00, r01, r02 = T[0, 0], T[0, 1], T[0, 2]
    r10, r11, r12 = T[1, 0], T[1, 1], T[1, 2]
    r20, r21, r22 = T[2, 0], T[2, 1], T[2, 2]
    t0, t1, t2 = T[0, 3], T[1, 3], T[2, 3]
    isig = 1.0 / sigma_px
    J = np.empty((2, 6))
    for i in range(pts_target.shape[0]):
        X, Y, Z = pts_target[i, 0], pts_target[i, 1], pts_target[i, 2]
        dx, dy, dz = X - t0, Y - t1, Z - t2
        # X_s = R^T (X_t - t)
        xs = r00 * dx + r10 * dy + r20 * dz
        ys = r01 * dx + r11 * dy + r21 * dz
        zs = r02 * dx + r12 * dy + r22 * dz
        if zs <= 0.0:
            continue
        iz = 1.0 / zs
        e0 = (fx * xs * iz + cx - uv_source[i, 0]) * isig
        e1 = (fy * ys * iz + cy - uv_source[i, 1]) * isig
        en = np.sqrt(e0 * e0 + e1 * e1)
        h = 1.0 if en <= huber else huber / en
        w = weight * h
        # projection rows (scaled by 1 / sigma): P = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]] / sigma
        p00 = fx * iz * isig
        p02 = -fx * xs * iz * iz * isig
        p11 = fy * iz * isig
        p12 = -fy * ys * iz * iz * isig
        # M = P R^T (2 x 3)
        m00 = p00 * r00 + p02 * r02
        m01 = p00 * r10 + p02 * r12
        m02 = p00 * r20 + p02 * r22
        m10 = p11 * r01 + p12 * r02
        m11 = p11 * r11 + p12 * r12
        m12 = p11 * r21 + p12 * r22
        # J = M [[X_t]x  -I], [X_t]x = [[0, -Z, Y], [Z, 0, -X], [-Y, X, 0]]
        J[0, 0] = m01 * Z - m02 * Y
        J[0, 1] = -m00 * Z + m02 * X
        J[0, 2] = m00 * Y - m01 * X
        J[0, 3] = -m00
        J[0, 4] = -m01
        J[0, 5] = -m02
        J[1, 0] = m11 * Z - m12 * Y
        J[1, 1] = -m10 * Z + m12 * X
        J[1, 2] = m10 * Y - m11 * X
        J[1, 3] = -m10
        J[1, 4] = -m11
        J[1, 5] = -m12
        k = 0
        for a in range(6):
            ja0 = w * J[0, a]
            ja1 = w * J[1, a]
            for b in range(a, 6):
                out[k] += ja0 * J[0, b] + ja1 * J[1, b]
                k += 1
            out[21 + a] += ja0 * e0 + ja1 * e1
        out[27] += w * (e0 * e0 + e1 * e1)


def reprojection_system_ref(pts_target: np.ndarray, uv_source: np.ndarray, T: np.ndarray, fx: float, fy: float,
                            cx: float, cy: float, sigma_px: float, huber: float):
    """Numpy reference of :func:`accumulate_reprojection`, by numerical differentiation of the residual.

    Returns:
        ``(J (M, 2, 6), e (M, 2), h (M,))`` for the points in front of the source camera (others get zero rows):
        residuals in units of ``sigma_px``, their Jacobians for the left update ``exp(xi) T`` and Huber weights.
    """
    from surfelslam.geometry.se3 import exp as se3_exp
    from surfelslam.geometry.se3 import invert

    def residual(Tc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Xs = pts_target @ invert(Tc)[:3, :3].T + invert(Tc)[:3, 3]
        front = Xs[:, 2] > 0
        z = np.where(front, Xs[:, 2], 1.0)
        e = np.column_stack([fx * Xs[:, 0] / z + cx - uv_source[:, 0], fy * Xs[:, 1] / z + cy - uv_source[:, 1]])
        return np.where(front[:, None], e / sigma_px, 0.0), front

    e, front = residual(T)
    J = np.zeros((len(e), 2, 6))
    step = 1e-7
    for k in range(6):
        d = np.zeros(6)
        d[k] = step
        J[:, :, k] = (residual(se3_exp(d) @ T)[0] - residual(se3_exp(-d) @ T)[0]) / (2 * step)
    J[~front] = 0.0
    en = np.linalg.norm(e, axis=1)
    h = np.where(en <= huber, 1.0, huber / np.maximum(en, 1e-300))
    h[~front] = 0.0
    return J, e, h
