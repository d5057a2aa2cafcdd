"""TUM text files: one comment-skipping line parser; ``surfelslam.types`` does not import the file I/O."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from surfelslam.io.trajectory import data_lines, read_tum


def test_data_lines_skips_blanks_and_comments_and_keeps_line_numbers():
    text = "# header\n\n  1.0 a  \n   # indented comment\n2.0 b\n"
    assert list(data_lines(text)) == [(3, "1.0 a"), (5, "2.0 b")]


def test_read_tum_sorts_and_skips_comments(tmp_path):
    path = tmp_path / "t.txt"
    path.write_text("# timestamp tx ty tz qx qy qz qw\n\n2.0 1 2 3 0 0 0 1\n# note\n1.0 0,0,0 0 0 0 1\n")
    traj = read_tum(path)
    assert np.array_equal(traj.timestamps, [1.0, 2.0])
    assert np.array_equal(traj.T_world_cam[1, :3, 3], [1, 2, 3])


def test_types_does_not_import_the_trajectory_io_at_import_time():
    code = "import sys, surfelslam.types; print('surfelslam.io.trajectory' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
