"""Lucas-Kanade tracking of points whose template window is warped by a per-point homography (numba), with a
numpy reference.

Plain (translational) Lucas-Kanade compares a square window of the template image with a square window of the
search image. Under a camera rotation of a few degrees the patch around a point also rotates, shears and changes
scale in the image, and the translation that best explains the deformed patch is not the displacement of its
centre: the error per point is a fraction of a pixel, but it is correlated over the image, so a pose refined from
many points inherits it.
Here the template is sampled through a homography ``A`` (search-image pixel -> template-image pixel) predicted
from the pose, so both windows show the surface the same way and only a residual translation is searched.

:func:`track_warped` (numba, one point per iteration of the outer loop) and :func:`track_warped_ref` (numpy,
vectorised over points) solve the same problem with the same arithmetic: for each point ``k``, find ``s`` near
``start[k]`` minimising ``sum_o (S(s + o) - T(A_k (start[k] + o) + shift[k]))^2`` over the window offsets
``o in [-half, half]^2``, by Gauss-Newton with the warped template's gradients (central differences; the 2x2
system is then fixed per point, as in OpenCV's Lucas-Kanade, and each iteration samples the search image once per
window pixel).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: Gauss-Newton stops when the determinant of the 2x2 system is below this (per window pixel, intensity^4): a
#: window without texture in two directions cannot be tracked.
MIN_DET_PER_PIXEL = 1e-6


@njit(cache=True, nogil=True)
def _bilinear(img, x, y):
    """Bilinear sample of ``img (H, W)`` at ``(x, y)`` (inside ``[0, W - 1] x [0, H - 1]``)."""
    x0 = int(math.floor(x))
    y0 = int(math.floor(y))
    w_ = img.shape[1]
    h_ = img.shape[0]
    if x0 >= w_ - 1:
        x0 = w_ - 2
    if y0 >= h_ - 1:
        y0 = h_ - 2
    ax = x - x0
    ay = y - y0
    return ((1.0 - ay) * ((1.0 - ax) * img[y0, x0] + ax * img[y0, x0 + 1])
            + ay * ((1.0 - ax) * img[y0 + 1, x0] + ax * img[y0 + 1, x0 + 1]))


@njit(cache=True, nogil=True)
def track_warped(template, search, A, start, shift, half, max_iterations, epsilon_px, out, ok):
    """Warped-template Lucas-Kanade (see the module docstring).

    Args:
        template, search: ``(H, W)`` grey images (uint8 or float; sampled in float64).
        A: ``(N, 3, 3)`` float64 homographies, search pixel -> template pixel.
        start: ``(N, 2)`` float64 initial search positions (the window centres whose warp ``A`` was predicted).
        shift: ``(N, 2)`` float64 offsets added to the warped template positions.
        half: window half-size (pixels); max_iterations, epsilon_px: Gauss-Newton stops after that many
            iterations or once the update is below ``epsilon_px``.
        out: ``(N, 2)`` float64, the tracked positions; ok: ``(N,)`` bool, False when a window left either image
            or had no texture.
    """
    h, w = search.shape
    th, tw = template.shape
    side = 2 * half + 3  # the window plus a one-pixel margin for the template's central differences
    n_off = (2 * half + 1) * (2 * half + 1)
    tpl = np.empty((side, side))
    tgx = np.empty((side - 2, side - 2))
    tgy = np.empty((side - 2, side - 2))
    for k in range(start.shape[0]):
        ok[k] = True
        sx = start[k, 0]
        sy = start[k, 1]
        # the warped template, once per point
        for j in range(side):
            for i in range(side):
                px = sx + (i - half - 1)
                py = sy + (j - half - 1)
                zt = A[k, 2, 0] * px + A[k, 2, 1] * py + A[k, 2, 2]
                tx = (A[k, 0, 0] * px + A[k, 0, 1] * py + A[k, 0, 2]) / zt + shift[k, 0]
                ty = (A[k, 1, 0] * px + A[k, 1, 1] * py + A[k, 1, 2]) / zt + shift[k, 1]
                if not (zt > 0.0 and 0.0 <= tx <= tw - 1 and 0.0 <= ty <= th - 1):
                    ok[k] = False
                    break
                tpl[j, i] = _bilinear(template, tx, ty)
            if not ok[k]:
                break
        qx = sx
        qy = sy
        if ok[k]:
            # the template's gradients give a constant 2x2 system (as OpenCV's Lucas-Kanade does)
            a = 0.0
            b = 0.0
            c = 0.0
            for j in range(1, side - 1):
                for i in range(1, side - 1):
                    gx = 0.5 * (tpl[j, i + 1] - tpl[j, i - 1])
                    gy = 0.5 * (tpl[j + 1, i] - tpl[j - 1, i])
                    tgx[j - 1, i - 1] = gx
                    tgy[j - 1, i - 1] = gy
                    a += gx * gx
                    b += gx * gy
                    c += gy * gy
            det = a * c - b * b
            if not det > MIN_DET_PER_PIXEL * n_off * n_off:
                ok[k] = False
        if ok[k]:
            for _ in range(max_iterations):
                if not (half <= qx <= w - 1 - half and half <= qy <= h - 1 - half):
                    ok[k] = False
                    break
                ex = 0.0
                ey = 0.0
                # the window moves by whole pixels from its centre: one set of bilinear weights for all its pixels
                x0 = int(math.floor(qx))
                y0 = int(math.floor(qy))
                if x0 + half >= w - 1:
                    x0 = w - 2 - half
                if y0 + half >= h - 1:
                    y0 = h - 2 - half
                ax = qx - x0
                ay = qy - y0
                w00 = (1.0 - ax) * (1.0 - ay)
                w01 = ax * (1.0 - ay)
                w10 = (1.0 - ax) * ay
                w11 = ax * ay
                for j in range(1, side - 1):
                    yy = y0 + j - half - 1
                    for i in range(1, side - 1):
                        xx = x0 + i - half - 1
                        r = (w00 * search[yy, xx] + w01 * search[yy, xx + 1] + w10 * search[yy + 1, xx]
                             + w11 * search[yy + 1, xx + 1]) - tpl[j, i]
                        ex += tgx[j - 1, i - 1] * r
                        ey += tgy[j - 1, i - 1] * r
                dx = -(c * ex - b * ey) / det
                dy = -(a * ey - b * ex) / det
                qx += dx
                qy += dy
                if dx * dx + dy * dy < epsilon_px * epsilon_px:
                    break
        out[k, 0] = qx
        out[k, 1] = qy


def _bilinear_ref(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    h, w = img.shape
    x0 = np.minimum(np.floor(x).astype(np.int64), w - 2)
    y0 = np.minimum(np.floor(y).astype(np.int64), h - 2)
    ax, ay = x - x0, y - y0
    im = img.astype(np.float64)
    return ((1 - ay) * ((1 - ax) * im[y0, x0] + ax * im[y0, x0 + 1])
            + ay * ((1 - ax) * im[y0 + 1, x0] + ax * im[y0 + 1, x0 + 1]))


def track_warped_ref(template: np.ndarray, search: np.ndarray, A: np.ndarray, start: np.ndarray, shift: np.ndarray,
                     half: int, max_iterations: int, epsilon_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Numpy reference of :func:`track_warped` (vectorised over points): ``(out (N, 2), ok (N,))``."""
    h, w = search.shape
    side = 2 * half + 3
    g = np.arange(side) - half - 1
    oy, ox = np.meshgrid(g, g, indexing="ij")
    start = np.asarray(start, np.float64)
    n = len(start)
    P = start[:, None, :] + np.column_stack([ox.ravel(), oy.ravel()])[None].astype(np.float64)  # (N, side^2, 2)
    Ph = np.concatenate([P, np.ones(P.shape[:2] + (1,))], axis=2)
    Tw = np.einsum("nij,nmj->nmi", np.asarray(A, np.float64), Ph)
    zt = Tw[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        tx = Tw[..., 0] / zt + shift[:, None, 0]
        ty = Tw[..., 1] / zt + shift[:, None, 1]
    th, tw = template.shape
    ok = np.all((zt > 0) & (tx >= 0) & (tx <= tw - 1) & (ty >= 0) & (ty <= th - 1), axis=1)
    tpl = np.zeros(zt.shape)
    tpl[ok] = _bilinear_ref(np.asarray(template, np.float32), tx[ok], ty[ok])
    tpl = tpl.reshape(n, side, side)
    gx = (0.5 * (tpl[:, 1:-1, 2:] - tpl[:, 1:-1, :-2])).reshape(n, -1)
    gy = (0.5 * (tpl[:, 2:, 1:-1] - tpl[:, :-2, 1:-1])).reshape(n, -1)
    inner = tpl[:, 1:-1, 1:-1].reshape(n, -1)
    a, b, c = (gx * gx).sum(1), (gx * gy).sum(1), (gy * gy).sum(1)
    det = a * c - b * b
    n_off = (2 * half + 1) ** 2
    ok &= det > MIN_DET_PER_PIXEL * n_off * n_off
    win = np.arange(-half, half + 1)
    wy, wx = np.meshgrid(win, win, indexing="ij")
    wx, wy = wx.ravel().astype(np.float64), wy.ravel().astype(np.float64)
    q = start.copy()
    active = ok.copy()
    for _ in range(max_iterations):
        inside = (q[:, 0] >= half) & (q[:, 0] <= w - 1 - half) & (q[:, 1] >= half) & (q[:, 1] <= h - 1 - half)
        ok &= inside | ~active
        active &= inside
        if not active.any():
            break
        idx = np.flatnonzero(active)
        r = _bilinear_ref(np.asarray(search, np.float32), q[idx, None, 0] + wx, q[idx, None, 1] + wy) - inner[idx]
        ex, ey = (gx[idx] * r).sum(1), (gy[idx] * r).sum(1)
        dx = -(c[idx] * ex - b[idx] * ey) / det[idx]
        dy = -(a[idx] * ey - b[idx] * ex) / det[idx]
        q[idx, 0] += dx
        q[idx, 1] += dy
        active[idx[dx * dx + dy * dy < epsilon_px * epsilon_px]] = False
    return q, ok
