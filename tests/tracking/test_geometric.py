"""Shape-feature (FPFH) registration guess: invariances, matching against a brute-force reference, and the
recovery of a wide-baseline pair that image features cannot register."""

import functools

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from surfelslam.errors import ConfigError
from surfelslam.geometry import se3
from surfelslam.synth.render import render
from surfelslam.synth.scenes import make_scene
from surfelslam.synth.trajectories import make_trajectory
from surfelslam.synth.writer import default_intrinsics, make_frame, noise_config
from surfelslam.tracking.geometric import (
    GeometricGuessConfig,
    fpfh,
    geometric_guess,
    mutual_matches,
    pair_features,
    voxel_cloud,
)
from surfelslam.tracking.icp import pairwise_config
from surfelslam.tracking.preprocess import PreprocessConfig, Preprocessor
from surfelslam.tracking.registration import guess_level, guess_maps, register_pair
from surfelslam.types import RGBDFrame


def _random_pose(rng, angle_deg, trans_m):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    t = rng.normal(size=3)
    return se3.exp(np.r_[np.deg2rad(angle_deg) * axis, trans_m * t / np.linalg.norm(t)])


def _cloud(rng, n=400):
    """Points on a bumpy surface z = f(x, y) with their exact unit normals."""
    xy = rng.uniform(-0.5, 0.5, (n, 2))
    z = 1.5 + 0.1 * np.sin(6 * xy[:, 0]) * np.cos(4 * xy[:, 1])
    dzdx = 0.6 * np.cos(6 * xy[:, 0]) * np.cos(4 * xy[:, 1])
    dzdy = -0.4 * np.sin(6 * xy[:, 0]) * np.sin(4 * xy[:, 1])
    nrm = np.c_[dzdx, dzdy, -np.ones(n)]
    return np.c_[xy, z], nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def test_pair_features_ignore_order_and_rigid_motion():
    rng = np.random.default_rng(3)
    p, n = _cloud(rng, 60)
    i, j = np.triu_indices(60, 1)
    f = np.stack(pair_features(p, n, i, j))
    assert np.allclose(f, np.stack(pair_features(p, n, j, i)), atol=1e-9)
    T = _random_pose(rng, 40, 0.5)
    moved = np.stack(pair_features(se3.transform_points(T, p), n @ T[:3, :3].T, i, j))
    assert np.allclose(f, moved, atol=1e-9)
    assert np.all(np.abs(f[0]) <= np.pi) and np.all(np.abs(f[1:]) <= 1 + 1e-12)
    assert f[0].std() > 0.05 and f[2].std() > 0.05  # not a constant (the surface is curved)


def test_fpfh_is_invariant_and_drops_isolated_points():
    rng = np.random.default_rng(4)
    p, n = _cloud(rng)
    p = np.vstack([p, [[5.0, 5.0, 5.0]]])  # an isolated point: no neighbours, no descriptor
    n = np.vstack([n, [[0.0, 0.0, -1.0]]])
    desc, idx = fpfh(p, n, 0.15, 11, 5)
    assert desc.shape == (len(idx), 33) and len(p) - 1 not in idx and len(idx) > 300
    assert np.allclose(desc.reshape(-1, 3, 11).sum(axis=2), 1.0, atol=1e-5)
    T = _random_pose(rng, 60, 1.0)
    desc_m, idx_m = fpfh(se3.transform_points(T, p), n @ T[:3, :3].T, 0.15, 11, 5)
    assert np.array_equal(idx, idx_m) and np.allclose(desc, desc_m, atol=1e-5)


@pytest.mark.parametrize("block_rows", [1, 7, 1024])
def test_mutual_matches_equal_a_brute_force_reference(block_rows):
    rng = np.random.default_rng(5)
    a = rng.random((57, 33)).astype(np.float32)
    b = np.vstack([a[::3] + 0.01 * rng.random((19, 33)), rng.random((30, 33))]).astype(np.float32)
    D = cdist(a, b)
    ab, ba = D.argmin(axis=1), D.argmin(axis=0)
    ref = np.array([(k, ab[k]) for k in range(len(a)) if ba[ab[k]] == k])
    got = mutual_matches(a, b, block_rows=block_rows)
    assert np.array_equal(got, ref)
    assert len(got) >= 15  # most of the perturbed copies match back
    assert mutual_matches(a[:0], b).shape == (0, 2)


def test_voxel_cloud_averages_points_and_normals():
    vertex = np.zeros((2, 3, 3), np.float32)
    normal = np.zeros((2, 3, 3), np.float32)
    vertex[0, 0], normal[0, 0] = (0.01, 0.01, 1.01), (0, 0, -1)
    vertex[0, 1], normal[0, 1] = (0.03, 0.01, 1.01), (0, 0.6, -0.8)
    vertex[1, 2], normal[1, 2] = (0.51, 0.01, 1.01), (1, 0, 0)  # another voxel
    vertex[1, 0] = (0.2, 0.2, 1.0)  # no normal: ignored
    pts, nrm = voxel_cloud(vertex, normal, 0.04, 0.5)
    assert len(pts) == 2
    k = int(np.argmin(pts[:, 0]))
    assert np.allclose(pts[k], [0.02, 0.01, 1.01], atol=1e-6)
    assert np.allclose(nrm[k], np.array([0, 0.3, -0.9]) / np.linalg.norm([0, 0.3, -0.9]))
    assert np.allclose(np.linalg.norm(nrm, axis=1), 1.0)
    pts, _ = voxel_cloud(vertex, normal, 0.04, 0.99)  # the two disagreeing normals average below 0.99
    assert len(pts) == 1


@functools.cache
def _room_frames(frames: tuple[int, ...]):
    """Synthetic room, hand-held orbit, the given frames rendered at 320x240 with Kinect noise, and their poses."""
    intr = default_intrinsics(320, 240)
    scene = make_scene("room", 0)
    traj = make_trajectory("handheld", max(frames) + 1, scene, seed=0)
    out = {k: make_frame(k, k / 30.0, render(scene, traj.T_world_cam[k], intr), intr, noise_config("kinect"), 0)
           for k in frames}
    return intr, out, traj.T_world_cam


#: wide-baseline pairs of that orbit, 3 s apart
WIDE_PAIRS = ((100, 190), (30, 120), (150, 240), (60, 150))


def _wide_pair(a: int, b: int):
    intr, frames, T = _room_frames(tuple(sorted({k for p in WIDE_PAIRS for k in p})))
    return intr, (frames[a], frames[b]), se3.invert(T[b]) @ T[a]


@pytest.mark.heavy  # make test-all; make test keeps the shape guess's use by register (the next test)
def test_geometric_guess_recovers_wide_baseline_pairs():
    """The shape guess (FPFH on the depth alone) is a coarse start for relocalisation: it recovers most wide pairs
    (measured over 12 pairs 2 s apart: 10 with the default 2-pixel normals, 7 with 1-pixel ones, 12 with 3-pixel)."""
    recovered = 0
    for a, b in WIDE_PAIRS:
        intr, (src, tgt), T_gt = _wide_pair(a, b)
        pre = Preprocessor(intr, PreprocessConfig(pyramid_levels=3))
        ps, pt = pre.process(src.depth_m), pre.process(tgt.depth_m)
        g = geometric_guess(ps[0].vertex, ps[0].normal, pt[0].vertex, pt[0].normal)
        if g.reason is None:
            assert g.n_inliers >= 10
            dt, dr = se3.pose_error(g.T_target_source, T_gt)
            recovered += dt < 0.1 and dr < 10.0  # a coarse start (voxel means): ICP finishes it (next test)
    assert recovered >= 3, recovered
    again = geometric_guess(ps[0].vertex, ps[0].normal, pt[0].vertex, pt[0].normal)
    assert again.reason == g.reason and np.array_equal(again.T_target_source, g.T_target_source)  # deterministic
    none = geometric_guess(ps[0].vertex, np.zeros_like(ps[0].normal), pt[0].vertex, pt[0].normal)
    assert none.T_target_source is None and none.reason == "too_few_matches"


def test_register_features_falls_back_on_shape_when_images_are_blank():
    """Uniform grey images: no keypoints, so the PnP guess is rejected; the FPFH guess on the depth alone then
    starts ICP, which converges to the exact pose (ICP from the identity does not)."""
    intr, (src, tgt), T_gt = _wide_pair(30, 120)
    grey = np.full_like(src.rgb, 128)
    src, tgt = (RGBDFrame(f.index, f.timestamp, grey, f.depth_m) for f in (src, tgt))
    cfg = pairwise_config()
    pre = Preprocessor(intr, PreprocessConfig(pyramid_levels=cfg.levels))
    ps, pt = pre.process(src.depth_m), pre.process(tgt.depth_m)
    ident = register_pair(src, tgt, ps, pt, intr, cfg, "identity")
    assert se3.pose_error(ident.icp.T_target_source, T_gt)[0] > 0.2
    reg = register_pair(src, tgt, ps, pt, intr, cfg, "features")
    assert reg.motion is not None and not reg.motion.ok
    assert reg.init_used == "geometry" and reg.geometric is not None and reg.geometric.reason is None
    dt, dr = se3.pose_error(reg.icp.T_target_source, T_gt)
    assert dt < 0.01 and dr < 0.5, (dt, dr)
    geo = register_pair(src, tgt, ps, pt, intr, cfg, "geometry")
    assert geo.motion is None and np.array_equal(geo.icp.T_target_source, reg.icp.T_target_source)
    assert guess_level(ps) == 0 and guess_level(ps, 100) == 2 and guess_level(ps, 10) == len(ps) - 1


def test_guess_maps_subsample_frames_wider_than_320_px():
    """The shape guess sees a 640x480 frame as ``--downsample 2`` would (every second pixel, intrinsics / 2), not
    as the pyramid's block-averaged level; a 320x240 frame as it is."""
    intr = default_intrinsics(640, 480)
    scene = make_scene("room", seed=0)
    T = make_trajectory("handheld", 2, scene, seed=1).T_world_cam[0]
    frame = make_frame(0, 0.0, render(scene, T, intr), intr, None, seed=1)  # exact depth
    pyr = Preprocessor(intr, PreprocessConfig(pyramid_levels=3)).process(frame.depth_m)
    v, n = guess_maps(frame, pyr, intr)
    half = intr.scaled(2)
    ref = Preprocessor(half, PreprocessConfig(pyramid_levels=1)).process(np.ascontiguousarray(frame.depth_m[::2, ::2]))
    assert v.shape == (240, 320, 3) and np.array_equal(v, ref[0].vertex) and np.array_equal(n, ref[0].normal)
    valid = v[..., 2] > 0
    assert valid.mean() > 0.9  # pixel (u', v') is pixel (2u', 2v') of the frame (its depth, bilateral-filtered)
    assert np.median(np.abs(v[..., 2][valid] - frame.depth_m[::2, ::2][valid])) < 1e-4
    assert not np.array_equal(v, pyr[1].vertex)  # not the block means
    small = Preprocessor(half, PreprocessConfig(pyramid_levels=3)).process(ref[0].vertex[..., 2].copy())
    vs, _ = guess_maps(frame, small, half)
    assert vs is small[0].vertex
    # the caller's preprocessing settings reach the reduced maps (here a depth range that clips the far half)
    far_m = float(np.median(frame.depth_m[frame.depth_m > 0]))
    clipped, _ = guess_maps(frame, pyr, intr, preprocess_cfg=PreprocessConfig(max_depth_m=far_m))
    kept = clipped[..., 2] > 0
    assert 0.3 < kept.mean() / valid.mean() < 0.7 and clipped[..., 2][kept].max() <= far_m


def test_geometric_config_errors():
    with pytest.raises(ConfigError, match="voxel_m"):
        GeometricGuessConfig(voxel_m=0)
    with pytest.raises(ConfigError, match="min_normal_agreement"):
        GeometricGuessConfig(min_normal_agreement=1.0)
    with pytest.raises(ConfigError, match="min_inliers"):
        GeometricGuessConfig(min_inliers=2)


def test_fpfh_kernels_equal_their_numpy_references():
    from surfelslam.kernels import fpfh as kf

    rng = np.random.default_rng(6)
    p, n = _cloud(rng, 500)
    n[:5] = [0.0, 0.0, -1.0]  # a few flat normals: some pairs get a zero cross product
    pairs = np.array(sorted(cKDTree(p).query_pairs(0.12)), np.int64)
    i, j = pairs[:, 0].copy(), pairs[:, 1].copy()
    counts = np.zeros((len(p), 33))
    degree = np.zeros(len(p), np.int64)
    kf.spfh_accumulate(p, n, i, j, 11, counts, degree)
    ref_counts, ref_degree = kf.spfh_accumulate_ref(p, n, i, j, 11)
    assert np.array_equal(degree, ref_degree) and degree.sum() == 2 * len(pairs)
    # the same angles up to rounding: a pair may land in the next bin only at a bin edge (none here)
    assert np.array_equal(counts, ref_counts), np.abs(counts - ref_counts).sum()
    assert counts.sum() == 6 * len(pairs)
    acc = np.zeros_like(counts)
    wsum = np.zeros(len(p))
    kf.neighbour_sum(p, i, j, counts, acc, wsum)
    ref_acc, ref_wsum = kf.neighbour_sum_ref(p, i, j, counts)
    np.testing.assert_allclose(acc, ref_acc, rtol=1e-12)
    np.testing.assert_allclose(wsum, ref_wsum, rtol=1e-12)
