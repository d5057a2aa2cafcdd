"""Poses between the poses of a :class:`~surfelslam.types.Trajectory`: translation linear, rotation along the
geodesic (SLERP). Ground truth at the depth camera's stamps and replayed recorded motion use it."""

from __future__ import annotations

import numpy as np

from surfelslam.geometry.se3 import so3_exp, so3_log
from surfelslam.types import Trajectory


def interpolate_poses(traj: Trajectory, stamps: np.ndarray, max_gap_s: float,
                      max_dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Pose of ``traj`` at each query stamp, interpolated between the two poses that bracket it.

    Translation is interpolated linearly and rotation along the geodesic (SLERP) when the bracketing
    poses are at most ``max_gap_s`` apart; otherwise (a gap in the trajectory, or a stamp outside it) the
    nearest pose is used if it is within ``max_dt_s`` (:meth:`~surfelslam.types.Trajectory.lookup`).

    Returns:
        ``(T_world_cam (M, 4, 4), valid (M,) bool)``, invalid rows are the identity.
    """
    stamps = np.asarray(stamps, dtype=np.float64).reshape(-1)
    T, valid = traj.lookup(stamps, max_dt_s)
    t = traj.timestamps
    if len(t) < 2:
        return T, valid
    hi = np.searchsorted(t, stamps, side="right")
    for k in np.nonzero((hi > 0) & (hi < len(t)))[0]:
        a, b = hi[k] - 1, hi[k]
        gap = t[b] - t[a]
        if not 0 < gap <= max_gap_s:
            continue
        T[k], valid[k] = pose_between(traj, a, b, (stamps[k] - t[a]) / gap), True
    return T, valid


def pose_between(traj: Trajectory, a: int, b: int, s: float) -> np.ndarray:
    """``(4, 4)`` pose the fraction ``s`` of the way from pose ``a`` to pose ``b`` of ``traj``: translation linear,
    rotation along the geodesic (SLERP); ``s`` outside [0, 1] extrapolates."""
    Ta, Tb = traj.T_world_cam[a], traj.T_world_cam[b]
    Ti = np.eye(4)
    Ti[:3, :3] = Ta[:3, :3] @ so3_exp(s * so3_log(Ta[:3, :3].T @ Tb[:3, :3]))
    Ti[:3, 3] = (1 - s) * Ta[:3, 3] + s * Tb[:3, 3]
    return Ti
