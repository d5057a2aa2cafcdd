"""Sub-pixel tracking of keypoints by Lucas-Kanade: refining matches and search by projection."""

from __future__ import annotations

import cv2
import numpy as np

from surfelslam.geometry.camera import project
from surfelslam.kernels import lk as klk
from surfelslam.tracking.features.config import FeatureConfig
from surfelslam.tracking.features.extract import Features
from surfelslam.types import Intrinsics

_LK_MAX_ITERATIONS = 30  # Lucas-Kanade stops after this many iterations per level ...
_LK_EPSILON_PX = 0.01  # ... or when its update is below this (pixels)
_MIN_WARP_DET = 1e-6  # |det| of a warp's R + t n^T / d below this: the current camera is (nearly) on the plane


def track_subpixel(ref: Features, cur: Features, pairs: np.ndarray, cfg: FeatureConfig) -> np.ndarray:
    """Current-image points of the matches ``pairs (M, 2)``: LK-tracked reference keypoints (see
    ``FeatureConfig.lk_refine``) where tracking succeeds within ``lk_max_shift_px`` of the ORB keypoint,
    the ORB keypoints elsewhere; ``(M, 2)`` float32."""
    uv = cur.keypoints_uv[pairs[:, 1]].astype(np.float32)
    if not cfg.lk_refine or ref.grey is None or cur.grey is None or len(pairs) == 0 \
            or ref.grey.shape != cur.grey.shape:
        return uv
    p1, ok = _lk(ref.grey, cur.grey, ref.keypoints_uv[pairs[:, 0]], uv, cfg)
    ok &= np.linalg.norm(p1 - uv, axis=1) <= cfg.lk_max_shift_px
    uv[ok] = p1[ok]
    return uv


def _lk(grey_from: np.ndarray, grey_to: np.ndarray, p_from: np.ndarray, p_to: np.ndarray,
        cfg: FeatureConfig) -> tuple[np.ndarray, np.ndarray]:
    """Pyramidal Lucas-Kanade of the points ``p_from (M, 2)`` starting at ``p_to (M, 2)``:
    ``(tracked (M, 2) float32, ok (M,) bool)``."""
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, _LK_MAX_ITERATIONS, _LK_EPSILON_PX)
    p0 = np.ascontiguousarray(p_from, np.float32).reshape(-1, 1, 2)
    p1 = np.ascontiguousarray(p_to, np.float32).reshape(-1, 1, 2).copy()
    p1, status, _ = cv2.calcOpticalFlowPyrLK(
        grey_from, grey_to, p0, p1, winSize=(cfg.lk_window_px, cfg.lk_window_px), maxLevel=cfg.lk_levels,
        criteria=crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    p1 = p1.reshape(-1, 2)
    return p1, status.reshape(-1).astype(bool) & np.all(np.isfinite(p1), axis=1)


def lk_warped(grey_ref: np.ndarray, grey_cur: np.ndarray, uv_ref: np.ndarray, pred: np.ndarray, z_ref: np.ndarray,
               T_cur_ref: np.ndarray, intr: Intrinsics, half: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Warped-window Lucas-Kanade of the reference pixels ``uv_ref (M, 2)`` (depth ``z_ref (M,)``) into the current
    image, starting at their projections ``pred (M, 2)`` under ``T_cur_ref``, and back (``projection_search_warp``):
    ``(found (M, 2), back (M, 2), ok (M,))``."""
    K = intr.K  # signed fy: the warp lives in the images' own pixel grid
    T = np.asarray(T_cur_ref, np.float64)
    # homography of the fronto-parallel plane z = z_ref through each point: K (R + t (0, 0, 1/z)) K^-1, ref -> cur
    G = np.broadcast_to(T[:3, :3], (len(z_ref), 3, 3)).copy()
    G[:, :, 2] += T[None, :3, 3] / np.asarray(z_ref, np.float64)[:, None]
    # singular when the current camera lies on that plane (a point at zero depth there): not tracked
    singular = ~(np.abs(np.linalg.det(G)) > _MIN_WARP_DET)
    G[singular] = np.eye(3)
    H = K @ G @ np.linalg.inv(K)
    m = len(pred)
    found = np.empty((m, 2))
    ok = np.empty(m, np.bool_)
    klk.track_warped(grey_ref, grey_cur, np.linalg.inv(H), np.ascontiguousarray(pred, np.float64), np.zeros((m, 2)),
                     half, _LK_MAX_ITERATIONS, _LK_EPSILON_PX, found, ok)
    back = np.empty((m, 2))
    ok_back = np.empty(m, np.bool_)
    start = np.ascontiguousarray(uv_ref, np.float64)
    klk.track_warped(grey_cur, grey_ref, np.ascontiguousarray(H), start, found - pred, half, _LK_MAX_ITERATIONS,
                     _LK_EPSILON_PX, back, ok_back)
    return found, back, ok & ok_back & ~singular


def search_by_projection(ref: Features, cur: Features, T_cur_ref: np.ndarray, intr: Intrinsics,
                         cfg: FeatureConfig) -> tuple[np.ndarray, np.ndarray]:
    """Reference keypoints found in the current image by projection (see ``FeatureConfig.projection_search``).

    Args:
        ref, cur: features with their grey images (same size).
        T_cur_ref: ``(4, 4)`` pose that projects the reference points into the current image.

    Returns:
        ``(points_ref (K, 3) float64, uv_cur (K, 2) float64)``: reference-camera points and their tracked
        current pixels (``K = 0`` when the grey images are missing or differ in size).
    """
    none = np.zeros((0, 3)), np.zeros((0, 2))
    if ref.grey is None or cur.grey is None or ref.grey.shape != cur.grey.shape or not ref.valid.any():
        return none
    P = ref.points_cam[ref.valid].astype(np.float64)
    uv_ref = ref.keypoints_uv[ref.valid]
    T = np.asarray(T_cur_ref, np.float64)
    u, v, z = project(P @ T[:3, :3].T + T[:3, 3], intr)
    h, w = cur.grey.shape
    half = cfg.lk_window_px // 2
    inside = (z > 0) & (u >= half) & (u <= w - 1 - half) & (v >= half) & (v <= h - 1 - half)
    if not inside.any():
        return none
    pred = np.column_stack([u[inside], v[inside]])
    if cfg.projection_search_warp:
        found, back, ok = lk_warped(ref.grey, cur.grey, uv_ref[inside], pred, P[inside, 2], T, intr, half)
    else:
        found, ok = _lk(ref.grey, cur.grey, uv_ref[inside], pred, cfg)
        back, ok_back = _lk(cur.grey, ref.grey, found, uv_ref[inside], cfg)
        ok &= ok_back
    ok &= np.linalg.norm(back - uv_ref[inside], axis=1) <= cfg.projection_search_backtrack_px
    ok &= np.linalg.norm(found - pred, axis=1) <= cfg.projection_search_tol_px
    return P[inside][ok], found[ok].astype(np.float64)
