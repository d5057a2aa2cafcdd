"""Result types of the sparse SLAM: per frame, per run, keyframe matches and verified loop candidates."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surfelslam.backend.dense_edges import RefinedEdge
from surfelslam.backend.loops import Candidate
from surfelslam.tracking.features import MotionResult
from surfelslam.types import Trajectory


@dataclass(frozen=True)
class LoopCheck:
    """One verified loop candidate of a new keyframe (:meth:`.loop_checks.LoopChecker.check`).

    Attributes:
        candidate: the candidate keyframe and where it came from.
        result: its PnP verification (``result.T_cur_ref`` maps candidate points into the new keyframe).
        refined: the dense-refined edge (its ``T_cur_ref`` and information shape), or ``None`` (no refiner, PnP
            failed, or the dense check rejected the edge).
        dense_rejected: the PnP edge passed but the dense check rejected it (it then enters the PnP graph only).
        depth_only: PnP failed on this nearby candidate and ``refined`` is ICP from the graph's relative pose, by
            depth alone (``DenseEdgeConfig.depth_only_nearby``; it enters the refined edges' graph only).
    """

    candidate: Candidate
    result: MotionResult
    refined: RefinedEdge | None = None
    dense_rejected: bool = False
    depth_only: bool = False


@dataclass
class KeyframeMatch:
    """A frame registered to a keyframe by PnP (:meth:`SparseSlam.match_reference_keyframe`).

    Attributes:
        T_world_cam: ``(4, 4)`` the frame's pose (graph world frame).
        kf_id: the keyframe matched.
        points_world: ``(M, 3)`` float64 the PnP inliers' keyframe points (from the keyframe's depth), world frame.
        uv_cur: ``(M, 2)`` float64 their pixels in the frame (full resolution, sub-pixel tracked).
    """

    T_world_cam: np.ndarray
    kf_id: int
    points_world: np.ndarray
    uv_cur: np.ndarray


@dataclass
class SparseFrameResult:
    """Outcome of one :meth:`SparseSlam.process` call.

    Attributes:
        T_world_cam: ``(4, 4)`` current estimate of the frame's pose.
        is_keyframe: the frame became a keyframe.
        ok: odometry accepted (False: ``reason`` names the rejection rule).
        n_inliers: PnP inliers against the reference keyframe (-1: not computed, a dense pose was given).
        loops_added: edges to older keyframes accepted for this keyframe (nearby edges excluded).
        relocalised: the pose came from :meth:`SparseSlam.relocalise`.
        depth_only: the pose came from the depth odometry alone, from the prediction (PnP found too few inliers
            to be trusted): along directions the depth leaves free (a plain wall, a corridor) it is the prediction.
    """

    T_world_cam: np.ndarray
    is_keyframe: bool
    ok: bool
    reason: str | None
    n_inliers: int
    loops_added: int
    relocalised: bool = False
    depth_only: bool = False


@dataclass
class SparseSlamResult:
    """Outcome of :meth:`SparseSlam.finish`.

    Attributes:
        trajectory: every processed frame, after the final optimisation.
        keyframe_indices: ``(K,)`` frame index of each keyframe.
        keyframe_poses: ``(K, 4, 4)`` optimised ``T_world_kf``.
        loops_found: ``[(kf_old, kf_new, n_inliers)]`` older-keyframe candidates whose PnP succeeded.
        loops_accepted: the subset that became graph edges.
        n_nearby_edges: accepted edges to nearby keyframes.
        rejected: ``{reason: count}`` of rejected frames.
        map_xyz: ``(M, 3)`` float32 world points (voxel-filtered keyframe clouds).
        map_rgb: ``(M, 3)`` uint8 colours.
    """

    trajectory: Trajectory
    keyframe_indices: np.ndarray
    keyframe_poses: np.ndarray
    loops_found: list[tuple[int, int, int]]
    loops_accepted: list[tuple[int, int, int]]
    n_nearby_edges: int
    rejected: dict[str, int]
    map_xyz: np.ndarray
    map_rgb: np.ndarray
