"""Faults during `surfelslam run` (given poses, no figures: fast): bad frames are skipped with their reason, a full
disk stops the run with one line naming the file and a trajectory that still parses, an implausible depth scale
is refused before anything is written."""

from __future__ import annotations

import errno
import json
import os

import cv2
import pytest
from faultkit import assert_one_line, cli, index_rows, no_temp_files

from surfelslam.io.run_folder import staging_path
from surfelslam.io.trajectory import TumAppender, read_tum

RUN = ("--poses", "gt", "--no-figures", "--no-progress")


def _metrics(out):
    return json.loads((out / "metrics.json").read_text())


def test_truncated_jpeg_frame_is_skipped_with_its_reason(seq, tmp_path, capfd):
    rows = index_rows(seq / "rgb.txt")
    t, name = rows[3].split()
    jpg = seq / name.replace(".png", ".jpg")
    cv2.imwrite(str(jpg), cv2.imread(str(seq / name)))
    jpg.write_bytes(jpg.read_bytes()[:600])
    rows[3] = f"{t} {jpg.relative_to(seq)}"
    (seq / "rgb.txt").write_text("\n".join(rows) + "\n")
    out = tmp_path / "run"
    old = os.umask(0o022)
    try:
        res = cli("run", seq, "-o", out, *RUN)
    finally:
        os.umask(old)
    assert res.exit_code == 0, res.output
    m = _metrics(out)
    assert m["frames_processed"] == 9 and m["frames_skipped"] == 1
    assert m["skipped"][0]["position"] == 3 and "truncated colour JPEG" in m["skipped"][0]["reason"]
    assert jpg.name in m["skipped"][0]["reason"]
    assert len(read_tum(out / "trajectory.txt")) == 9
    for name in ("trajectory.txt", "map.ply", "config.toml", "metrics.json"):
        assert (out / name).stat().st_mode & 0o777 == 0o644, name
    assert no_temp_files(out)
    assert "JPEG" not in capfd.readouterr().err  # no libjpeg line of its own


def test_corrupt_first_frame_is_skipped_not_fatal(seq, tmp_path):
    first = seq / index_rows(seq / "depth.txt")[0].split()[1]
    first.write_bytes(b"")
    out = tmp_path / "run"
    res = cli("run", seq, "-o", out, *RUN)
    assert res.exit_code == 0, res.output
    m = _metrics(out)
    assert m["frames_processed"] == 9 and m["skipped"][0]["position"] == 0
    assert str(first) in m["skipped"][0]["reason"] and "empty file" in m["skipped"][0]["reason"]


def test_disk_full_mid_run_names_the_trajectory_and_keeps_it_valid(seq, tmp_path, monkeypatch):
    calls = {"n": 0}

    def full_after_five_poses(fd, data):
        calls["n"] += 1
        if calls["n"] > 6:  # the header and 5 poses fit
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return os.write(fd, data)

    monkeypatch.setattr(TumAppender, "_write_fn", staticmethod(full_after_five_poses))
    out = tmp_path / "run"
    res = cli("run", seq, "-o", out, *RUN)
    partial = staging_path(out) / "trajectory.txt"  # the run writes there until it is complete
    assert_one_line(res, 2, str(partial), "No space left on device", "keeps the 5 poses")
    assert len(read_tum(partial)) == 5
    assert partial.read_text().endswith("\n")
    assert not (out / "trajectory.txt").exists() and not (out / ".lock").exists()
    assert no_temp_files(out)


@pytest.mark.parametrize("args, fragment", [
    (("--depth-scale", "1"), "--depth-scale 1 units per metre"),
    (("--intrinsics", "585,585,5000,240"), "--intrinsics 585,585,5000,240"),
])
def test_implausible_camera_is_refused_before_any_output(seq, tmp_path, args, fragment):
    out = tmp_path / "run"
    assert_one_line(cli("run", seq, "-o", out, *RUN, *args), 2, fragment)
    assert not out.exists()
