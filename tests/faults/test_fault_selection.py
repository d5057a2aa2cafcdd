"""Options checked against the opened sequence before anything runs (issue 71.5): the message names the option;
unpaired images are counted only within the selection (issue 70.5)."""

from __future__ import annotations

import pytest
from faultkit import assert_one_line, cli, index_rows

from surfelslam.datasets import DatasetOptions, open_sequence
from surfelslam.datasets.base import MIN_DOWNSAMPLED_SIDE_PX
from surfelslam.errors import ConfigError


def test_downsample_too_large_names_the_option(seq):
    intr = open_sequence(seq).full_intrinsics  # 160x120 (the fixture's)
    largest = min(intr.width, intr.height) // MIN_DOWNSAMPLED_SIDE_PX
    assert largest == 7
    res = cli("info", seq, "--downsample", 1000)
    assert_one_line(res, 2, str(seq), "--downsample 1000", "160x120 images into 1x1",
                    f"use --downsample {largest} or less")
    assert open_sequence(seq, DatasetOptions(downsample=largest)).intrinsics.height >= MIN_DOWNSAMPLED_SIDE_PX
    with pytest.raises(ConfigError, match=f"--downsample {largest + 1} "):
        open_sequence(seq, DatasetOptions(downsample=largest + 1))


def test_start_past_the_end_names_the_option_and_the_frame_count(seq):
    res = cli("info", seq, "--start", 50)
    assert_one_line(res, 2, str(seq), "--start 50 keeps no frame", "10 frames (positions 0-9)")


def test_end_past_the_end_is_a_warning(seq):
    s = open_sequence(seq, DatasetOptions(end=100))
    assert len(s) == 10
    assert [w for w in s.warnings if "--end 100 is past the last frame (10 frames)" in w]
    assert not open_sequence(seq, DatasetOptions(end=10)).warnings


def test_unpaired_images_are_counted_within_the_selection(seq):
    rows = index_rows(seq / "depth.txt")
    (seq / "depth.txt").write_text("\n".join(rows[:3] + rows[5:]) + "\n")  # colour images 3 and 4 lose depth
    whole = open_sequence(seq)
    assert len(whole.unpaired) == 2 and len(whole.all_unpaired) == 2
    before = open_sequence(seq, DatasetOptions(end=3))  # frames 0-2: the unpaired images come later
    assert before.unpaired == [] and len(before.all_unpaired) == 2
    around = open_sequence(seq, DatasetOptions(start=2, end=6))
    assert [u.timestamp for u in around.unpaired] == [u.timestamp for u in whole.unpaired]
    after = open_sequence(seq, DatasetOptions(start=5))
    assert after.unpaired == [] and after.info()["images_unpaired"] == 0
