"""Frame sources: folders, bags, numpy arrays and a (fake) live device all feed surfelslam.Slam the same way."""

from __future__ import annotations

import numpy as np
import pytest

import surfelslam as ss
from surfelslam.api import run_sequence
from surfelslam.datasets import DatasetOptions, open_sequence
from surfelslam.datasets.rosbag.write import write_bag
from surfelslam.datasets.stream import ArraySource, DeviceSource, FrameSource, track_source
from surfelslam.errors import ConfigError, FrameError
from surfelslam.slam import SlamConfig
from surfelslam.synth.writer import generate_sequence

# every test here streams frames of a generated sequence (several run it through a tracker)
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return generate_sequence(tmp_path_factory.mktemp("src") / "seq", "room", "slow", 8, "kinect", 0, 160, 120)


def _arrays(seq):
    frames = list(seq)
    return ([f.rgb for f in frames], [f.depth_m for f in frames], [f.timestamp for f in frames])


class FakeDevice:
    """Replays a sequence's raw frames like a camera: colour, raw depth (units of ``depth_scale``), stamp."""

    def __init__(self, seq, repeat_first: bool = False):
        self.seq = seq
        self.intrinsics = seq.intrinsics
        self.depth_scale = seq.depth_scale
        self.k = 0
        self.repeat_first = repeat_first
        self.closed = False

    def read(self):
        if self.k >= len(self.seq):
            return None
        k = self.k
        if self.repeat_first and k == 1:
            self.repeat_first = False
            k = 0  # the device hands the same frame twice
        else:
            self.k += 1
        f = self.seq[k]
        raw = np.round(f.depth_m * self.depth_scale).astype(np.uint16)
        return f.rgb, raw, f.timestamp

    def close(self):
        self.closed = True


def test_every_source_is_a_frame_source(folder, tmp_path):
    seq = open_sequence(folder)
    bag = open_sequence(write_bag(open_sequence(folder, DatasetOptions(end=3)), tmp_path / "s.bag", "ros1"))
    arrays = ArraySource(*_arrays(seq), seq.intrinsics)
    device = DeviceSource(FakeDevice(seq))
    for src in (seq, bag, arrays, device):
        assert isinstance(src, FrameSource), type(src)


def test_array_source_through_slam_equals_the_folder(folder):
    """The same frames from numpy arrays and from the folder give the same poses through ss.Slam.track."""
    seq = open_sequence(folder)
    ref = track_source(ss.Slam(seq.intrinsics, "dense"), seq)
    src = ArraySource(*_arrays(seq), seq.intrinsics, seq.ground_truth)
    run = track_source(ss.Slam(src.intrinsics, "dense"), src)
    assert np.array_equal(run.trajectory.T_world_cam, ref.trajectory.T_world_cam)
    assert np.array_equal(run.trajectory.timestamps, seq.timestamps)
    assert ss.evaluate(run.trajectory, src.ground_truth)["ate_rmse_m"] < 0.02


def test_array_source_runs_through_the_run_loop(folder, tmp_path):
    seq = open_sequence(folder)
    run_sequence(seq, tmp_path / "a", SlamConfig(), "dense", progress=False, figures=False)
    src = ArraySource(*_arrays(seq), seq.intrinsics, seq.ground_truth)
    m = run_sequence(src, tmp_path / "b", SlamConfig(), "dense", progress=False, figures=False)
    assert m["layout"] == "arrays" and m["frames_processed"] == len(seq)
    assert (tmp_path / "a" / "trajectory.txt").read_bytes() == (tmp_path / "b" / "trajectory.txt").read_bytes()


def test_array_source_checks_its_input(folder):
    seq = open_sequence(folder, DatasetOptions(end=2))
    rgb, depth, t = _arrays(seq)
    with pytest.raises(ConfigError, match="frame 1: depth_m"):
        ArraySource(rgb, [depth[0], depth[1][:-1]], t, seq.intrinsics)
    with pytest.raises(ConfigError, match="increasing"):
        ArraySource(rgb, depth, [t[1], t[0]], seq.intrinsics)
    with pytest.raises(ConfigError, match="one of each"):
        ArraySource(rgb, depth[:1], t, seq.intrinsics)
    nan = depth[0].copy()
    nan[0, 0] = np.nan
    assert ArraySource(rgb[:1], [nan], t[:1], seq.intrinsics)[0].depth_m[0, 0] == 0.0


def test_device_source_streams_records_and_closes(folder):
    seq = open_sequence(folder)
    dev = FakeDevice(seq, repeat_first=True)
    seen = []
    frames = list(DeviceSource(dev, max_frames=5, record=seen.append))
    assert [f.index for f in frames] == [0, 1, 2, 3, 4] and seen == frames
    assert [f.timestamp for f in frames] == list(seq.timestamps[:5])  # the repeated frame is dropped
    assert np.allclose(frames[2].depth_m, seq[2].depth_m, atol=0.5 / seq.depth_scale)
    assert dev.closed
    bad = FakeDevice(seq)
    bad.intrinsics = ss.Intrinsics(1, 1, 1, 1, 10, 10)
    with pytest.raises(FrameError, match="device frame 0"):
        list(DeviceSource(bad))
    assert bad.closed
