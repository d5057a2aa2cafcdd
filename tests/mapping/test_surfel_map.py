"""SurfelMap storage, culling index and rendering kernels (vs numpy references and analytic planes)."""

from __future__ import annotations

import numpy as np
import pytest

from surfelslam.errors import ConfigError
from surfelslam.geometry.se3 import invert, make_T, so3_exp
from surfelslam.kernels import render as kr
from surfelslam.kernels import surfels as ks
from surfelslam.mapping import MapConfig, RenderConfig, SurfelMap, render, render_index_map
from surfelslam.types import Intrinsics

CAM_NEG = Intrinsics(120.0, -115.0, 79.5, 59.5, 160, 120)  # negative fy on purpose (ICL-NUIM style)


def _random_map(n: int, seed: int = 0, cfg: MapConfig | None = None) -> SurfelMap:
    rng = np.random.default_rng(seed)
    m = SurfelMap(cfg or MapConfig(initial_capacity=8))
    pos = rng.uniform([-3, -2, 0.5], [3, 2, 6], size=(n, 3))
    nrm = rng.normal(size=(n, 3))
    nrm[:, 2] = -np.abs(nrm[:, 2]) - 0.5  # mostly facing a camera at the origin looking along +z
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    col = rng.uniform(0, 255, size=(n, 3))
    m.append(pos, nrm, col, rng.uniform(0.5, 5, n).astype(np.float32), rng.uniform(0.005, 0.03, n), 0)
    m.confidence[:] = rng.uniform(0.5, 5, n)
    m.first_seen[:] = rng.integers(0, 20, n)
    return m


def _plane_map(z_m: float, spacing_m: float = 0.01, half_m: float = 3.0) -> SurfelMap:
    g = np.arange(-half_m, half_m, spacing_m)
    xx, yy = np.meshgrid(g, g)
    pos = np.column_stack([xx.ravel(), yy.ravel(), np.full(xx.size, z_m)])
    m = SurfelMap()
    m.append(pos, np.tile([0.0, 0.0, -1.0], (len(pos), 1)), np.full((len(pos), 3), 77.0), 1.0, spacing_m, 0)
    return m


# ------------------------------------------------------------------------------------------------ storage
def test_growth_by_doubling_preserves_data():
    m = SurfelMap(MapConfig(initial_capacity=4))
    rng = np.random.default_rng(1)
    chunks = [rng.normal(size=(k, 3)).astype(np.float32) for k in (3, 2, 7, 1, 20)]
    caps = []
    for f, c in enumerate(chunks):
        m.append(c, c, np.abs(c) * 10, float(f + 1), 0.01, f)
        caps.append(m.capacity)
    allp = np.concatenate(chunks)
    assert m.size == len(allp) == 33
    np.testing.assert_array_equal(m.position, allp)
    np.testing.assert_array_equal(m.first_seen, np.repeat(np.arange(5), [3, 2, 7, 1, 20]))
    np.testing.assert_array_equal(m.confidence, np.repeat(np.arange(1, 6), [3, 2, 7, 1, 20]))
    assert caps == [4, 8, 16, 16, 33]  # doubles (or jumps to the request when doubling is not enough)
    assert np.all(m.hits == 1)


def test_remove_compacts_stably_and_deterministically():
    m = _random_map(1000, seed=2)
    before = {k: getattr(m, k).copy() for k in ("position", "normal", "colour", "confidence", "first_seen")}
    mask = np.random.default_rng(3).random(1000) < 0.3
    removed = m.remove(mask)
    assert removed == mask.sum()
    assert m.size == m.n_alive == 1000 - mask.sum()
    for k, v in before.items():
        np.testing.assert_array_equal(getattr(m, k), v[~mask])
    m2 = _random_map(1000, seed=2)
    m2.remove(mask)
    np.testing.assert_array_equal(m.position, m2.position)
    with pytest.raises(ValueError, match="mask must have shape"):
        m.remove(np.zeros(3, bool))


def test_compact_kernel_matches_reference():
    m = _random_map(500, seed=4)
    dead = (np.random.default_rng(5).random(500) < 0.4).astype(np.uint8)
    ref = ks.compact_rows_ref([m.position.copy(), m.confidence.copy(), m.first_seen.copy()], dead, 500)
    m.mark_dead(dead.astype(bool))
    assert m.n_dead == dead.sum()
    m.compact()
    np.testing.assert_array_equal(m.position, ref[0])
    np.testing.assert_array_equal(m.confidence, ref[1])
    np.testing.assert_array_equal(m.first_seen, ref[2])
    assert m.n_dead == 0 and not m.dead.any()


def test_bad_config_is_rejected():
    with pytest.raises(ConfigError, match="block_size_m"):
        MapConfig(block_size_m=0)
    with pytest.raises(ConfigError, match="min_depth_m"):
        RenderConfig(min_depth_m=5, max_depth_m=1)


# ------------------------------------------------------------------------------------------------ index
def test_group_by_block_matches_reference():
    rng = np.random.default_rng(6)
    ids = rng.integers(0, 37, 2000).astype(np.int32)
    order = np.zeros(2000, np.int32)
    start = np.zeros(37, np.int32)
    count = np.zeros(37, np.int32)
    ks.group_by_block(ids, 2000, 37, order, start, count)
    o2, s2, c2 = ks.group_by_block_ref(ids, 2000, 37)
    np.testing.assert_array_equal(order, o2)
    np.testing.assert_array_equal(start, s2)
    np.testing.assert_array_equal(count, c2)


def test_cull_and_gather_match_reference_and_keep_every_visible_surfel():
    m = _random_map(20000, seed=7, cfg=MapConfig(initial_capacity=8, index_max_tail=5000, block_size_m=0.5))
    m.rebuild_index()
    # a tail of ungrouped surfels too
    rng = np.random.default_rng(8)
    extra = rng.uniform([-3, -2, 0.5], [3, 2, 6], size=(3000, 3))
    m.append(extra, np.tile([0, 0, -1.0], (3000, 1)), np.zeros((3000, 3)), 1.0, 0.01, 1)
    assert m.n_grouped == 20000 and m.size == 23000
    T = make_T(so3_exp([0.1, 0.4, -0.05]), [0.2, -0.1, 0.3])
    cand = m.visible_candidates(T, CAM_NEG, 0.1, 4.0).copy()
    # reference culling + gathering
    Tcw = invert(T)
    view = (CAM_NEG.fx, CAM_NEG.fy, CAM_NEG.cx, CAM_NEG.cy, -0.5, CAM_NEG.width - 0.5, -0.5, CAM_NEG.height - 0.5)
    reach = kr.frustum_reach(*view, 4.0)
    assert reach == pytest.approx(4.0 * np.sqrt(1 + (CAM_NEG.cx + 0.5) ** 2 / CAM_NEG.fx ** 2
                                                + (CAM_NEG.cy + 0.5) ** 2 / CAM_NEG.fy ** 2))
    vis_ref = kr.cull_blocks_ref(m._block_ijk, m.n_blocks, 0.5, m.cfg.block_margin_m, Tcw[:3, :3], Tcw[:3, 3],
                                 *view, 0.1, 4.0, reach)
    np.testing.assert_array_equal(m._visible[: m.n_blocks], vis_ref)
    # the distance test keeps whatever the face tests keep within the frustum's reach (here: all), culls beyond it
    vis_faces = kr.cull_blocks_ref(m._block_ijk, m.n_blocks, 0.5, m.cfg.block_margin_m, Tcw[:3, :3], Tcw[:3, 3],
                                   *view, 0.1, 4.0)
    np.testing.assert_array_equal(vis_ref, vis_faces)
    vis_near = kr.cull_blocks_ref(m._block_ijk, m.n_blocks, 0.5, m.cfg.block_margin_m, Tcw[:3, :3], Tcw[:3, 3],
                                  *view, 0.1, 4.0, 1.5)
    assert np.all(vis_near <= vis_faces) and 0 < vis_near.sum() < vis_faces.sum()
    assert 0 < vis_ref.sum() < m.n_blocks  # some culled, some kept
    ref = ks.gather_candidates_ref(vis_ref, m._order, m._block_start, m._block_count, m._n_blocks_grouped,
                                   m._block_id, m.n_grouped, m.size, m._dead)
    np.testing.assert_array_equal(cand, ref)
    # every surfel that projects into the image within the depth range is a candidate
    pc = m.position.astype(np.float64) @ Tcw[:3, :3].T + Tcw[:3, 3]
    z = pc[:, 2]
    u = CAM_NEG.fx * pc[:, 0] / z + CAM_NEG.cx
    v = CAM_NEG.fy * pc[:, 1] / z + CAM_NEG.cy
    inview = (z > 0.1) & (z < 4.0) & (u > -0.5) & (u < CAM_NEG.width - 0.5) & (v > -0.5) & (v < CAM_NEG.height - 0.5)
    assert inview.sum() > 1000
    assert np.isin(np.flatnonzero(inview), cand).all()
    assert len(cand) < 0.8 * m.size  # and culling removed a real share


def test_culling_by_cubes_of_blocks_equals_culling_block_by_block():
    """A floor-sized map (a floor and walls over 20 x 15 m, negative coordinates, blocks at the cubes' edges),
    grouped in cubes, then more blocks added (tested one by one): at 60 poses, some looking into empty space and some
    from inside a cube, the cubes give exactly the per-block test's flags, and most blocks are rejected by their
    cube."""
    rng = np.random.default_rng(11)
    m = MapConfig(initial_capacity=8)
    smap = SurfelMap(m)
    floor = rng.uniform([-10, -7.5, 0], [10, 7.5, 0], size=(8300, 3))
    wall = rng.uniform([-10, -7.5, 0], [10, 7.5, 2.5], size=(8300, 3))
    wall[:, 0] = np.round(wall[:, 0] / 5) * 5  # walls every 5 m across the floor
    xyz = np.where(rng.random((8300, 1)) < 0.6, floor, wall)[rng.permutation(8300)]
    smap.append(xyz[:8000], np.tile([0, 0, 1.0], (8000, 1)), np.zeros((8000, 3)), 1.0, 0.01, 0)
    intr = Intrinsics(262.5, 262.5, 159.5, 119.5, 320, 240)
    smap.visible_candidates(np.eye(4), intr, 0.1, 8.0)  # groups the blocks so far in cubes
    smap.append(xyz[8000:], np.tile([0, 0, 1.0], (300, 1)), np.zeros((300, 3)), 1.0, 0.01, 1)
    group_ijk, start, blocks, n_in = smap._cull_groups()
    assert n_in < smap.n_blocks and len(group_ijk) < n_in / 4
    nb, bs, margin = smap.n_blocks, m.block_size_m, m.block_margin_m
    view = (intr.fx, intr.fy, intr.cx, intr.cy, -2.5, intr.width + 1.5, -2.5, intr.height + 1.5)
    rejected = []
    for k in range(60):
        centre = xyz[rng.integers(len(xyz))] + rng.normal(0, 0.2, 3) if k % 2 else rng.uniform(-15, 15, 3)
        Tcw = invert(make_T(so3_exp(rng.uniform(-np.pi, np.pi, 3)), centre))
        R, t = np.ascontiguousarray(Tcw[:3, :3]), np.ascontiguousarray(Tcw[:3, 3])
        args = (bs, margin, R, t, *view, 0.1, 8.0, kr.frustum_reach(*view, 8.0))
        cubes = np.full(nb, 7, np.uint8)
        kr.cull_blocks_grouped(group_ijk, start, blocks, 4 * bs, n_in, smap._block_ijk, nb, *args, cubes)
        np.testing.assert_array_equal(cubes, kr.cull_blocks_ref(smap._block_ijk, nb, *args))
        in_view = kr.cull_blocks_ref(group_ijk, len(group_ijk), 4 * bs, margin + 1e-3, R, t, *view, 0.1, 8.0,
                                     kr.frustum_reach(*view, 8.0))
        rejected.append(np.sum(np.diff(start)[in_view == 0]) / n_in)
    assert np.mean(rejected) > 0.8


# ------------------------------------------------------------------------------------------------ render
def test_render_plane_depth_and_normal_at_known_pixels():
    z0 = 2.0
    m = _plane_map(z0)
    # camera translated and rotated about y: plane z = z0 in world
    T = make_T(so3_exp([0.0, 0.2, 0.0]), [0.1, 0.05, -0.3])
    view = render(m, T, CAM_NEG, RenderConfig(vertex="disc"))  # disc mode: the exact plane point on each ray
    assert view.valid.mean() > 0.99  # no holes
    centre = render(m, T, CAM_NEG)  # centre mode (default): the surfel centres, on the plane too
    Tcw = invert(T)
    n_cam = Tcw[:3, :3] @ np.array([0.0, 0.0, -1.0])
    # expected: intersection of each pixel ray with the plane n_cam . x = n_cam . p0 (p0 a plane point in cam)
    p0 = Tcw[:3, :3] @ np.array([0.0, 0.0, z0]) + Tcw[:3, 3]
    for u, v in [(0, 0), (80, 60), (159, 119), (23, 97), (140, 11)]:
        d = np.array([(u - CAM_NEG.cx) / CAM_NEG.fx, (v - CAM_NEG.cy) / CAM_NEG.fy, 1.0])
        t = n_cam @ p0 / (n_cam @ d)
        np.testing.assert_allclose(view.vertex_cam[v, u], t * d, atol=1e-5)
        np.testing.assert_allclose(view.normal_cam[v, u], n_cam, atol=1e-6)
        assert view.colour[v, u].tolist() == [77, 77, 77]
        assert abs(n_cam @ (centre.vertex_cam[v, u] - p0)) < 1e-5  # centre lies on the plane
        assert np.linalg.norm(centre.vertex_cam[v, u] - t * d) < 0.03  # ... within a surfel spacing of the ray
    # image row 0 sees world y > 0 side? with fy < 0, v = 0 is +y: check sign convention directly
    assert view.vertex_cam[0, 80, 1] > 0 and view.vertex_cam[119, 80, 1] < 0


def test_render_draws_the_confident_surface_not_a_noisy_surfel_just_in_front():
    """A well-observed plane at 2 m (confidence 10) with single-view surfels 8 mm in front of it (confidence 1, the
    noise of one Kinect frame at 2 m): with ``front_band_rel`` 0.01 (2 cm here) the more confident plane is drawn;
    with 0, the nearest, as the plain z-test did, the noisy surfels. An object 10 cm in front (outside the band)
    still occludes the plane."""
    m = _plane_map(2.0)
    m.confidence[:] = 10.0
    rng = np.random.default_rng(3)
    noisy = rng.uniform([-0.5, -0.4, 1.992], [0.5, 0.4, 1.992], size=(400, 3))
    m.append(noisy, np.tile([0.0, 0.0, -1.0], (400, 1)), np.full((400, 3), 9.0), 1.0, 0.01, 0)
    box = np.column_stack([np.full(25, 0.3) + np.repeat(np.arange(5), 5) * 0.01,
                           np.tile(np.arange(5), 5) * 0.01, np.full(25, 1.9)])
    m.append(box, np.tile([0.0, 0.0, -1.0], (25, 1)), np.full((25, 3), 200.0), 1.0, 0.01, 0)
    near = render(m, np.eye(4), CAM_NEG, RenderConfig(front_band_rel=0.0))
    band = render(m, np.eye(4), CAM_NEG, RenderConfig(front_band_rel=0.01))
    plane = near.index < m.size - 425
    in_front = (near.index >= m.size - 425) & (near.index < m.size - 25)
    assert in_front.sum() > 200  # the plain z-test draws the noisy surfels
    np.testing.assert_allclose(near.vertex_cam[in_front, 2], 1.992, atol=1e-6)
    np.testing.assert_allclose(band.vertex_cam[in_front, 2], 2.0, atol=1e-6)  # the band draws the plane there
    assert np.array_equal(band.index[plane & (near.index >= 0)], near.index[plane & (near.index >= 0)])
    box_px = near.index >= m.size - 25
    assert box_px.sum() > 10 and np.array_equal(band.index[box_px], near.index[box_px])  # occluders stay


def test_render_from_closer_has_no_holes_thanks_to_splats():
    m = _plane_map(2.0, spacing_m=0.012)
    view = render(m, make_T(np.eye(3), [0, 0, 0.6]), CAM_NEG)  # 1.4 m away: spacing ~1.0 px... closer than creation
    assert view.valid.mean() > 0.99
    view0 = render(m, make_T(np.eye(3), [0, 0, 0.6]), CAM_NEG, RenderConfig(max_splat_radius_px=0.0))
    assert view0.valid.mean() < view.valid.mean()


def test_render_culls_backfaces_and_handles_min_confidence_fallback():
    m = _plane_map(2.0)
    # the camera behind the plane (looking along -z from z = 4) sees the back of every surfel
    T_back = make_T(so3_exp([0.0, np.pi, 0.0]), [0.0, 0.0, 4.0])
    assert not render(m, T_back, CAM_NEG).valid.any()
    assert render(m, T_back, CAM_NEG, RenderConfig(cull_backfaces=False)).valid.mean() > 0.99
    # min_confidence: all surfels have confidence 1, first seen at frame 0
    m.latest_frame = 5
    strict = RenderConfig(min_confidence=2.0, young_age_frames=3)
    assert not render(m, np.eye(4), CAM_NEG, strict).valid.any()  # old and unstable: hidden
    young = RenderConfig(min_confidence=2.0, young_age_frames=10)
    assert render(m, np.eye(4), CAM_NEG, young).valid.mean() > 0.99  # young map: fallback draws them


def test_splat_fill_and_index_kernels_match_references():
    m = _random_map(30000, seed=9)
    T = make_T(so3_exp([0.02, -0.05, 0.01]), [0.05, 0.0, -0.1])
    Tcw = invert(T)
    R, t = Tcw[:3, :3].copy(), Tcw[:3, 3].copy()
    cand = np.arange(m.size, dtype=np.int32)[::-1].copy()  # arbitrary order matters only for exact ties
    a = m.raw()
    H, W = CAM_NEG.shape
    args = (cand, len(cand), a["position"], a["normal"], a["radius"], a["confidence"], a["first_seen"], 2.0, 15,
            R, t, CAM_NEG.fx, CAM_NEG.fy, CAM_NEG.cx, CAM_NEG.cy, 2.0, 0.1, 8.0, True)
    for band_rel in (0.0, 0.01, 0.05):  # the nearest disc wins; the most confident within the band
        depth = np.full((H, W), np.inf)
        index = np.full((H, W), -1, np.int32)
        kr.splat_zbuffer(*args, band_rel, depth, index)
        depth_r, index_r = kr.splat_zbuffer_ref(*args, band_rel, (H, W))
        assert (index >= 0).mean() > 0.5
        np.testing.assert_array_equal(index, index_r)
        np.testing.assert_array_equal(depth, depth_r)
        if band_rel == 0.0:
            nearest = depth.copy()
        else:  # a drawn disc lies within the band of the nearest; some pixels change hands
            hit = index >= 0
            assert np.all(depth[hit] <= nearest[hit] * (1 + band_rel)) and np.any(depth[hit] > nearest[hit])
    depth = np.full((H, W), np.inf)
    index = np.full((H, W), -1, np.int32)
    kr.splat_zbuffer(*args, 0.0, depth, index)

    out = [np.empty((H, W, 3), np.float32), np.empty((H, W, 3), np.float32), np.empty((H, W, 3), np.uint8),
           np.empty((H, W), np.float32)]
    for use_centre in (True, False):
        kr.fill_view(index, depth, a["position"], a["normal"], a["colour"], a["confidence"], R, t,
                     CAM_NEG.fx, CAM_NEG.fy, CAM_NEG.cx, CAM_NEG.cy, use_centre, *out)
        ref = kr.fill_view_ref(index, depth, a["position"], a["normal"], a["colour"], a["confidence"], R, t,
                               CAM_NEG.fx, CAM_NEG.fy, CAM_NEG.cx, CAM_NEG.cy, use_centre)
        for o, r in zip(out, ref, strict=True):
            np.testing.assert_allclose(o.astype(np.float64), r.astype(np.float64), atol=1e-5)

    shape_s = (H * 4, W * 4)
    d4 = np.full(shape_s, np.inf)
    i4 = np.full(shape_s, -1, np.int32)
    c = CAM_NEG
    iargs = (cand, len(cand), a["position"], a["normal"], R, t, c.fx, c.fy, c.cx, c.cy, 4, 0.1, 8.0, True)
    kr.index_zbuffer(*iargs, d4, i4)
    d4r, i4r = kr.index_zbuffer_ref(*iargs, shape_s)
    np.testing.assert_array_equal(i4, i4r)
    np.testing.assert_array_equal(d4, d4r)
    # each surfel appears at most once in the index map
    ids = i4[i4 >= 0]
    assert len(np.unique(ids)) == len(ids) > 1000


def test_splat_early_outs_match_the_reference_far_from_the_origin():
    """The splat's early outs (a back face found in the world frame, a pixel already nearer than the disc can be) only
    skip what its exact tests reject: layered surfels, half of them facing away, 60 m from the world origin, drawn
    exactly as the reference draws them."""
    rng = np.random.default_rng(4)
    n = 60000
    offset = np.array([60.0, -45.0, 20.0])
    m = SurfelMap(MapConfig(initial_capacity=8))
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    pos = rng.uniform([-2, -1.5, 0.5], [2, 1.5, 5], size=(n, 3)) + offset
    m.append(pos, nrm, rng.uniform(0, 255, size=(n, 3)), 1.0, rng.uniform(0.005, 0.04, n), 0)
    T = make_T(so3_exp([0.03, 0.02, -0.01]), offset)
    Tcw = invert(T)
    R, t = Tcw[:3, :3].copy(), Tcw[:3, 3].copy()
    cand = np.arange(n, dtype=np.int32)
    a = m.raw()
    H, W = CAM_NEG.shape
    args = (cand, n, a["position"], a["normal"], a["radius"], a["confidence"], a["first_seen"], 0.0, 0,
            R, t, CAM_NEG.fx, CAM_NEG.fy, CAM_NEG.cx, CAM_NEG.cy, 2.0, 0.1, 8.0, True)
    p_cam = (a["position"][:n].astype(np.float64) - T[:3, 3]) @ T[:3, :3]
    facing = np.einsum("ij,ij->i", a["normal"][:n].astype(np.float64) @ T[:3, :3], p_cam) < 0
    assert 0.4 < facing.mean() < 0.6
    for band_rel in (0.0, 0.02):
        depth = np.full((H, W), np.inf)
        index = np.full((H, W), -1, np.int32)
        kr.splat_zbuffer(*args, band_rel, depth, index)
        depth_r, index_r = kr.splat_zbuffer_ref(*args, band_rel, (H, W))
        drawn = index[index >= 0]
        assert (index >= 0).mean() > 0.8 and facing[drawn].all()
        assert len(np.unique(drawn)) < 0.5 * facing.sum()  # most facing surfels are hidden by nearer ones
        np.testing.assert_array_equal(index, index_r)
        np.testing.assert_array_equal(depth, depth_r)


def test_render_index_map_cell_of_known_surfel():
    m = SurfelMap()
    # one surfel exactly on the ray of pixel (u, v) = (10.3, 20.6) at 2 m
    u, v, z = 10.3, 20.6, 2.0
    p = [(u - CAM_NEG.cx) / CAM_NEG.fx * z, (v - CAM_NEG.cy) / CAM_NEG.fy * z, z]
    m.append(np.array([p]), np.array([[0, 0, -1.0]]), np.zeros((1, 3)), 1.0, 0.01, 0)
    im = render_index_map(m, np.eye(4), CAM_NEG, scale=4)
    sv, su = np.argwhere(im.index == 0)[0]
    assert (su, sv) == (int(np.floor((u + 0.5) * 4)), int(np.floor((v + 0.5) * 4)))
    assert (su // 4, sv // 4) == (10, 21)
    assert (im.index >= 0).sum() == 1


def test_reorder_by_block_groups_checked_rows_and_keeps_the_rest():
    m = _random_map(3000, seed=4, cfg=MapConfig(initial_capacity=8, block_size_m=0.5))
    m.first_seen[:] = np.sort(m.first_seen)  # fusion order
    m.mark_dead(np.arange(0, 3000, 7))
    before = {name: getattr(m, name[1:]).copy() for name in ("_position", "_first_seen", "_block_id")}
    dead_before = m._dead[: m.size].copy()
    T = make_T(np.eye(3), np.zeros(3))
    intr = Intrinsics(100.0, 100.0, 79.5, 59.5, 160, 120)
    seen_before = {tuple(p) for p in m.position[m.visible_candidates(T, intr, 0.1, 8.0)]}
    n = 2000
    m.reorder_by_block(n)
    blocks = m._block_id[:n]
    assert np.all(np.diff(blocks) >= 0)  # each block contiguous, blocks in id order
    # a permutation of the first n rows (dead flags travel with their rows); the rest untouched
    key = lambda pos, fs, dead: sorted(map(tuple, np.column_stack([pos, fs, dead]).tolist()))  # noqa: E731
    assert key(m.position[:n], m.first_seen[:n], m._dead[:n]) == key(
        before["_position"][:n], before["_first_seen"][:n], dead_before[:n])
    np.testing.assert_array_equal(m.position[n:], before["_position"][n:])
    np.testing.assert_array_equal(m.first_seen[n:], before["_first_seen"][n:])
    # the culling index follows the moved rows: the same surfels are candidates
    assert {tuple(p) for p in m.position[m.visible_candidates(T, intr, 0.1, 8.0)]} == seen_before
    # maybe_reorder only acts once enough rows were checked by the dormant rule
    m2 = _random_map(100, cfg=MapConfig(initial_capacity=8, reorder_every_rows=50))
    m2.dormant_cursor = 40
    assert not m2.maybe_reorder()
    m2.dormant_cursor = 60
    assert m2.maybe_reorder() and np.all(np.diff(m2._block_id[:60]) >= 0)


def test_maybe_reorder_regroups_only_new_rows_until_they_reach_a_quarter():
    m = _random_map(3000, seed=5, cfg=MapConfig(initial_capacity=8, block_size_m=0.5, reorder_every_rows=100))
    m.dormant_cursor = 2000
    assert m.maybe_reorder() and np.all(np.diff(m._block_id[:2000]) >= 0)  # the first time: all checked rows
    head = m.position[:2000].copy()
    m.dormant_cursor = 2300  # 300 new rows < 2000 / 4: regrouped among themselves, the first 2000 stay
    tail_before = sorted(map(tuple, m.position[2000:2300].tolist()))
    assert m.maybe_reorder()
    np.testing.assert_array_equal(m.position[:2000], head)
    assert np.all(np.diff(m._block_id[2000:2300]) >= 0)
    assert sorted(map(tuple, m.position[2000:2300].tolist())) == tail_before
    assert not np.all(np.diff(m._block_id[:2300]) >= 0)  # two groupings, one after the other
    m.dormant_cursor = 2500  # 500 rows since the whole regrouping: all 2500 again
    assert m.maybe_reorder() and np.all(np.diff(m._block_id[:2500]) >= 0)


def test_transform_some_rows_moves_them_alone_and_regroups_their_blocks():
    """``transform_surfels`` on some rows equals the whole-map move on those rows, leaves the others untouched, and
    puts every moved surfel in the block of its new position (the grouping covers the whole map again)."""
    m = _random_map(3000, seed=5, cfg=MapConfig(initial_capacity=8, block_size_m=0.5))
    whole = _random_map(3000, seed=5, cfg=MapConfig(initial_capacity=8, block_size_m=0.5))
    rows = np.flatnonzero(np.random.default_rng(1).random(3000) < 0.3)
    T = make_T(so3_exp([0.1, -0.2, 0.3]), [2.0, -1.0, 0.7])
    R_all = np.broadcast_to(T[:3, :3].astype(np.float32), (3000, 3, 3)).copy()
    t_all = np.broadcast_to(T[:3, 3].astype(np.float32), (3000, 3)).copy()
    before = m.position.copy()
    m.transform_surfels(R_all[rows], t_all[rows], rows)
    whole.transform_surfels(R_all, t_all)
    keep = np.ones(3000, bool)
    keep[rows] = False
    np.testing.assert_array_equal(m.position[rows], whole.position[rows])
    np.testing.assert_array_equal(m.normal[rows], whole.normal[rows])
    np.testing.assert_array_equal(m.position[keep], before[keep])
    ijk = np.floor(m.position / 0.5).astype(np.int32)
    np.testing.assert_array_equal(m._block_ijk[m._block_id[: m.size]], ijk)
    assert m.n_grouped == m.size
    with pytest.raises(ValueError, match="rows"):
        m.transform_surfels(R_all[:1], t_all[:1], np.array([3000]))


def test_transform_groups_matches_its_reference():
    """Rows moved by their group's transform (the numba kernel) equal the per-row matrix products of the reference;
    the other rows stay."""
    m = _random_map(2000, seed=6, cfg=MapConfig(initial_capacity=8, block_size_m=0.5))
    rng = np.random.default_rng(2)
    R = np.array([so3_exp(rng.normal(0, 0.2, 3)) for _ in range(5)], np.float32)
    t = rng.normal(0, 1.0, (5, 3)).astype(np.float32)
    rows = np.flatnonzero(rng.random(2000) < 0.5)
    group = rng.integers(0, 5, len(rows))
    pos0, nrm0 = m.position.copy(), m.normal.copy()
    ref_p, ref_n = ks.transform_rows_ref(pos0, nrm0, rows, group, R, t)
    m.transform_groups(R, t, group, rows)
    np.testing.assert_allclose(m.position[rows], ref_p, atol=1e-5)
    np.testing.assert_allclose(m.normal[rows], ref_n, atol=1e-6)
    keep = np.setdiff1d(np.arange(2000), rows)
    np.testing.assert_array_equal(m.position[keep], pos0[keep])
    with pytest.raises(ValueError, match="groups"):
        m.transform_groups(R, t, np.array([5]), np.array([0]))


def test_rows_off_block_matches_its_reference_to_the_row():
    """The one-pass kernel that finds the surfels a correction moved out of their block returns exactly the rows of the
    numpy reference (float32 product, floor, int32), also for positions on block faces, negative ones and rows in
    no particular order; an empty ``rows`` gives none."""
    rng = np.random.default_rng(7)
    m = _random_map(5000, seed=7, cfg=MapConfig(initial_capacity=8, block_size_m=0.3))
    pos = m._position
    pos[:500] = np.round(pos[:500] / 0.3) * np.float32(0.3)  # on (or a rounding away from) the block faces
    pos[500:1000] *= -1.0
    rows = rng.permutation(5000)[:3500].astype(np.int64)
    inv = np.float32(m._inv_block)
    got = ks.rows_off_block(pos, rows, m._block_id, m._block_ijk, inv)
    ref = ks.rows_off_block_ref(pos, rows, m._block_id, m._block_ijk, m._inv_block)
    assert 300 <= len(ref) < len(rows) // 2  # the negated rows left their blocks, most others did not
    np.testing.assert_array_equal(got, ref)
    assert len(ks.rows_off_block(pos, rows[:0], m._block_id, m._block_ijk, inv)) == 0
