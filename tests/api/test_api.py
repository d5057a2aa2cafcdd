"""The public API (``surfelslam.Slam`` and friends) against the run loop and the ground truth."""

from __future__ import annotations

import numpy as np
import pytest

import surfelslam as ss
from surfelslam.api import run_sequence
from surfelslam.errors import ConfigError, FrameError
from surfelslam.io.trajectory import read_tum
from surfelslam.synth.writer import generate_sequence

pytestmark = pytest.mark.slow  # whole (short) sequences through the trackers


@pytest.fixture(scope="module")
def seq_path(tmp_path_factory):
    return generate_sequence(tmp_path_factory.mktemp("api") / "seq", "room", "slow", 16, "kinect", 3, 160, 120)


@pytest.mark.parametrize("tracker", ["dense", "orb", "hybrid"])
def test_slam_track_finish_equals_the_run_loop(seq_path, tmp_path, tracker):
    """``Slam.track`` frame by frame, then ``finish().trajectory``, is the trajectory ``surfelslam run`` writes, bit
    for bit, for every tracker (orb and hybrid: the pose-graph-optimised one)."""
    seq = ss.open_sequence(seq_path)
    slam = ss.Slam.from_sequence(seq, tracker=tracker)
    results = [slam.track(f) for f in seq]
    run = slam.finish()
    assert len(results) == len(seq) == len(run.trajectory)
    run_sequence(seq, tmp_path / "run", ss.SlamConfig(), tracker, progress=False, figures=False)
    written = read_tum(tmp_path / "run" / "trajectory.txt")
    out = run.save(tmp_path / "api")
    saved = read_tum(out / "trajectory.txt")
    np.testing.assert_array_equal(saved.T_world_cam, written.T_world_cam)
    np.testing.assert_array_equal(saved.timestamps, written.timestamps)
    assert (out / "map.ply").stat().st_size > 1000 and (out / "metrics.json").is_file()
    e = ss.evaluate(run.trajectory, seq.ground_truth)
    assert e["ate_rmse_m"] < 0.02, e


def test_track_from_arrays_matches_track_from_frames(seq_path):
    seq = ss.open_sequence(seq_path, end=6)
    a = ss.Slam(seq.intrinsics)
    b = ss.Slam(seq.intrinsics, warmup=False)
    for f in seq:
        ra = a.track(f)
        depth = f.depth_m.copy()
        depth[depth == 0] = np.nan  # NaN means no depth, as 0 does
        rb = b.track(f.rgb, depth, f.timestamp)
        np.testing.assert_array_equal(ra.T_world_cam, rb.T_world_cam)
    np.testing.assert_array_equal(a.finish().trajectory.T_world_cam, b.finish().trajectory.T_world_cam)


def test_bad_calls_give_clear_errors(seq_path):
    seq = ss.open_sequence(seq_path, end=3)
    with pytest.raises(ConfigError, match="tracker must be one of"):
        ss.Slam(seq.intrinsics, tracker="kiss")
    with pytest.raises(ConfigError, match="open_sequence"):
        ss.open_sequence(seq_path, bogus=1)
    slam = ss.Slam(seq.intrinsics, warmup=False)
    f = seq[0]
    with pytest.raises(FrameError, match=r"depth_m must be \(120, 160\)"):
        slam.track(f.rgb, f.depth_m[:10], 0.0)
    with pytest.raises(ConfigError, match="rgb, depth_m and timestamp"):
        slam.track(f.rgb)
    slam.track(f)
    slam.finish()
    with pytest.raises(ConfigError, match="finished"):
        slam.track(f)


def test_config_from_dict_and_toml(seq_path, tmp_path):
    seq = ss.open_sequence(seq_path, end=4)
    slam = ss.Slam(seq.intrinsics, config={"tracking": {"max_width_px": 0}}, warmup=False)
    assert slam.config.tracking.max_width_px == 0
    toml = tmp_path / "c.toml"
    toml.write_text("[tracking]\nmax_width_px = 0\n")
    assert ss.Slam(seq.intrinsics, config=toml, warmup=False).config == slam.config


def test_register_recovers_a_known_motion(seq_path):
    seq = ss.open_sequence(seq_path)
    src, tgt = seq[4], seq[0]
    reg = ss.register(src, tgt, seq.intrinsics)
    T_gt, _ = seq.gt_poses()
    T_true = np.linalg.inv(T_gt[0]) @ T_gt[4]
    err = np.linalg.norm(reg.icp.T_target_source[:3, 3] - T_true[:3, 3])
    assert err < 0.005, err
