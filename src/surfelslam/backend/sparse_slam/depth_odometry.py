"""Depth odometry of the sparse SLAM: a frame's PnP pose against its reference keyframe registered by ICP of the
frame's depth to the keyframe's (:class:`~surfelslam.backend.sparse_slam.config.DepthOdometryConfig`)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from surfelslam.backend.dense_edges import DenseEdgeRefiner
from surfelslam.backend.sparse_slam.config import DepthOdometryConfig
from surfelslam.geometry.se3 import motion_norm, so3_log
from surfelslam.tracking.features import Features, MotionResult
from surfelslam.tracking.preprocess import FramePyramid

#: Outcomes of :func:`register_depth`.
OUTCOMES = ("refined", "from_prediction", "icp_failed")


def register_depth(res: MotionResult, T_pred_cur_ref: np.ndarray, source: FramePyramid, store: DenseEdgeRefiner,
                   kf_id: int, kf_features: Features, cfg: DepthOdometryConfig,
                   max_motion_norm: float) -> tuple[MotionResult, str]:
    """``res`` (PnP against keyframe ``kf_id``, whose features are ``kf_features``) with its pose registered by ICP
    of the frame's depth ``source`` to the keyframe's depth in ``store``: from the PnP pose with its inliers when PnP
    has at least ``cfg.trust_min_inliers``, else from the prediction ``T_pred_cur_ref`` ``(4, 4)`` by depth alone.

    Returns:
        ``(result, outcome)``: ``outcome`` is ``"refined"`` (the PnP pose refined), ``"from_prediction"`` or
        ``"icp_failed"`` (``result`` is then ``res`` itself: ICP failed or moved farther than ``max_motion_norm``).
    """
    from_pnp = res.ok and res.n_inliers >= cfg.trust_min_inliers
    if from_pnp:
        inl = res.inlier_mask
        pts = kf_features.points_cam[res.pairs[inl, 0]]
        uv = None if res.uv_cur is None else res.uv_cur[inl]
        T = store.refine_frame(kf_id, source, res.T_cur_ref, pts, uv, cfg.max_shift_m, cfg.max_shift_deg)
    else:
        T = store.refine_frame(kf_id, source, T_pred_cur_ref, None, None, np.inf, np.inf)
    if T is None or motion_norm(T) > max_motion_norm:
        return res, "icp_failed"
    # a PnP pose refined keeps its information as the keyframe edge's weight; a pose from depth alone has
    # none (the graph's isotropic odometry weight)
    new = replace(res, T_cur_ref=T, ok=True, reason=None, rvec=so3_log(T[:3, :3]), tvec=T[:3, 3].copy(),
                  information=res.information if from_pnp else None)
    return new, "refined" if from_pnp else "from_prediction"
