"""Dense (ICP) refinement of PnP keyframe edges: precision, the feature terms, the gate, storage, config."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from surfelslam.backend.dense_edges import EDGE_ICP, DenseEdgeConfig, DenseEdgeRefiner, weak_direction_shape
from surfelslam.errors import ConfigError
from surfelslam.geometry import se3
from surfelslam.synth import make_scene, render
from surfelslam.synth.noise import KinectNoiseConfig, noisy_depth
from surfelslam.synth.trajectories import look_at
from surfelslam.tracking.preprocess import FramePyramid, PreprocessConfig, Preprocessor, level_for_width
from surfelslam.types import Intrinsics

from helpers import INTR


def _keypoints(depth_ref: np.ndarray, T_cur_ref: np.ndarray, n: int, seed: int, noise_px: float = 0.3):
    """``n`` points of the ref depth (ref camera) and their noisy pixels in the cur image."""
    rng = np.random.default_rng(seed)
    v, u = np.nonzero(depth_ref > 0)
    pick = rng.choice(len(u), n, replace=False)
    z = depth_ref[v[pick], u[pick]].astype(np.float64)
    pts = np.column_stack([(u[pick] - INTR.cx) / INTR.fx * z, (v[pick] - INTR.cy) / INTR.fy * z, z])
    X = se3.transform_points(T_cur_ref, pts)
    uv = np.column_stack([INTR.fx * X[:, 0] / X[:, 2] + INTR.cx, INTR.fy * X[:, 1] / X[:, 2] + INTR.cy])
    return pts, uv + rng.normal(0, noise_px, uv.shape)


def _pair(scene_name: str, eye, target, xi_cur_ref, noise_seed: int | None = None):
    """Rendered ref and cur depth of ``scene_name`` and the true ``T_cur_ref``."""
    scene = make_scene(scene_name)
    T_w_ref = look_at(np.asarray(eye, float), np.asarray(target, float))[0]
    T_cur_ref = se3.exp(np.asarray(xi_cur_ref, float))
    out = []
    for T in (T_w_ref, T_w_ref @ se3.invert(T_cur_ref)):
        r = render(scene, T, INTR)
        d = r.depth_m.copy()
        if noise_seed is not None:
            d = noisy_depth(d, r.normal_cam, INTR, KinectNoiseConfig(), np.random.default_rng(noise_seed + len(out)))
        out.append(d)
    return out[0], out[1], T_cur_ref


@pytest.fixture(scope="module")
def room_pair():
    return _pair("room", [2.5, 2.0, 1.4], [2.5, 0.0, 0.8], [0.05, -0.08, 0.03, 0.12, 0.04, -0.06], noise_seed=5)


def _refiner(cfg: DenseEdgeConfig | None = None) -> DenseEdgeRefiner:
    return DenseEdgeRefiner(INTR, PreprocessConfig(), cfg or DenseEdgeConfig())


def test_a_pnp_edge_is_refined_to_dense_precision(room_pair):
    """A PnP-quality edge (15 mm, 0.4 deg off) between two Kinect-noise keyframes comes out within a millimetre."""
    d_ref, d_cur, T_true = room_pair
    ref = _refiner()
    ref.add_keyframe(0, d_ref)
    ref.add_keyframe(1, d_cur)
    T_pnp = se3.exp(np.array([0.004, -0.005, 0.003, 0.009, -0.008, 0.008])) @ T_true
    assert se3.pose_error(T_pnp, T_true)[0] > 0.01
    pts, uv = _keypoints(d_ref, T_true, 200, seed=1)
    for features in ((pts, uv), (None, None)):
        edge = ref.refine(0, 1, T_pnp, *features)
        assert edge is not None and edge.information_shape is None  # weak_direction_ratio 0: isotropic
        dt, dr = se3.pose_error(edge.T_cur_ref, T_true)
        assert dt < 1.5e-3 and dr < 0.05, (dt, dr)


def test_an_edge_from_an_odometry_close_start_is_refined_at_the_finest_level_alone(room_pair, monkeypatch):
    """``finest_only`` (a nearby pair from its odometry, a few mm off): one pyramid level is registered instead of
    three, and the edge comes out within a millimetre of the truth and of the whole pyramid's edge."""
    from surfelslam.backend import dense_edges

    d_ref, d_cur, T_true = room_pair
    ref = _refiner()
    ref.add_keyframe(0, d_ref)
    ref.add_keyframe(1, d_cur)
    T_odometry = se3.exp(np.array([0.002, -0.002, 0.001, 0.002, -0.002, 0.002])) @ T_true
    pts, uv = _keypoints(d_ref, T_true, 200, seed=1)
    levels = []
    real_icp = dense_edges.icp
    monkeypatch.setattr(dense_edges, "icp", lambda *a, **k: levels.append(k["cfg"].levels) or real_icp(*a, **k))
    full = ref.refine(0, 1, T_odometry, pts, uv)
    finest = ref.refine(0, 1, T_odometry, pts, uv, finest_only=True)
    assert levels == [EDGE_ICP.levels, 1]
    assert full is not None and finest is not None
    dt, dr = se3.pose_error(finest.T_cur_ref, full.T_cur_ref)
    assert dt < 1e-3 and dr < 0.02, (dt, dr)  # the finest level's own minimum, a fraction of a mm away
    assert se3.pose_error(T_odometry, T_true)[0] > 3e-3
    dt, dr = se3.pose_error(finest.T_cur_ref, T_true)
    assert dt < 1e-3 and dr < 0.02, (dt, dr)


def test_feature_terms_hold_what_a_plane_leaves_free():
    """One textured plane leaves 3 DoF free: geometry alone is degenerate (edge dropped). 150 PnP inliers as
    reprojection terms at the default weight still leave the joint system ill-conditioned (condition number
    2.7e4), so the edge is dropped; at weight 0.3 they make it well-conditioned and the edge is recovered."""
    d_ref, d_cur, T_true = _pair("plane", [1.5, 0.0, 1.5], [0.0, 0.1, 1.4], [0.0, 0.03, 0.0, 0.02, 0.0, 0.01])
    T_pnp = se3.exp(np.array([0.0, 0.0, 0.004, 0.008, -0.006, 0.0])) @ T_true
    pts, uv = _keypoints(d_ref, T_true, 150, seed=2)
    ref = _refiner()
    ref.add_keyframe(3, d_ref)
    ref.add_keyframe(7, d_cur)
    assert ref.refine(3, 7, T_pnp) is None
    assert ref.refine(3, 7, T_pnp, pts, uv) is None
    ref = _refiner(DenseEdgeConfig(feature_weight=0.3))
    ref.add_keyframe(3, d_ref)
    ref.add_keyframe(7, d_cur)
    edge = ref.refine(3, 7, T_pnp, pts, uv)
    assert edge is not None
    dt, dr = se3.pose_error(edge.T_cur_ref, T_true)
    assert dt < 2e-3 and dr < 0.1, (dt, dr)


def test_edges_the_depth_moves_beyond_the_gate_are_dropped(room_pair):
    """ICP converging 5 cm away from the PnP pose means the two disagree: no edge."""
    d_ref, d_cur, T_true = room_pair
    ref = _refiner()
    ref.add_keyframe(0, d_ref)
    ref.add_keyframe(1, d_cur)
    T_far = se3.exp(np.array([0.0, 0.0, 0.0, 0.05, 0.0, 0.0])) @ T_true
    assert ref.refine(0, 1, T_far) is None
    wide = _refiner(DenseEdgeConfig(max_shift_m=0.08))
    wide.add_keyframe(0, d_ref)
    wide.add_keyframe(1, d_cur)
    edge = wide.refine(0, 1, T_far)
    assert edge is not None and se3.pose_error(edge.T_cur_ref, T_true)[0] < 2e-3


def test_keyframe_depth_is_stored_reduced_and_quantised():
    big = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 4.0, (480, 640)).astype(np.float32)
    depth[:10] = 0.0
    depth[20:30] = 7.0  # beyond max_depth_m: invalid
    ref = DenseEdgeRefiner(big, PreprocessConfig(), DenseEdgeConfig(max_width_px=320))
    ref.add_keyframe(0, depth)
    assert (ref.intrinsics.width, ref.intrinsics.height) == (320, 240)
    assert ref.intrinsics.fx == pytest.approx(262.5)
    stored = ref.depth_m(0)
    assert stored.shape == (240, 320) and stored.dtype == np.float32
    assert np.all(stored[:5] == 0) and np.all(stored[10:15] == 0)
    same = DenseEdgeRefiner(big, PreprocessConfig(), DenseEdgeConfig(max_width_px=640))
    same.add_keyframe(0, depth)
    valid = depth <= PreprocessConfig().max_depth_m
    err = np.abs(same.depth_m(0) - np.where(valid, depth, 0))
    assert err.max() <= 0.5 * PreprocessConfig().max_depth_m / 65535 + 1e-6
    assert [level_for_width(640, w) for w in (640, 320, 200, 160, 1)] == [0, 1, 2, 2, 6]


def test_a_trackers_pyramid_stands_in_for_the_keyframes_rebuilt_one(room_pair):
    """The tracker's own pyramid of a keyframe (more levels, same preprocessing) is taken as the one the refiner would
    build from the stored depth: the same maps, level by level, and the same refined edge; a pyramid of another size
    (the stored depth is reduced from a larger input) is refused."""
    d_ref, d_cur, T_true = room_pair
    ref = _refiner()
    ref.add_keyframe(0, d_ref)
    ref.add_keyframe(1, d_cur)
    stored = ref.depth_m(1)  # the input the refiner rebuilds from: the tracker's pyramid of it must be identical
    tracker_pyr = Preprocessor(INTR, replace(PreprocessConfig(), pyramid_levels=4)).process(stored)
    taken = ref.keyframe_pyramid(tracker_pyr)
    rebuilt = ref.frame_pyramid(stored)
    assert taken is not None and len(taken) == len(rebuilt) == EDGE_ICP.levels
    for a, b in zip(taken.levels, rebuilt.levels, strict=True):
        assert a.intrinsics == b.intrinsics
        np.testing.assert_array_equal(a.vertex, b.vertex)
        np.testing.assert_array_equal(a.normal, b.normal)
    assert not np.shares_memory(taken[0].vertex, tracker_pyr[0].vertex)  # a copy: the tracker reuses its buffers
    T_pnp = se3.exp(np.array([0.004, -0.005, 0.003, 0.009, -0.008, 0.008])) @ T_true
    plain = ref.refine(0, 1, T_pnp)
    adopted = _refiner()
    adopted.add_keyframe(0, d_ref)
    adopted.add_keyframe(1, np.zeros_like(d_cur))  # the stored depth is not used: the adopted pyramid is
    adopted.adopt(1, taken)
    edge = adopted.refine(0, 1, T_pnp)
    assert plain is not None and edge is not None
    np.testing.assert_array_equal(edge.T_cur_ref, plain.T_cur_ref)
    big = Intrinsics(2 * INTR.fx, 2 * INTR.fy, 2 * INTR.cx + 0.5, 2 * INTR.cy + 0.5, 640, 480)
    reduced = DenseEdgeRefiner(big, PreprocessConfig(), DenseEdgeConfig(max_width_px=320))
    big_pyr = Preprocessor(big, replace(PreprocessConfig(), pyramid_levels=4)).process(
        np.kron(stored, np.ones((2, 2), np.float32)))
    assert reduced.keyframe_pyramid(big_pyr) is None
    assert reduced.keyframe_pyramid(FramePyramid(big_pyr.levels[1:])) is None  # right size, other filter scale


def test_edge_sigma_follows_the_spread_of_nearby_edges():
    """sigma_m until min_spread_edges nearby edges were seen, then the robust spread of their discrepancies with
    the odometry (never below sigma_m)."""
    ref = _refiner(DenseEdgeConfig(min_spread_edges=5, spread_window_edges=20))
    rng = np.random.default_rng(4)
    seen = []  # |log| components of every edge: the spread is over the last 20 edges' (kept once per change)
    for k in range(40):
        if k < 5:
            assert ref.edge_sigma() == 0.003 and ref.spread() is None
        else:
            assert ref.spread() == float(np.median(seen[-6 * 20:])) / 0.6745
        T = se3.exp(rng.normal(0, 0.02, 6))
        T_odo = T @ se3.exp(rng.normal(0, 0.01, 6))
        ref.observe_nearby(T, T_odo)
        seen += np.abs(se3.log(se3.invert(T) @ T_odo)).tolist()
    assert ref.edge_sigma() == pytest.approx(0.01, rel=0.3) and ref.edge_sigma() == ref.spread()
    tight = _refiner(DenseEdgeConfig(min_spread_edges=5))
    for _ in range(10):
        T = se3.exp(rng.normal(0, 0.02, 6))
        tight.observe_nearby(T, T @ se3.exp(rng.normal(0, 1e-4, 6)))
    assert tight.edge_sigma() == 0.003


@pytest.mark.parametrize(("sigma_rad", "sigma_m", "trusted"),
                         [(0.0001, 0.0002, True), (0.001, 0.0002, False), (0.0001, 0.002, False)])
def test_edges_whose_graph_leaves_large_residuals_are_not_trusted(sigma_rad, sigma_m, trusted):
    """The robust spreads of the refined edges' rotation and translation residuals at their graph's optimum:
    mutually consistent edges leave 0.1-0.2 mrad and 0.2 mm (synthetic Kinect-like noise); biased ones 0.5-1.1 mrad
    (7-Scenes, distorted synthetic depth) or, biased along a corridor's axis, about 0.9 mm; above
    ``max_trusted_residual_rad`` or ``max_trusted_residual_m`` they are not trusted. Odometry edges do not count,
    nor do fewer than ``min_spread_edges`` refined edges."""
    from surfelslam.backend.pose_graph import PoseEdge

    cfg = DenseEdgeConfig(min_spread_edges=10)
    ref = _refiner(cfg)
    rng = np.random.default_rng(6)
    P = np.stack([se3.exp(rng.normal(0, 0.5, 6)) for _ in range(30)])
    loops = []
    for _ in range(60):
        i, j = rng.choice(30, 2, replace=False)
        noise = se3.exp(np.r_[rng.normal(0, sigma_rad, 3), rng.normal(0, sigma_m, 3)])
        loops.append(PoseEdge(int(i), int(j), se3.invert(P[i]) @ P[j] @ noise, "loop"))
    odo = [PoseEdge(k, k + 1, se3.exp(rng.normal(0, 0.1, 6)), "odometry") for k in range(29)]  # far off: ignored
    # the edges in a pose graph, which stacks its loop edges (and only those) as they come
    from surfelslam.backend.pose_graph import PoseGraph

    graph = PoseGraph()
    for T in P:
        graph.add_node(T)
    for e in [*odo[:15], *loops[:9]]:
        graph.add_edge(e)
    assert ref.loop_residual_spread(*graph.loop_edges(), P) is None and not ref.trusted(None)
    for e in [*odo[15:], *loops[9:]]:
        graph.add_edge(e)
    T_ij, i, j = graph.loop_edges()
    assert len(T_ij) == 60 and i.tolist() == [e.i for e in loops] and j.tolist() == [e.j for e in loops]
    r = ref.loop_residual_spread(T_ij, i, j, P)
    assert r == pytest.approx((sigma_rad, sigma_m), rel=0.25)
    assert ref.trusted(r) == trusted


def test_loop_residuals_kept_between_calls_equal_a_full_recomputation():
    """LoopResiduals recomputes only new edges and those whose keyframes moved: after edges are added, a few poses
    move and new keyframes come, its residuals and the spreads are bit-for-bit those of a fresh computation, and
    the residual of a planted 0.02 rad / 0.05 m error is found."""
    from surfelslam.backend.dense_edges import LoopResiduals, loop_residuals

    rng = np.random.default_rng(11)
    P = np.stack([se3.exp(rng.normal(0, 0.5, 6)) for _ in range(40)])
    ij = rng.choice(30, (50, 2))
    ij = ij[ij[:, 0] != ij[:, 1]]
    T = np.stack([se3.invert(P[a]) @ P[b] @ se3.exp(rng.normal(0, 0.01, 6)) for a, b in ij])
    E = se3.exp(np.r_[0.02, 0, 0, 0, 0, 0])
    E[:3, 3] = [0.05, 0, 0]  # along the rotation axis: the residual is (0.02, 0, 0) rad, (0.05, 0, 0) m
    T[0] = se3.invert(P[ij[0, 0]]) @ P[ij[0, 1]] @ E
    kept, ref = LoopResiduals(), _refiner(DenseEdgeConfig(min_spread_edges=5))
    n = 30
    kept.update(T[:n], ij[:n, 0], ij[:n, 1], P[:30])
    P2 = P.copy()
    P2[[3, 17]] = P2[[3, 17]] @ se3.exp(np.r_[0.01, 0, 0, 0.02, 0, 0])  # two keyframes move, ten more come
    got = kept.update(T, ij[:, 0], ij[:, 1], P2)
    want = loop_residuals(T, ij[:, 0], ij[:, 1], P2)
    assert np.array_equal(got, want)
    assert got[0] == pytest.approx([0.02, 0, 0, 0.05, 0, 0], abs=1e-9)  # edge (19, 1): neither moved
    assert ref.loop_residual_spread(T, ij[:, 0], ij[:, 1], P2, kept) == ref.loop_residual_spread(
        T, ij[:, 0], ij[:, 1], P2)


def test_config_errors_name_the_field():
    for kw, name in [({"max_width_px": 4}, "max_width_px"), ({"max_shift_m": 0}, "max_shift_m"),
                     ({"sigma_m": -1.0}, "sigma_m"), ({"feature_weight": -0.1}, "feature_weight"),
                     ({"cached_pyramids": -1}, "cached_pyramids"),
                     ({"min_spread_edges": 0}, "min_spread_edges"),
                     ({"spread_window_edges": 3, "min_spread_edges": 5}, "spread_window_edges")]:
        with pytest.raises(ConfigError, match=name):
            replace(DenseEdgeConfig(), **kw)


def test_loop_icp_settings_round_trip_through_config_toml(tmp_path):
    from surfelslam.config import dumps_toml, load_toml
    from surfelslam.slam import SlamConfig

    cfg = SlamConfig()
    cfg = replace(cfg, hybrid=replace(cfg.hybrid, loop_icp=replace(cfg.hybrid.loop_icp, enabled=True, sigma_m=0.004,
                                                                      feature_weight=0.2)))
    path = tmp_path / "config.toml"
    path.write_text(dumps_toml(cfg))
    back = load_toml(SlamConfig, path)
    assert back.hybrid.loop_icp == cfg.hybrid.loop_icp and back.hybrid.loop_icp.feature_weight == 0.2
    path.write_text("[hybrid.loop_icp]\nmax_shift_m = -1.0\n")
    with pytest.raises(ConfigError, match="max_shift_m"):
        load_toml(SlamConfig, path)
    # the edge ICP's settings are a constant now: an old file that sets them says so in one line
    path.write_text("[hybrid.loop_icp.icp]\nlevels = 2\n")
    with pytest.raises(ConfigError, match=r"^\S+config.toml: config: \[hybrid.loop_icp\] icp was removed: .*EDGE_ICP"):
        load_toml(SlamConfig, path)


def test_a_frame_is_registered_to_a_keyframe_from_a_prediction(room_pair):
    """The orb tracker's depth odometry: a frame's depth pyramid (``frame_pyramid``) registered to a stored keyframe
    from a prediction 4 cm / 2 deg off, by depth alone, ends within 1.5 mm / 0.05 deg; the bound on the move from
    the start applies (1 cm: rejected); threads (the reader builds pyramids while the loop checks refine) give the
    same pose to the last bit."""
    from concurrent.futures import ThreadPoolExecutor

    d_ref, d_cur, T_true = room_pair
    ref = _refiner()
    ref.add_keyframe(0, d_ref)
    T_pred = se3.exp(np.array([0.02, -0.025, 0.015, 0.03, 0.025, -0.01])) @ T_true
    dt0, dr0 = se3.pose_error(T_pred, T_true)
    assert dt0 > 0.03 and dr0 > 1.5, (dt0, dr0)
    T = ref.refine_frame(0, ref.frame_pyramid(d_cur), T_pred, None, None, np.inf, np.inf)
    assert T is not None
    dt, dr = se3.pose_error(T, T_true)
    assert dt < 1.5e-3 and dr < 0.05, (dt, dr)
    assert ref.refine_frame(0, ref.frame_pyramid(d_cur), T_pred, None, None, 0.01, 5.0) is None

    def register(_):
        return ref.refine_frame(0, ref.frame_pyramid(d_cur), T_pred, None, None, np.inf, np.inf)

    with ThreadPoolExecutor(max_workers=2) as pool:
        for T_thread in pool.map(register, range(4)):
            np.testing.assert_array_equal(T_thread, T)


def _corridor_normal_matrix() -> tuple[np.ndarray, float]:
    """Point-to-plane normal matrix ``(6, 6)`` (left perturbation, ``(omega, v)``) of a wall (normal x) and a floor
    (normal y) running along z from 1 to 4 m: translation along z is free; and their mean depth (m)."""
    rng = np.random.default_rng(0)
    z, s = rng.uniform(1.0, 4.0, 50), rng.uniform(-1.0, 1.0, 50)
    wall = np.column_stack([np.full(50, 1.0), s, z])
    floor = np.column_stack([s, np.full(50, -1.0), z])
    rows = [np.concatenate([np.cross(p, n), n]) for pts, n in ((wall, [1.0, 0, 0]), (floor, [0, 1.0, 0]))
            for p in pts]
    A = np.array(rows)
    return A.T @ A, float(z.mean())


def test_weak_direction_shape_lowers_only_the_direction_icp_leaves_free():
    """The corridor's free direction (translation along z in the target frame) gets the floor, seen through the
    edge's right perturbation; well-constrained directions keep information 1; a closed box gives no shape."""
    H, d = _corridor_normal_matrix()
    T = se3.exp(np.array([0.1, -0.2, 0.3, 0.5, -0.4, 0.2]))
    shape = weak_direction_shape(H, d, T, weak_ratio=100.0, floor=1e-4)
    assert shape is not None
    np.testing.assert_allclose(shape, shape.T, atol=1e-12)
    ev = np.linalg.eigvalsh(shape)
    assert ev[0] == pytest.approx(1e-4, rel=1e-6) and ev[1] == pytest.approx(1.0) and ev[-1] == pytest.approx(1.0)
    xi_left = np.array([0, 0, 0, 0, 0, 1.0])  # the free direction, as ICP's left perturbation of T
    xi_right = se3.adjoint(se3.invert(T)) @ xi_left
    np.testing.assert_allclose(se3.exp(xi_left * 0.01) @ T, T @ se3.exp(xi_right * 0.01), atol=1e-12)
    assert xi_right @ shape @ xi_right / (xi_right @ xi_right) == pytest.approx(1e-4, rel=1e-3)
    across = se3.adjoint(se3.invert(T)) @ np.array([0, 0, 0, 1.0, 0, 0])
    assert across @ shape @ across / (across @ across) > 0.99
    box = H + np.diag([1.0, 1.0, 1.0, 0, 0, 0]) * d ** 2 * 50 + np.diag([0, 0, 0, 0, 0, 50.0])
    assert weak_direction_shape(box, d, T, weak_ratio=100.0, floor=1e-4) is None



def _room_keyframes(poses, feat_cfg, refiner) -> list:
    """Keyframes (ORB features, no map points) of the synthetic room rendered at ``poses`` ``(K, 4, 4)``, their depth
    added to ``refiner``."""
    from surfelslam.backend.keyframes import Keyframe
    from surfelslam.tracking.features import extract

    from helpers import ROOM_INTR, render_room

    kfs = []
    for k, T in enumerate(poses):
        rgb, depth = render_room(T, ROOM_INTR)
        refiner.add_keyframe(k, depth)
        kfs.append(Keyframe(k, k, k / 30, extract(rgb, depth, ROOM_INTR, feat_cfg), np.zeros((0, 3), np.float32),
                            np.zeros((0, 3), np.uint8)))
    return kfs

@pytest.mark.parametrize("pnp_refinement", [True, False])
def test_loop_checks_leave_the_pnp_refinement_to_the_edge_icp_when_asked(pnp_refinement):
    """With ``pnp_refinement`` off a verified keyframe edge skips the feature refinement (no RGB-D information is
    computed) and its ICP alone refines it, to the same precision."""
    from surfelslam.backend.loops import LoopConfig
    from surfelslam.backend.sparse_slam.loop_checks import LoopChecker
    from surfelslam.tracking.features import FeatureConfig

    from helpers import ROOM_INTR, look_pose

    poses = np.stack([look_pose(np.array([0.04 * k, 0.0, -0.3]), 0.06 * k) for k in range(3)])
    feat_cfg = FeatureConfig(n_features=500)
    refiner = DenseEdgeRefiner(ROOM_INTR, PreprocessConfig(), DenseEdgeConfig(pnp_refinement=pnp_refinement))
    kfs = _room_keyframes(poses, feat_cfg, refiner)
    checker = LoopChecker(ROOM_INTR, feat_cfg, LoopConfig(n_nearby=1, n_random=0, n_retrieved=0), refiner, kfs)
    kf_id, checks = checker.check(2, kfs[2].features, poses)
    assert kf_id == 2 and [c.candidate.kf_id for c in checks] == [0]
    check = checks[0]
    assert check.result.ok and check.refined is not None
    assert (check.result.information is not None) == pnp_refinement
    dt, dr = se3.pose_error(check.refined.T_cur_ref, se3.invert(poses[2]) @ poses[0])
    assert dt < 1e-3 and dr < 0.05, (dt, dr)


@pytest.mark.parametrize(("closed_retrieved", "graph_off_m", "n_retrieved_checked"),
                         [(0, 0.0, 3), (1, 0.0, 1), (1, 0.03, 3)])
def test_retrieved_candidates_stop_once_the_loop_is_closed(closed_retrieved, graph_off_m, n_retrieved_checked):
    """``loop.closed_retrieved``: once that many retrieved keyframes are verified within 1 cm / 1 deg of where the
    graph puts them, the keyframe's other retrieved candidates are skipped; where the graph is 3 cm off (the loop not
    closed yet) every one is verified."""
    from surfelslam.backend.loops import LoopConfig
    from surfelslam.backend.sparse_slam.loop_checks import LoopChecker
    from surfelslam.tracking.features import FeatureConfig

    from helpers import ROOM_INTR, look_pose

    poses = np.stack([look_pose(np.array([0.01 * k, 0.0, -0.3]), 0.01 * k) for k in range(5)])
    feat_cfg = FeatureConfig(n_features=500)
    refiner = DenseEdgeRefiner(ROOM_INTR, PreprocessConfig(), DenseEdgeConfig())
    kfs = _room_keyframes(poses, feat_cfg, refiner)
    cfg = LoopConfig(n_nearby=0, n_random=0, n_retrieved=3, closed_retrieved=closed_retrieved,
                     retrieval=replace(LoopConfig().retrieval, min_votes=1))
    checker = LoopChecker(ROOM_INTR, feat_cfg, cfg, refiner, kfs)
    for k in range(4):
        checker.add_to_index(kfs[k].features)
    graph = poses.copy()
    graph[:4, 0, 3] += graph_off_m
    _, checks = checker.check(4, kfs[4].features, graph)
    assert [c.candidate.source for c in checks] == ["retrieved"] * n_retrieved_checked
    assert all(c.result.ok and c.refined is not None for c in checks)
