"""Level of detail of the model render (``RenderConfig.lod_surfels_per_px``): per-block strides vs their numpy
reference, and what a far, crowded plane and a near one look like with it on and off."""

from __future__ import annotations

import dataclasses

import numpy as np

from surfelslam.geometry.se3 import invert, make_T, so3_exp
from surfelslam.kernels import render as kr
from surfelslam.kernels import surfels as ks
from surfelslam.mapping import MapConfig, RenderConfig, SurfelMap, render
from surfelslam.types import Intrinsics

CAM = Intrinsics(262.5, 262.5, 159.5, 119.5, 320, 240)


def _plane(z_m: float, spacing_m: float, half_m: float) -> SurfelMap:
    """A fronto-parallel grid of surfels at depth ``z_m`` facing a camera at the origin."""
    g = np.arange(-half_m, half_m, spacing_m)
    xx, yy = np.meshgrid(g, g)
    pos = np.column_stack([xx.ravel(), yy.ravel(), np.full(xx.size, z_m)])
    m = SurfelMap(MapConfig(block_size_m=0.25))
    m.append(pos, np.tile([0.0, 0.0, -1.0], (len(pos), 1)), np.full((len(pos), 3), 77.0), 1.0, spacing_m, 0)
    m.rebuild_index()
    return m


def test_lod_strides_and_strided_gather_match_their_references():
    rng = np.random.default_rng(3)
    m = SurfelMap(MapConfig(block_size_m=0.25, index_max_tail=10**9))
    m.append(rng.uniform([-2, -2, 0.05], [2, 2, 7], (60000, 3)), np.tile([0.0, 0.0, -1.0], (60000, 1)),
             np.zeros((60000, 3)), 1.0, 0.01, 0)
    m.rebuild_index()
    m.append(rng.uniform([-2, -2, 1], [2, 2, 7], (500, 3)), np.tile([0.0, 0.0, -1.0], (500, 1)),
             np.zeros((500, 3)), 1.0, 0.01, 1)  # an ungrouped tail: always taken whole
    m.mark_dead(np.arange(0, 60000, 7))
    T = make_T(so3_exp([0.05, -0.1, 0.02]), [0.1, 0.0, -0.2])
    per_px = 0.02  # few surfels per block here: a small target makes strides > 1
    cand = m.visible_candidates(T, CAM, 0.1, 6.5, lod_surfels_per_px=per_px).copy()
    Tcw = invert(T)
    vis = m._visible[: m.n_blocks].copy()
    m.visible_candidates(T, CAM, 0.1, 6.5)  # the same culling without strides
    plain = m._visible[: m.n_blocks].copy()
    ref = kr.lod_strides_ref(plain, m.n_blocks, m._block_ijk, m._block_count, 0.25, Tcw[:3, :3], Tcw[:3, 3],
                             CAM.fx, CAM.fy, per_px, 255)
    np.testing.assert_array_equal(vis, ref)
    assert (vis > 1).sum() > 20 and (vis == 1).sum() > 5 and np.all((vis == 0) == (plain == 0))
    gathered = ks.gather_candidates_ref(vis, m._order, m._block_start, m._block_count, m._n_blocks_grouped,
                                        m._block_id, m.n_grouped, m.size, m._dead)
    np.testing.assert_array_equal(cand, gathered)
    assert np.isin(np.arange(60000, 60500), cand).sum() == (vis[m.block_id[60000:]] > 0).sum()  # the whole tail


def test_far_crowded_plane_draws_a_fraction_of_its_surfels_on_the_plane():
    m = _plane(5.0, 0.003, 0.5)  # ~40 surfels on each pixel at 5 m
    T = np.eye(4)
    off = render(m, T, CAM, RenderConfig(lod_surfels_per_px=0.0), attributes=False)
    assert off.valid.sum() > 2500
    lost = {}
    for per_px in (2.0, 4.0):
        on = render(m, T, CAM, RenderConfig(lod_surfels_per_px=per_px), attributes=False)
        again = render(m, T, CAM, RenderConfig(lod_surfels_per_px=per_px), attributes=False)
        np.testing.assert_array_equal(on.index, again.index)  # deterministic
        assert 40 / per_px * 0.7 * on.n_candidates < off.n_candidates  # strides of ~40 / per_px
        assert not np.any(on.valid & ~off.valid)
        lost[per_px] = 1.0 - on.valid.sum() / off.valid.sum()
        np.testing.assert_allclose(on.depth_m[on.valid], 5.0, atol=1e-6)
        np.testing.assert_allclose(on.normal_cam[on.valid] - [0.0, 0.0, -1.0], 0.0, atol=1e-6)
        # each drawn centre lies within the pixel's footprint on the plane
        v, u = np.nonzero(on.valid)
        x_ray = (u - CAM.cx) / CAM.fx * 5.0
        assert np.abs(on.vertex_cam[v, u, 0] - x_ray).max() < 0.5 * 5.0 / CAM.fx + 1e-6
    # thinned at random within runs of the block's order, a uniformly crowded plane loses about exp(-per_px) of its
    # pixels (per_px surfels kept on each on average; on floor3's saved map, 0.3 % of the rendered pixels at 2)
    assert 0.08 < lost[2.0] < 0.2 and lost[4.0] < 0.03


def test_near_plane_renders_identically_with_lod_on():
    m = _plane(1.0, 0.01, 1.0)  # < 1 surfel per pixel: every block keeps stride 1
    T = make_T(so3_exp([0.02, 0.03, 0.0]), [0.05, 0.0, 0.0])
    cfg = RenderConfig()
    off = render(m, T, CAM, cfg, attributes=False)
    on = render(m, T, CAM, dataclasses.replace(cfg, lod_surfels_per_px=2.0), attributes=False)
    assert on.n_candidates == off.n_candidates
    np.testing.assert_array_equal(on.index, off.index)
    np.testing.assert_array_equal(on.vertex_cam, off.vertex_cam)
