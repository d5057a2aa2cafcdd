"""Joint RGB-D refinement of a PnP pose: reprojection plus inverse-depth residuals (Gauss-Newton, Huber).

:func:`refine_rgbd` runs the numba kernel :func:`surfelslam.kernels.rgbd_refine.rgbd_refine`; :func:`refine_rgbd_ref`
is its numpy reference.
"""

from __future__ import annotations

import numpy as np

from surfelslam.geometry.se3 import exp as se3_exp
from surfelslam.kernels.rgbd_refine import rgbd_refine
from surfelslam.tracking.features.config import FeatureConfig
from surfelslam.tracking.features.reprojection import MIN_POINTS_FOR_SPREAD, reprojection_spread_px, robust_sigma
from surfelslam.types import Intrinsics

_MIN_POINTS_FOR_SPREAD = 6  # fewest depth residuals to estimate their spread from the data
_RGBD_CONVERGED_UPDATE = 1e-9  # twist norm (rad + m) below which the RGB-D refinement stops


def _rgbd_system(T: np.ndarray, P: np.ndarray, uv: np.ndarray, q: np.ndarray, w_inv: np.ndarray, sp: float,
                 si: float, intr: Intrinsics, cfg: FeatureConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """Huber-weighted normal equations ``(H (6, 6), g (6,))`` of the joint refinement at ``T`` (left update
    ``exp(xi) T``, ``xi = (omega, v)``; residuals normalised by their sigmas: ``sp`` px, ``si`` 1/m);
    ``None`` if a point is behind."""
    X = P @ T[:3, :3].T + T[:3, 3]
    z = X[:, 2]
    if np.any(z <= 0):
        return None
    n = len(P)
    fx, fy = intr.fx, intr.fy
    k = cfg.rgbd_huber
    iz = 1.0 / z
    # d(point)/d(xi) for a left update exp(xi) T: dX = -[X]x omega + v
    J_X = np.zeros((n, 3, 6))
    J_X[:, 0, 1], J_X[:, 0, 2] = X[:, 2], -X[:, 1]
    J_X[:, 1, 0], J_X[:, 1, 2] = -X[:, 2], X[:, 0]
    J_X[:, 2, 0], J_X[:, 2, 1] = X[:, 1], -X[:, 0]
    J_X[:, 0, 3] = J_X[:, 1, 4] = J_X[:, 2, 5] = 1.0
    # projection u = fx x/z + cx, v = fy y/z + cy; inverse depth 1/z
    J_u = np.zeros((n, 3, 3))
    J_u[:, 0, 0] = fx * iz
    J_u[:, 0, 2] = -fx * X[:, 0] * iz * iz
    J_u[:, 1, 1] = fy * iz
    J_u[:, 1, 2] = -fy * X[:, 1] * iz * iz
    J_u[:, 2, 2] = -iz * iz
    J = J_u @ J_X  # (n, 3, 6)
    r = np.empty((n, 3))
    r[:, 0] = (fx * X[:, 0] * iz + intr.cx - uv[:, 0]) / sp
    r[:, 1] = (fy * X[:, 1] * iz + intr.cy - uv[:, 1]) / sp
    r[:, 2] = np.where(w_inv, (iz - q) / si, 0.0)
    J[:, :2] /= sp
    J[:, 2] = np.where(w_inv[:, None], J[:, 2] / si, 0.0)
    a = np.abs(r)
    w = np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))
    Jf = J.reshape(-1, 6)  # one row per residual: two BLAS products instead of a three-operand einsum
    Jw = Jf * w.reshape(-1, 1)
    H = Jw.T @ Jf
    g = Jw.T @ r.reshape(-1)
    return H, g


def refine_rgbd(T_cur_ref: np.ndarray, pts_ref: np.ndarray, uv_cur: np.ndarray, inv_depth_cur: np.ndarray,
                intr: Intrinsics, cfg: FeatureConfig, with_information: bool = False):
    """Joint reprojection + inverse-depth refinement of ``T_cur_ref``: :func:`refine_rgbd_ref` (arguments and
    results) in a numba kernel."""
    T0 = np.ascontiguousarray(T_cur_ref, np.float64)
    P = np.ascontiguousarray(pts_ref, np.float64).reshape(-1, 3)
    uv = np.ascontiguousarray(uv_cur, np.float64).reshape(-1, 2)
    inv = np.asarray(inv_depth_cur, np.float64)
    w_inv = np.isfinite(inv)
    q = np.where(w_inv, inv, 0.0)
    T = np.empty((4, 4))
    H = np.empty((6, 6))
    has_info = rgbd_refine(T0, P, uv, q, w_inv, float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy),
                           int(cfg.rgbd_refine_iterations), float(cfg.rgbd_huber), MIN_POINTS_FOR_SPREAD,
                           float(cfg.rgbd_pixel_sigma_px), float(cfg.rgbd_min_pixel_sigma_px), _MIN_POINTS_FOR_SPREAD,
                           float(cfg.rgbd_inverse_depth_sigma), _RGBD_CONVERGED_UPDATE, with_information, T, H)
    if not with_information:
        return T
    return T, (H if has_info else None)


def refine_rgbd_ref(T_cur_ref: np.ndarray, pts_ref: np.ndarray, uv_cur: np.ndarray, inv_depth_cur: np.ndarray,
                    intr: Intrinsics, cfg: FeatureConfig, with_information: bool = False):
    """Joint reprojection + inverse-depth refinement of ``T_cur_ref`` (see ``FeatureConfig.rgbd_refine_iterations``).

    Args:
        T_cur_ref: ``(4, 4)`` initial pose (PnP).
        pts_ref: ``(N, 3)`` reference-camera points; uv_cur: ``(N, 2)`` their pixels in the current image.
        inv_depth_cur: ``(N,)`` measured inverse depth (1/m) at ``uv_cur``; NaN = none (reprojection only).
        with_information: also return the information matrix of the result.

    Returns:
        ``(4, 4)`` refined ``T_cur_ref`` (Gauss-Newton with Huber weights, left-multiplied SE(3) updates); with
        ``with_information``, ``(T, information)`` where ``information (6, 6)`` is the Gauss-Newton Hessian at
        ``T`` in normalised residual units, for a left perturbation ``exp(xi) T``, ``xi = (omega, v)``
        (``None`` when it cannot be formed): the inverse covariance of the pose under the residual sigmas (the
        points' own spreads: pixels at least ``rgbd_min_pixel_sigma_px``, inverse depth at least
        ``rgbd_inverse_depth_sigma``; see :class:`FeatureConfig`).
    """
    T = np.asarray(T_cur_ref, np.float64).copy()
    P = np.asarray(pts_ref, np.float64)
    uv = np.asarray(uv_cur, np.float64)
    w_inv = np.isfinite(inv_depth_cur)
    q = np.where(w_inv, inv_depth_cur, 0.0)
    si_model = cfg.rgbd_inverse_depth_sigma

    def pixel_sigma(T: np.ndarray) -> float:
        """The data's own reprojection spread (px), at least ``rgbd_min_pixel_sigma_px``."""
        if len(P) < MIN_POINTS_FOR_SPREAD:
            return cfg.rgbd_pixel_sigma_px
        return max(cfg.rgbd_min_pixel_sigma_px, reprojection_spread_px(P @ T[:3, :3].T + T[:3, 3], uv, intr))

    def spread(T: np.ndarray) -> float:
        """The data's own inverse-depth spread, when it exceeds the model (``si_model``)."""
        if w_inv.sum() < _MIN_POINTS_FOR_SPREAD:
            return si_model
        z = P[w_inv] @ T[2, :3] + T[2, 3]
        return max(si_model, robust_sigma(1.0 / z - q[w_inv]))

    for _ in range(cfg.rgbd_refine_iterations):
        if np.any(P @ T[2, :3] + T[2, 3] <= 0):
            break
        system = _rgbd_system(T, P, uv, q, w_inv, pixel_sigma(T), spread(T), intr, cfg)
        if system is None:
            break
        H, g = system
        try:
            xi = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        T = se3_exp(xi) @ T
        if np.linalg.norm(xi) < _RGBD_CONVERGED_UPDATE:
            break
    if not with_information:
        return T
    finite = bool(np.all(np.isfinite(T)))
    system = _rgbd_system(T, P, uv, q, w_inv, pixel_sigma(T), spread(T), intr, cfg) if finite else None
    info = None if system is None or not np.all(np.isfinite(system[0])) else system[0]
    return T, info
