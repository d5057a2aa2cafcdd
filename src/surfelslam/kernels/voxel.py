"""Voxel-grid filter: one averaged point (and colour) per occupied voxel.

:func:`voxel_filter` computes integer voxel keys, sorts them (stable, numpy) and calls the numba
kernel :func:`voxel_reduce_sorted`, which averages each run of equal keys in a single pass. The
output is ordered by voxel key, so it is deterministic. :func:`voxel_filter_ref` is the plain-numpy
reference (``np.unique`` + ``np.add.at``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

_KEY_BITS = 21  # bits per axis in the packed voxel key (2^21 voxels per axis)


def voxel_keys(points: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """Packed int64 voxel key per point ``(N,)`` (indices relative to the cloud's minimum corner).

    Raises:
        ValueError: when the cloud spans more than 2^21 voxels along an axis.
    """
    if voxel_size_m <= 0:
        raise ValueError(f"voxel_size_m must be positive, got {voxel_size_m}")
    if len(points) == 0:
        return np.zeros(0, np.int64)
    idx = np.floor(points.astype(np.float64) / voxel_size_m).astype(np.int64)
    idx -= idx.min(axis=0)
    if idx.max() >= (1 << _KEY_BITS):
        raise ValueError(f"point cloud too large for voxel size {voxel_size_m} m (> 2^{_KEY_BITS} voxels per axis)")
    return (idx[:, 0] << (2 * _KEY_BITS)) | (idx[:, 1] << _KEY_BITS) | idx[:, 2]


@njit(cache=True)
def voxel_reduce_sorted(
    keys_sorted: np.ndarray, order: np.ndarray, xyz: np.ndarray, rgb: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Average runs of equal keys.

    Args:
        keys_sorted: ``(N,)`` int64 keys in ascending order.
        order: ``(N,)`` int64 indices into ``xyz``/``rgb`` giving that order.
        xyz: ``(N, 3)`` float32 points (m).
        rgb: ``(N, 3)`` uint8 colours.

    Returns:
        ``(xyz_out (M, 3) float32, rgb_out (M, 3) uint8, count (M,) int64)`` for the M distinct keys,
        in key order; sums accumulate in float64 in sorted order.
    """
    n = keys_sorted.shape[0]
    out_xyz = np.empty((n, 3), np.float32)
    out_rgb = np.empty((n, 3), np.uint8)
    count = np.empty(n, np.int64)
    m = 0
    s0 = s1 = s2 = c0 = c1 = c2 = 0.0
    c = 0
    for k in range(n):
        i = order[k]
        if k > 0 and keys_sorted[k] != keys_sorted[k - 1]:
            out_xyz[m, 0] = s0 / c
            out_xyz[m, 1] = s1 / c
            out_xyz[m, 2] = s2 / c
            out_rgb[m, 0] = np.uint8(np.floor(c0 / c + 0.5))
            out_rgb[m, 1] = np.uint8(np.floor(c1 / c + 0.5))
            out_rgb[m, 2] = np.uint8(np.floor(c2 / c + 0.5))
            count[m] = c
            m += 1
            s0 = s1 = s2 = c0 = c1 = c2 = 0.0
            c = 0
        s0 += xyz[i, 0]
        s1 += xyz[i, 1]
        s2 += xyz[i, 2]
        c0 += rgb[i, 0]
        c1 += rgb[i, 1]
        c2 += rgb[i, 2]
        c += 1
    if c > 0:
        out_xyz[m, 0] = s0 / c
        out_xyz[m, 1] = s1 / c
        out_xyz[m, 2] = s2 / c
        out_rgb[m, 0] = np.uint8(np.floor(c0 / c + 0.5))
        out_rgb[m, 1] = np.uint8(np.floor(c1 / c + 0.5))
        out_rgb[m, 2] = np.uint8(np.floor(c2 / c + 0.5))
        count[m] = c
        m += 1
    return out_xyz[:m], out_rgb[:m], count[:m]


def voxel_filter(
    xyz: np.ndarray, rgb: np.ndarray, voxel_size_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Voxel-grid filter: ``(N, 3)`` points + ``(N, 3)`` uint8 colours -> per-voxel means.

    Returns:
        ``(xyz (M, 3) float32, rgb (M, 3) uint8, count (M,) int64)`` ordered by voxel key.
    """
    xyz = np.ascontiguousarray(xyz, dtype=np.float32).reshape(-1, 3)
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8).reshape(-1, 3)
    if len(xyz) != len(rgb):
        raise ValueError(f"{len(xyz)} points but {len(rgb)} colours")
    keys = voxel_keys(xyz, voxel_size_m)
    order = np.argsort(keys, kind="stable")
    return voxel_reduce_sorted(keys[order], order.astype(np.int64), xyz, rgb)


def voxel_filter_ref(
    xyz: np.ndarray, rgb: np.ndarray, voxel_size_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plain-numpy reference of :func:`voxel_filter` (same outputs, same order)."""
    xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    rgb = np.asarray(rgb, dtype=np.uint8).reshape(-1, 3)
    keys = voxel_keys(xyz, voxel_size_m)
    uniq, inv, count = np.unique(keys, return_inverse=True, return_counts=True)
    sums = np.zeros((len(uniq), 3))
    csum = np.zeros((len(uniq), 3))
    np.add.at(sums, inv, xyz.astype(np.float64))
    np.add.at(csum, inv, rgb.astype(np.float64))
    out_xyz = (sums / count[:, None]).astype(np.float32)
    out_rgb = np.floor(csum / count[:, None] + 0.5).astype(np.uint8)
    return out_xyz, out_rgb, count.astype(np.int64)
