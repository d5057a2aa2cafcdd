"""Reprojection statistics: inliers within a pixel bound and the robust spread of the residuals."""

from __future__ import annotations

import numpy as np

from surfelslam.geometry.camera import project
from surfelslam.types import Intrinsics

_MAD_TO_SIGMA = 1.4826  # median absolute deviation -> standard deviation of a Gaussian


def robust_sigma(values: np.ndarray) -> float:
    """Standard deviation of ``values (N,)`` estimated from their median absolute deviation (outlier-proof)."""
    v = np.asarray(values, np.float64)
    return _MAD_TO_SIGMA * float(np.median(np.abs(v - np.median(v))))


#: Fewest points in front of the camera for :func:`reprojection_spread_px` to estimate a spread.
MIN_POINTS_FOR_SPREAD = 10


def reprojection_spread_px(points_cam: np.ndarray, uv: np.ndarray, intr: Intrinsics) -> float:
    """Robust spread (px) of the reprojection residuals of ``points_cam (N, 3)`` (camera frame, m) against their
    observed pixels ``uv (N, 2)``: :func:`robust_sigma` over both coordinates of the points in front of the camera;
    0 when fewer than :data:`MIN_POINTS_FOR_SPREAD` are."""
    X = np.asarray(points_cam, np.float64)
    uv = np.asarray(uv, np.float64)
    ok = X[:, 2] > 0
    if ok.sum() < MIN_POINTS_FOR_SPREAD:
        return 0.0
    z = X[ok, 2]
    return robust_sigma(np.concatenate([intr.fx * X[ok, 0] / z + intr.cx - uv[ok, 0],
                                        intr.fy * X[ok, 1] / z + intr.cy - uv[ok, 1]]))


def reprojection_inliers(points_cam: np.ndarray, uv: np.ndarray, intr: Intrinsics, bound_px: float) -> np.ndarray:
    """``(N,)`` bool: camera-frame points ``(N, 3)`` in front of the camera that project within ``bound_px`` of their
    pixels ``uv (N, 2)``."""
    u, v, z = project(points_cam, intr)
    return (z > 0) & (np.hypot(u - uv[:, 0], v - uv[:, 1]) < bound_px)
