"""Point-based fusion: kernels vs numpy references, merge/add behaviour, accuracy with GT poses, removal rules."""

from __future__ import annotations

import math

import numpy as np
import pytest

from surfelslam.errors import ConfigError
from surfelslam.geometry.camera import backproject
from surfelslam.geometry.se3 import make_T, so3_exp
from surfelslam.kernels import fusion as kf
from surfelslam.mapping import FusionConfig, SurfelMap, fuse, pixel_weights, render
from surfelslam.types import Intrinsics

CAM_NEG = Intrinsics(130.0, -130.0, 79.5, 59.5, 160, 120)  # negative fy (ICL-NUIM convention)
ROOM_LO = np.array([-2.5, -1.5, -2.0])
ROOM_HI = np.array([2.5, 1.5, 3.0])


def room_frame(T_world_cam: np.ndarray, intr: Intrinsics = CAM_NEG, noise_m: float = 0.0, seed: int = 0):
    """Ray-cast the inside of an axis-aligned box room: (vertex_cam, normal_cam, rgb, depth)."""
    H, W = intr.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    d_cam = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], -1)
    R, c = T_world_cam[:3, :3], T_world_cam[:3, 3]
    d_w = d_cam @ R.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t_axis = np.where(d_w > 0, (ROOM_HI - c) / d_w, np.where(d_w < 0, (ROOM_LO - c) / d_w, np.inf))
    k = np.argmin(t_axis, axis=-1)
    t = np.take_along_axis(t_axis, k[..., None], -1)[..., 0]
    n_w = np.zeros_like(d_w)
    np.put_along_axis(n_w, k[..., None], -np.sign(np.take_along_axis(d_w, k[..., None], -1)), -1)
    p_w = c + t[..., None] * d_w
    depth = t.astype(np.float32)
    if noise_m > 0:
        depth = depth + np.random.default_rng(seed).normal(0, noise_m, depth.shape).astype(np.float32)
    vertex = backproject(depth, intr)
    normal = (n_w @ R).astype(np.float32)  # R^T n
    check = (np.floor(p_w * 4).sum(-1) % 2).astype(np.uint8)
    rgb = np.stack([check * 200 + 20, (k * 80).astype(np.uint8), np.full_like(check, 90)], -1).astype(np.uint8)
    return vertex, normal, rgb, depth


def dist_to_room(p: np.ndarray) -> np.ndarray:
    return np.minimum(np.abs(p - ROOM_LO), np.abs(p - ROOM_HI)).min(-1)


def numpy_normals(vertex: np.ndarray) -> np.ndarray:
    """Small numpy normal estimate: cross product of central differences, oriented to the camera."""
    dx = np.zeros_like(vertex)
    dy = np.zeros_like(vertex)
    dx[:, 1:-1] = vertex[:, 2:] - vertex[:, :-2]
    dy[1:-1] = vertex[2:] - vertex[:-2]
    n = np.cross(dx, dy)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(norm > 0, n / np.where(norm > 0, norm, 1), 0)
    n = np.where((n * vertex).sum(-1, keepdims=True) > 0, -n, n)
    bad = (vertex[..., 2] <= 0) | (norm[..., 0] == 0)
    n[bad] = 0
    return n.astype(np.float32)


def pose(rot, trans):
    return make_T(so3_exp(np.asarray(rot, float)), np.asarray(trans, float))


# ------------------------------------------------------------------------------------------------ references
def _setup_two_frames(noise_m=0.003):
    m = SurfelMap()
    cfg = FusionConfig(remove_unstable=False)
    T0 = pose([0.0, 0.1, 0.0], [0.1, 0.0, 0.0])
    V, N, C, _ = room_frame(T0, noise_m=noise_m, seed=1)
    fuse(m, V, N, C, T0, CAM_NEG, 0, cfg)
    T1 = pose([0.01, 0.13, 0.0], [0.13, 0.02, 0.05])
    V1, _, C1, _ = room_frame(T1, noise_m=noise_m, seed=2)
    N1 = numpy_normals(V1)
    return m, cfg, T1, V1, N1, C1


def _buckets(m, T):
    cand = m.visible_candidates(T, CAM_NEG, 0.1, 4.0).copy()
    a = m.raw()
    Tcw = np.linalg.inv(T)
    H, W = CAM_NEG.shape
    start = np.empty(H * W + 1, np.int32)
    order = np.empty(len(cand), np.int32)
    pix = np.empty(len(cand), np.int32)
    args = (cand, len(cand), a["position"], a["normal"], Tcw[:3, :3].copy(), Tcw[:3, 3].copy(),
            CAM_NEG.fx, CAM_NEG.fy, CAM_NEG.cx, CAM_NEG.cy, H, W, 0.1, 4.0, True)
    n = kf.bucket_by_pixel(*args, pix, start, order)
    start_r, order_r = kf.bucket_by_pixel_ref(*args)
    np.testing.assert_array_equal(start, start_r)
    np.testing.assert_array_equal(order[:n], order_r)
    return start, order


def test_bucket_and_associate_kernels_match_references():
    m, cfg, T1, V1, N1, _ = _setup_two_frames()
    start, order = _buckets(m, T1)
    assert np.diff(start).max() >= 1 and start[-1] > 0.5 * CAM_NEG.width * CAM_NEG.height
    a = m.raw()
    R, t = T1[:3, :3].copy(), T1[:3, 3].copy()
    cos_a = math.cos(math.radians(20))
    for cover in (0, 1):
        out = np.empty(CAM_NEG.shape, np.int32)
        args = (V1, N1, start, order, a["position"], a["normal"], a["confidence"], R, t, 0.03, cos_a, 0.1, 4.0,
                cover)
        kf.associate(*args, out)
        ref = kf.associate_ref(*args)
        np.testing.assert_array_equal(out, ref)
        assert (out >= 0).mean() > 0.5 and (out == kf.ASSOC_NEW).any()
        if cover:
            assert (out == kf.ASSOC_COVERED).any()
        merged = out[out >= 0]
        assert len(np.unique(merged)) == len(merged)  # a surfel is updated by at most one pixel


def test_merge_and_add_kernels_match_references():
    m, cfg, T1, V1, N1, C1 = _setup_two_frames()
    start, order = _buckets(m, T1)
    a = m.raw()
    R, t = T1[:3, :3].copy(), T1[:3, 3].copy()
    assoc = np.empty(CAM_NEG.shape, np.int32)
    kf.associate(V1, N1, start, order, a["position"], a["normal"], a["confidence"], R, t, 0.03,
                 math.cos(math.radians(20)), 0.1, 4.0, 1, assoc)
    w = pixel_weights(CAM_NEG, "keller", 0.6)
    rpd = 1.0 / 130.0
    n = m.size
    before = [a[k][:n].copy() for k in ("position", "normal", "colour", "confidence", "radius", "last_seen", "hits")]
    ref = kf.merge_ref(assoc, V1, N1, C1, w, R, t, 7, 1.5, rpd, 0.2, 0.05, *before)
    kf.merge(assoc, V1, N1, C1, w, R, t, 7, 1.5, rpd, 0.2, 0.05, a["position"], a["normal"], a["colour"],
             a["confidence"], a["radius"], a["last_seen"], a["hits"])
    after = [a[k][:n] for k in ("position", "normal", "colour", "confidence", "radius", "last_seen", "hits")]
    for got, exp in zip(after, ref, strict=True):
        np.testing.assert_allclose(got.astype(np.float64), exp.astype(np.float64), rtol=1e-5, atol=1e-5)
    assert not np.allclose(before[0], after[0])  # something did move
    k = int((assoc == kf.ASSOC_NEW).sum())
    m.reserve(n + k)
    a = m.raw()
    added = kf.add_new(assoc, V1, N1, C1, w, R, t, 7, rpd, 0.2, 0.05, n, a["position"], a["normal"], a["colour"],
                       a["confidence"], a["radius"], a["first_seen"], a["last_seen"], a["hits"], a["dead"])
    assert added == k > 0
    p, nn, c, cf, r = kf.add_new_ref(assoc, V1, N1, C1, w, R, t, rpd, 0.2, 0.05)
    np.testing.assert_allclose(a["position"][n : n + k], p, atol=1e-5)
    np.testing.assert_allclose(a["normal"][n : n + k], nn, atol=1e-5)
    np.testing.assert_array_equal(a["colour"][n : n + k], c)
    np.testing.assert_array_equal(a["confidence"][n : n + k], cf)
    np.testing.assert_allclose(a["radius"][n : n + k], r, rtol=1e-5)


def test_removal_kernels_match_references():
    rng = np.random.default_rng(3)
    n = 5000
    first = np.sort(rng.integers(0, 100, n)).astype(np.int32)
    hits = rng.integers(1, 10, n).astype(np.int32)
    dead = (rng.random(n) < 0.05).astype(np.uint8)
    cur, k = kf.dormant_scan(first, hits, dead.copy(), 100, n, 90, 20, 4)
    cur_r, rows = kf.dormant_scan_ref(first, hits, dead, 100, n, 90, 20, 4)
    assert cur == cur_r and k == len(rows) > 0
    conf = rng.uniform(0, 6, n).astype(np.float32)
    last = rng.integers(0, 100, n).astype(np.int32)
    cand = rng.permutation(n)[:2000].astype(np.int32)
    d2 = dead.copy()
    k2 = kf.stale_unstable(cand, len(cand), conf, last, d2, 100, 30, 3.0)
    rows2 = kf.stale_unstable_ref(cand, len(cand), conf, last, dead, 100, 30, 3.0)
    assert k2 == len(rows2) > 0
    np.testing.assert_array_equal(np.flatnonzero(d2 != dead), np.sort(rows2))


# ------------------------------------------------------------------------------------------------ behaviour
def test_same_frame_twice_merges_without_duplicates():
    m = SurfelMap()
    T = pose([0.0, 0.3, 0.0], [0.0, 0.2, 0.0])
    V, N, C, depth = room_frame(T)
    cfg = FusionConfig(weight_mode="constant")
    s1 = fuse(m, V, N, C, T, CAM_NEG, 0, cfg)
    assert s1.added == m.size == int((depth > 0.1).sum() - ((depth > 4.0).sum()))
    pos0 = m.position.copy()
    s2 = fuse(m, V, N, C, T, CAM_NEG, 1, cfg)
    assert s2.added == 0 and s2.merged == m.size == s1.added
    np.testing.assert_array_equal(m.confidence, 2.0)
    np.testing.assert_array_equal(m.hits, 2)
    np.testing.assert_array_equal(m.last_seen, 1)
    np.testing.assert_allclose(m.position, pos0, atol=1e-6)
    # Keller weights: confidence grows by the radial weight, 1 at the centre
    m2 = SurfelMap()
    fuse(m2, V, N, C, T, CAM_NEG, 0)
    c1 = m2.confidence.copy()
    fuse(m2, V, N, C, T, CAM_NEG, 1)
    np.testing.assert_allclose(m2.confidence, 2 * c1, rtol=1e-6)
    assert c1.max() <= 1.0 and c1.min() >= math.exp(-1 / (2 * 0.6**2)) - 1e-6


def test_pixel_weights_keller_and_constant():
    w = pixel_weights(CAM_NEG, "keller", 0.6)
    assert w.shape == CAM_NEG.shape
    assert w.max() <= 1.0 and w[60, 80] > 0.999
    np.testing.assert_allclose(w[0, 0], math.exp(-1 / (2 * 0.36)), rtol=1e-5)
    assert (pixel_weights(CAM_NEG, "constant", 0.6) == 1).all()


def _trajectory(n: int) -> list[np.ndarray]:
    return [pose([0.02 * math.sin(i / 3), 0.25 * i / n, 0.0], [0.3 * i / n, 0.05 * math.sin(i / 2), 0.2 * i / n])
            for i in range(n)]


def test_gt_fusion_gives_surfels_on_the_true_surfaces():
    m = SurfelMap()
    cfg = FusionConfig(remove_unstable=False)
    poses = _trajectory(12)
    stats = []
    for i, T in enumerate(poses):
        V, _, C, _ = room_frame(T, noise_m=0.002, seed=i)
        N = numpy_normals(V)
        stats.append(fuse(m, V, N, C, T, CAM_NEG, i, cfg))
    d = dist_to_room(m.position.astype(np.float64))
    assert np.quantile(d, 0.99) < 0.01
    stable = m.hits >= 4
    assert stable.mean() > 0.5
    assert d[stable].max() < 0.01
    assert np.abs(d[stable]).mean() < 0.0015  # averaging beats the 2 mm noise
    # most pixels merge once the map exists; the map grows far slower than the input
    assert all(s.merged > 0.7 * (CAM_NEG.width * CAM_NEG.height) for s in stats[1:])
    ratio = m.size / (len(poses) * CAM_NEG.width * CAM_NEG.height)
    assert ratio < 0.25
    # the map rendered at a frame's pose reproduces its depth
    view = render(m, poses[6], CAM_NEG)
    _, _, _, depth = room_frame(poses[6])
    ok = view.valid & (depth < 4.0)
    assert ok.mean() > 0.9
    assert np.median(np.abs(view.depth_m[ok] - depth[ok])) < 0.002


def test_fusion_is_deterministic():
    def run():
        m = SurfelMap()
        for i, T in enumerate(_trajectory(5)):
            V, _, C, _ = room_frame(T, noise_m=0.003, seed=i)
            fuse(m, V, numpy_normals(V), C, T, CAM_NEG, i)
        return m

    a, b = run(), run()
    for k in ("position", "normal", "colour", "confidence", "radius", "hits", "first_seen", "last_seen"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))


def test_a_read_only_colour_image_fuses_alike_without_a_kernel_of_its_own():
    """Colour from a camera's or a bag's buffer is read-only, a type of its own to numba: fused as it is, it made the
    merge and add kernels compile again in the middle of a run (seconds). It is copied once instead."""
    T = pose([0.0, 0.3, 0.0], [0.0, 0.2, 0.0])
    V, N, C, _ = room_frame(T)
    writable, read_only = SurfelMap(), SurfelMap()
    for i in range(2):
        fuse(writable, V, N, C, T, CAM_NEG, i)
    kernels = [getattr(k, "serial", k) for k in (kf.merge, kf.add_new)]  # a DualKernel's serial twin runs here
    n_compiled = {k: len(k.signatures) for k in kernels}
    C_ro = C.copy()
    C_ro.flags.writeable = False
    for i in range(2):
        fuse(read_only, V, N, C_ro, T, CAM_NEG, i)
    assert {k: len(k.signatures) for k in n_compiled} == n_compiled
    for k in ("position", "normal", "colour", "confidence", "radius", "hits"):
        np.testing.assert_array_equal(getattr(read_only, k), getattr(writable, k))


def test_dormant_rule_on_and_off():
    T_a = pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])  # looks at the +z wall
    T_b = pose([0.0, math.pi, 0.0], [0.0, 0.0, 0.0])  # looks at the -z wall: region A is out of view
    Va, Na, Ca, _ = room_frame(T_a)
    Vb, Nb, Cb, _ = room_frame(T_b)
    counts = {}
    for on in (False, True):
        m = SurfelMap()
        cfg = FusionConfig(remove_unstable=on, unstable_max_age_frames=5, stable_min_hits=3,
                           compact_dead_fraction=0.0, weight_mode="constant")
        fuse(m, Va, Na, Ca, T_a, CAM_NEG, 0, cfg)  # region A seen once
        n_a = m.size
        for f in range(1, 10):  # region B seen every frame
            fuse(m, Vb, Nb, Cb, T_b, CAM_NEG, f, cfg)
        counts[on] = (n_a, m.size, m.n_alive)
        if on:
            assert np.all(m.hits >= 3)  # the once-seen surfels are gone, the stable ones stay
            assert np.all(m.first_seen >= 1)
    n_a, size_off, _ = counts[False]
    _, size_on, alive_on = counts[True]
    assert size_on == alive_on == size_off - n_a


def test_keller_stale_rule_removes_unstable_surfels_left_in_view():
    # constant weights, confidence threshold above what one sighting gives; the dormant rule is made inert
    T = pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    V, N, C, _ = room_frame(T)
    m = SurfelMap()
    cfg = FusionConfig(unstable_max_age_frames=3, stable_min_hits=0, stable_min_confidence=1.5,
                       weight_mode="constant", compact_dead_fraction=0.0)
    fuse(m, V, N, C, T, CAM_NEG, 0, cfg)
    n0 = m.size
    empty = np.zeros_like(V)
    for f in range(1, 5):  # the camera sees nothing valid (e.g. depth dropout); the surfels stay in view
        s = fuse(m, empty, empty, C, T, CAM_NEG, f, cfg)
    assert s.removed == n0 and m.size == 0


def test_bad_input_and_config():
    m = SurfelMap()
    V, N, C, _ = room_frame(np.eye(4))
    with pytest.raises(ValueError, match="vertex/normal maps"):
        fuse(m, V[:, :-1], N, C, np.eye(4), CAM_NEG, 0)
    with pytest.raises(ValueError, match="frame_rgb"):
        fuse(m, V, N, C.astype(np.float32), np.eye(4), CAM_NEG, 0)
    with pytest.raises(ConfigError, match="weight_mode"):
        FusionConfig(weight_mode="linear")
    with pytest.raises(ConfigError, match="angle_diff_deg"):
        FusionConfig(angle_diff_deg=0)


@pytest.mark.parametrize("offset_m", [0.01, 0.025, 0.04])
def test_a_planted_duplicate_layer_is_merged_into_one(offset_m):
    """Issue 68: a revisit must not leave a second layer. The +z wall of the room is planted twice, the true copy
    and one ``offset_m`` nearer the camera (a near-copy within duplicate_dist_m, or a layer in front within
    dist_diff_m: what a pose-graph correction can leave), both confirmed (confidence and hits of several sightings),
    with their own ids; the nearer copy wins the rendered depth. Fusing a few noisy frames of the wall keeps one
    surfel per wall pixel and the rendered depth goes back onto the wall."""
    T = pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])  # looks at the +z wall (z = 3 m) head on
    V, N, C, depth = room_frame(T)
    m = SurfelMap()
    cfg = FusionConfig(weight_mode="constant", compact_dead_fraction=0.0)
    fuse(m, V, N, C, T, CAM_NEG, 0, cfg)
    wall = np.abs(m.position[:, 2] - ROOM_HI[2]) < 1e-4
    n_wall = int(wall.sum())
    assert n_wall == int((np.abs(depth - ROOM_HI[2]) < 1e-4).sum()) > 1000  # one surfel per wall pixel
    m.append(m.position[wall] - [0.0, 0.0, offset_m], m.normal[wall], m.colour[wall], 10.0, m.radius[wall], 0)
    m.confidence[:] = 10.0
    m.hits[:] = 10  # confirmed: the dormant rule does not remove either copy
    on_wall_px = np.abs(depth - ROOM_HI[2]) < 1e-4
    on_wall_px[:3] = on_wall_px[-3:] = False  # splats cross the border rows/columns
    on_wall_px[:, :3] = on_wall_px[:, -3:] = False
    before = render(m, T, CAM_NEG).depth_m[on_wall_px]
    np.testing.assert_allclose(np.median(before), ROOM_HI[2] - offset_m, atol=1e-3)  # the planted layer is in front
    for f in range(1, 4):
        Vn, Nn, Cn, _ = room_frame(T, noise_m=0.001, seed=f)  # well inside the 5 mm between the layers
        fuse(m, Vn, Nn, Cn, T, CAM_NEG, f, cfg)
    # in the image's interior (a copy that projects outside the image is not seen: it stays, as it should)
    uv = m.position[:, :2] / m.position[:, 2:] * [CAM_NEG.fx, CAM_NEG.fy] + [CAM_NEG.cx, CAM_NEG.cy]
    inner = np.all((uv >= 2) & (uv <= [CAM_NEG.width - 3, CAM_NEG.height - 3]), axis=1)
    n_inner = int((wall & inner[: len(wall)]).sum())  # the wall's pixels there (one surfel each)
    near_wall = m.alive_mask() & (np.abs(m.position[:, 2] - ROOM_HI[2]) < 0.05)
    assert int((near_wall & inner).sum()) == n_inner > 1000  # one layer: as many surfels as wall pixels
    assert np.abs(m.position[near_wall & inner, 2] - ROOM_HI[2]).max() < 0.005  # ... on the true wall
    after = render(m, T, CAM_NEG).depth_m[on_wall_px]
    np.testing.assert_allclose(np.median(after), ROOM_HI[2], atol=1e-3)
    assert np.abs(after - ROOM_HI[2]).max() < 0.005


def test_a_layer_behind_the_measured_surface_is_kept():
    """The rule for layers acts on what the sensor saw through: a confirmed copy 3 cm BEHIND the wall (hidden by it,
    beyond duplicate_dist_m) is left alone; the measurements keep merging into the wall."""
    T = pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    V, N, C, _ = room_frame(T)
    m = SurfelMap()
    cfg = FusionConfig(weight_mode="constant", compact_dead_fraction=0.0)
    fuse(m, V, N, C, T, CAM_NEG, 0, cfg)
    wall = np.flatnonzero(np.abs(m.position[:, 2] - ROOM_HI[2]) < 1e-4)
    m.append(m.position[wall] + [0.0, 0.0, 0.03], m.normal[wall], m.colour[wall], 10.0, m.radius[wall], 0)
    m.confidence[:] = 10.0
    m.hits[:] = 10
    n0 = m.n_alive
    for f in range(1, 4):
        fuse(m, V, N, C, T, CAM_NEG, f, cfg)
    assert m.n_alive == n0
    np.testing.assert_array_equal(m.hits[wall], 13)  # the wall took every measurement
