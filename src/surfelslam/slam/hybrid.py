"""Hybrid SLAM (tracker ``hybrid``).

Hybrid SLAM (:class:`HybridSlam`, tracker ``hybrid``) is dense SLAM with the sparse back end alongside:

1. ``match``: the reference keyframe's points are found in the frame (a pose and its inliers: keyframe points,
   sub-pixel pixels in the frame): by default tracked by Lucas-Kanade from the predicted pose
   (``SparseSlam.track_reference_keyframe``, ``hybrid.frame_features``), on a worker thread while the map is
   rendered; ORB features are extracted only for keyframes, relocalisation, and frames where too few points track
   (then matched by PnP, ``SparseSlam.match_reference_keyframe``).
2. ``track``: ICP from the constant-velocity guess, as in dense SLAM, when the last step succeeded, jointly
   with the inliers' reprojection terms (``hybrid.joint_features``; off by default where colour and depth are
   not registered). When ICP fails (:func:`icp_failure`), reports degeneracy, or the velocity is not trusted
   (the last frame failed), the PnP pose becomes the initial guess: the map is rendered at that pose and ICP
   retried from it. After ``tracking.relocalise_after_failures`` failed frames in a row,
   ``SparseSlam.relocalise`` (all keyframes) gives the guess instead, or, when it finds no pose, the shape
   guess of dense SLAM (against the map rendered at the current pose); on success fusing goes on.
   With ``hybrid.pnp_check`` every ICP pose is also compared with the PnP pose; one that disagrees is
   retried from the PnP pose and, if it still disagrees, the frame is not fused (ICP can slide along weakly
   constrained geometry while reporting a well-conditioned system).
3. ``sparse``: every tracked frame goes to ``SparseSlam.process(frame, T_world_cam_dense=pose)``, so
   keyframes carry dense poses and loop edges are verified by PnP between keyframes (in a background thread,
   applied at the next keyframe: ``sparse.background_loop_checks``).
4. ``correct``: loop edges move keyframes in the pose graph; the dense state follows. Choice made here:
   each frame is *anchored* to the last keyframe when it was processed, its pose kept as ``T_kf_cam``
   relative to that keyframe's pose *in the dense frame* (``T_kf_dense``, the ICP pose it was created
   with); each surfel is anchored to the anchor of the frame that created it (``first_seen`` -> anchor,
   a sorted frame-index table looked up with ``searchsorted``; surfels merged later keep their first
   anchor). A keyframe's correction is ``C_k = T_kf_graph inv(T_kf_dense)``. Dense poses are fed to the
   graph as ``C_last T_world_cam``, so odometry edges are exactly the dense relative motion whatever the
   pending correction. Corrections are applied to the surfels (positions and normals, one vectorised
   numpy step, culling index rebuilt) and to the current pose during the run only when a keyframe's surfels
   would move by more than ``hybrid.live_correction_min_m`` (re-posing the live map for centimetre
   corrections smears it), and then only the keyframes (with their surfels) that move by more than
   ``hybrid.live_correction_keyframe_min_m``, so the cost follows what moves, not the map; the rest wait for
   a later correction or ``finish``, which moves every surfel to its keyframe's final correction. At
   ``finish`` the last frame, if placed and not a keyframe, becomes one (its loop checks correct the frames after
   the last keyframe too). The written trajectory is every frame's ``T_kf_graph(final) T_kf_cam`` with the
   graph's change of the next keyframe relative to its own shared in proportion to time
   (:meth:`KeyframeAnchors.trajectory`).

The parts are components the tracker holds: the dense front end (:mod:`.frontend`), the sparse back end, the
PnP-guided localisation (:mod:`.hybrid_localise`) and the keyframe anchors with their corrections
(:mod:`.hybrid_anchors`).
"""

from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from surfelslam.backend.dense_edges import DenseEdgeRefiner
from surfelslam.backend.sparse_slam import SparseSlam
from surfelslam.geometry import se3
from surfelslam.mapping.surfel_map import SurfelMap
from surfelslam.slam.config import SlamConfig, relocalise_due
from surfelslam.slam.frame import (
    FrameResult,
    FrameStatus,
    PreparedFrame,
    SlamResult,
    StageTimer,
    prepared_for,
    refuse_given_pose,
)
from surfelslam.slam.frontend import DenseFrontEnd
from surfelslam.slam.hybrid_anchors import KeyframeAnchors
from surfelslam.slam.hybrid_localise import JUMPED, HybridLocaliser, Localised
from surfelslam.slam.hybrid_profile import LOOP_ROBUST_SCALE_M, hybrid_sparse_config
from surfelslam.slam.map_edges import MapEdges
from surfelslam.slam.motion import step_and_pose
from surfelslam.slam.orb import loop_stamps, sparse_metrics
from surfelslam.slam.registry import register_tracker
from surfelslam.slam.warmup import warm_up_tracker
from surfelslam.tracking.features import Features
from surfelslam.tracking.photometric import colour_switch
from surfelslam.types import ColourCamera, Intrinsics, RGBDFrame, Trajectory

#: the worker thread's name prefix (the feature work beside the tracking thread)
WORKER_THREAD = "surfelslam-hybrid"


def _sparse_back_end(cfg: SlamConfig, intr: Intrinsics, colour_registered: bool) -> SparseSlam:
    """The hybrid's sparse back end (:func:`hybrid_sparse_config`); ICP-refined keyframe edges with
    ``hybrid.loop_icp`` (they carry a tight sigma, see :mod:`~surfelslam.backend.dense_edges`)."""
    h = cfg.hybrid
    refiner = DenseEdgeRefiner(intr, cfg.preprocess, h.loop_icp) if h.loop_icp.enabled else None
    refined_scale = LOOP_ROBUST_SCALE_M / h.loop_icp.sigma_m  # the loop kernel's scale in refined-edge sigmas
    return SparseSlam(intr, hybrid_sparse_config(cfg, intr.fx), edge_refiner=refiner,
                      refined_robust_scale=refined_scale, colour_registered=colour_registered,
                      coarse_rgbd_refine=h.pnp_rgbd_refine, keyframe_clouds=False,  # the map is the surfels
                      relocalise_after_failures=cfg.tracking.relocalise_after_failures)


@register_tracker("hybrid")
class HybridSlam:
    """Tracker ``hybrid``: dense frame-to-model SLAM + PnP guesses, relocalisation and loop correction.

    See the module docstring for the stages and the map-correction scheme.
    """

    def __init__(self, intr: Intrinsics, cfg: SlamConfig, colour_registered: bool = True,
                 colour_camera: ColourCamera | None = None):
        self.intr = intr
        self.cfg = cfg
        # the saved keyframes and the map localisation use the back end's features
        self.front = DenseFrontEnd(intr, cfg, colour_registered, colour_camera, features_of=self._features,
                                   tracker_name=self.name, features_later=self._features_later)
        self.joint = colour_switch(cfg.hybrid.joint_features, colour_registered)
        self.sparse = _sparse_back_end(cfg, intr, colour_registered)
        self.anchors = KeyframeAnchors(self.sparse)
        self.map_edges = MapEdges(self.anchors, self.sparse, cfg.icp, self.front.render_cfg, cfg.preprocess)
        # one worker thread beside the main one: the frame's match while the map is rendered, a new keyframe's
        # features while the frame is fused
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix=WORKER_THREAD)
        self.localiser = HybridLocaliser(self.front, self.sparse, self.anchors, cfg, intr, self.joint,
                                         self._features, self._worker)
        self._keyframe_feats: Future | None = None  # the features of a frame about to become a keyframe
        self._stamp_of_frame: dict[int, float] = {}
        self._feats: Features | None = None  # the current frame's ORB features (extracted at most once)
        self._last_placed: RGBDFrame | None = None  # the last frame, if the back end placed it (not a keyframe)
        self._final_correction_m: float | None = None
        self._loop_correction_skipped = 0

    @property
    def map(self) -> SurfelMap:
        """The surfel map."""
        return self.front.map

    @property
    def photometric(self) -> bool:
        """Whether ICP has the photometric term."""
        return self.front.photometric

    @property
    def failures(self) -> int:
        """Frames not registered so far."""
        return self.front.state.failures

    @property
    def pooled_pyramids(self) -> int:
        """Free source pyramids kept for reuse (:attr:`FusingMapper.pooled_pyramids`)."""
        return self.front.mapper.pooled_pyramids

    @property
    def counts(self) -> dict:
        """The hybrid's own counts (PnP guesses, relocalisations, corrections), as in ``metrics.json``."""
        c = self.localiser.counts
        return {"pnp_guesses_tried": c["pnp_guesses_tried"], "pnp_guesses_tracked": c["pnp_guesses_tracked"],
                "relocalisations_tried": c["relocalisations_tried"],
                "relocalisations_tracked": c["relocalisations_tracked"],
                "map_corrections": self.anchors.map_corrections, "pnp_disagreements": c["pnp_disagreements"],
                "pnp_unsupported": c["pnp_unsupported"], "unconverged_slides": c["unconverged_slides"],
                "fine_retries_tried": c["fine_retries_tried"], "fine_retries_tracked": c["fine_retries_tracked"],
                "loop_correction_skipped": self._loop_correction_skipped,
                "final_correction_m": self._final_correction_m, **self.map_edges.counts.as_metrics()}

    def warmup(self) -> None:
        """The dense kernels, the feature side's (matching, PnP, keypoint depth, RGB-D refinement), then a throwaway
        hybrid run on a few synthetic frames (keyframes, loop checks, the joint term); excluded from FPS
        (:mod:`surfelslam.slam.warmup`)."""
        warm_up_tracker(self)

    def prepare(self, frame: RGBDFrame) -> PreparedFrame:
        """Preprocessing and ORB extraction, for another thread to do ahead (see :meth:`DenseFrontEnd.prepare`).
        Without the joint term or the PnP check, or with the keyframe's points tracked into the frame
        (``hybrid.frame_features``), a frame needs features only when it becomes a keyframe or tracking fails: they
        are then extracted when needed, not ahead for every frame."""
        p = self.front.prepare(frame)
        if not (self.joint or self.cfg.hybrid.pnp_check) or self.localiser.tracks_features:
            return p
        c0, t0 = time.thread_time(), time.perf_counter()
        p.features = self.sparse.features(frame)
        p.timings_ms["orb_extract"] = (time.perf_counter() - t0) * 1e3
        p.cpu_ms += (time.thread_time() - c0) * 1e3
        return p

    def discard(self, prepared: PreparedFrame | None) -> None:
        """A prepared frame that will not be processed (skipped): its pyramid goes back to the pool."""
        self.front.discard(prepared)

    def use_prior_map(self, saved, localize_only: bool = False) -> None:
        """Continue from the saved map ``saved``; the first frames are localised in it (before the first frame)."""
        self.front.use_prior_map(saved, localize_only)

    def _features(self, frame: RGBDFrame) -> Features:
        """The current frame's ORB features: the prepared ones, else extracted once here."""
        if self._feats is None:
            self._feats = self.sparse.features(frame)
        return self._feats

    def _features_later(self, frame: RGBDFrame) -> Future | None:
        """A future of the current frame's ORB features for the saved map: the ones a new keyframe of the back end is
        having extracted, else the prepared or extracted ones; ``None`` when the frame has none (it is then not saved:
        the saved keyframes are frames whose features the back end extracts anyway)."""
        if self._keyframe_feats is not None:
            return self._keyframe_feats
        if self._feats is None:
            return None
        done: Future = Future()
        done.set_result(self._feats)
        return done

    def process(self, frame: RGBDFrame, prepared: PreparedFrame | None = None,
                T_world_cam: np.ndarray | None = None) -> FrameResult:
        """Localise the frame (ICP, PnP guesses and checks, relocalisation), fuse it when tracked, then feed the
        sparse back end (keyframes, loops, map corrections)."""
        refuse_given_pose(self.name, T_world_cam)
        front, s = self.front, self.front.state
        t = StageTimer(prepared)
        p = prepared_for(frame, prepared)
        self._feats = None if p is None else p.features
        front.begin_frame(frame, prepared)
        t.lap("preprocess" if prepared is None else None)
        self._stamp_of_frame[frame.index] = frame.timestamp
        if s.T_world_cam is None:  # the world frame, or the pose localised in a loaded map
            return self._first_frame(frame, t)
        T_prev = s.T_world_cam
        T_pred = front.predict()
        if relocalise_due(self.cfg.tracking, s.failures_in_a_row):
            loc = self.localiser.relocalise(frame, T_prev, t)
        else:
            loc = self.localiser.localise(frame, T_prev, T_pred, t)
        if loc.failure is None and loc.T_new is not None and self._feats is None \
                and self.sparse.becomes_keyframe(self._graph_pose(loc.T_new)):
            self._keyframe_feats = self._worker.submit(self.sparse.features, frame)  # extracted while fusing
        tracked, T_new, failure, status = self._fuse_or_count(frame, loc, T_prev, T_pred, t)
        self._after_tracking(frame, T_new, tracked, t)
        front.end_frame()
        res = loc.res
        return FrameResult(index=frame.index, timestamp=frame.timestamp, T_world_cam=s.T_world_cam.copy(),
                           tracked=tracked, fused=tracked,
                           reason=None if res is None else res.reason if tracked else failure, timings_ms=t.ms,
                           map_points=self.map.n_alive, icp=res, status=status)

    def _first_frame(self, frame: RGBDFrame, t: StageTimer) -> FrameResult:
        """The first posed frame: the world frame, or its pose localised in a loaded map (none yet: not posed)."""
        front = self.front
        T_new = front.first_pose(frame, t)
        if T_new is None:
            return front.not_localised(frame, t)
        status = front.first_status()
        front.motion.mark_tracked(T_new, frame.time_s, status)
        if self._feats is None:  # the first keyframe's features, extracted while fusing (the saved map's first too)
            self._keyframe_feats = self._worker.submit(self.sparse.features, frame)
        front.fuse(frame, T_new)
        t.lap("fuse")
        self._after_tracking(frame, T_new, True, t)
        front.end_frame()
        return FrameResult(index=frame.index, timestamp=frame.timestamp, T_world_cam=front.state.T_world_cam.copy(),
                           tracked=True, fused=True, reason=None, timings_ms=t.ms, map_points=self.map.n_alive,
                           status=status)

    def _fuse_or_count(self, frame: RGBDFrame, loc: Localised, T_prev: np.ndarray, T_pred: np.ndarray,
                       t: StageTimer) -> tuple[bool, np.ndarray, str | None, FrameStatus]:
        """A tracked frame updates the velocity and is fused; one whose registration jumped is held at the prediction,
        one the map refuses but a trusted PnP pose near the prediction places is bridged there, neither counted as a
        failure (``tracking.max_held_frames`` in a row at most); a failed one is counted and posed at the PnP guess
        (bridged) or the prediction (lost). Returns ``(tracked, T_world_cam, failure, status)``."""
        front = self.front
        res, failure, T_new = loc.res, loc.failure, loc.T_new
        tracked = res is not None and failure is None
        if failure == JUMPED and front.motion.may_hold():  # ICP slid off: held at the prediction, velocity kept
            front.motion.mark_held(frame.time_s)
            return False, T_pred, failure, FrameStatus.HELD
        if (failure is not None and loc.guess_trusted and not loc.relocalised
                and front.motion.bridge_holds(T_pred, loc.guess, frame.time_s)):
            # the map disagrees but the features agree with the prediction: bridged, the velocity kept, no
            # relocalisation started (it would drop the reference keyframe's PnP for a search of all keyframes)
            front.motion.mark_held(frame.time_s)
            return False, loc.guess, failure, FrameStatus.BRIDGED
        if tracked:
            status = (FrameStatus.RELOCALISED if loc.relocalised else
                      FrameStatus.WEAK if res.degenerate else FrameStatus.TRACKED)
            if not relocalise_due(self.cfg.tracking, front.state.failures_in_a_row):
                step = (step_and_pose(T_prev, res)[0] if loc.from_prev
                        else se3.orthonormalize(se3.invert(T_prev) @ T_new))
                # a weak step is ICP's slide along the free directions: not fed back (MotionModel.velocity_after)
                front.state.velocity = front.motion.velocity_after(step, status, frame.time_s,
                                                                   res if loc.from_prev else None)
            front.motion.mark_tracked(T_new, frame.time_s, status)
            self.localiser.record_noise(res)
            front.fuse(frame, T_new)
            t.lap("fuse")
        else:
            failure = failure or "relocalisation_failed"
            status = FrameStatus.BRIDGED if loc.guess is not None else FrameStatus.LOST
            T_new = loc.guess if loc.guess is not None else T_pred
            # the last fully tracked step is kept: a weak frame after the streak fades from it
            front.motion.count_failure(failure, forget_tracked_step=False)
        return tracked, T_new, failure, status

    def _after_tracking(self, frame: RGBDFrame, T_new: np.ndarray, tracked: bool, t: StageTimer) -> None:
        """Feed the sparse back end, anchor the frame, apply large pose-graph corrections to the dense state."""
        sr = None
        if tracked:
            # the graph frame may differ from the dense frame by the last keyframe's pending correction:
            # feed the pose in the graph frame, so the odometry edge is exactly the dense relative motion
            T_feed = self._graph_pose(T_new)
            if self._feats is None and self._keyframe_feats is not None and self.sparse.becomes_keyframe(T_feed):
                self._feats = self._keyframe_feats.result()
            # feats None: extracted there if it becomes a keyframe; the source pyramid serves its loop checks when
            # its finest level is computed (the input is not reduced first)
            sr = self.sparse.process(frame, T_world_cam_dense=T_feed, feats=self._feats,
                                     tracker_pyramid=self.front.full_source())
            t.lap("sparse")
            if sr.is_keyframe:
                self.anchors.add_keyframe(T_new)
        map_closure = sr is not None and sr.is_keyframe and self._map_edge(frame, T_new, t)
        self._last_placed = frame if sr is not None and not sr.is_keyframe else None
        self._keyframe_feats = None
        self.anchors.record(frame.index, frame.timestamp, T_new, tracked)
        self.front.state.T_world_cam = T_new
        if sr is not None and (sr.loops_added > 0 or map_closure) and self.cfg.hybrid.loop_correction:
            kf = self.sparse.keyframe_poses()
            if self.anchors.keyframe_moves_m(kf).max() > self.cfg.hybrid.live_correction_min_m:
                self.correct(kf, min_move_m=self.cfg.hybrid.live_correction_keyframe_min_m)
                t.lap("correct")

    def _map_edge(self, frame: RGBDFrame, T_new: np.ndarray, t: StageTimer) -> bool:
        """The new keyframe registered to the inactive map (:mod:`.map_edges`, not with a frozen loaded map): whether
        its edge made the back end re-optimise (a correction to apply)."""
        if self.front.mapper.frozen or len(self.anchors) < 2:
            return False
        sigma = self.sparse.dense_edge_stats()["edge_sigma_m"] or self.cfg.hybrid.loop_icp.sigma_m
        closes = self.map_edges.check(self.map, self.front.track_source, T_new, frame.timestamp, frame.index, sigma,
                                      frame.seconds_per_stamp)
        t.lap("map_edge")
        return closes

    def _graph_pose(self, T_world_cam: np.ndarray) -> np.ndarray:
        """A dense pose in the graph frame: moved by the last keyframe's pending correction, so the odometry edge is
        exactly the dense relative motion."""
        K = self.sparse.n_keyframes
        return se3.orthonormalize(T_world_cam if K == 0 else self.anchors.correction(K - 1) @ T_world_cam)

    def correct(self, kf_new: np.ndarray, C: np.ndarray | None = None, min_move_m: float = 0.0) -> None:
        """Move the surfels and the current pose by each keyframe's correction ``C`` (default: to the graph poses
        ``kf_new`` ``(K, 4, 4)``, :meth:`KeyframeAnchors.corrections`), only the keyframes moving more than
        ``min_move_m`` when it is > 0 (:meth:`KeyframeAnchors.correct`); a localise-only run's map never moves."""
        smap = None if self.front.mapper.frozen else self.map
        self.front.state.T_world_cam = self.anchors.correct(kf_new, smap, C, min_move_m)

    def trajectory(self, kf_poses: np.ndarray | None = None) -> Trajectory:
        """Every frame's pose ``T_world_kf T_kf_cam`` with ``kf_poses`` ``(K, 4, 4)`` (default: the graph's)."""
        return self.anchors.trajectory(kf_poses)

    def _correction_is_noise(self, moved_m: float) -> bool:
        """The refined edges are distrusted, and the final graph poses (the PnP edges') move no keyframe by more than
        ``hybrid.untrusted_min_correction_m`` (``moved_m``: :meth:`KeyframeAnchors.correction_m`; see
        :class:`HybridConfig`)."""
        return self.sparse.dense_edges_trusted is False and moved_m <= self.cfg.hybrid.untrusted_min_correction_m

    def _final_keyframes(self, kf_final: np.ndarray) -> np.ndarray:
        """The keyframe poses the run ends with: the final graph's, applied to the map, unless the correction is
        noise (:meth:`_correction_is_noise`: then the dense ones)."""
        if not (self.cfg.hybrid.loop_correction and len(self.anchors)):
            return kf_final
        self._final_correction_m = self.anchors.correction_m(kf_final)
        if self._correction_is_noise(self._final_correction_m):
            self._loop_correction_skipped = 1
            return self.anchors.kf_dense.poses.copy()
        self.correct(kf_final)
        return kf_final

    def finish(self) -> SlamResult:
        """End of the run: the final loop correction, the map, the corrected trajectory and the counts."""
        self._worker.shutdown(wait=True)
        # the frames after the last keyframe are corrected too when the last one becomes a keyframe
        if self.cfg.hybrid.loop_correction and self._last_placed is not None \
                and self.sparse.promote_last_frame(self._last_placed):
            self.anchors.promote_last()
        self._last_placed = None
        res = self.sparse.finish()
        kf_final = self._final_keyframes(res.keyframe_poses)
        corrected = self.cfg.hybrid.loop_correction and self.anchors.map_corrections > 0
        if corrected and self.front.mapper.saves_map:
            self.front.mapper.repose_keyframes(self.trajectory(kf_final))  # the saved keyframes follow the map
        out = self.front.mapper.result(self._metrics(res))
        # with nothing corrected at all, the frames keep their tracked poses (T_kf T_kf_cam would round them)
        if corrected:
            out.trajectory_override = self.trajectory(kf_final)
        out.loop_stamps = loop_stamps(res, self._stamp_of_frame)
        return out

    def _metrics(self, res) -> dict:
        """The hybrid's part of ``metrics.json`` (``res``: the sparse back end's end-of-run result)."""
        s = self.front.state
        counts = self.counts
        noise = self.localiser.depth_noise_per_frame
        return {"tracking_failures": s.failures, "tracking_failure_reasons": s.failure_reasons,
                "photometric": self.photometric, "joint_features": self.joint, **counts,
                "shape_relocalisations_tried": s.relocalisations["tried"],
                "shape_relocalisations": s.relocalisations["tracked"],
                "relocalisations_refused": s.relocalisations["refused_implausible"],
                "weak_frames": s.weak_frames, "held_frames": s.held_frames,
                "depth_noise_m": float(np.median(noise)) if noise else None,
                # recovered frames by either route, the key every tracker reports
                "relocalisations": counts["relocalisations_tracked"] + s.relocalisations["tracked"],
                **sparse_metrics(self.sparse, res)}
