"""Sparse SLAM on a synthetic loop (loop closure reduces the error), relocalisation, voxel filter kernel."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from surfelslam.backend.loops import LoopConfig
from surfelslam.backend.place_recognition import DescriptorIndex
from surfelslam.backend.sparse_slam import SparseSlam, SparseSlamConfig
from surfelslam.geometry.se3 import pose_error
from surfelslam.kernels.voxel import voxel_filter, voxel_filter_ref
from surfelslam.tracking.features import FeatureConfig
from surfelslam.types import Intrinsics, RGBDFrame

from helpers import ROOM_INTR, ate_m, look_pose, render_room

pytestmark = pytest.mark.xdist_group("sparse_slam_loop")  # the module's loop run is shared: one worker

N_LOOP = 40  # frames per revolution (9 deg and ~8 cm per frame)
N_EXTRA = 6  # frames past the start: the loop closes


def _loop_poses() -> np.ndarray:
    poses = []
    for k in range(N_LOOP + N_EXTRA):
        th = 2 * np.pi * k / N_LOOP
        pos = np.array([0.5 * np.sin(th), 0.05 * np.sin(3 * th), -0.5 * np.cos(th)])
        poses.append(look_pose(pos, th + 0.3, 0.05 * np.cos(2 * th)))
    return np.array(poses)


@pytest.fixture(scope="module")
def loop_frames() -> tuple[np.ndarray, list[RGBDFrame]]:
    rng = np.random.default_rng(0)
    poses = _loop_poses()
    frames = []
    for k, T in enumerate(poses):
        rgb, depth = render_room(T, ROOM_INTR, supersample=1)
        depth = depth * (1.0 + rng.normal(0.0, 0.01, depth.shape)).astype(np.float32)  # 1 % depth noise
        rgb = np.clip(rgb + rng.normal(0.0, 4.0, rgb.shape), 0, 255).astype(np.uint8)
        frames.append(RGBDFrame(k, k / 30.0, rgb, depth))
    return poses, frames


LOOP_CFG = SparseSlamConfig(
    features=FeatureConfig(n_features=400),
    loop=LoopConfig(n_nearby=2, n_random=1, n_retrieved=2),
)
NO_LOOP_CFG = replace(LOOP_CFG, loop=LoopConfig(n_nearby=0, n_random=0, n_retrieved=0))


def _run(cfg: SparseSlamConfig, poses: np.ndarray, frames: list[RGBDFrame]):
    slam = SparseSlam(ROOM_INTR, cfg, T_world_first=poses[0])
    per_frame = [slam.process(f) for f in frames]
    return slam, per_frame, slam.finish()



@pytest.fixture(scope="module")
def loop_run(loop_frames):
    poses, frames = loop_frames
    return _run(LOOP_CFG, poses, frames)


def test_loop_closure_found_and_reduces_ate(loop_frames, loop_run) -> None:
    poses, frames = loop_frames
    slam, per_frame, res = loop_run
    assert all(r.ok for r in per_frame) and res.rejected == {}
    assert len(res.trajectory) == len(frames)
    assert per_frame[0].is_keyframe and len(res.keyframe_indices) > 10
    # the revisit of the start is recognised: edges from the last frames back to the first keyframes
    far = [(i, j, n) for i, j, n in res.loops_accepted if j - i > N_LOOP // 2]
    assert len(far) >= 3 and min(i for i, _, _ in far) <= 2
    assert all(n >= LOOP_CFG.loop.min_loop_inliers for _, _, n in res.loops_accepted)
    assert len(res.loops_accepted) <= len(res.loops_found)
    _, _, res_no = _run(NO_LOOP_CFG, poses, frames)
    assert res_no.loops_accepted == []
    ate_loop = ate_m(res.trajectory.T_world_cam, poses)
    ate_no = ate_m(res_no.trajectory.T_world_cam, poses)
    assert ate_loop < 0.6 * ate_no
    assert ate_loop < 0.05
    # keyframe poses exposed for re-posing a dense map
    np.testing.assert_allclose(slam.keyframe_poses(), res.keyframe_poses)
    kf_frames = res.keyframe_indices
    np.testing.assert_allclose(res.trajectory.T_world_cam[kf_frames], res.keyframe_poses, atol=1e-9)
    # the map: voxel-filtered keyframe clouds inside the room
    assert len(res.map_xyz) > 10000 and res.map_rgb.shape == res.map_xyz.shape
    assert np.all(np.abs(res.map_xyz) < np.array([2.2, 1.4, 2.7]))


@pytest.mark.heavy  # make test-all (one more run); make test keeps the hybrid's, which runs this back end
def test_deterministic(loop_frames, loop_run) -> None:
    poses, frames = loop_frames
    _, _, a = loop_run
    _, _, b = _run(LOOP_CFG, poses, frames)
    np.testing.assert_array_equal(a.trajectory.T_world_cam, b.trajectory.T_world_cam)
    assert a.loops_accepted == b.loops_accepted
    np.testing.assert_array_equal(a.map_xyz, b.map_xyz)


def test_relocalise_and_pose_guess(loop_frames, loop_run) -> None:
    poses, frames = loop_frames
    slam, _, _ = loop_run
    k = N_LOOP // 4  # a frame a quarter of the way round
    found = slam.relocalise(frames[k])
    assert found is not None
    T, kf = found
    dt, dr = pose_error(T, poses[k])
    assert dt < 0.05 and dr < 3.0
    # textureless frame: nothing to relocalise against
    flat = RGBDFrame(0, 0.0, np.full_like(frames[0].rgb, 90), frames[0].depth_m)
    assert slam.relocalise(flat) is None
    # the last frame against the last keyframe
    g = slam.match_reference_keyframe(frames[-1])
    assert g is not None
    assert pose_error(g.T_world_cam, poses[-1])[0] < 0.05


def test_coarse_reference_match_is_close_to_the_precise_one(loop_frames, loop_run) -> None:
    """``coarse``: PnP-RANSAC + inlier refinement only (what the hybrid uses to check ICP when its joint term is off):
    the pose is within a few millimetres of the precise match (search by projection + RGB-D refinement), far inside
    the hybrid's 5 cm / 5 deg check, and the inliers are the same PnP ones."""
    poses, frames = loop_frames
    slam, _, _ = loop_run
    fine = slam.match_reference_keyframe(frames[-1], poses[-1])
    coarse = slam.match_reference_keyframe(frames[-1], poses[-1], coarse=True)
    assert fine is not None and coarse is not None and coarse.kf_id == fine.kf_id
    dt, dr = pose_error(coarse.T_world_cam, fine.T_world_cam)
    assert dt < 0.01 and dr < 0.5, (dt, dr)
    assert dt > 0  # a different estimate, not the same computation
    assert pose_error(coarse.T_world_cam, poses[-1])[0] < 0.02
    np.testing.assert_array_equal(coarse.uv_cur, fine.uv_cur)


def test_coarse_match_keeps_the_rgbd_refinement_when_asked(loop_frames) -> None:
    """``coarse_rgbd_refine`` (the hybrid's ``pnp_rgbd_refine``): the coarse match's pose is refined on the keypoints'
    pixels and depths too; the inliers stay the PnP ones, and the pose stays on the ground truth."""
    poses, frames = loop_frames
    plain = SparseSlam(ROOM_INTR, NO_LOOP_CFG, T_world_first=poses[0])
    rgbd = SparseSlam(ROOM_INTR, NO_LOOP_CFG, T_world_first=poses[0], coarse_rgbd_refine=True)
    for f in frames[:6]:
        plain.process(f)
        rgbd.process(f)
    a = plain.match_reference_keyframe(frames[6], poses[6], coarse=True)
    b = rgbd.match_reference_keyframe(frames[6], poses[6], coarse=True)
    assert a is not None and b is not None and a.kf_id == b.kf_id
    np.testing.assert_array_equal(a.uv_cur, b.uv_cur)
    assert 1e-5 < pose_error(a.T_world_cam, b.T_world_cam)[0] < 0.01
    # 1 % depth noise: the depths move the pose closer to the truth (3.3 against 3.6 mm)
    assert pose_error(b.T_world_cam, poses[6])[0] < min(0.005, pose_error(a.T_world_cam, poses[6])[0])
    plain.finish()  # their background threads stop here, not in a later test (whose patched functions they would call)
    rgbd.finish()


def test_rejected_frames_counted_and_predicted(loop_frames) -> None:
    poses, frames = loop_frames
    slam = SparseSlam(ROOM_INTR, NO_LOOP_CFG, T_world_first=poses[0], relocalise_after_failures=100)
    for f in frames[:3]:
        assert slam.process(f).ok
    flat = RGBDFrame(3, 0.1, np.full_like(frames[0].rgb, 90), frames[3].depth_m)
    r = slam.process(flat)
    assert not r.ok and r.reason == "too_few_matches" and not r.is_keyframe
    # constant velocity: the rejected frame continues the last motion
    traj = slam.trajectory().T_world_cam
    expected = traj[2] @ np.linalg.inv(traj[1]) @ traj[2]
    np.testing.assert_allclose(r.T_world_cam, expected, atol=1e-9)
    assert slam.finish().rejected == {"too_few_matches": 1}


def test_descriptor_index_votes_and_prefix() -> None:
    rng = np.random.default_rng(0)
    kf_desc = [rng.integers(0, 256, (100, 32), dtype=np.uint8) for _ in range(5)]
    idx = DescriptorIndex()
    for d in kf_desc:
        idx.add(d)
    # a query made of keyframe 3's descriptors with a few flipped bits
    q = kf_desc[3].copy()
    q[:, 0] ^= 0b101
    res = idx.query(q, 2)
    assert res[0][0] == 3 and res[0][1] >= 90
    assert all(k != 3 for k, _ in idx.query(q, 2, before_kf=3))  # keyframe 3 excluded by the prefix


# --- voxel filter kernel -----------------------------------------------------------------------


def test_voxel_filter_matches_reference() -> None:
    rng = np.random.default_rng(1)
    xyz = rng.uniform(-1.0, 1.0, (20000, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (20000, 3), dtype=np.uint8)
    a = voxel_filter(xyz, rgb, 0.05)
    b = voxel_filter_ref(xyz, rgb, 0.05)
    np.testing.assert_allclose(a[0], b[0], atol=1e-6)
    np.testing.assert_array_equal(a[1], b[1])
    np.testing.assert_array_equal(a[2], b[2])
    n_vox = len(np.unique(np.floor(xyz.astype(np.float64) / 0.05).astype(np.int64), axis=0))
    assert a[2].sum() == 20000 and len(a[0]) == n_vox


def test_voxel_filter_known_values() -> None:
    xyz = np.array([[0.01, 0.01, 0.01], [0.03, 0.01, 0.01], [0.5, 0.5, 0.5]], np.float32)
    rgb = np.array([[10, 20, 30], [20, 40, 61], [1, 2, 3]], np.uint8)
    out, col, cnt = voxel_filter(xyz, rgb, 0.1)
    np.testing.assert_allclose(out, [[0.02, 0.01, 0.01], [0.5, 0.5, 0.5]], atol=1e-7)
    np.testing.assert_array_equal(col, [[15, 30, 46], [1, 2, 3]])
    np.testing.assert_array_equal(cnt, [2, 1])
    e = voxel_filter(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), 0.1)
    assert e[0].shape == (0, 3)
    with pytest.raises(ValueError):
        voxel_filter(xyz, rgb, 0.0)


def test_sparse_trackers_refuse_float_descriptors() -> None:
    """Place recognition votes with binary words: SIFT is for pairwise guesses (``register``), not the trackers."""
    from surfelslam.tracking.features import FeatureConfig

    with pytest.raises(ValueError, match="detector"):
        SparseSlamConfig(features=FeatureConfig(detector="sift"))
    assert SparseSlamConfig(features=FeatureConfig(detector="orb")).features.detector == "orb"


def test_pnp_inlier_bound_scales_with_image_width():
    """``reprojection_error_px`` and ``depth_edge_radius_px`` are given for 320-px-wide images: doubled at 640x480,
    as given at 320 and below."""
    from surfelslam.backend.sparse_slam import SparseSlamConfig, features_for_width

    cfg = SparseSlamConfig()
    assert features_for_width(cfg, 640).features.reprojection_error_px == 2 * cfg.features.reprojection_error_px
    assert features_for_width(cfg, 640).features.depth_edge_radius_px == 2 * cfg.features.depth_edge_radius_px
    assert features_for_width(cfg, 320) is cfg and features_for_width(cfg, 160) is cfg
    fixed = SparseSlamConfig(features_reference_width_px=0)
    assert features_for_width(fixed, 640) is fixed
    slam = SparseSlam(Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480), cfg)
    assert slam.cfg.features.reprojection_error_px == 4.0
    with pytest.raises(ValueError, match="features_reference_width_px"):
        SparseSlamConfig(features_reference_width_px=-1)


def test_a_long_texture_loss_holds_the_last_pose(loop_frames) -> None:
    """Forty frames without texture (a plain wall filling the view): every one is rejected; the first
    ``velocity_reset_after_failures`` extrapolate the last motion, the rest keep the last pose, and every pose stays
    a finite rigid transform (unbounded extrapolation once drifted metres and overflowed)."""
    _, frames = loop_frames
    cfg = SparseSlamConfig(features=FeatureConfig(n_features=600))
    slam = SparseSlam(ROOM_INTR, cfg, relocalise_after_failures=0)
    poses = [slam.process(f).T_world_cam for f in frames[:8]]
    blank = [RGBDFrame(f.index, f.timestamp, np.full_like(f.rgb, 128), f.depth_m) for f in frames[8:]]
    blank = (blank * 3)[:40]
    for f in blank:
        r = slam.process(f)
        assert not r.ok and r.reason == "too_few_matches"
        poses.append(r.T_world_cam)
    poses = np.array(poses)
    assert np.isfinite(poses).all()
    R = poses[:, :3, :3]
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    n = cfg.velocity_reset_after_failures
    step = pose_error(poses[8 + n - 1], poses[8 + n - 2])[0]
    assert step > 1e-3  # the first rejected frames follow the last motion
    np.testing.assert_allclose(poses[8 + n :], np.broadcast_to(poses[8 + n - 1], poses[8 + n :].shape))
    with pytest.raises(ValueError, match="velocity_reset_after_failures"):
        SparseSlamConfig(velocity_reset_after_failures=0)
    slam.finish()  # its background loop checks stop here, not in a later test (they would call its patched functions)


@pytest.mark.parametrize("field,value", [("reinit_after_failures", -1), ("reinit_min_keypoints", -5),
                                         ("reinit_sigma_m", 0.0), ("reinit_sigma_rad", -1.0)])
def test_bad_reinit_settings_are_rejected(field, value):
    with pytest.raises(ValueError, match=field):
        SparseSlamConfig(**{field: value})


@pytest.mark.parametrize("field,value", [("trust_min_inliers", -1), ("max_shift_m", 0.0), ("max_shift_deg", -2.0)])
def test_bad_depth_odometry_settings_are_rejected(field, value):
    from surfelslam.backend.sparse_slam import DepthOdometryConfig

    with pytest.raises(ValueError, match=field):
        DepthOdometryConfig(**{field: value})


def test_depth_odometry_needs_the_keyframe_depth_store(tmp_path):
    """Without a store of the keyframes' depth there is nothing to register to: a clear error; disabled, none is
    needed. In a config file a bad value names its section."""
    from surfelslam.backend.sparse_slam import DepthOdometryConfig
    from surfelslam.config import dumps_toml, load_toml
    from surfelslam.errors import ConfigError
    from surfelslam.slam import SlamConfig

    with pytest.raises(ValueError, match="edge_refiner"):
        SparseSlam(ROOM_INTR, SparseSlamConfig(), depth_odometry=DepthOdometryConfig())
    assert not SparseSlam(ROOM_INTR, SparseSlamConfig(), depth_odometry=DepthOdometryConfig(enabled=False)).uses_depth
    cfg = SlamConfig()
    cfg = replace(cfg, orb=replace(cfg.orb, depth_odometry=DepthOdometryConfig(trust_min_inliers=50)))
    path = tmp_path / "config.toml"
    path.write_text(dumps_toml(cfg))
    assert load_toml(SlamConfig, path).orb == cfg.orb
    path.write_text("[orb.depth_odometry]\nmax_shift_m = -0.1\n")
    with pytest.raises(ConfigError, match=r"\[orb.depth_odometry\].*max_shift_m"):
        load_toml(SlamConfig, path)


def test_posed_frames_are_extracted_only_when_they_become_keyframes(loop_frames) -> None:
    """Frames posed by another tracker (the hybrid) need ORB features only as keyframes: the others are never
    extracted, and the keyframes get the given poses."""
    poses, frames = loop_frames

    class Counting(SparseSlam):
        extracted: list[int] = []

        def features(self, frame):
            self.extracted.append(frame.index)
            return super().features(frame)

    slam = Counting(ROOM_INTR, replace(NO_LOOP_CFG, keyframe_threshold=0.5), T_world_first=poses[0])
    out = [slam.process(f, T_world_cam_dense=T) for f, T in zip(frames[:12], poses[:12], strict=True)]
    kf_frames = [f.index for f, r in zip(frames, out, strict=False) if r.is_keyframe]
    assert 2 < len(kf_frames) < 12 and slam.extracted == kf_frames
    assert all(r.ok and r.n_inliers == -1 for r in out[1:])
    np.testing.assert_allclose(slam.keyframe_poses(), poses[kf_frames], atol=1e-9)
    slam.finish()  # its background thread stops with the test


def test_the_last_placed_frame_can_become_a_keyframe_at_its_pose(loop_frames) -> None:
    """Before finish, the last posed frame (not a keyframe) becomes one: a keyframe more, at the frame's pose, with the
    odometry edge from the previous keyframe; the trajectory is unchanged, and a keyframe is not promoted again."""
    poses, frames = loop_frames
    slam = SparseSlam(ROOM_INTR, replace(NO_LOOP_CFG, keyframe_threshold=0.5), T_world_first=poses[0])
    out = [slam.process(f, T_world_cam_dense=T) for f, T in zip(frames[:12], poses[:12], strict=True)]
    assert not out[-1].is_keyframe
    n_kf, before = slam.n_keyframes, slam.trajectory().T_world_cam
    assert slam.promote_last_frame(frames[11])
    assert slam.n_keyframes == n_kf + 1 and slam.keyframe_frame_indices()[-1] == 11
    np.testing.assert_allclose(slam.keyframe_poses()[-1], poses[11], atol=1e-9)
    np.testing.assert_allclose(slam.trajectory().T_world_cam, before, atol=1e-9)
    assert not slam.promote_last_frame(frames[11])
    res = slam.finish()
    np.testing.assert_allclose(res.keyframe_poses[-1], poses[11], atol=1e-6)  # the odometry edge holds it there


def test_keyframe_clouds_can_be_left_out(loop_frames) -> None:
    """A caller with its own map (the hybrid's surfels) leaves the keyframe clouds out: the poses are the same, the
    sparse map is empty; by default the map holds the keyframes' points."""
    poses, frames = loop_frames
    runs = []
    for clouds in (True, False):
        slam = SparseSlam(ROOM_INTR, replace(NO_LOOP_CFG, keyframe_threshold=0.3), T_world_first=poses[0],
                          keyframe_clouds=clouds)
        for f, T in zip(frames[:10], poses[:10], strict=True):
            slam.process(f, T_world_cam_dense=T)
        runs.append(slam.finish())
    with_clouds, without = runs
    assert len(with_clouds.map_xyz) > 1000 and len(without.map_xyz) == 0 and without.map_rgb.shape == (0, 3)
    np.testing.assert_array_equal(with_clouds.keyframe_poses, without.keyframe_poses)


def test_nearby_pairs_are_matched_near_the_graphs_prediction(loop_frames, monkeypatch) -> None:
    """With the graph's relative pose of a nearby pair, :func:`verify_edge` matches near where it projects the
    keypoints (a guided match); a prior far off finds too few there and falls back to brute force. Both verify the
    edge to the true pose."""
    from surfelslam.backend import loops
    from surfelslam.geometry.se3 import invert, make_T
    from surfelslam.tracking.features import extract, motion

    poses, frames = loop_frames
    cfg = FeatureConfig(n_features=400, guided_radius_px=8.0)
    ref, cur = (extract(frames[k].rgb, frames[k].depth_m, ROOM_INTR, cfg) for k in (0, 2))
    T_true = invert(poses[2]) @ poses[0]
    guided = []
    real_match = motion.match
    monkeypatch.setattr(motion, "match", lambda *a, **k: guided.append(k.get("pred_uv") is not None)
                        or real_match(*a, **k))
    off = make_T(np.eye(3), np.array([0.3, 0.0, 0.0])) @ T_true  # 30 cm: far outside the 8 px discs
    for prior, expect in ((T_true, [True]), (off, [True, False]), (None, [False])):
        guided.clear()
        res = loops.verify_edge(ref, cur, ROOM_INTR, cfg, LoopConfig(), prior)
        dt_m, dr_deg = pose_error(res.T_cur_ref, T_true)
        assert res.ok and dt_m < 0.01 and dr_deg < 0.5, (prior is None, dt_m, dr_deg)
        assert guided == expect


def test_a_nearby_pair_is_verified_by_its_odometry_without_ransac(loop_frames, monkeypatch) -> None:
    """``prior_min_inlier_fraction``: the guided matches that a trusted prior (a nearby pair's odometry) reprojects
    are the inliers and RANSAC does not run; the pose is that prior refined on them, as precise as RANSAC's. A prior
    30 cm off explains too few: RANSAC runs and verifies the true pose."""
    from surfelslam.backend import loops
    from surfelslam.geometry.se3 import invert, make_T, so3_exp
    from surfelslam.tracking.features import extract, motion

    poses, frames = loop_frames
    cfg = FeatureConfig(n_features=400, guided_radius_px=8.0)
    ref, cur = (extract(frames[k].rgb, frames[k].depth_m, ROOM_INTR, cfg) for k in (0, 2))
    T_true = invert(poses[2]) @ poses[0]
    ransac = []
    real_ransac = motion.pnp_ransac
    monkeypatch.setattr(motion, "pnp_ransac", lambda *a, **k: ransac.append(1) or real_ransac(*a, **k))
    by_ransac = loops.verify_edge(ref, cur, ROOM_INTR, cfg, LoopConfig(), T_true)
    assert len(ransac) == 1
    ransac.clear()
    T_odometry = make_T(so3_exp(np.array([0.0, 0.002, 0.0])), np.array([0.002, 0.0, 0.0])) @ T_true  # 2 mm, 0.1 deg
    by_prior = loops.verify_edge(ref, cur, ROOM_INTR, cfg, LoopConfig(), T_odometry, prior_min_inlier_fraction=0.5)
    assert ransac == [] and by_prior.ok
    assert by_prior.n_inliers >= 0.5 * by_prior.n_good and by_prior.n_inliers >= 0.9 * by_ransac.n_inliers
    assert by_prior.inlier_mask.sum() == by_prior.n_inliers
    assert pose_error(by_prior.T_cur_ref, by_ransac.T_cur_ref)[0] < 3e-4  # the same pose (both 2.4 mm off)
    dt_prior, dr_prior = pose_error(by_prior.T_cur_ref, T_true)
    assert dt_prior < 5e-3 and dr_prior < 0.1, (dt_prior, dr_prior)
    off = make_T(np.eye(3), np.array([0.3, 0.0, 0.0])) @ T_true
    res = loops.verify_edge(ref, cur, ROOM_INTR, cfg, LoopConfig(), off, prior_min_inlier_fraction=0.5)
    assert len(ransac) >= 1 and res.ok and pose_error(res.T_cur_ref, T_true)[0] < 0.01


def _same_loops_as_inline(runs, poses, frames) -> None:
    _, _, inline = _run(replace(LOOP_CFG, background_loop_checks=False), poses, frames)
    assert len(inline.loops_found) > 10
    for res in runs:
        assert res.loops_found == inline.loops_found
        assert np.abs(res.trajectory.T_world_cam[:, :3, 3] - inline.trajectory.T_world_cam[:, :3, 3]).max() < 1e-3


def test_background_checks_find_the_inline_loops(loop_frames, loop_run) -> None:
    """Candidates depend on keyframe ids, descriptors and the seeded draws, not on when the results are applied:
    background checks applied 2 keyframes later (the module's run) verify the same pairs as inline checks, and the
    trajectory stays within a millimetre of the inline one."""
    poses, frames = loop_frames
    assert LOOP_CFG.background_loop_checks and LOOP_CFG.loop_check_lag_keyframes == 2
    _same_loops_as_inline([loop_run[2]], poses, frames)


@pytest.mark.heavy  # make test-all (one more run); make test compares the default lag with inline checks (above)
def test_background_checks_find_the_inline_loops_whatever_the_lag(loop_frames, loop_run) -> None:
    """The same with the results applied 1 keyframe later."""
    poses, frames = loop_frames
    _, _, lag1 = _run(replace(LOOP_CFG, loop_check_lag_keyframes=1), poses, frames)
    _same_loops_as_inline([loop_run[2], lag1], poses, frames)


@pytest.mark.heavy  # make test-all (a run each); make test's loop runs match with the default (guided) priors
@pytest.mark.parametrize("guided_older", [True, False],
                         ids=["guided_older", "brute_force_older"])
def test_older_candidates_are_matched_near_the_graphs_estimate_when_asked(loop_frames, monkeypatch,
                                                                          guided_older) -> None:
    """``loop.guided_older``: retrieved and random candidates get the graph's relative pose as the prior of their
    matching, as nearby ones always do (off: none, brute force); either way the revisit of the start is verified and
    closes the loop to the same precision."""
    from surfelslam.backend.sparse_slam import loop_checks

    candidates, priors = [], []
    real_candidates, real_verify = loop_checks.loop_candidates, loop_checks.verify_edge

    def candidates_seen(*a, **k):
        out = real_candidates(*a, **k)
        candidates.extend(out)
        return out

    def verify_seen(ref, cur, intr, feat_cfg, cfg, prior=None, *more):
        priors.append(prior)
        return real_verify(ref, cur, intr, feat_cfg, cfg, prior, *more)

    monkeypatch.setattr(loop_checks, "loop_candidates", candidates_seen)
    monkeypatch.setattr(loop_checks, "verify_edge", verify_seen)
    poses, frames = loop_frames
    cfg = replace(LOOP_CFG, background_loop_checks=False, loop=replace(LOOP_CFG.loop, guided_older=guided_older))
    _, _, res = _run(cfg, poses, frames)
    assert len(candidates) == len(priors) > 0
    older = [p for c, p in zip(candidates, priors, strict=True) if c.source != "nearby"]
    assert len(older) >= 10 and all((p is not None) == guided_older for p in older)
    assert all(p is not None for c, p in zip(candidates, priors, strict=True) if c.source == "nearby")
    far = [(i, j) for i, j, _ in res.loops_accepted if j - i > N_LOOP // 2]
    assert len(far) >= 3
    assert ate_m(res.trajectory.T_world_cam, poses) < 0.05
