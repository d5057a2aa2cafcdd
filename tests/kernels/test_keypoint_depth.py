"""Keypoint depth kernels against their numpy references: bit for bit, on noisy depth with holes and edges."""

import numpy as np
import pytest

from surfelslam.kernels import keypoint_depth as kd


def _scene(rng, h=60, w=80):
    """Noisy slanted planes with a foreground box, holes and out-of-range pixels: ``(H, W)`` float32 metres."""
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    depth = 1.0 / (0.5 + 0.004 * (uu - w / 2) - 0.003 * (vv - h / 2))
    depth[15:35, 20:45] = 0.9  # a box in front: occluding contours
    depth *= 1.0 + rng.normal(0, 0.004, depth.shape)
    depth[rng.random(depth.shape) < 0.08] = 0.0  # holes
    depth[rng.random(depth.shape) < 0.01] = 9.0  # beyond max_depth_m
    return depth.astype(np.float32)


def _keypoints(rng, h, w, n=400):
    uv = np.column_stack([rng.uniform(-1, w, n), rng.uniform(-1, h, n)]).astype(np.float32)
    ui = np.clip(np.floor(uv[:, 0] + 0.5).astype(np.int64), 0, w - 1)
    vi = np.clip(np.floor(uv[:, 1] + 0.5).astype(np.int64), 0, h - 1)
    return ui, vi, uv[:, 0].astype(np.float64), uv[:, 1].astype(np.float64)


@pytest.mark.parametrize("median_3x3, plane_r, min_pixels, edge_rel, edge_r", [
    (True, 2, 12.0, 0.1, 3),  # the default
    (True, 0, 12.0, 0.1, 3),  # median only
    (True, 5, 30.0, 0.0, 3),  # a larger plane patch (121 pixels), no contour test
    (True, 7, 40.0, 0.05, 1),  # 225 pixels: the pairwise sum splits in halves
    (False, 2, 12.0, 0.1, 2),  # nearest pixel
])
def test_keypoint_depths_equal_the_reference(median_3x3, plane_r, min_pixels, edge_rel, edge_r):
    rng = np.random.default_rng(plane_r + 10 * edge_r)
    depth = _scene(rng)
    ui, vi, u, v = _keypoints(rng, *depth.shape)
    args = (median_3x3, plane_r, 0.03, min_pixels, edge_rel, edge_r, 0.1, 6.0)
    got = kd.keypoint_depths(depth, ui, vi, u, v, *args)
    want = kd.keypoint_depths_ref(depth, ui, vi, u, v, *args)
    assert np.isfinite(got).sum() > 100 and np.isnan(got).sum() > 20  # both outcomes occur
    np.testing.assert_array_equal(got, want)  # NaN where NaN, equal bits elsewhere


def test_plane_fit_sums_equal_numpy_sums_bit_for_bit():
    rng = np.random.default_rng(5)
    depth = _scene(rng)
    ui, vi, u, v = _keypoints(rng, *depth.shape, n=200)
    z0 = depth[vi, ui].astype(np.float64)
    z0[~(z0 > 0)] = np.nan
    for r in (1, 2, 9):  # 9, 25 and 361 pixels
        M, rhs, fit = kd.plane_fit_sums(depth, ui, vi, u, v, z0, r, 0.05, 5.0)
        M_ref, rhs_ref, fit_ref = kd.plane_fit_sums_ref(depth, ui, vi, u, v, z0, r, 0.05, 5.0)
        np.testing.assert_array_equal(fit, fit_ref)
        assert fit.sum() > 50
        np.testing.assert_array_equal(M[fit], M_ref[fit])
        np.testing.assert_array_equal(rhs[fit], rhs_ref[fit])


@pytest.mark.parametrize("n", [0, 1, 7, 8, 9, 25, 128, 129, 257, 1681, 10_007])
def test_pairwise_sum_is_numpys(n):
    a = np.random.default_rng(n).normal(size=n) * np.exp(np.random.default_rng(n + 1).normal(size=n) * 5)
    assert kd._pairwise_sum(a, n) == a.sum()  # same bits: the same order of additions


def test_depth_edge_flags_equal_the_reference():
    rng = np.random.default_rng(2)
    depth = _scene(rng)
    ui, vi, _, _ = _keypoints(rng, *depth.shape)
    z = depth[vi, ui].astype(np.float64)
    z[~(z > 0)] = np.nan
    got = kd.depth_edge_flags(depth, ui, vi, z, 0.1, 3)
    np.testing.assert_array_equal(got, kd.depth_edge_flags_ref(depth, ui, vi, z, 0.1, 3))
    assert 20 < got.sum() < len(got) - 20
