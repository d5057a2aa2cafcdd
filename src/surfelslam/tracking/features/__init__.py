"""Sparse feature odometry: ORB keypoints with depth, Hamming matching, PnP-RANSAC.

The pipeline follows the feature-based RGB-D tutorial of the reference assignment:

1. :func:`extract` detects ORB keypoints spread over the image (retain-best per grid cell), computes
   their descriptors and lifts each keypoint to 3D with the depth image (camera frame).
2. :func:`match` pairs descriptors of a reference and a current frame (cross-check or ratio test)
   and keeps the "good" matches, whose Hamming distance is below ``k * max(min_distance, floor)``.
3. :func:`estimate_motion` solves PnP-RANSAC with 3D points from the *reference* frame and 2D
   keypoints of the *current* frame, refines on the inliers, and applies the rejection rules
   (too few good matches, too few inliers, motion norm too large). The solution maps reference
   camera points into the current camera: ``T_cur_ref``.

Modules: :mod:`.config` (:class:`FeatureConfig`), :mod:`.extract` (detection, :class:`Features`), :mod:`.depth`
(keypoint depth, occluding contours), :mod:`.matching`, :mod:`.subpixel` (Lucas-Kanade, search by projection),
:mod:`.reprojection` (inliers, residual spread), :mod:`.refine` (joint RGB-D refinement) and :mod:`.motion`
(PnP-RANSAC, :func:`estimate_motion`; negative ``fy``).
"""

from surfelslam.tracking.features.config import DETECTORS, MATCHING_MODES, FeatureConfig, with_max_motion_norm
from surfelslam.tracking.features.depth import keypoint_depth, on_occluding_contour
from surfelslam.tracking.features.extract import Features, bucket_keypoints, extract, to_grey
from surfelslam.tracking.features.matching import MatchResult, match
from surfelslam.tracking.features.motion import REJECT_REASONS, MotionResult, estimate_motion, feature_guess
from surfelslam.tracking.features.refine import refine_rgbd
from surfelslam.tracking.features.reprojection import (
    MIN_POINTS_FOR_SPREAD,
    reprojection_inliers,
    reprojection_spread_px,
    robust_sigma,
)
from surfelslam.tracking.features.subpixel import lk_warped, search_by_projection, track_subpixel

__all__ = [
    "DETECTORS",
    "MATCHING_MODES",
    "MIN_POINTS_FOR_SPREAD",
    "REJECT_REASONS",
    "FeatureConfig",
    "Features",
    "MatchResult",
    "MotionResult",
    "bucket_keypoints",
    "estimate_motion",
    "extract",
    "feature_guess",
    "keypoint_depth",
    "lk_warped",
    "match",
    "on_occluding_contour",
    "refine_rgbd",
    "reprojection_inliers",
    "reprojection_spread_px",
    "robust_sigma",
    "search_by_projection",
    "to_grey",
    "track_subpixel",
    "with_max_motion_norm",
]
