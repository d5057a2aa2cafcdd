"""Speed-related kernels: duplicate removal vs its reference, serial vs parallel twins, in-place render target."""

import numpy as np
import pytest

from surfelslam.kernels import fusion as kf
from surfelslam.kernels import icp as kicp
from surfelslam.kernels import threads
from surfelslam.mapping import SurfelMap, render
from surfelslam.tracking.preprocess import Preprocessor, pyramid_from_maps
from surfelslam.types import Intrinsics

CAM64 = Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)


def _buckets(rng, H=6, W=7, n=60):
    pix = rng.integers(0, H * W, n)
    order = np.argsort(pix, kind="stable").astype(np.int32)
    counts = np.bincount(pix, minlength=H * W)
    bstart = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
    return bstart, order


def test_flag_duplicates_matches_reference():
    rng = np.random.default_rng(3)
    H, W, n = 6, 7, 200
    bstart, border = _buckets(rng, H, W, n)
    pos = (rng.normal(0, 0.01, (n, 3)) * [1, 1, 2.5]).astype(np.float32)  # layers a few cm apart along z
    nrm = rng.normal(0, 1, (n, 3)) + [0, 0, -4]
    nrm = (nrm / np.linalg.norm(nrm, axis=1, keepdims=True)).astype(np.float32)
    conf = rng.uniform(0, 10, n).astype(np.float32)
    rad = rng.uniform(0.002, 0.01, n).astype(np.float32)
    assoc = np.full((H, W), kf.ASSOC_NEW, np.int32)
    for p in range(H * W):  # the most confident surfel of each bucket is the chosen one, in most pixels
        rows = border[bstart[p] : bstart[p + 1]]
        if len(rows) and p % 5:
            assoc.flat[p] = rows[np.argmax(conf[rows])]
    dead = np.zeros(n, np.uint8)
    dead[::11] = 1
    want = kf.flag_duplicates_ref(assoc, bstart, border, pos, nrm, rad, conf, 0.02, np.cos(np.radians(30)), 0.05, dead)
    got_dead = dead.copy()
    k = kf.flag_duplicates(assoc, bstart, border, pos, nrm, rad, conf, 0.02, np.cos(np.radians(30)), 0.05, got_dead)
    assert k == len(want) > 3
    cos30 = np.cos(np.radians(30))
    near_only = kf.flag_duplicates_ref(assoc, bstart, border, pos, nrm, rad, conf, 0.02, cos30, 0.0, dead)
    assert set(near_only) < set(want)  # the layers in front of the chosen surfel count too
    np.testing.assert_array_equal(np.flatnonzero(got_dead != dead), want)
    assert not np.any(got_dead[assoc[assoc >= 0]] != dead[assoc[assoc >= 0]])  # chosen surfels are kept


def _plane_pyramid(z0, tilt):
    v, u = np.mgrid[0 : CAM64.height, 0 : CAM64.width].astype(np.float32)
    depth = (z0 + tilt * u + 0.3 * tilt * v + 0.05 * np.sin(u / 5.0) * np.cos(v / 7.0)).astype(np.float32)
    return Preprocessor(CAM64).process(depth)


@pytest.mark.heavy  # make test-all: compiles the parallel twins, which only compute.parallel_kernels uses
def test_serial_and_parallel_twins_agree_bitwise():
    src, tgt = _plane_pyramid(1.5, 0.004), _plane_pyramid(1.52, 0.0041)
    T = np.eye(4)
    T[:3, 3] = [0.01, -0.005, 0.02]
    out = {}
    for on in (False, True):
        threads.set_parallel(on)
        try:
            stats = np.zeros(kicp.N_STATS)
            kicp.accumulate_normal_equations(src[0].vertex, src[0].normal, tgt[0].vertex, tgt[0].normal, T,
                                             CAM64.fx, CAM64.fy, CAM64.cx, CAM64.cy, 0.1, 0.5, 1, 0.02, stats, 1, 0.0)
            out[on] = stats
        finally:
            threads.set_parallel(False)
    assert out[False][29] > 100
    np.testing.assert_array_equal(out[False], out[True])


def test_render_into_pyramid_level0_without_copy():
    m = SurfelMap()
    g = np.mgrid[-0.6:0.6:0.01, -0.45:0.45:0.01].reshape(2, -1).T
    pos = np.c_[g, np.full(len(g), 1.0)]
    m.append(pos, np.tile([0.0, 0.0, -1.0], (len(g), 1)), np.zeros((len(g), 3)), 1.0, 0.008, 0)
    T = np.eye(4)
    ref = render(m, T, CAM64)
    pyr = Preprocessor(CAM64).new_pyramid()
    view = render(m, T, CAM64, vertex_out=pyr[0].vertex, normal_out=pyr[0].normal)
    assert view.vertex_cam is pyr[0].vertex
    np.testing.assert_array_equal(pyr[0].vertex, ref.vertex_cam)
    np.testing.assert_array_equal(pyr[0].normal, ref.normal_cam)
    a = pyramid_from_maps(view.vertex_cam, view.normal_cam, CAM64, len(pyr), out=pyr)
    b = pyramid_from_maps(ref.vertex_cam, ref.normal_cam, CAM64, len(pyr))
    for la, lb in zip(a.levels, b.levels, strict=True):
        np.testing.assert_array_equal(la.vertex, lb.vertex)
        np.testing.assert_array_equal(la.normal, lb.normal)


def test_fused_downsample_equals_separate_kernels():
    from surfelslam.kernels import preprocess as kp

    pyr = _plane_pyramid(1.5, 0.004)
    v, n = pyr[0].vertex.copy(), pyr[0].normal.copy()
    v[10:14, 20:30, 2] += 0.2  # a depth step: foreground/background selection inside blocks
    v[5, 5] = 0.0
    vo = np.empty((24, 32, 3), np.float32)
    no = np.empty((24, 32, 3), np.float32)
    kp.downsample_vertex_normal(v, n, 0.05, vo, no)
    sep_v, sep_n = _sep(kp, v, n)
    np.testing.assert_array_equal(vo, sep_v)
    np.testing.assert_array_equal(no, sep_n)
    np.testing.assert_allclose(vo, kp.downsample_vertex_ref(v, 0.05), atol=1e-6)
    np.testing.assert_allclose(no, kp.downsample_normal_ref(v, n, 0.05), atol=1e-6)


def _sep(kp, v, n):
    vo = np.empty((24, 32, 3), np.float32)
    no = np.empty((24, 32, 3), np.float32)
    kp.downsample_vertex(v, 0.05, vo)
    kp.downsample_normal(v, n, 0.05, no)
    return vo, no


def test_render_geometry_only_equals_full_render():
    m = SurfelMap()
    g = np.mgrid[-0.6:0.6:0.01, -0.45:0.45:0.01].reshape(2, -1).T
    pos = np.c_[g, 1.0 + 0.3 * g[:, 0]]
    nrm = np.tile([-0.3, 0.0, -1.0], (len(g), 1)) / np.hypot(0.3, 1.0)
    m.append(pos, nrm, np.full((len(g), 3), 100.0), 1.0, 0.008, 0)
    T = np.eye(4)
    full = render(m, T, CAM64)
    geo = render(m, T, CAM64, attributes=False)
    assert geo.colour is None and geo.confidence is None
    assert full.valid.mean() > 0.5
    np.testing.assert_array_equal(geo.index, full.index)
    np.testing.assert_array_equal(geo.vertex_cam, full.vertex_cam)
    np.testing.assert_array_equal(geo.normal_cam, full.normal_cam)


def test_concurrent_launch_guard(monkeypatch):
    """Serial kernels may always run in two threads; parallel ones only on the OpenMP / TBB threading layers."""
    import numba

    from surfelslam.kernels import threads

    assert threads.concurrent_launch_safe() is True or threads.parallel_enabled()
    monkeypatch.setitem(threads._STATE, "parallel", True)
    for layer, ok in (("omp", True), ("tbb", True), ("workqueue", False)):
        monkeypatch.setattr(numba, "threading_layer", lambda layer=layer: layer)
        assert threads.concurrent_launch_safe() is ok

    def unknown():
        raise ValueError("Threading layer is not initialized.")

    monkeypatch.setattr(numba, "threading_layer", unknown)
    assert threads.concurrent_launch_safe() is False
    monkeypatch.setitem(threads._STATE, "parallel", False)
    assert threads.concurrent_launch_safe() is True
