"""Dense frame-to-model SLAM on synthetic sequences with exact ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from surfelslam.geometry import se3
from surfelslam.slam import DenseSlam, SlamConfig
from surfelslam.synth.scenes import make_scene
from surfelslam.synth.trajectories import make_trajectory
from surfelslam.synth.writer import default_intrinsics, iter_frames, noise_config

pytestmark = pytest.mark.slow  # whole sequences through trackers or commands


def _track(noise: str, n: int = 60, style: str = "handheld", cfg: SlamConfig | None = None):
    scene = make_scene("room")
    intr = default_intrinsics(320, 240)
    traj = make_trajectory(style, n, scene)
    gt = se3.invert(traj.T_world_cam[0]) @ traj.T_world_cam
    slam = DenseSlam(intr, cfg or SlamConfig())
    est = np.stack([slam.process(f).T_world_cam for f in iter_frames(scene, traj, intr, noise_config(noise), 0)])
    err = np.array([se3.pose_error(e, g)[0] for e, g in zip(est, gt, strict=True)])
    return est, err, slam


def test_noiseless_sequence_is_tracked_to_a_millimetre():
    est, err, slam = _track("none")
    assert slam.failures == 0
    assert err.max() < 2e-3
    # poses stay rigid: the chain is re-orthonormalised (a drift off SO(3) used to blow up after ~25 frames)
    R = est[:, :3, :3]
    assert np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max() < 1e-9


def test_kinect_noise_drift_stays_small():
    _, err, slam = _track("kinect")
    assert slam.failures == 0
    assert np.sqrt(np.mean(err**2)) < 0.03


def test_same_input_same_trajectory():
    a, _, _ = _track("kinect", n=15)
    b, _, _ = _track("kinect", n=15)
    assert np.array_equal(a, b)


def test_orthonormalize_projects_onto_se3():
    rng = np.random.default_rng(0)
    T = se3.exp(rng.normal(size=6))
    T[:3, :3] *= 1.001
    Tn = se3.orthonormalize(T)
    assert np.allclose(Tn[:3, :3] @ Tn[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.allclose(Tn[:3, 3], T[:3, 3])
    assert np.linalg.norm(Tn[:3, :3] - T[:3, :3]) < 3e-3


def test_working_level_tracks_and_fuses_the_block_averaged_level():
    """Input wider than the working width is tracked and fused at its 2x2 block-averaged level."""
    from dataclasses import replace

    from surfelslam.tracking.preprocess import level_for_width

    base = SlamConfig()
    cfg = replace(base, tracking=replace(base.tracking, max_width_px=160),
                  fusion=replace(base.fusion, max_width_px=160))
    est, err, slam = _track("none", n=30, cfg=cfg)
    assert (slam.front.track_level, slam.front.mapper.fuse_level) == (1, 1)
    assert slam.failures == 0
    assert err.max() < 4e-3
    # the map is made at 160x120: at most one new surfel per working-level pixel and frame, and far fewer
    # than a single full-resolution frame's pixels would give
    assert 0 < slam.map.n_alive < 160 * 120 * 2
    assert [level_for_width(default_intrinsics(w, w * 3 // 4).width, 320) for w in (320, 640, 1280)] == [0, 1, 2]
    assert level_for_width(default_intrinsics(640, 480).width, 0) == 0
