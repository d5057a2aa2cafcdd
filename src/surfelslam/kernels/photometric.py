"""Dense photometric term of the ICP normal equations (numba), with numpy references.

Joint geometric + photometric tracking (the RGB term of Kintinuous / ElasticFusion, after Steinbruecker et
al. 2011 and Kerl et al. 2013). For every valid source pixel ``u`` with point ``p`` (source camera frame)
and intensity ``I_s(u)``:

    p' = R p + t                      (current estimate of T_target_source)
    x = pi(p')                        (continuous pixel in the target image)
    e = (I_t(x) - I_s(u) - o) / sigma (intensity residual in units of the noise ``sigma``, ``o`` a global
                                       brightness offset held fixed during one accumulation)

``I_t`` and its gradient are sampled bilinearly. The pair is used when ``x`` lies inside the target
image with all four bilinear neighbours valid (finite intensity and gradient) and the target depth at the
nearest pixel is within ``dist_thresh_m`` of ``p'_z`` (the point is not occluded in the target view). With
``g = dI_t/dp' / sigma = (g_x fx / z, g_y fy / z, -(g_x fx x + g_y fy y) / z^2) / sigma`` the Jacobian
for the left update ``exp(xi) T`` (``xi = (omega, t)``, the ICP kernel's order) is

    J = [ (p' x g)^T , g^T ]                                    (1 x 6)

and the Huber weight of ``|e|`` is ``h``. The term adds ``weight h J^T J`` to ``[0:21]``, ``weight h J^T e``
to ``[21:27]`` and ``weight h e^2`` to ``[27]`` of the ICP accumulator
(:mod:`surfelslam.kernels.icp` layout); the inlier counters ``[28:32]`` stay the geometric pairs'. ``aux``
receives ``[sum h, sum h (I_t - I_s), pairs]``, from which the caller re-estimates the offset ``o``.

Determinism: fixed row chunks reduced in chunk order, as in :mod:`surfelslam.kernels.icp`.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from surfelslam.kernels.icp import N_CHUNKS, N_STATS
from surfelslam.kernels.threads import dual_njit

_FASTMATH = {"contract"}
N_AUX = 3
_N_SYSTEM = 28  # the accumulator entries this term adds to: AtA (21), Atb (6), cost (1)


@njit(cache=True, nogil=True)
def _bilinear(img, x0, y0, ax, ay, ch):
    return ((1.0 - ay) * ((1.0 - ax) * img[y0, x0, ch] + ax * img[y0, x0 + 1, ch])
            + ay * ((1.0 - ax) * img[y0 + 1, x0, ch] + ax * img[y0 + 1, x0 + 1, ch]))


@njit(cache=True, nogil=True, fastmath=_FASTMATH, error_model="numpy")
def _photometric_chunk(src_vertex, src_intensity, tgt_vertex, tgt_igg, T, fx, fy, cx, cy, dist_thresh_m, sigma, huber,
                       weight, offset, src_stride, c, pc):
    """Chunk ``c`` of :func:`accumulate_photometric` (its source rows), sums into ``pc (N_STATS + N_AUX,)``; a
    function of its own for the parallel twin's compile time (as ``icp._normal_equations_chunk``)."""
    H, W = src_vertex.shape[0], src_vertex.shape[1]
    Ht, Wt = tgt_vertex.shape[0], tgt_vertex.shape[1]
    r00, r01, r02, t0 = T[0, 0], T[0, 1], T[0, 2], T[0, 3]
    r10, r11, r12, t1 = T[1, 0], T[1, 1], T[1, 2], T[1, 3]
    r20, r21, r22, t2 = T[2, 0], T[2, 1], T[2, 2], T[2, 3]
    isig = 1.0 / sigma
    # scalar accumulators (kept in registers): s0..s20 AtA, s21..s26 Atb, s27 cost, then aux sums
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = s8 = s9 = s10 = 0.0
    s11 = s12 = s13 = s14 = s15 = s16 = s17 = s18 = s19 = s20 = 0.0
    s21 = s22 = s23 = s24 = s25 = s26 = s27 = 0.0
    x0_ = x1_ = x2_ = 0.0
    row0 = (c * H) // N_CHUNKS
    row1 = ((c + 1) * H) // N_CHUNKS
    for v in range(row0, row1):
        if v % src_stride != 0:
            continue
        for u in range(0, W, src_stride):
            pz0 = np.float64(src_vertex[v, u, 2])
            if pz0 <= 0.0:
                continue
            i_s = np.float64(src_intensity[v, u])
            if not np.isfinite(i_s):
                continue
            px0 = np.float64(src_vertex[v, u, 0])
            py0 = np.float64(src_vertex[v, u, 1])
            px = r00 * px0 + r01 * py0 + r02 * pz0 + t0
            py = r10 * px0 + r11 * py0 + r12 * pz0 + t1
            pz = r20 * px0 + r21 * py0 + r22 * pz0 + t2
            if pz <= 0.0:
                continue
            iz = 1.0 / pz
            xf = fx * px * iz + cx
            yf = fy * py * iz + cy
            if not (xf >= 0.0 and xf < Wt - 1 and yf >= 0.0 and yf < Ht - 1):
                continue
            x0 = int(xf)
            y0 = int(yf)
            ax = xf - x0
            ay = yf - y0
            qz = np.float64(tgt_vertex[int(yf + 0.5), int(xf + 0.5), 2])
            if qz <= 0.0 or abs(qz - pz) >= dist_thresh_m:
                continue
            i_t = _bilinear(tgt_igg, x0, y0, ax, ay, 0)
            gx = _bilinear(tgt_igg, x0, y0, ax, ay, 1)
            gy = _bilinear(tgt_igg, x0, y0, ax, ay, 2)
            if not np.isfinite(i_t + gx + gy):  # NaN at any corner propagates
                continue
            d = i_t - i_s
            e = (d - offset) * isig
            ae = abs(e)
            h = 1.0 if ae <= huber else huber / ae
            g0 = gx * fx * iz * isig
            g1 = gy * fy * iz * isig
            g2 = -(g0 * px + g1 * py) * iz
            a0 = py * g2 - pz * g1
            a1 = pz * g0 - px * g2
            a2 = px * g1 - py * g0
            w = weight * h
            wa0 = w * a0
            wa1 = w * a1
            wa2 = w * a2
            wa3 = w * g0
            wa4 = w * g1
            wa5 = w * g2
            s0 += wa0 * a0
            s1 += wa0 * a1
            s2 += wa0 * a2
            s3 += wa0 * g0
            s4 += wa0 * g1
            s5 += wa0 * g2
            s6 += wa1 * a1
            s7 += wa1 * a2
            s8 += wa1 * g0
            s9 += wa1 * g1
            s10 += wa1 * g2
            s11 += wa2 * a2
            s12 += wa2 * g0
            s13 += wa2 * g1
            s14 += wa2 * g2
            s15 += wa3 * g0
            s16 += wa3 * g1
            s17 += wa3 * g2
            s18 += wa4 * g1
            s19 += wa4 * g2
            s20 += wa5 * g2
            s21 += wa0 * e
            s22 += wa1 * e
            s23 += wa2 * e
            s24 += wa3 * e
            s25 += wa4 * e
            s26 += wa5 * e
            s27 += w * e * e
            x0_ += h
            x1_ += h * d
            x2_ += 1.0
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
    pc[N_STATS] = x0_
    pc[N_STATS + 1] = x1_
    pc[N_STATS + 2] = x2_


@dual_njit(fastmath=_FASTMATH, error_model="numpy")
def accumulate_photometric(src_vertex, src_intensity, tgt_vertex, tgt_igg, T, fx, fy, cx, cy, dist_thresh_m, sigma,
                           huber, weight, offset, out, aux, src_stride=1):
    """Add the photometric pairs to the normal equations ``out`` (in place); sums in ``aux``.

    Args:
        src_vertex: ``(H, W, 3)`` float32 source camera frame (invalid: ``z <= 0``).
        src_intensity: ``(H, W)`` float32 source intensity (NaN = invalid).
        tgt_vertex: ``(H', W', 3)`` float32 target camera frame (occlusion test).
        tgt_igg: ``(H', W', 3)`` float32 target intensity and its gradient per pixel ``(I, gx, gy)`` (NaN =
            invalid; packed so that one bilinear corner is one memory access).
        T: ``(4, 4)`` float64 current ``T_target_source``; fx, fy, cx, cy: target intrinsics.
        dist_thresh_m: largest ``|p'_z - q_z|`` at the nearest target pixel.
        sigma: intensity noise; huber: Huber threshold in units of ``sigma``; weight: cost of one unit
            residual in the units of ``out``; offset: brightness offset ``o`` subtracted from the residual.
        out: ``(N_STATS,)`` float64 (added to). aux: ``(N_AUX,)`` float64 (overwritten).
        src_stride: use only source pixels ``[::src_stride, ::src_stride]``.
    """
    partial = np.zeros((N_CHUNKS, N_STATS + N_AUX))
    for c in prange(N_CHUNKS):
        _photometric_chunk(src_vertex, src_intensity, tgt_vertex, tgt_igg, T, fx, fy, cx, cy, dist_thresh_m, sigma,
                           huber, weight, offset, src_stride, np.int64(c), partial[c])
    for k in range(N_STATS + N_AUX):
        s = 0.0
        for c in range(N_CHUNKS):
            s += partial[c, k]
        if k < _N_SYSTEM:
            out[k] += s
        elif k >= N_STATS:
            aux[k - N_STATS] = s


def photometric_system_ref(src_vertex, src_intensity, tgt_vertex, tgt_igg, T, fx, fy, cx, cy, dist_thresh_m, sigma,
                           huber, offset, src_stride=1):
    """Numpy reference of :func:`accumulate_photometric`: the pairs' residuals, Huber weights and Jacobians.

    The Jacobian is obtained by numerical differentiation of the residual under the left update ``exp(xi) T``
    with the target image *and its gradient images* interpolated bilinearly, i.e. it differentiates the same
    model the kernel linearises (the sampled gradient stands for the image derivative).

    Returns:
        ``(J (N, 6), e (N,), h (N,))`` for the pairs the kernel uses, in row-major source pixel order.
    """
    from surfelslam.geometry.se3 import exp as se3_exp

    tgt_intensity, tgt_gx, tgt_gy = (np.asarray(tgt_igg[..., k]) for k in range(3))
    Ht, Wt = tgt_intensity.shape
    P = src_vertex[::src_stride, ::src_stride].reshape(-1, 3).astype(np.float64)
    Is = src_intensity[::src_stride, ::src_stride].reshape(-1).astype(np.float64)
    keep = (P[:, 2] > 0) & np.isfinite(Is)
    P, Is = P[keep], Is[keep]

    def project(Tc):
        Q = P @ Tc[:3, :3].T + Tc[:3, 3]
        z = np.where(Q[:, 2] > 0, Q[:, 2], np.nan)
        return Q, fx * Q[:, 0] / z + cx, fy * Q[:, 1] / z + cy

    def sample(img, x, y):
        x0 = np.clip(np.floor(x).astype(int), 0, Wt - 2)
        y0 = np.clip(np.floor(y).astype(int), 0, Ht - 2)
        ax, ay = x - x0, y - y0
        return ((1 - ay) * ((1 - ax) * img[y0, x0] + ax * img[y0, x0 + 1])
                + ay * ((1 - ax) * img[y0 + 1, x0] + ax * img[y0 + 1, x0 + 1]))

    Q, x, y = project(T)
    inside = (Q[:, 2] > 0) & (x >= 0) & (x < Wt - 1) & (y >= 0) & (y < Ht - 1)
    xs, ys = np.where(inside, x, 0.0), np.where(inside, y, 0.0)
    qz = tgt_vertex[np.floor(ys + 0.5).astype(int), np.floor(xs + 0.5).astype(int), 2].astype(np.float64)
    ok = inside & (qz > 0) & (np.abs(qz - Q[:, 2]) < dist_thresh_m)
    for img in (tgt_intensity, tgt_gx, tgt_gy):
        ok &= np.isfinite(sample(img.astype(np.float64), xs, ys))
    I_t = tgt_intensity.astype(np.float64)

    def residual(Tc):
        _, xc, yc = project(Tc)
        return (sample(I_t, xc, yc)[ok] - Is[ok] - offset) / sigma

    e = residual(T)
    # the model the kernel linearises: intensity moves with the sampled gradient (d I = g . d x)
    gx = sample(tgt_gx.astype(np.float64), xs, ys)[ok]
    gy = sample(tgt_gy.astype(np.float64), xs, ys)[ok]
    J = np.zeros((len(e), 6))
    step = 1e-7
    for k in range(6):
        d = np.zeros(6)
        d[k] = step
        _, xp, yp = project(se3_exp(d) @ T)
        _, xm, ym = project(se3_exp(-d) @ T)
        J[:, k] = (gx * (xp[ok] - xm[ok]) + gy * (yp[ok] - ym[ok])) / (2 * step) / sigma
    ae = np.abs(e)
    h = np.where(ae <= huber, 1.0, huber / np.maximum(ae, 1e-300))
    return J, e, h


def intensity_from_rgb(rgb: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB -> ``(H, W)`` float32 intensity in [0, 1] (ITU-R BT.601 luma weights)."""
    x = rgb.astype(np.float32)
    return (np.float32(0.299 / 255) * x[..., 0] + np.float32(0.587 / 255) * x[..., 1]
            + np.float32(0.114 / 255) * x[..., 2])


@njit(cache=True, nogil=True)
def intensity_from_rgb_u8(rgb, valid, masked):
    """:func:`intensity_from_rgb` of ``(H, W, 3)`` uint8 in one pass, bit for bit (the same float32 products and sums,
    left to right, no contraction), NaN where ``masked`` and not ``valid (H, W)`` bool. The numpy form makes four
    full-size temporaries (and the mask a fifth): about 1 ms a 320x240 frame, for the rendered view in the main thread
    and the frame in the reader's."""
    H, W = rgb.shape[0], rgb.shape[1]
    a = np.float32(0.299 / 255)
    b = np.float32(0.587 / 255)
    c = np.float32(0.114 / 255)
    out = np.empty((H, W), np.float32)
    for v in range(H):
        for u in range(W):
            if masked and not valid[v, u]:
                out[v, u] = np.nan
            else:
                out[v, u] = (a * np.float32(rgb[v, u, 0]) + b * np.float32(rgb[v, u, 1])) + c * np.float32(rgb[v, u, 2])
    return out


@njit(cache=True, nogil=True)
def halve_intensity(img):
    """2x2 block mean over the finite pixels of ``(H, W)`` float32 (NaN where a block has none); the
    :mod:`surfelslam.tracking.preprocess` pyramid convention (an odd last row / column is dropped).
    Returns ``(H // 2, W // 2)`` float32."""
    Ho, Wo = img.shape[0] // 2, img.shape[1] // 2
    out = np.empty((Ho, Wo), np.float32)
    for vo in range(Ho):
        for uo in range(Wo):
            s = np.float32(0.0)
            n = 0
            for dv in range(2):
                for du in range(2):
                    x = img[2 * vo + dv, 2 * uo + du]
                    if np.isfinite(x):
                        s += x
                        n += 1
            out[vo, uo] = s / n if n > 0 else np.nan
    return out


def halve_intensity_ref(img: np.ndarray) -> np.ndarray:
    """Numpy reference of :func:`halve_intensity`."""
    H, W = img.shape[0] // 2 * 2, img.shape[1] // 2 * 2
    b = img[:H, :W].reshape(H // 2, 2, W // 2, 2)
    fin = np.isfinite(b)
    n = fin.sum(axis=(1, 3))
    s = np.where(fin, b, 0.0).sum(axis=(1, 3), dtype=np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, s / n, np.nan).astype(np.float32)


@njit(cache=True, nogil=True)
def pack_target(img):
    """``(H, W)`` float32 intensity -> ``(H, W, 3)`` float32 ``(I, gx, gy)``, the target layout of
    :func:`accumulate_photometric` (gradients as :func:`gradients`)."""
    H, W = img.shape
    out = np.empty((H, W, 3), np.float32)
    for v in range(H):  # a loop, not out[:, :, 0] = img: the slice assignment compiles seconds of error handling
        for u in range(W):
            out[v, u, 0] = img[v, u]
    _gradients_into(img, out[:, :, 1], out[:, :, 2])  # written in place: no temporary gradient images
    return out


@njit(cache=True, nogil=True)
def _gradients_into(img, gx, gy):
    """Fill ``gx``, ``gy`` (``(H, W)`` float32, possibly strided views) with the gradients of :func:`gradients`."""
    H, W = img.shape
    for v in range(H):
        for u in range(W):
            gx[v, u] = np.float32(0.5) * (img[v, u + 1] - img[v, u - 1]) if 0 < u < W - 1 else np.nan
            gy[v, u] = np.float32(0.5) * (img[v + 1, u] - img[v - 1, u]) if 0 < v < H - 1 else np.nan


@njit(cache=True, nogil=True)
def gradients(img):
    """Central-difference gradients ``(gx, gy)`` of ``(H, W)`` float32 in intensity per pixel; NaN on the
    border and wherever a neighbour used is NaN."""
    H, W = img.shape
    gx = np.empty((H, W), np.float32)
    gy = np.empty((H, W), np.float32)
    _gradients_into(img, gx, gy)
    return gx, gy


def gradients_ref(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Numpy reference of :func:`gradients`."""
    gx = np.full(img.shape, np.nan, np.float32)
    gy = np.full(img.shape, np.nan, np.float32)
    gx[:, 1:-1] = 0.5 * (img[:, 2:] - img[:, :-2])
    gy[1:-1, :] = 0.5 * (img[2:, :] - img[:-2, :])
    return gx, gy
