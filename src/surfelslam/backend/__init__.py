"""Sparse SLAM back end: keyframes, loop closure, descriptor retrieval and the gtsam pose graph."""

from surfelslam.backend.pose_graph import PoseEdge, PoseGraph, PoseGraphConfig, optimise
from surfelslam.backend.sparse_slam import SparseFrameResult, SparseSlam, SparseSlamConfig, SparseSlamResult

__all__ = [
    "PoseEdge",
    "PoseGraph",
    "PoseGraphConfig",
    "SparseFrameResult",
    "SparseSlam",
    "SparseSlamConfig",
    "SparseSlamResult",
    "optimise",
]
