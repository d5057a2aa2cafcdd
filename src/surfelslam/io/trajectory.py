"""TUM trajectory files: ``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments."""

from __future__ import annotations

import errno
import math
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from surfelslam.errors import InputError, OutputError, TrackingError
from surfelslam.geometry.se3 import make_T, quat_xyzw_to_rotation, rotation_to_quat_xyzw
from surfelslam.io.atomic import NEW_FILE_MODE, atomic_open, os_error_text
from surfelslam.types import Trajectory

#: Largest |timestamp| read from a TUM-style file [s]: far beyond any clock (nanoseconds since 1970 are 1.7e18), and the
#: difference of two such stamps is still finite (1e308 - -1e308 overflows)
MAX_ABS_STAMP_S = 1e300


def tum_rows(traj: Trajectory) -> np.ndarray:
    """``(N, 8)`` rows ``timestamp tx ty tz qx qy qz qw`` of ``traj``."""
    q = rotation_to_quat_xyzw(traj.T_world_cam[:, :3, :3])
    return np.column_stack([traj.timestamps, traj.positions, q])


def trajectory_from_tum_rows(rows: np.ndarray) -> Trajectory:
    """The trajectory of ``(N, 8)`` rows ``timestamp tx ty tz qx qy qz qw``."""
    rows = np.asarray(rows, dtype=np.float64).reshape(-1, 8)
    T = make_T(quat_xyzw_to_rotation(rows[:, 4:8]), rows[:, 1:4])
    return Trajectory(rows[:, 0], T)


def data_lines(text: str) -> Iterator[tuple[int, str]]:
    """``(line number, stripped line)`` of the lines of a TUM text file that are neither blank nor ``#`` comments.

    One parser for every TUM-style file: trajectories here, and the dataset index files (``rgb.txt``,
    ``depth.txt``, ``associations.txt``).
    """
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if line and not line.startswith("#"):
            yield lineno, line


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory; sorts by timestamp and rejects malformed rows and duplicated timestamps with the
    line numbers."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "trajectory file not found")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read trajectory file ({exc})") from None
    rows, linenos = [], []
    for lineno, line in data_lines(text):
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise InputError(
                path, f"line {lineno}: expected 8 values 'timestamp tx ty tz qx qy qz qw', got {len(parts)}"
            )
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            raise InputError(path, f"line {lineno}: not a number in {line!r}") from None
        if not np.all(np.isfinite(vals)):
            raise InputError(path, f"line {lineno}: non-finite value in {line!r}")
        if abs(vals[0]) > MAX_ABS_STAMP_S:
            raise InputError(path, f"line {lineno}: timestamp {parts[0]} is out of range (|t| > {MAX_ABS_STAMP_S:g} s)")
        if math.hypot(*vals[4:8]) < 1e-6:  # hypot: no overflow for huge components
            raise InputError(path, f"line {lineno}: zero quaternion")
        exponent = math.frexp(max(abs(x) for x in vals[4:8]))[1]
        vals[4:8] = [math.ldexp(x, -exponent) for x in vals[4:8]]  # exact power-of-two scaling: 1e200 stays finite
        rows.append(vals)
        linenos.append(lineno)
    if not rows:
        raise InputError(path, "trajectory file has no poses")
    arr = np.asarray(rows, dtype=np.float64)
    order = np.argsort(arr[:, 0], kind="stable")
    dup = np.nonzero(np.diff(arr[order, 0]) == 0)[0]
    if len(dup):
        a, b = linenos[order[dup[0]]], linenos[order[dup[0] + 1]]
        more = f" ({len(dup)} duplicated stamps in all)" if len(dup) > 1 else ""
        raise InputError(path, f"duplicate timestamp {arr[order[dup[0]], 0]:.6f} (lines {a} and {b}){more}; "
                               "each pose needs its own timestamp")
    return trajectory_from_tum_rows(arr[order])


#: Largest deviation from a rotation (max |R R^T - I|) of a pose written to a trajectory file.
MAX_ROTATION_DEVIATION = 1e-3


def format_tum_line(timestamp: float, T_world_cam: np.ndarray) -> str:
    """One ``timestamp tx ty tz qx qy qz qw`` line; TrackingError (naming the timestamp) when ``T_world_cam`` is not
    a finite rigid transform (a tracker fault, reported instead of a traceback; earlier lines stay written)."""
    T = np.asarray(T_world_cam, np.float64)
    R = T[:3, :3]
    if not np.all(np.isfinite(T)) or np.abs(R @ R.T - np.eye(3)).max() > MAX_ROTATION_DEVIATION:
        raise TrackingError(f"frame at t = {timestamp:.6f} s: the tracker produced a pose that is not a finite rigid "
                            "transform; the trajectory up to the previous frame is written")
    row = tum_rows(Trajectory(np.array([timestamp]), T[None]))[0]
    return f"{row[0]:.6f} " + " ".join(f"{x:.9f}" for x in row[1:]) + "\n"


def write_tum(traj: Trajectory, path: str | Path) -> None:
    """Write atomically (temp file + rename)."""
    rows = tum_rows(traj)
    with atomic_open(path, "w") as fh:
        fh.write("# timestamp tx ty tz qx qy qz qw\n")
        for r in rows:
            fh.write(f"{r[0]:.6f} " + " ".join(f"{x:.9f}" for x in r[1:]) + "\n")


class TumAppender:
    """Append poses line by line, each written whole with one ``write`` call, so a killed run keeps every
    finished frame and the file never ends in a torn line.

    A write error (disk full, ...) cuts the file back to its last complete line and raises
    :class:`~surfelslam.errors.OutputError` naming the file.
    """

    HEADER = "# timestamp tx ty tz qx qy qz qw\n"
    #: the low-level write (``os.write``); a class attribute so that tests can inject failures
    _write_fn = staticmethod(os.write)

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.lines = 0  # poses written
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, NEW_FILE_MODE)
        except OSError as exc:
            raise OutputError(self.path, f"cannot create the trajectory file ({os_error_text(exc)})") from None
        self._size = 0  # bytes of complete lines on disk
        self._write_line(self.HEADER)

    def append(self, timestamp: float, T_world_cam: np.ndarray) -> None:
        self._write_line(format_tum_line(timestamp, T_world_cam))
        self.lines += 1

    def _write_line(self, line: str) -> None:
        if self._fd is None:
            raise OutputError(self.path, "trajectory file already closed")
        data = line.encode("ascii")
        done = 0
        try:
            while done < len(data):
                n = self._write_fn(self._fd, data[done:])
                if n <= 0:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                done += n
        except OSError as exc:
            cut = ""
            if done:
                try:
                    os.ftruncate(self._fd, self._size)
                    os.lseek(self._fd, self._size, os.SEEK_SET)
                    cut = "; the partial line was removed"
                except OSError:
                    cut = "; the partial line could not be removed"
            raise OutputError(self.path, f"cannot write ({os_error_text(exc)}); the file keeps the "
                                         f"{self.lines} poses written before{cut}") from None
        self._size += len(data)

    def close(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            try:
                os.close(fd)
            except OSError as exc:
                raise OutputError(self.path, f"cannot close ({os_error_text(exc)})") from None

    def __enter__(self) -> TumAppender:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
