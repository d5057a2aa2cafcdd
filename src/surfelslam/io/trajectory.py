"""TUM trajectory files: ``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from surfelslam.errors import InputError, TrackingError
from surfelslam.io.atomic import atomic_open
from surfelslam.types import Trajectory


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory; sorts by timestamp and rejects malformed rows with the line number."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "trajectory file not found")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read trajectory file ({exc})") from None
    rows = []
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
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
        if np.linalg.norm(vals[4:8]) < 1e-6:
            raise InputError(path, f"line {lineno}: zero quaternion")
        rows.append(vals)
    if not rows:
        raise InputError(path, "trajectory file has no poses")
    arr = np.asarray(rows, dtype=np.float64)
    order = np.argsort(arr[:, 0], kind="stable")
    return Trajectory.from_tum_rows(arr[order])


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
    row = Trajectory(np.array([timestamp]), T[None]).to_tum_rows()[0]
    return f"{row[0]:.6f} " + " ".join(f"{x:.9f}" for x in row[1:]) + "\n"


def write_tum(traj: Trajectory, path: str | Path) -> None:
    """Write atomically (temp file + rename)."""
    rows = traj.to_tum_rows()
    with atomic_open(path, "w") as fh:
        fh.write("# timestamp tx ty tz qx qy qz qw\n")
        for r in rows:
            fh.write(f"{r[0]:.6f} " + " ".join(f"{x:.9f}" for x in r[1:]) + "\n")


class TumAppender:
    """Append poses line by line, flushed per frame, so a killed run keeps every finished frame."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = open(self.path, "w")  # noqa: SIM115 - closed in close()
        self._fh.write("# timestamp tx ty tz qx qy qz qw\n")
        self._fh.flush()

    def append(self, timestamp: float, T_world_cam: np.ndarray) -> None:
        self._fh.write(format_tum_line(timestamp, T_world_cam))
        self._fh.flush()

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.close()

    def __enter__(self) -> TumAppender:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
