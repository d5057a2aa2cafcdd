"""Frame stamps that count frames (ICL-NUIM's frame ids) against stamps in seconds: the trajectory keeps the
dataset's stamps, the motion checks get seconds (``RGBDFrame.time_s``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_datasets import make_tum, write_frame
from typer.testing import CliRunner

from surfelslam.datasets import open_sequence
from surfelslam.datasets.base import FRAME_NUMBER_RATE_HZ, stamps_are_frame_numbers
from surfelslam.types import RGBDFrame

from helpers import command_app


def make_icl_native(root: Path, n: int = 4) -> Path:
    """A tiny native ICL-NUIM folder: rgb/0.png.. depth/0.png.., GT ids 1..n moving 0.1 m along x per frame."""
    for k in range(n):
        write_frame(root, f"rgb/{k}.png", f"depth/{k}.png")
    (root / "livingRoom2.gt.freiburg").write_text("".join(f"{k} {0.1 * k} 0 -2.25 0 0 0 1\n" for k in range(1, n + 1)))
    return root


def test_icl_native_numbering(tmp_path):
    """rgb/0.png.. with GT ids from 1: the i-th GT line belongs to the i-th image (timestamp n + 1)."""
    seq = open_sequence(make_icl_native(tmp_path / "lr_kt2"))
    assert seq.layout == "icl"
    assert np.allclose(seq.timestamps, [1, 2, 3, 4])
    T, valid = seq.gt_poses()
    assert valid.all() and np.allclose(T[:, 0, 3], [0.1, 0.2, 0.3, 0.4])
    assert seq.entries[0].rgb_path.name == "0.png"


@pytest.mark.parametrize(("stamps", "expected"), [
    ([1, 2, 3, 4], True),  # ICL-NUIM ids
    ([2, 301, 601, 901, 1201], True),  # every 300th ICL frame
    ([0, 1, 2, 4, 5], True),  # one frame missing
    ([100.0, 100.0 + 1 / 30, 100.0 + 2 / 30], False),  # seconds at 30 Hz
    ([1305031102.175304, 1305031102.211214], False),  # TUM
    ([0, 30, 60, 61], True),  # whole numbers at least 1 apart: frame numbers with gaps
    ([10.0, 10.5, 11.0, 11.5], False),  # half seconds
    ([3, 3, 4], False),  # not increasing
    ([5], False),
])
def test_frame_number_stamps_are_told_from_seconds(stamps, expected):
    assert stamps_are_frame_numbers(np.array(stamps, np.float64)) is expected


def test_icl_frame_ids_stay_in_the_trajectory_and_are_seconds_for_motion(tmp_path):
    root = make_icl_native(tmp_path / "lr_kt2")
    seq = open_sequence(root)
    assert seq.layout == "icl" and seq.seconds_per_stamp == pytest.approx(1 / FRAME_NUMBER_RATE_HZ)
    frame = seq[2]
    assert frame.timestamp == 3.0 and frame.time_s == pytest.approx(3 / 30) and frame.depth_stamp_s == frame.time_s
    assert any("count frames" in w for w in seq.warnings) and seq.info()["seconds_per_stamp"] == seq.seconds_per_stamp
    res = CliRunner().invoke(command_app("info"), ["info", str(root)], terminal_width=200)
    assert res.exit_code == 0 and "frame numbers, 30 Hz for motion checks" in res.output, res.output


def test_tum_layout_stamps_are_seconds_unless_they_count_frames(tmp_path):
    seconds = open_sequence(make_tum(tmp_path / "fr1_desk", n=4))
    assert seconds.seconds_per_stamp == 1.0 and not any("count frames" in w for w in seconds.warnings)
    f = seconds[1]
    assert f.time_s == f.timestamp and f.colour_minus_depth_s == 0.0
    counted = open_sequence(make_tum(tmp_path / "counted", n=4, dt_s=1.0))
    assert counted.layout == "tum" and counted.seconds_per_stamp == pytest.approx(1 / 30)
    assert counted[3].timestamp == 103.0 and counted[3].time_s == pytest.approx(103 / 30)


def test_a_separate_depth_stamp_is_scaled_too():
    f = RGBDFrame(0, 12.0, np.zeros((2, 2, 3), np.uint8), np.zeros((2, 2), np.float32), 11.0, 0.5)
    assert f.time_s == 6.0 and f.depth_stamp_s == 5.5 and f.colour_minus_depth_s == 0.5
