"""Depth preprocessing: kernels vs numpy references, normals, pyramid intrinsics and consistency."""

from dataclasses import replace

import numpy as np
import pytest

from surfelslam.errors import ConfigError
from surfelslam.kernels import preprocess as kp
from surfelslam.tracking.preprocess import (
    FramePyramid,
    PreprocessConfig,
    Preprocessor,
    build_pyramid,
    halve_intrinsics,
    pyramid_from_maps,
)
from surfelslam.types import Intrinsics

CAM80 = Intrinsics(150.0, 150.0, 39.5, 29.5, 80, 60)


def plane_depth(intr: Intrinsics, n=(0.2, -0.3, -1.0), d=2.0) -> np.ndarray:
    """Depth of the plane ``n . p = -d`` (camera frame) seen by ``intr``."""
    n = np.asarray(n, float)
    v, u = np.mgrid[0 : intr.height, 0 : intr.width].astype(float)
    ray = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], -1)
    return (-d / (ray @ n)).astype(np.float32)


def noisy_scene_depth(seed=0, intr=CAM80) -> np.ndarray:
    rng = np.random.default_rng(seed)
    z = plane_depth(intr) + rng.normal(0, 0.004, intr.shape).astype(np.float32)
    z[10:25, 20:40] -= 0.4  # a box in front: depth discontinuities
    z[rng.random(intr.shape) < 0.08] = 0.0  # holes
    z[0, :5] = 9.0  # beyond max depth
    return z


def test_bilateral_kernel_matches_reference():
    z = noisy_scene_depth()
    sp, lut, step = kp.bilateral_tables(2, 1.5, 0.03)
    out = np.empty_like(z)
    kp.bilateral_filter(z, 0.1, 5.0, sp, lut, step, out)
    ref = kp.bilateral_filter_ref(z, 0.1, 5.0, sp, lut, step)
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-6)
    assert np.all(out[z == 0] == 0) and out[0, 0] == 0  # invalid / out-of-range stay invalid
    # edge preserving: the box front and the wall behind are not blended
    assert abs(out[17, 30] - z[10:25, 20:40][z[10:25, 20:40] > 0].mean()) < 0.05
    # smoothing reduces the noise on the plane
    clean = plane_depth(CAM80)
    m = (z > 0) & (z < 5)
    m[8:27, 18:42] = False
    assert np.std((out - clean)[m]) < 0.6 * np.std((z - clean)[m])


def test_vertex_normal_downsample_kernels_match_reference():
    z = noisy_scene_depth(1)
    i = CAM80
    V = np.empty((*z.shape, 3), np.float32)
    kp.depth_to_vertex(z, i.fx, i.fy, i.cx, i.cy, 0.1, 5.0, V)
    np.testing.assert_allclose(V, kp.depth_to_vertex_ref(z, i.fx, i.fy, i.cx, i.cy, 0.1, 5.0), atol=1e-6)
    N = np.empty_like(V)
    for step in (3, 2, 1):  # 1 last: N is used below
        kp.vertex_normals(V, 0.05, N, step)
        Nref = kp.vertex_normals_ref(V, 0.05, step)
        np.testing.assert_allclose(N, Nref, atol=1e-5)
        assert np.array_equal(np.any(N != 0, -1), np.any(Nref != 0, -1))
        assert not np.any(N[:step]) and not np.any(N[:, -step:])  # no normal within step pixels of the border
    Vd = np.empty((30, 40, 3), np.float32)
    kp.downsample_vertex(V, 0.05, Vd)
    np.testing.assert_allclose(Vd, kp.downsample_vertex_ref(V, 0.05), atol=1e-6)
    Nd = np.empty_like(Vd)
    kp.downsample_normal(V, N, 0.05, Nd)
    np.testing.assert_allclose(Nd, kp.downsample_normal_ref(V, N, 0.05), atol=1e-5)


def test_wider_normals_see_through_disparity_steps():
    """A slanted plane quantised into constant-depth treads (a structured-light sensor's disparity steps): 1-pixel
    differences give many treads' normal, the optical axis; differences 2 pixels either side follow the plane."""
    intr = Intrinsics(150.0, 150.0, 39.5, 29.5, 80, 60)
    u = np.arange(intr.width, dtype=np.float32)
    z = np.tile(2.0 + 0.004 * u, (intr.height, 1))  # 4 mm per pixel along u: a plane turned about the y axis
    args = (intr.fx, intr.fy, intr.cx, intr.cy, 0.1, 5.0)
    n_true = kp.vertex_normals_ref(kp.depth_to_vertex_ref(z, *args), 0.05)  # exact on a plane
    stairs = kp.depth_to_vertex_ref((np.round(z / 0.01) * 0.01).astype(np.float32), *args)  # 1 cm steps, ~2.5 px
    for step in (1, 2):
        N = kp.vertex_normals_ref(stairs, 0.05, step)
        ok = np.any(N != 0, -1) & np.any(n_true != 0, -1)
        on_axis = np.mean(np.abs(N[ok][:, 2]) > 0.9999)  # a tread's normal: along the optical axis
        err_deg = np.degrees(np.arccos(np.clip(np.sum(N[ok] * n_true[ok], -1), -1, 1)))
        if step == 1:  # measured: 19 % on the axis, 90th percentile 15.5 deg off
            assert on_axis > 0.15 and np.percentile(err_deg, 90) > 12.0
        else:  # measured: none on the axis, 90th percentile 6.2 deg off
            assert on_axis == 0.0 and np.percentile(err_deg, 90) < 8.0, np.percentile(err_deg, 90)


@pytest.mark.parametrize("fy_sign", [1.0, -1.0])
def test_plane_normals_exact_and_face_camera(fy_sign):
    intr = Intrinsics(150.0, fy_sign * 150.0, 39.5, 29.5, 80, 60)
    n_true = np.array([0.2, -0.3, -1.0]) / np.linalg.norm([0.2, -0.3, -1.0])
    cfg = PreprocessConfig(bilateral=False, pyramid_levels=3)
    pyr = build_pyramid(plane_depth(intr), intr, cfg)
    for i, lvl in enumerate(pyr.levels):
        ok = np.any(lvl.normal != 0, -1)
        b = cfg.normal_step_px if i == 0 else 1  # the working level's normals span normal_step_px either side
        assert ok[b:-b, b:-b].all() and not ok[:b].any()  # only the border is invalid
        assert np.all(np.sum(lvl.normal[ok] * lvl.vertex[ok], -1) < 0)  # faces the camera
        np.testing.assert_allclose(lvl.normal[ok], np.broadcast_to(n_true, lvl.normal[ok].shape), atol=1e-4)


@pytest.mark.parametrize("s", [1, 2])
def test_normals_invalid_at_holes_and_discontinuities(s):
    z = plane_depth(CAM80)
    z[30, 40] = 0.0
    z[10:20, 10:20] -= 0.5
    pyr = build_pyramid(z, CAM80, PreprocessConfig(bilateral=False, pyramid_levels=1, normal_step_px=s))
    n = pyr[0].normal
    for v, u in [(30, 40), (30 - s, 40), (30 + s, 40), (30, 40 - s), (30, 40 + s), (15, 10 - s), (15, 10),
                 (15, 20 - s), (15, 20 + s - 1)]:
        assert np.all(n[v, u] == 0), (v, u)
    assert np.any(n[15, 15] != 0) and np.any(n[15, 22] != 0) and np.any(n[29, 40] != 0) == (s > 1)


def test_pyramid_intrinsics_convention_projects_consistently():
    """A point seen at the centre of a 2x2 block projects to the coarse pixel with cx' = (cx - 0.5) / 2."""
    intr = Intrinsics(150.0, -140.0, 40.3, 29.1, 81, 61)
    half = halve_intrinsics(intr)
    assert (half.width, half.height) == (40, 30)
    assert half.cx == pytest.approx((40.3 - 0.5) / 2) and half.fy == -70.0
    # fronto-parallel plane: block-averaged points lie on the ray through the block centre
    z = np.full(intr.shape, 2.0, np.float32)
    pyr = build_pyramid(z, intr, PreprocessConfig(bilateral=False, pyramid_levels=3))
    for lvl in pyr.levels:
        li = lvl.intrinsics
        V = lvl.vertex
        v, u = np.mgrid[0 : li.height, 0 : li.width]
        np.testing.assert_allclose(li.fx * V[..., 0] / V[..., 2] + li.cx, u, atol=1e-4)
        np.testing.assert_allclose(li.fy * V[..., 1] / V[..., 2] + li.cy, v, atol=1e-4)


def test_pyramid_block_average_does_not_mix_depths():
    V = np.zeros((2, 2, 3), np.float32)
    V[..., 2] = [[1.0, 1.02], [3.0, 0.0]]
    V[..., 0] = [[0.1, 0.2], [5.0, 0.0]]
    out = np.empty((1, 1, 3), np.float32)
    kp.downsample_vertex(V, 0.05, out)
    np.testing.assert_allclose(out[0, 0], [0.15, 0.0, 1.01], atol=1e-6)


def test_preprocessor_reuses_buffers_and_matches_build_pyramid():
    z = noisy_scene_depth(2)
    cfg = PreprocessConfig(pyramid_levels=3)
    pre = Preprocessor(CAM80, cfg)
    out = pre.new_pyramid()
    ids = [id(lvl.vertex) for lvl in out.levels]
    res = pre.process(z, out=out)
    assert res is out and [id(lvl.vertex) for lvl in out.levels] == ids
    ref = build_pyramid(z, CAM80, cfg)
    for a, b in zip(out.levels, ref.levels, strict=True):
        assert np.array_equal(a.vertex, b.vertex) and np.array_equal(a.normal, b.normal)
        assert a.intrinsics == b.intrinsics
    assert np.all(out[0].vertex[z == 0] == 0) and np.all(out[0].vertex[0, :5] == 0)


def test_pyramid_from_maps():
    z = noisy_scene_depth(3)
    src = build_pyramid(z, CAM80, PreprocessConfig(bilateral=False, pyramid_levels=1))
    pyr = pyramid_from_maps(src[0].vertex, src[0].normal, CAM80, levels=3)
    assert isinstance(pyr, FramePyramid) and len(pyr) == 3
    assert np.array_equal(pyr[0].vertex, src[0].vertex)
    np.testing.assert_allclose(pyr[1].vertex, kp.downsample_vertex_ref(src[0].vertex, 0.05), atol=1e-6)
    nrm = np.linalg.norm(pyr[2].normal, axis=-1)
    assert np.allclose(nrm[nrm > 0], 1.0, atol=1e-5)
    assert pyr[2].intrinsics == halve_intrinsics(halve_intrinsics(CAM80))
    with pytest.raises(ConfigError):
        pyramid_from_maps(src[0].vertex[:-1], src[0].normal[:-1], CAM80, levels=2)


def test_bad_config_and_shapes():
    with pytest.raises(ConfigError):
        PreprocessConfig(min_depth_m=3.0, max_depth_m=2.0)
    with pytest.raises(ConfigError):
        PreprocessConfig(pyramid_levels=0)
    with pytest.raises(ConfigError, match="depth image"):
        build_pyramid(np.zeros((10, 10), np.float32), CAM80)


def test_depth_downsample_kernel_matches_reference_and_keeps_depths_apart():
    z = noisy_scene_depth(3)
    out = np.empty((z.shape[0] // 2, z.shape[1] // 2), np.float32)
    kp.downsample_depth(z, 0.1, 5.0, 0.05, out)
    ref = kp.downsample_depth_ref(z, 0.1, 5.0, 0.05)
    np.testing.assert_allclose(out, ref, rtol=1e-6, atol=0)
    # a block holding a near and a far surface keeps the near depth only; invalid pixels do not count
    mixed = np.array([[1.0, 1.0], [1.5, 0.0]], np.float32)
    one = np.empty((1, 1), np.float32)
    kp.downsample_depth(mixed, 0.1, 5.0, 0.05, one)
    assert one[0, 0] == pytest.approx(1.0)
    kp.downsample_depth(np.zeros((2, 2), np.float32), 0.1, 5.0, 0.05, one)
    assert one[0, 0] == 0.0
    # the cluster of the block's first valid pixel (by position) is kept, never a mix
    kp.downsample_depth(np.array([[0.0, 1.5], [1.0, 1.52]], np.float32), 0.1, 5.0, 0.05, one)
    assert one[0, 0] == pytest.approx(1.51)


def test_depth_downsample_is_unbiased_under_kinect_noise():
    """A plane at 4 m with Kinect-like noise (sigma 2.6 cm, about half the 5 cm window): the block means keep
    the plane's depth. Referencing the block's smallest depth instead cut off the far tail of the noise and pulled
    the plane 11 mm towards the camera."""
    rng = np.random.default_rng(0)
    z = (4.0 + rng.normal(0.0, 0.026, (480, 640))).astype(np.float32)
    out = np.empty((240, 320), np.float32)
    kp.downsample_depth(z, 0.1, 5.0, 0.05, out)
    assert abs(float(out.mean()) - 4.0) < 3e-4
    blocks = z.reshape(240, 2, 320, 2).transpose(0, 2, 1, 3).reshape(240, 320, 4).astype(np.float64)
    zmin = blocks.min(axis=-1, keepdims=True)
    near = np.where(blocks - zmin <= 0.05, blocks, np.nan)
    assert np.nanmean(near, axis=-1).mean() - 4.0 < -5e-3  # the min-referenced selection's bias, for contrast


def test_preprocess_from_a_coarser_first_level():
    """first_level=1: level 1 is the block-averaged depth processed at level-1 intrinsics; coarser levels follow."""
    z = noisy_scene_depth(4)
    cfg = PreprocessConfig(pyramid_levels=3)
    pre = Preprocessor(CAM80, cfg)
    pyr = pre.process(z, first_level=1)
    half = kp.downsample_depth_ref(z, cfg.min_depth_m, cfg.max_depth_m, cfg.pyramid_max_depth_diff_m)
    direct = Preprocessor(halve_intrinsics(CAM80), replace(cfg, pyramid_levels=2,
                                                          normal_max_depth_jump_m=2 * cfg.normal_max_depth_jump_m,
                                                          pyramid_max_depth_diff_m=2 * cfg.pyramid_max_depth_diff_m))
    ref = direct.process(half)
    for lvl in (1, 2):
        np.testing.assert_allclose(pyr[lvl].vertex, ref[lvl - 1].vertex, atol=1e-6)
        np.testing.assert_allclose(pyr[lvl].normal, ref[lvl - 1].normal, atol=1e-5)
    assert (pyr[1].vertex[..., 2] > 0).mean() > 0.8
    with pytest.raises(ConfigError, match="first_level"):
        pre.process(z, first_level=3)
