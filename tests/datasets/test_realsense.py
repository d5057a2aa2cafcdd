"""The live camera path (`surfelslam run realsense`), on a fake device that replays a synthetic sequence: the run
sees the folder's frames, --record writes a bag that replays them exactly. The RealSense SDK itself is not
exercised (no camera here)."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from surfelslam.api import run_sequence
from surfelslam.cli import app
from surfelslam.datasets import DatasetOptions, open_sequence
from surfelslam.datasets.realsense import open_realsense
from surfelslam.errors import ConfigError, FrameError
from surfelslam.slam import SlamConfig
from surfelslam.synth.writer import generate_sequence

runner = CliRunner()


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return generate_sequence(tmp_path_factory.mktemp("rs") / "seq", "room", "slow", 8, "kinect", 0, 160, 120)


class FakeDevice:
    """A camera that sends a sequence's frames: colour, raw depth (its depth scale's units), stamp; then stops."""

    def __init__(self, seq):
        self.seq, self.k, self.closed = seq, 0, False
        self.intrinsics, self.depth_scale = seq.full_intrinsics, seq.depth_scale

    def read(self):
        if self.k >= len(self.seq):
            return None
        e = self.seq.entries[self.k]
        self.k += 1
        from surfelslam.io.images import read_depth_raw, read_rgb

        return read_rgb(e.rgb_path), read_depth_raw(e.depth_path), e.timestamp

    def close(self):
        self.closed = True


@pytest.mark.slow
def test_live_run_and_its_recording_give_the_folder_trajectory(folder, tmp_path):
    ref = open_sequence(folder)
    run_sequence(ref, tmp_path / "folder", SlamConfig(), "dense", progress=False, figures=False)
    expected = (tmp_path / "folder" / "trajectory.txt").read_bytes()
    dev = FakeDevice(ref)
    live = open_realsense(DatasetOptions(end=len(ref)), record=tmp_path / "live.bag", device=dev)
    m = run_sequence(live, tmp_path / "live", SlamConfig(), "dense", progress=False, figures=False)
    assert m["layout"] == "live" and m["frames_processed"] == len(ref) and dev.closed
    assert (tmp_path / "live" / "trajectory.txt").read_bytes() == expected
    bag = open_sequence(tmp_path / "live.bag")  # the recording: finished when the last frame was read
    assert len(bag) == len(ref) and bag.intrinsics == ref.intrinsics
    run_sequence(bag, tmp_path / "replay", SlamConfig(), "dense", progress=False, figures=False)
    assert (tmp_path / "replay" / "trajectory.txt").read_bytes() == expected


@pytest.mark.slow
def test_selection_order_and_end_of_stream(folder):
    ref = open_sequence(folder)
    live = open_realsense(DatasetOptions(start=2, end=8, stride=2, downsample=2), device=FakeDevice(ref))
    assert len(live) == 3 and live.intrinsics == ref.intrinsics.scaled(2)
    with pytest.raises(FrameError, match="read once, in order"):
        live[1]
    frames = list(live)
    assert [f.timestamp for f in frames] == [ref.timestamps[k] for k in (2, 4, 6)]
    assert frames[0].depth_m.shape == (60, 80) and np.array_equal(frames[0].depth_m, ref[2].depth_m[::2, ::2])
    short = open_realsense(DatasetOptions(end=20), device=FakeDevice(ref))
    for i in range(len(ref)):
        short[i]
    with pytest.raises(FrameError, match="ended after 8 frames"):
        short[len(ref)]


@pytest.mark.slow
def test_options_are_checked(folder, tmp_path):
    ref = open_sequence(folder)
    with pytest.raises(ConfigError, match="--end"):
        open_realsense(DatasetOptions(), device=FakeDevice(ref))
    with pytest.raises(ConfigError, match="--record needs the live camera"):
        open_realsense(DatasetOptions(end=2), record=tmp_path / "x.bag", device=FakeDevice(ref), path=folder)
    live = open_realsense(DatasetOptions(end=2, intrinsics=(100, 100, 80, 60), depth_scale=1000.0),
                          device=FakeDevice(ref))
    assert live.intrinsics.fx == 100 and live.depth_scale == 1000.0


def test_cli_without_a_camera_is_one_line(tmp_path):
    res = runner.invoke(app, ["run", "realsense", "--end", "3", "--out", str(tmp_path / "r"), "--no-progress"])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and ("pyrealsense2" in lines[0] or "camera" in lines[0])
