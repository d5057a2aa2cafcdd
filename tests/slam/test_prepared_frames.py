"""Frames prepared ahead in the reader thread (``prepare``, as ``run`` does): the same poses, the same errors, pyramid
buffers returned to the pool (synthetic room, 320x240, Kinect noise)."""

from __future__ import annotations

import numpy as np
import pytest

from surfelslam.slam import TRACKERS, SlamConfig, build_slam
from tracker_helpers import N_SLOW
from tracker_helpers import room_frames as _frames
from tracker_helpers import run_tracker as _run

from helpers import INTR

pytestmark = pytest.mark.slow  # whole sequences through trackers


@pytest.mark.parametrize("tracker", [t if t != "orb" else pytest.param(t, marks=pytest.mark.heavy)  # orb: test-all
                                     for t in TRACKERS])
def test_prepared_in_reader_thread_gives_the_same_poses(tracker):
    """``prepare`` run ahead in the reader thread (as ``run`` does) changes nothing: bit-identical poses."""
    from surfelslam.io.prefetch import prefetch_frames

    frames, _ = _frames("fast", N_SLOW)
    frames = frames[:12]
    sync, _, _ = _run(tracker, frames)
    slam = build_slam(INTR, SlamConfig(), tracker)
    poses, prepared = [], 0
    for item in prefetch_frames(frames, ahead=3, prepare=slam.prepare):
        prepared += item.prepared is not None
        poses.append(slam.process(item.frame, prepared=item.prepared).T_world_cam)
    res = slam.finish()
    ahead = np.stack(poses) if res.trajectory_override is None else res.trajectory_override.T_world_cam
    assert prepared == len(frames)
    np.testing.assert_array_equal(ahead, sync)
    if tracker != "orb":  # the pool holds only what was in flight, then is reused
        assert slam.pooled_pyramids <= 3 + 2


def test_a_wrong_size_frame_prepared_ahead_raises_the_pipelines_own_error():
    from surfelslam.errors import ConfigError
    from surfelslam.types import RGBDFrame

    frames, _ = _frames("slow", N_SLOW)
    f = frames[0]
    bad = RGBDFrame(f.index, f.timestamp, f.rgb[:-2], f.depth_m[:-2])
    slam = build_slam(INTR, SlamConfig(), "dense")
    with pytest.raises(ConfigError, match="expected 320x240"):
        slam.prepare(bad)
    with pytest.raises(ConfigError, match="expected 320x240"):
        slam.process(bad, prepared=None)


def test_a_discarded_prepared_frame_returns_its_pyramid_to_the_pool():
    """``run --poses`` skips frames without a pose after they were prepared: their pyramids are reused, so
    skipping many frames does not grow memory."""
    frames, gt = _frames("slow", N_SLOW)
    slam = build_slam(INTR, SlamConfig(), "given")
    pyramids = []  # kept alive, so distinct buffers have distinct ids
    for k, f in enumerate(frames[:10]):
        prep = slam.prepare(f)
        if all(prep.pyramid is not p for p in pyramids):
            pyramids.append(prep.pyramid)
        if k % 2:
            slam.discard(prep)
            assert prep.pyramid is None
        else:
            slam.process(f, T_world_cam=gt[k], prepared=prep)
    assert len(pyramids) <= 3  # the current, the previous and one in flight: buffers are reused
