"""Sparse RGB-D SLAM: ORB/PnP odometry against the last keyframe, keyframes, loops, pose graph.

Per frame (:meth:`SparseSlam.process`):

1. ORB features are extracted and matched against the reference keyframe (the last one); PnP-
   RANSAC gives ``T_cur_kf`` with the rejection rules of :mod:`surfelslam.tracking.features`.
2. Accepted: ``T_world_cam = T_world_kf T_kf_cam``. If the motion norm from the keyframe reaches
   ``keyframe_threshold`` the frame becomes a keyframe: a graph node with an odometry edge, then
   loop candidates (nearby, appearance-retrieved, random; :mod:`surfelslam.backend.loops`) are verified by PnP and
   accepted ones become robust loop edges, unless an edge to an older keyframe disagrees with the odometry chain
   between the two (chi-square gate, :mod:`surfelslam.backend.loop_consistency`). The graph is optimised whenever
   an edge to an older (non-nearby) keyframe is accepted, and in :meth:`finish`.
3. Rejected: the reason is counted and the frame gets the constant-velocity prediction
   (``rejected_pose = "constant_velocity"``) or the last pose (``"last"``); it never becomes a
   keyframe. After ``relocalise_after_failures`` consecutive rejections, :meth:`relocalise`
   searches all keyframes and, on success, tracking resumes against the keyframe found. When nothing is
   found for ``reinit_after_failures`` frames (the view after a gap shares no feature with any keyframe), a
   frame with enough keypoints starts a new segment: a keyframe at the last pose, joined to the old one by an
   edge that all but ignores the unknown motion (``reinit_sigma_*``). The first accepted edge (nearby or loop)
   from the new segment to a keyframe before it moves the segment rigidly onto it, then the graph is optimised.

With depth odometry (:class:`DepthOdometryConfig`, the orb tracker's default) step 1 also registers the frame's
depth to the reference keyframe's by point-to-plane ICP (:class:`~surfelslam.backend.dense_edges.DenseEdgeRefiner`),
jointly with the PnP inliers as reprojection terms, from the PnP pose; where PnP is weak (fewer than
``trust_min_inliers`` inliers) or rejected, from the constant-velocity prediction, without them. Features then
decide where texture is rich and geometry where it is not (plain walls, one poster in view), as RGB-D ICP mapping
does (Henry et al., IJRR 2012).

Every frame pose is stored relative to its reference keyframe, so graph corrections move whole
stretches of the trajectory rigidly with their keyframe.

Modules: :mod:`.config` (settings), :mod:`.slam` (:class:`SparseSlam`), :mod:`.graph` (the keyframes' pose graphs),
:mod:`.loop_checks` (loop-candidate verification, retrieval index), :mod:`.depth_odometry` and :mod:`.results`.
"""

from surfelslam.backend.sparse_slam.config import (
    BACK_END_PROFILE,
    REJECTED_POSE_MODES,
    DepthOdometryConfig,
    SparseProfile,
    SparseSlamConfig,
    features_for_width,
    with_profile,
)
from surfelslam.backend.sparse_slam.results import KeyframeMatch, LoopCheck, SparseFrameResult, SparseSlamResult
from surfelslam.backend.sparse_slam.slam import SparseSlam

__all__ = [
    "BACK_END_PROFILE",
    "REJECTED_POSE_MODES",
    "DepthOdometryConfig",
    "KeyframeMatch",
    "LoopCheck",
    "SparseFrameResult",
    "SparseProfile",
    "SparseSlam",
    "SparseSlamConfig",
    "SparseSlamResult",
    "features_for_width",
    "with_profile",
]
