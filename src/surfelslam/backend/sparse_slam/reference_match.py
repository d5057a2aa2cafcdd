"""A frame matched against one keyframe, in the graph's world frame: by its own ORB features and PnP, or by the
keyframe's points tracked into it (:meth:`SparseSlam.match_reference_keyframe`,
:meth:`SparseSlam.track_reference_keyframe`)."""

from __future__ import annotations

import numpy as np

from surfelslam.backend.sparse_slam.results import KeyframeMatch
from surfelslam.geometry.se3 import invert, transform_points
from surfelslam.tracking.features import FeatureConfig, Features, estimate_motion
from surfelslam.tracking.features.keyframe_track import KeyframePoints, track_keyframe
from surfelslam.types import Intrinsics


def match_in_world(kf: int, T_world_kf: np.ndarray, T_cur_ref: np.ndarray, points_kf: np.ndarray,
                   uv_cur: np.ndarray) -> KeyframeMatch:
    """The match of a frame at ``T_cur_ref`` against keyframe ``kf`` (at ``T_world_kf``; its points ``(M, 3)``,
    their pixels ``(M, 2)`` in the frame) in the world frame."""
    return KeyframeMatch(T_world_kf @ invert(T_cur_ref), kf, transform_points(T_world_kf, points_kf.astype(np.float64)),
                         uv_cur.astype(np.float64))


def pnp_match(kf: int, T_world_kf: np.ndarray, ref: Features, feats: Features, T_world_cam_pred: np.ndarray | None,
              intr: Intrinsics, cfg: FeatureConfig) -> KeyframeMatch | None:
    """PnP of the frame's features ``feats`` against keyframe ``kf``'s ``ref`` (from the prediction, if any);
    ``None`` when a rejection rule fired."""
    init = None if T_world_cam_pred is None else invert(T_world_cam_pred) @ T_world_kf
    res = estimate_motion(ref, feats, intr, cfg, init)
    if not res.ok or res.uv_cur is None:
        return None
    inl = res.inlier_mask
    return match_in_world(kf, T_world_kf, res.T_cur_ref, ref.points_cam[res.pairs[inl, 0]], res.uv_cur[inl])


def tracked_match(kf: int, T_world_kf: np.ndarray, ref: Features, grey: np.ndarray, T_world_cam_pred: np.ndarray,
                  intr: Intrinsics, cfg: FeatureConfig, points: KeyframePoints | None = None) -> KeyframeMatch | None:
    """Keyframe ``kf``'s points (``ref``) tracked into the frame ``grey (H, W)`` from the prediction
    (:func:`~surfelslam.tracking.features.keyframe_track.track_keyframe`; ``points``: the keyframe's selected points
    kept between frames); ``None`` when too few are found."""
    tracked = track_keyframe(ref, grey, invert(T_world_cam_pred) @ T_world_kf, intr, cfg, points)
    return None if tracked is None else match_in_world(kf, T_world_kf, tracked.T_cur_ref, tracked.points_ref,
                                                       tracked.uv_cur)
