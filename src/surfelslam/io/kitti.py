"""KITTI odometry pose files: one pose a line, the 3x4 matrix ``[R | t]`` of ``T_world_cam`` row by row, no stamps.

Written beside ``trajectory.txt`` by ``surfelslam run --format kitti`` (``trajectory_kitti.txt``), for the tools
that read KITTI's format; the line order is the TUM file's (the frames in time order).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from surfelslam.io.atomic import atomic_open
from surfelslam.types import Trajectory

#: Significant digits of each value (``%.9e``: the TUM file's nanometre and 1e-9 resolution, at any scale).
KITTI_DIGITS = 9


def format_kitti_line(T_world_cam: np.ndarray) -> str:
    """``r00 r01 r02 tx r10 r11 r12 ty r20 r21 r22 tz`` of a ``(4, 4)`` pose, newline-terminated."""
    rows = np.asarray(T_world_cam, np.float64)[:3, :4].reshape(-1)
    return " ".join(f"{x:.{KITTI_DIGITS}e}" for x in rows) + "\n"


def write_kitti(traj: Trajectory, path: str | Path) -> None:
    """Write ``traj``'s poses as a KITTI pose file, atomically (temp file + rename)."""
    with atomic_open(path, "w") as fh:
        for T in traj.T_world_cam:
            fh.write(format_kitti_line(T))


def read_kitti(path: str | Path) -> np.ndarray:
    """The ``(N, 4, 4)`` poses of a KITTI pose file (for tests and tools; no validation beyond the shape)."""
    rows = np.loadtxt(path, dtype=np.float64, ndmin=2)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :4] = rows.reshape(-1, 3, 4)
    return poses
