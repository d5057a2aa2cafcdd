"""Output faults: file modes, disk full, torn trajectory lines, unwritable folders. Whatever is left on disk is
valid (trajectory parses, PLY body matches its header, no temp file) and the error names the file."""

from __future__ import annotations

import contextlib
import errno
import os
from pathlib import Path

import numpy as np
import pytest

from surfelslam.errors import InputError, OutputError
from surfelslam.io import atomic
from surfelslam.io.atomic import atomic_open, write_text_atomic
from surfelslam.io.ply import read_ply, write_points_ply
from surfelslam.io.trajectory import TumAppender, read_tum, write_tum
from surfelslam.types import Trajectory


@pytest.fixture
def umask022():
    old = os.umask(0o022)
    yield
    os.umask(old)


def _write_png_figure(path: Path) -> None:
    from surfelslam.viz.save import new_figure, save_figure

    fig = new_figure((1.0, 1.0))
    fig.add_subplot(1, 1, 1).plot([0, 1], [0, 1])
    save_figure(fig, path)


WRITERS = {
    "config.toml": lambda p: write_text_atomic(p, "[io]\n"),
    "metrics.json": lambda p: write_text_atomic(p, "{}\n"),
    "map.ply": lambda p: write_points_ply(p, np.zeros((3, 3)), np.zeros((3, 3), np.uint8)),
    "map_top.png": _write_png_figure,
    "groundtruth.txt": lambda p: write_tum(Trajectory(np.arange(2.0), np.tile(np.eye(4), (2, 1, 1))), p),
}


@pytest.mark.parametrize("name", sorted(WRITERS))
def test_outputs_are_0644_under_umask_022(tmp_path, umask022, name):
    path = tmp_path / name
    WRITERS[name](path)
    assert (path.stat().st_mode & 0o777) == 0o644
    assert [p.name for p in tmp_path.iterdir()] == [name]  # no temp file beside it


def test_trajectory_appender_is_0644_and_mode_follows_the_umask(tmp_path):
    old = os.umask(0o077)
    try:
        write_text_atomic(tmp_path / "private.txt", "x")
        with TumAppender(tmp_path / "t.txt"):
            pass
    finally:
        os.umask(old)
    assert (tmp_path / "private.txt").stat().st_mode & 0o777 == 0o600
    assert (tmp_path / "t.txt").stat().st_mode & 0o777 == 0o600
    assert atomic.current_umask() == old


def test_disk_full_during_an_atomic_write_names_the_file_and_keeps_the_old_one(tmp_path):
    path = tmp_path / "metrics.json"
    path.write_text("old\n")
    with pytest.raises(OutputError) as err, atomic_open(path) as fh:
        fh.write("new")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert str(path) in str(err.value) and "No space left on device" in str(err.value)
    assert "\n" not in str(err.value)
    assert path.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.json"]  # no temp file left


def test_disk_full_while_writing_a_ply_leaves_no_temp_file(tmp_path, monkeypatch):
    path = tmp_path / "map.ply"

    class FullFile:
        def __init__(self, real):
            self.real = real

        def write(self, data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        def __getattr__(self, name):
            return getattr(self.real, name)

    @contextlib.contextmanager
    def full_open(p, mode="w"):
        with atomic.atomic_path(p) as tmp, open(tmp, mode) as fh:
            yield FullFile(fh)

    monkeypatch.setattr("surfelslam.io.ply.atomic_open", full_open)
    with pytest.raises(OutputError, match=f"{path}: cannot write the file .No space left on device"):
        write_points_ply(path, np.zeros((4, 3)), np.zeros((4, 3), np.uint8))
    assert list(tmp_path.iterdir()) == []


def test_output_folder_below_a_file_is_one_clear_error(tmp_path):
    blocker = tmp_path / "out"
    blocker.write_text("a file where the run folder should be")
    with pytest.raises(OutputError, match="out/config.toml: cannot create the file"):
        write_text_atomic(blocker / "config.toml", "x")
    with pytest.raises(OutputError, match="out/trajectory.txt: cannot create the trajectory file"):
        TumAppender(blocker / "trajectory.txt")


def _pose(i: int) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = 0.01 * i
    return T


def test_torn_trajectory_line_is_cut_back_on_disk_full(tmp_path, monkeypatch):
    """The 4th pose is half written when the disk fills up: the file keeps 3 whole poses, no torn line."""
    path = tmp_path / "trajectory.txt"
    calls = {"n": 0}

    def filling_write(fd, data):
        calls["n"] += 1
        if calls["n"] == 5:  # header, 3 poses, then half of the 4th
            return os.write(fd, data[: len(data) // 2])
        if calls["n"] > 5:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return os.write(fd, data)

    monkeypatch.setattr(TumAppender, "_write_fn", staticmethod(filling_write))
    with pytest.raises(OutputError) as err, TumAppender(path) as out:
        for i in range(6):
            out.append(0.1 * i, _pose(i))
    msg = str(err.value)
    assert msg.startswith(f"{path}: ") and "No space left on device" in msg and "3 poses" in msg
    text = path.read_text()
    assert text.endswith("\n")
    traj = read_tum(path)
    assert len(traj) == 3 and np.allclose(traj.positions[:, 0], [0.0, 0.01, 0.02])


def test_disk_full_on_the_first_pose_keeps_a_header_only_file(tmp_path, monkeypatch):
    path = tmp_path / "trajectory.txt"
    calls = {"n": 0}

    def full_after_header(fd, data):
        calls["n"] += 1
        if calls["n"] > 1:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return os.write(fd, data)

    monkeypatch.setattr(TumAppender, "_write_fn", staticmethod(full_after_header))
    with pytest.raises(OutputError, match="0 poses written"), TumAppender(path) as out:
        out.append(0.0, np.eye(4))
    assert path.read_text() == TumAppender.HEADER


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
def test_trajectory_on_a_full_device_names_the_file(tmp_path):
    link = tmp_path / "trajectory.txt"
    link.symlink_to("/dev/full")
    with pytest.raises(OutputError, match=f"{link}: cannot write .No space left on device"):
        TumAppender(link)


def test_ply_written_is_valid(tmp_path):
    path = tmp_path / "map.ply"
    n = write_points_ply(path, np.arange(12.0).reshape(4, 3), np.full((4, 3), 7, np.uint8))
    ply = read_ply(path)
    assert n == 4 and len(ply["x"]) == 4 and np.all(ply["red"] == 7)
    header, body = path.read_bytes().split(b"end_header\n", 1)
    assert b"element vertex 4" in header and len(body) == 4 * (3 * 4 + 3)


def test_duplicate_trajectory_stamps_name_both_lines(tmp_path):
    path = tmp_path / "est.txt"
    path.write_text("# t x y z qx qy qz qw\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n1.0 1 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match=r"est.txt: duplicate timestamp 1.000000 \(lines 2 and 4\)"):
        read_tum(path)
