"""The sparse SLAM itself (:class:`SparseSlam`): per-frame ORB/PnP tracking against the reference keyframe, keyframe
decisions, relocalisation and re-initialisation (see :mod:`surfelslam.backend.sparse_slam`)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from surfelslam.backend.dense_edges import DenseEdgeRefiner
from surfelslam.backend.keyframes import Keyframe, joined_clouds, keyframe_cloud
from surfelslam.backend.loops import verify_edge
from surfelslam.backend.pose_graph import PoseEdge
from surfelslam.backend.sparse_slam.config import (
    BACK_END_PROFILE,
    DepthOdometryConfig,
    SparseSlamConfig,
    features_for_width,
    with_profile,
)
from surfelslam.backend.sparse_slam.depth_odometry import register_depth
from surfelslam.backend.sparse_slam.graph import KeyframeGraph
from surfelslam.backend.sparse_slam.loop_checks import LoopChecker
from surfelslam.backend.sparse_slam.reference_match import pnp_match, tracked_match
from surfelslam.backend.sparse_slam.results import KeyframeMatch, LoopCheck, SparseFrameResult, SparseSlamResult
from surfelslam.geometry.se3 import invert, motion_norm, orthonormalize
from surfelslam.tracking.features import Features, MotionResult, estimate_motion, extract
from surfelslam.tracking.features.keyframe_track import KeyframePoints
from surfelslam.tracking.photometric import colour_switch
from surfelslam.tracking.preprocess import FramePyramid
from surfelslam.types import Intrinsics, RGBDFrame, Trajectory

#: Rejected frames in a row before relocalisation, when the caller does not say (the trackers' default, frames).
RELOCALISE_AFTER_FAILURES = 3


class SparseSlam:
    """Frame-by-frame sparse SLAM (see the package docstring, :mod:`surfelslam.backend.sparse_slam`).

    Args:
        intr: intrinsics of the frames that will be processed (``fy`` may be negative).
        cfg: settings.
        T_world_first: pose of the first frame (default identity).
        edge_refiner: optional dense check of keyframe edges (:mod:`~surfelslam.backend.dense_edges`): every
            PnP-verified edge (nearby or loop) is refined by ICP between the keyframes' depth maps, or dropped when
            that fails. While the refined edges are not consistent enough to be trusted, the poses come from the PnP
            edges' graph.
        refined_robust_scale: scale (whitened units) of the loop kernel on refined edges (``None``: the config's).
        cloud_rgb: the colour of each depth pixel of a frame for the keyframe clouds, ``(H, W, 3)`` uint8 (``None``:
            ``frame.rgb``; e.g. colour sampled through a separate colour camera).
        refine_edges: use ``edge_refiner`` for the keyframe edges (False: it only serves the depth odometry).
        depth_odometry: register frames to the reference keyframe by ICP too (package docstring; needs
            ``edge_refiner``, which keeps the keyframes' depth); ``None`` or disabled: PnP alone.
        colour_registered: whether colour is registered to depth (``RGBDSequence.colour_registered``): with
            ``loop.pnp_nearby_edges = "auto"`` PnP edges to nearby keyframes enter the PnP graph only then.
        coarse_rgbd_refine: the coarse match (:meth:`match_reference_keyframe`) keeps the joint RGB-D refinement of
            the pose (``features.rgbd_refine_iterations``).
        keyframe_clouds: keep each keyframe's voxel-filtered cloud for :meth:`map_points` (False: the map is made
            elsewhere, e.g. the hybrid's surfels; :meth:`map_points` is then empty).
        relocalise_after_failures: rejected frames in a row after which relocalisation is tried; 0 = never (the
            trackers pass ``[tracking] relocalise_after_failures``).
    """

    def __init__(self, intr: Intrinsics, cfg: SparseSlamConfig | None = None,
                 T_world_first: np.ndarray | None = None, edge_refiner: DenseEdgeRefiner | None = None,
                 refined_robust_scale: float | None = None,
                 cloud_rgb: Callable[[RGBDFrame], np.ndarray] | None = None, refine_edges: bool = True,
                 depth_odometry: DepthOdometryConfig | None = None, colour_registered: bool = True,
                 coarse_rgbd_refine: bool = False, keyframe_clouds: bool = True,
                 relocalise_after_failures: int = RELOCALISE_AFTER_FAILURES) -> None:
        self.intr = intr
        self._relocalise_after = relocalise_after_failures
        # keys a tracker's profile left unset (none) take the back end's own values
        self.cfg = features_for_width(with_profile(cfg or SparseSlamConfig(), BACK_END_PROFILE), intr.width)
        # the settings of ``match_reference_keyframe(coarse=True)``: PnP-RANSAC and its inlier refinement, without
        # search by projection (and without the RGB-D refinement unless coarse_rgbd_refine)
        rgbd_iterations = self.cfg.features.rgbd_refine_iterations if coarse_rgbd_refine else 0
        self._coarse_features = replace(self.cfg.features, projection_search=False,
                                        rgbd_refine_iterations=rgbd_iterations)
        self._depth_cfg = depth_odometry if depth_odometry is not None and depth_odometry.enabled else None
        if self._depth_cfg is not None and edge_refiner is None:
            raise ValueError("depth odometry needs an edge_refiner (the keyframes' depth store)")
        self._store = edge_refiner  # keyframe depth (edge refinement and depth odometry)
        self._refiner = edge_refiner if refine_edges else None
        # frames whose PnP pose ICP refined / that ICP tracked from the prediction (of them: PnP rejected) / where
        # ICP failed (the PnP pose or the rejection stands)
        self.depth_counts = {"refined": 0, "from_prediction": 0, "rescued": 0, "icp_failed": 0}
        self._cloud_rgb = cloud_rgb
        self._keyframe_clouds = keyframe_clouds
        self._T_world_first = np.eye(4) if T_world_first is None else np.asarray(T_world_first, np.float64)
        self._kfs: list[Keyframe] = []
        pnp_nearby = colour_switch(self.cfg.loop.pnp_nearby_edges, colour_registered)
        self._graph = KeyframeGraph(self.cfg.graph, self._refiner, refined_robust_scale, self.cfg.loop.consistency,
                                    pnp_nearby)
        self._loops = LoopChecker(intr, self.cfg.features, self.cfg.loop, self._refiner, self._kfs)
        self._ref_kf = -1
        self._ref_points = KeyframePoints()  # the reference keyframe's points tracked into each frame
        # per processed frame: timestamp, reference keyframe, pose relative to it
        self._timestamps: list[float] = []
        self._frame_kf: list[int] = []
        self._frames_since_kf = 0  # frames placed since the last keyframe was added
        self._T_kf_cam: list[np.ndarray] = []
        self._velocity = np.eye(4)  # T_prev_last: last inter-frame motion (camera frame)
        self._n_failures = 0
        self.rejected: Counter[str] = Counter()
        self._unreported_loops = 0  # loops applied since the last frame result
        self.n_reinitialisations = 0  # segments started after a long loss
        self._lost: list[tuple[int, Features]] = []  # (frame slot, features) of the lost frames in a row
        self.n_lost_placed = 0  # lost frames placed afterwards against the keyframe of a new segment

    # --- state: the keyframe graph's edges, loops and poses -------------------------------------------
    @property
    def dense_edges_trusted(self) -> bool | None:
        """Whether the poses come from the dense-refined edges' graph (else the PnP edges'); ``None``: no refiner."""
        return None if self._refiner is None else self._graph.refined_trusted

    def dense_edge_stats(self) -> dict[str, float | bool | None]:
        """The refined edges' gate by their ``metrics.json`` names (:meth:`KeyframeGraph.dense_edge_stats`)."""
        return self._graph.dense_edge_stats()

    @property
    def loops_found(self) -> list[tuple[int, int, int]]:
        """``[(kf_old, kf_new, n_inliers)]`` older-keyframe candidates whose PnP succeeded."""
        return self._graph.loops_found

    @property
    def loops_accepted(self) -> list[tuple[int, int, int]]:
        """The subset of :attr:`loops_found` that became graph edges."""
        return self._graph.loops_accepted

    @property
    def edge_counts(self) -> dict[str, int]:
        """The keyframe graph's edge and segment counts by ``metrics.json`` name (:meth:`KeyframeGraph.edge_counts`)."""
        return self._graph.edge_counts()

    @property
    def n_keyframes(self) -> int:
        return len(self._kfs)

    @property
    def _kf_poses(self) -> np.ndarray:
        return self._graph.poses

    def keyframe_poses(self) -> np.ndarray:
        """Current (optimised) keyframe poses ``T_world_kf`` ``(K, 4, 4)``; ids = keyframe ids."""
        return self._kf_poses.copy()

    def keyframe_pose(self, k: int) -> np.ndarray:
        """Keyframe ``k``'s current pose ``T_world_kf`` ``(4, 4)``, a copy of it alone (not of every pose)."""
        return self._kf_poses[k].copy()

    def keyframe_frame_indices(self) -> np.ndarray:
        """``(K,)`` frame index of each keyframe."""
        return np.array([k.frame_index for k in self._kfs], dtype=np.int64)

    def _last_pose(self) -> np.ndarray:
        return self._kf_poses[self._frame_kf[-1]] @ self._T_kf_cam[-1]

    def _predict(self) -> np.ndarray:
        """Constant-velocity prediction of the next ``T_world_cam``."""
        return orthonormalize(self._last_pose() @ self._velocity)

    # --- processing ----------------------------------------------------------------------------------

    def features(self, frame: RGBDFrame) -> Features:
        """ORB features of ``frame`` with this SLAM's settings (thread-safe: no state is touched).

        Pass them as ``feats`` to :meth:`process`, :meth:`relocalise` or
        :meth:`match_reference_keyframe` so a frame is extracted once (possibly ahead, in another thread).
        """
        return extract(frame.rgb, frame.depth_m, self.intr, self.cfg.features)

    @property
    def uses_depth(self) -> bool:
        """Whether frames are registered by ICP too (depth odometry), i.e. :meth:`process` uses a
        :meth:`depth_pyramid`."""
        return self._depth_cfg is not None

    def depth_pyramid(self, frame: RGBDFrame) -> FramePyramid | None:
        """The frame's depth pyramid for the depth odometry (thread-safe; ``None`` without depth odometry).

        Pass it as ``depth_pyramid`` to :meth:`process` so it can be built ahead, in another thread."""
        return None if self._depth_cfg is None else self._store.frame_pyramid(frame.depth_m)

    def process(self, frame: RGBDFrame, T_world_cam_dense: np.ndarray | None = None,
                feats: Features | None = None, depth_pyramid: FramePyramid | None = None,
                tracker_pyramid: FramePyramid | None = None) -> SparseFrameResult:
        """Track one frame; may add a keyframe, loop edges and re-optimise the graph.

        Args:
            frame: the next frame (any resolution matching ``intr``).
            T_world_cam_dense: optional pose from another tracker (hybrid mode). When given it is the
                frame's pose and the odometry measurement of a new keyframe, and no PnP runs here (the
                keyframe decision uses that pose; the hybrid tracker does its own PnP check); features are
                extracted only for a new keyframe.
            feats: the frame's :meth:`features`, when already extracted.
            depth_pyramid: the frame's :meth:`depth_pyramid`, when already built.
            tracker_pyramid: with ``T_world_cam_dense``, the other tracker's pyramid of the frame (its preprocessing
                settings, finest level computed): if the frame becomes a keyframe, its loop checks start from a copy
                of it instead of rebuilding it (:meth:`DenseEdgeRefiner.keyframe_pyramid`).
        """
        if T_world_cam_dense is not None and self._kfs:
            return self._process_posed(frame, np.asarray(T_world_cam_dense, np.float64), feats, tracker_pyramid)
        feats = self.features(frame) if feats is None else feats
        if not self._kfs:
            T0 = self._T_world_first if T_world_cam_dense is None else np.asarray(T_world_cam_dense, np.float64)
            self._add_keyframe(frame, feats, T0, None, None)
            self._record(frame.timestamp, 0, np.eye(4), None)
            return SparseFrameResult(T0.copy(), True, True, None, 0, 0)

        T_pred = self._predict()
        T_world_kf = self._kf_poses[self._ref_kf]
        ref = self._kfs[self._ref_kf]
        relocalised = False
        information = None  # of the measurement behind a new keyframe's edge (None: isotropic)
        depth_only = False  # this frame's pose comes from depth alone (no trusted PnP)
        T_pred_cur_ref = invert(T_pred) @ T_world_kf
        res = estimate_motion(ref.features, feats, self.intr, self.cfg.features, T_init_cur_ref=T_pred_cur_ref)
        if self._depth_cfg is not None:
            pyr = self.depth_pyramid(frame) if depth_pyramid is None else depth_pyramid
            res, depth_only = self._with_depth(res, T_pred_cur_ref, pyr)
        if res.ok:
            T_kf_cam = invert(res.T_cur_ref)
            T_world_cam = T_world_kf @ T_kf_cam
            ok = True
            information = res.information
        else:
            ok = False
            self.rejected[res.reason or "pnp_failed"] += 1
            self._n_failures += 1
            reloc = None
            if 0 < self._relocalise_after <= self._n_failures:
                reloc = self._relocalise_features(feats)
            if reloc is None and self._may_reinitialise(feats):
                return self._reinitialise(frame, feats, res)
            if reloc is None:
                extrapolate = (self.cfg.rejected_pose == "constant_velocity"
                               and self._n_failures <= self.cfg.velocity_reset_after_failures)
                T_world_cam = T_pred if extrapolate else self._last_pose()
                if self.cfg.reinit_after_failures > 0:  # a new segment may place it later (_reinitialise)
                    self._lost.append((len(self._timestamps), feats))
                    del self._lost[: max(0, len(self._lost) - self.cfg.reinit_after_failures)]  # the last ones
                self._record(frame.timestamp, self._ref_kf, invert(T_world_kf) @ T_world_cam, T_world_cam)
                return SparseFrameResult(T_world_cam.copy(), False, False, res.reason, res.n_inliers, 0)
            # Relocalised: the keyframe rule below applies as to a tracked frame. From the keyframe it was found
            # against, the next frames are as far as this one (up to relocalise_max_norm), beyond the odometry's
            # motion bound, so without a keyframe here every one of them was rejected and relocalised again.
            T_world_cam, self._ref_kf, reloc_res = reloc
            relocalised = True
            T_kf_cam = invert(self._kf_poses[self._ref_kf]) @ T_world_cam
            information = reloc_res.information

        T_world_cam, is_kf = self._keyframe_or_record(frame, feats, T_world_cam, T_kf_cam, information)
        if relocalised:
            self._velocity = np.eye(4)  # the motion across the loss is unknown
            return SparseFrameResult(T_world_cam.copy(), is_kf, False, res.reason, res.n_inliers, 0, True)
        if depth_only and self._depth_cfg.hold_after_depth_only:
            self._velocity = np.eye(4)  # its step along the depth's free directions is the prediction: not fed back
        loops_added, self._unreported_loops = self._unreported_loops, 0
        return SparseFrameResult(T_world_cam.copy(), is_kf, ok, None, res.n_inliers, loops_added,
                                 depth_only=depth_only)

    def _process_posed(self, frame: RGBDFrame, T_world_cam: np.ndarray, feats: Features | None,
                       pyramid: FramePyramid | None) -> SparseFrameResult:
        """:meth:`process` of a frame posed by another tracker (after the first keyframe): it becomes a keyframe
        when far enough from the reference one (its features extracted then, unless given), with the dense pose
        as the odometry measurement (isotropic weight)."""
        T_kf_cam = invert(self._kf_poses[self._ref_kf]) @ T_world_cam
        T_world_cam, is_kf = self._keyframe_or_record(frame, feats, T_world_cam, T_kf_cam, pyramid=pyramid)
        loops_added, self._unreported_loops = self._unreported_loops, 0
        return SparseFrameResult(T_world_cam.copy(), is_kf, True, None, -1, loops_added)

    def promote_last_frame(self, frame: RGBDFrame, feats: Features | None = None) -> bool:
        """Before :meth:`finish`: the last processed frame (``frame``, placed against the reference keyframe) becomes a
        keyframe at its pose, so the graph corrects the frames after the last keyframe too. Returns whether it did."""
        if not self._timestamps or self._frame_kf[-1] != self._ref_kf or self._kfs[-1].frame_index == frame.index:
            return False
        ref, T_kf_cam = self._frame_kf.pop(), self._T_kf_cam.pop()
        self._timestamps.pop()
        self._add_keyframe(frame, self.features(frame) if feats is None else feats,
                           self._kf_poses[ref] @ T_kf_cam, ref, T_kf_cam)
        self._record(frame.timestamp, self.n_keyframes - 1, np.eye(4), None)
        return True

    def becomes_keyframe(self, T_world_cam: np.ndarray) -> bool:
        """Whether a frame posed at ``T_world_cam`` by another tracker, processed next, becomes a keyframe (its
        features can then be extracted ahead). State is unchanged."""
        return not self._kfs or self._is_keyframe(invert(self._kf_poses[self._ref_kf]) @ T_world_cam,
                                                  self._frames_since_kf + 1)

    def _is_keyframe(self, T_kf_cam: np.ndarray, frames_since_kf: int) -> bool:
        """The keyframe rule: far enough from the reference keyframe, and not too soon after it."""
        return (motion_norm(T_kf_cam) >= self.cfg.keyframe_threshold
                and frames_since_kf >= self.cfg.keyframe_min_gap_frames)

    def _keyframe_or_record(self, frame: RGBDFrame, feats: Features | None, T_world_cam: np.ndarray,
                            T_kf_cam: np.ndarray, information: np.ndarray | None = None,
                            pyramid: FramePyramid | None = None) -> tuple[np.ndarray, bool]:
        """A placed frame: a keyframe when far enough from the reference one (features extracted then, unless
        given; ``information`` of its odometry edge; ``pyramid``: see :meth:`process`), else recorded against it.
        Returns ``(T_world_cam, is_kf)``."""
        self._n_failures = 0
        self._lost = []
        self._frames_since_kf += 1
        is_kf = self._is_keyframe(T_kf_cam, self._frames_since_kf)
        if is_kf:
            feats = self.features(frame) if feats is None else feats
            self._add_keyframe(frame, feats, T_world_cam, self._ref_kf, T_kf_cam, information, pyramid)
            T_world_cam = self._kf_poses[-1]
            self._record(frame.timestamp, self.n_keyframes - 1, np.eye(4), T_world_cam)
        else:
            self._record(frame.timestamp, self._ref_kf, T_kf_cam, T_world_cam)
        return T_world_cam, is_kf

    def _with_depth(self, res: MotionResult, T_pred_cur_ref: np.ndarray,
                    source: FramePyramid) -> tuple[MotionResult, bool]:
        """``res`` (PnP against the reference keyframe) with its pose registered by ICP of the frame's depth
        ``source`` to the keyframe's (:func:`.depth_odometry.register_depth`; ``res`` itself when ICP fails), and
        whether that pose comes from depth alone (PnP not trusted)."""
        out, outcome = register_depth(res, T_pred_cur_ref, source, self._store, self._ref_kf,
                                      self._kfs[self._ref_kf].features, self._depth_cfg,
                                      self.cfg.features.max_motion_norm)
        self.depth_counts[outcome] += 1
        if outcome == "from_prediction":
            self.depth_counts["rescued"] += int(not res.ok)
        return out, outcome == "from_prediction"

    def _may_reinitialise(self, feats: Features) -> bool:
        n = self.cfg.reinit_after_failures
        return n > 0 and self._n_failures >= n and np.count_nonzero(feats.valid) >= self.cfg.reinit_min_keypoints

    def _reinitialise(self, frame: RGBDFrame, feats: Features, res: MotionResult) -> SparseFrameResult:
        """Start a new segment at this (lost) frame: a keyframe at the last pose, joined to the reference keyframe
        by a weak edge (``reinit_sigma_*``); tracking goes on against it, and the frames lost just before it that
        PnP places against it join it."""
        T_world_cam = self._last_pose()
        T_kf_cam = invert(self._kf_poses[self._ref_kf]) @ T_world_cam
        # information in gtsam's tangent order (rotation, translation)
        info = np.diag([self.cfg.reinit_sigma_rad ** -2] * 3 + [self.cfg.reinit_sigma_m ** -2] * 3)
        self._add_keyframe(frame, feats, T_world_cam, self._ref_kf, T_kf_cam, info)
        kf = self.n_keyframes - 1
        self._graph.start_segment(kf)
        self.n_reinitialisations += 1
        self._n_failures = 0
        # the frames lost just before are mostly close to this one: placed by PnP against it, they join the segment
        for slot, lost in self._lost:
            r = estimate_motion(self._kfs[kf].features, lost, self.intr, self.cfg.features)
            if r.ok:
                self._frame_kf[slot], self._T_kf_cam[slot] = kf, invert(r.T_cur_ref)
                self.n_lost_placed += 1
        self._lost = []
        T_world_cam = self._kf_poses[-1]
        self._record(frame.timestamp, self.n_keyframes - 1, np.eye(4), T_world_cam)
        self._velocity = np.eye(4)  # the motion across the loss is unknown
        return SparseFrameResult(T_world_cam.copy(), True, False, res.reason, res.n_inliers, 0)

    def _record(self, timestamp: float, kf: int, T_kf_cam: np.ndarray, T_world_cam: np.ndarray | None) -> None:
        if T_world_cam is not None and self._timestamps:
            self._velocity = invert(self._last_pose()) @ T_world_cam
        self._timestamps.append(float(timestamp))
        self._frame_kf.append(kf)
        self._T_kf_cam.append(np.asarray(T_kf_cam, np.float64).copy())

    def _add_keyframe(self, frame: RGBDFrame, feats: Features, T_world_cam: np.ndarray,
                      prev_kf: int | None, T_prev_new: np.ndarray | None,
                      information: np.ndarray | None = None, pyramid: FramePyramid | None = None) -> None:
        """Add a keyframe and its odometry edge, and start its loop checks (the checks of the keyframe
        ``loop_check_lag_keyframes`` back are applied first: they may move ``prev_kf``, and the new keyframe is placed
        by its odometry from there).

        ``information``: ``(6, 6)`` of the odometry measurement (the PnP's, see ``MotionResult.information``), or
        ``None`` (a dense pose: isotropic weight); ``pyramid``: the tracker's pyramid of the frame (see
        :meth:`process`)."""
        if prev_kf is not None:
            T_prev_before = self._kf_poses[prev_kf].copy()
        self._collect_loop_checks(keep=self.cfg.loop_check_lag_keyframes - 1)
        if prev_kf is not None and not np.array_equal(self._kf_poses[prev_kf], T_prev_before):
            # the graph moved the previous keyframe: keep the new one's pose relative to it
            T_world_cam = orthonormalize(self._kf_poses[prev_kf] @ invert(T_prev_before) @ T_world_cam)
        kf_id = self._graph.add_node(T_world_cam, prev_kf, T_prev_new)
        if self._store is not None:
            self._store.add_keyframe(kf_id, frame.depth_m)
        if self._keyframe_clouds:
            xyz, rgb = keyframe_cloud(frame, self.intr, self.cfg.map,
                                      None if self._cloud_rgb is None else self._cloud_rgb(frame))
        else:
            xyz, rgb = np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
        # a keyframe is only ever a pair's reference side: its grey image is kept (sub-pixel tracking), its depth not
        self._kfs.append(Keyframe(kf_id, frame.index, frame.timestamp, replace(feats, depth_m=None), xyz, rgb))
        self._ref_kf = kf_id
        self._frames_since_kf = 0
        if prev_kf is not None and T_prev_new is not None:
            self._graph.add_edge(PoseEdge(prev_kf, kf_id, T_prev_new, "odometry", information_matrix=information))
        if prev_kf is None:
            self._loops.add_to_index(feats)
            return
        kf_pyramid = None if pyramid is None or self._refiner is None else self._refiner.keyframe_pyramid(pyramid)
        if self.cfg.background_loop_checks:
            self._loops.submit(kf_id, feats, self._kf_poses, kf_pyramid)
        else:
            self._apply_loop_checks(*self._loops.check(kf_id, feats, self._kf_poses, kf_pyramid))

    def _apply_loop_checks(self, kf_id: int, checked: list[LoopCheck]) -> None:
        """Add the verified edges of keyframe ``kf_id`` to the graph (:meth:`KeyframeGraph.apply_loop_checks`)."""
        self._unreported_loops += self._graph.apply_loop_checks(kf_id, checked, self.cfg.features.min_inliers)

    def _collect_loop_checks(self, keep: int = 0) -> None:
        """Apply the oldest keyframes' background loop checks, in keyframe order, until at most ``keep`` pend."""
        while self._loops.n_pending > keep:
            self._apply_loop_checks(*self._loops.collect())

    def add_map_edge(self, kf_old: int, kf_new: int, T_old_new: np.ndarray, sigma: float, shift_m: float,
                     shift_deg: float) -> bool:
        """Whether the edge ``T_old_new`` ``(4, 4)`` from outside the back end (keyframe ``kf_new`` registered to the
        map anchored to ``kf_old``) was added: :meth:`KeyframeGraph.add_map_edge`. Tracking thread only."""
        return self._graph.add_map_edge(kf_old, kf_new, T_old_new, sigma, shift_m, shift_deg)

    # --- queries for the dense pipeline ---------------------------------------------------------------

    def _relocalise_features(self, feats: Features) -> tuple[np.ndarray, int, MotionResult] | None:
        self._collect_loop_checks()  # the retrieval index must hold every keyframe
        cands = self._loops.retrieve(feats, self.cfg.loop.n_retrieved)
        last = self.n_keyframes - 1
        if last >= 0 and last not in cands:
            cands.append(last)
        loop_cfg = replace(self.cfg.loop, max_norm_loop=self.cfg.relocalise_max_norm)
        best: tuple[np.ndarray, int, MotionResult] | None = None
        for k in cands:
            res = verify_edge(self._kfs[k].features, feats, self.intr, self.cfg.features, loop_cfg)
            if res.ok and (best is None or res.n_inliers > best[2].n_inliers):
                best = (self._kf_poses[k] @ invert(res.T_cur_ref), k, res)
        return best

    def relocalise(self, frame: RGBDFrame, feats: Features | None = None) -> tuple[np.ndarray, int] | None:
        """Pose of ``frame`` found by retrieval over all keyframes + PnP verification.

        Returns:
            ``(T_world_cam (4, 4), kf_id)`` of the best-verified keyframe, or ``None``. State is unchanged.
        """
        feats = self.features(frame) if feats is None else feats
        best = self._relocalise_features(feats)
        return None if best is None else (best[0], best[1])

    def track_reference_keyframe(self, grey: np.ndarray, T_world_cam_pred: np.ndarray) -> KeyframeMatch | None:
        """The reference keyframe's points found in a frame (``grey (H, W)`` uint8) by Lucas-Kanade from the predicted
        pose, without the frame's features (:func:`~surfelslam.tracking.features.keyframe_track.track_keyframe`);
        ``None`` when too few are found or there is no keyframe. State is unchanged."""
        if not self._kfs:
            return None
        kf = self._ref_kf
        return tracked_match(kf, self._kf_poses[kf], self._kfs[kf].features, grey, T_world_cam_pred, self.intr,
                             self.cfg.features, self._ref_points)

    def match_reference_keyframe(self, frame: RGBDFrame, T_world_cam_pred: np.ndarray | None = None,
                                 feats: Features | None = None, coarse: bool = False) -> KeyframeMatch | None:
        """PnP pose of ``frame`` against the reference keyframe, with the inlier correspondences.

        ``coarse``: PnP-RANSAC and its inlier refinement, without search by projection (and without the joint
        RGB-D refinement unless the constructor's ``coarse_rgbd_refine``;
        :func:`~surfelslam.tracking.features.estimate_motion`; same rejection rules): enough for a sanity check, an
        ICP start or the joint term's inliers, at a third to half the cost.

        Returns:
            :class:`KeyframeMatch` (poses and points in the graph's world frame), or ``None`` when there is no
            keyframe yet or a rejection rule fired. State is unchanged.
        """
        if not self._kfs:
            return None
        feats = self.features(frame) if feats is None else feats
        kf = self._ref_kf
        return pnp_match(kf, self._kf_poses[kf], self._kfs[kf].features, feats, T_world_cam_pred, self.intr,
                         self._coarse_features if coarse else self.cfg.features)

    # --- results -------------------------------------------------------------------------------------

    def trajectory(self) -> Trajectory:
        """Current estimate of every processed frame's pose."""
        kf = np.asarray(self._frame_kf, dtype=np.int64)
        T = self._kf_poses[kf] @ np.asarray(self._T_kf_cam).reshape(-1, 4, 4)
        return Trajectory(np.asarray(self._timestamps), T)

    def map_points(self) -> tuple[np.ndarray, np.ndarray]:
        """Keyframe clouds in the world frame, joined and voxel-filtered: ``(xyz (M, 3) f32, rgb (M, 3) u8)``."""
        if not self._keyframe_clouds:
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
        return joined_clouds(self._kfs, self._kf_poses, self.cfg.map.voxel_size_m)

    def finish(self) -> SparseSlamResult:
        """Optimise the whole graph once more (batch: not hanging on when loops came); return trajectory, map etc."""
        self._collect_loop_checks()
        self._loops.shutdown()
        if self.n_keyframes > 1:
            self._graph.optimise(full=True)
        xyz, rgb = self.map_points()
        return SparseSlamResult(trajectory=self.trajectory(), keyframe_indices=self.keyframe_frame_indices(),
                                keyframe_poses=self.keyframe_poses(), loops_found=list(self.loops_found),
                                loops_accepted=list(self.loops_accepted), n_nearby_edges=self._graph.n_nearby_edges,
                                rejected=dict(self.rejected), map_xyz=xyz, map_rgb=rgb)
