"""Rotation-stack kernels for :func:`surfelslam.geometry.se3.so3_log`: the per-matrix scalar steps of its stack path
(Markley's quaternion, the log's angle scale) in one compiled loop instead of a Python call per matrix, with the same
operations in the same order (IEEE float64, no fast-math), so the numbers are the scalar path's bit for bit. The
back end's trust gate takes the log of every loop edge's residual at each optimisation (thousands on a floor).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def markley_many(R9):
    """Unit quaternions ``(N, 4)`` (``x, y, z, w``; either sign) of rotations given as rows ``(N, 9)`` float64
    (row-major): ``se3._markley`` of each row (the largest of the diagonal entries and the trace, the first on ties)."""
    n_rot = R9.shape[0]
    q = np.empty((n_rot, 4))
    for k in range(n_rot):
        r00, r01, r02 = R9[k, 0], R9[k, 1], R9[k, 2]
        r10, r11, r12 = R9[k, 3], R9[k, 4], R9[k, 5]
        r20, r21, r22 = R9[k, 6], R9[k, 7], R9[k, 8]
        tr = r00 + r11 + r22
        choice = 0
        best = r00
        if r11 > best:
            choice, best = 1, r11
        if r22 > best:
            choice, best = 2, r22
        if tr > best:
            choice = 3
        if choice == 0:
            x, y, z, w = 1.0 - tr + 2.0 * r00, r10 + r01, r20 + r02, r21 - r12
        elif choice == 1:
            x, y, z, w = r01 + r10, 1.0 - tr + 2.0 * r11, r21 + r12, r02 - r20
        elif choice == 2:
            x, y, z, w = r02 + r20, r12 + r21, 1.0 - tr + 2.0 * r22, r10 - r01
        else:
            x, y, z, w = r21 - r12, r02 - r20, r10 - r01, 1.0 + tr
        nrm = math.sqrt(x * x + y * y + z * z + w * w)
        q[k, 0], q[k, 1], q[k, 2], q[k, 3] = x / nrm, y / nrm, z / nrm, w / nrm
    return q


@njit(cache=True, nogil=True)
def log_scales(v_norm, w, series_below_rad):
    """``(N,)`` ``se3._log_scale(2 atan2(v_norm, w))`` of each quaternion's vector norm ``v_norm`` and scalar part
    ``w`` ``(N,)``: ``angle / sin(angle / 2)``, its series at or below ``series_below_rad``."""
    out = np.empty(v_norm.shape[0])
    for k in range(v_norm.shape[0]):
        angle = 2.0 * math.atan2(v_norm[k], w[k])
        if angle <= series_below_rad:
            a2 = angle * angle
            out[k] = 2.0 + a2 / 12.0 + 7.0 * a2 * a2 / 2880.0
        else:
            out[k] = angle / math.sin(angle / 2.0)
    return out
