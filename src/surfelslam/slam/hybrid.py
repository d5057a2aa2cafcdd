"""Hybrid SLAM (tracker ``hybrid``).

Hybrid SLAM (:class:`HybridSlam`, tracker ``hybrid``) is dense SLAM with the sparse back end alongside:

1. ``match``: the frame is matched to the reference keyframe by PnP (``SparseSlam.match_reference_keyframe``):
   a pose and its inliers (keyframe points, sub-pixel pixels in the frame).
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
   numpy step over all surfels, culling index rebuilt) and to the current pose during the run only when a
   keyframe moved by more than ``hybrid.live_correction_min_m`` (re-posing the live map for centimetre
   corrections smears it); otherwise once, in ``finish``. The written trajectory is every frame's
   ``T_kf_graph(final) T_kf_cam``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from surfelslam.backend.dense_edges import DenseEdgeRefiner
from surfelslam.backend.sparse_slam import (
    KeyframeMatch,
    SparseSlam,
    features_for_width,
)
from surfelslam.geometry import se3
from surfelslam.slam.config import HybridConfig, SlamConfig, hybrid_sparse_config, relocalise_due
from surfelslam.slam.dense import DenseSlam
from surfelslam.slam.frame import FrameResult, FrameStatus, PreparedFrame, SlamResult, StageTimer, prepared_for
from surfelslam.slam.orb import loop_stamps, sparse_metrics
from surfelslam.slam.registry import register_tracker
from surfelslam.slam.warmup_run import warm_up_run
from surfelslam.tracking.features import Features, on_occluding_contour, reprojection_inliers, reprojection_spread_px
from surfelslam.tracking.features.warmup import warm_up_features
from surfelslam.tracking.icp import ICPResult, ReprojectionTerm, icp
from surfelslam.tracking.photometric import (
    colour_switch,
)
from surfelslam.types import ColourCamera, Intrinsics, PoseArray, RGBDFrame, Trajectory


@dataclass
class _Localised:
    """Where localising one frame ended: the kept ICP result, its failure (``None``: usable), its pose, the PnP or
    relocalisation guess, and whether the result was tracked against the map rendered at the previous pose."""

    res: ICPResult | None = None
    failure: str | None = None
    T_new: np.ndarray | None = None
    guess: np.ndarray | None = None
    from_prev: bool = False
    relocalised: bool = False  # the result comes from a relocalisation (after too many failures)


def joint_term_weight(h: HybridConfig, finest_robust_scale_m: float, depth_noise_m: float) -> float:
    """Weight (m^2) of a unit feature residual in the joint term: ``hybrid.joint_weight`` point-to-plane pairs whose
    residual is ``hybrid.joint_weight_unit``: the finest robust scale, or ``depth_noise_m``, the depth noise the last
    tracked frame's ICP measured (the scale until one was measured, ``depth_noise_m`` 0)."""
    unit_m = depth_noise_m if h.joint_weight_unit == "depth_noise" and depth_noise_m > 0 else finest_robust_scale_m
    return h.joint_weight * unit_m**2


@register_tracker("hybrid")
class HybridSlam(DenseSlam):
    """Tracker ``hybrid``: dense frame-to-model SLAM + PnP guesses, relocalisation and loop correction.

    See the module docstring for the stages and the map-correction scheme.
    """

    def __init__(self, intr: Intrinsics, cfg: SlamConfig, colour_registered: bool = True,
                 colour_camera: ColourCamera | None = None):
        super().__init__(intr, cfg, colour_registered, colour_camera)
        mode = cfg.hybrid.joint_features
        self.joint = colour_switch(mode, colour_registered)
        # the sparse back end with the hybrid's own settings ([hybrid]: keyframe spacing, loop candidates, edge
        # weighting...: hybrid_sparse_config); the joint term leaves contour keypoints out itself (_pnp_match)
        sp = hybrid_sparse_config(cfg, intr.fx)
        self._contour_cfg = features_for_width(cfg.sparse, intr.width).features
        refiner, refined_scale = None, None
        if cfg.hybrid.loop_icp.enabled:  # ICP-refined keyframe edges carry a tight sigma (see dense_edges)
            refiner = DenseEdgeRefiner(intr, cfg.preprocess, cfg.hybrid.loop_icp)
        if cfg.hybrid.loop_robust_scale_m > 0:  # the loop kernel's scale in refined edges' sigmas
            refined_scale = cfg.hybrid.loop_robust_scale_m / cfg.hybrid.loop_icp.sigma_m
        self.sparse = SparseSlam(intr, sp, edge_refiner=refiner, refined_robust_scale=refined_scale,
                                 colour_registered=colour_registered, coarse_rgbd_refine=cfg.hybrid.pnp_rgbd_refine,
                                 keyframe_clouds=False,  # the map is the surfels
                                 relocalise_after_failures=cfg.tracking.relocalise_after_failures)
        self._kf_dense = PoseArray()  # keyframe poses in the dense (tracking and map) frame
        self._stamps: list[float] = []
        self._anchor: list[int] = []  # per frame: anchor keyframe (-1: before any keyframe, never happens)
        self._T_kf_cam: list[np.ndarray] = []
        self._fused_frames: list[int] = []  # frame index of each fused frame (increasing)
        self._fused_anchor: list[int] = []
        self._stamp_of_frame: dict[int, float] = {}
        self._feats: Features | None = None  # the current frame's ORB features (extracted at most once)
        # finest-level point-to-plane noise of every tracked frame (the last weighs the joint term; the median is
        # reported)
        self._depth_noise_per_frame: list[float] = []
        self.counts = {"pnp_guesses_tried": 0, "pnp_guesses_tracked": 0, "relocalisations_tried": 0,
                       "relocalisations_tracked": 0, "map_corrections": 0,
                       "pnp_disagreements": 0, "loop_correction_skipped": 0,
                       "final_correction_m": None}

    def warmup(self) -> None:
        """The dense kernels, the feature side's (matching, PnP, keypoint depth, RGB-D refinement), then a throwaway
        hybrid run on a few synthetic frames (keyframes, loop checks, the joint term); excluded from FPS."""
        super().warmup()
        warm_up_features(self.sparse.cfg.features)
        warm_up_run(self.cfg, "hybrid")

    def prepare(self, frame: RGBDFrame) -> PreparedFrame:
        """Preprocessing and ORB extraction, for another thread to do ahead (see :meth:`DenseSlam.prepare`). Without
        the joint term or the PnP check a frame needs features only when it becomes a keyframe or tracking fails:
        they are then extracted when needed, not ahead for every frame."""
        p = super().prepare(frame)
        if not (self.joint or self.cfg.hybrid.pnp_check):
            return p
        c0, t0 = time.thread_time(), time.perf_counter()
        p.features = self.sparse.features(frame)
        p.timings_ms["orb_extract"] = (time.perf_counter() - t0) * 1e3
        p.cpu_ms += (time.thread_time() - c0) * 1e3
        return p

    def _map_features(self, frame: RGBDFrame) -> Features:
        """The saved keyframes' and the map localisation's features: the back end's own."""
        return self._features(frame)

    def _features(self, frame: RGBDFrame) -> Features:
        """The current frame's ORB features: the prepared ones, else extracted once here."""
        if self._feats is None:
            self._feats = self.sparse.features(frame)
        return self._feats

    def _icp_from(self, T_render: np.ndarray, T_init_rel: np.ndarray, match: KeyframeMatch | None = None):
        """ICP of the current source against the map rendered at ``T_render``, jointly with ``match``'s
        reprojection terms when ``hybrid.joint_features`` is on; returns (res, failure, T)."""
        target = self.render_target(T_render)
        term = self._reprojection_term(T_render, match)
        res = icp(self.track_source, target, T_init=se3.orthonormalize(T_init_rel), cfg=self.cfg.icp,
                  reprojection=term, photometric=self.photometric_term())
        return res, self.failure_of(res), self._step_and_pose(T_render, res)[1]

    def _reprojection_term(self, T_render: np.ndarray, match: KeyframeMatch | None) -> ReprojectionTerm | None:
        h = self.cfg.hybrid
        if match is None or not self.joint or h.joint_weight == 0 or not self._trusted(match):
            return None
        pts_t = se3.transform_points(se3.invert(T_render), match.points_world)
        sigma = max(h.joint_sigma_px, self._match_spread_px(match))
        return ReprojectionTerm(pts_t, match.uv_cur, self.intr, sigma, h.joint_huber,
                                joint_term_weight(h, self.cfg.icp.finest_robust_scale_m,
                                                  self._depth_noise_per_frame[-1] if self._depth_noise_per_frame
                                                  else 0.0))

    def _match_spread_px(self, match: KeyframeMatch) -> float:
        """Robust spread (px) of the inliers' reprojection residuals at the PnP pose: the data's own pixel noise
        (larger where colour and depth are misregistered or keypoints are poorly localised)."""
        X = se3.transform_points(se3.invert(match.T_world_cam), match.points_world)
        return reprojection_spread_px(X, match.uv_cur, self.intr)

    def process(self, frame: RGBDFrame, prepared: PreparedFrame | None = None) -> FrameResult:
        """Localise the frame (ICP, PnP guesses and checks, relocalisation), fuse it when tracked, then feed the
        sparse back end (keyframes, loops, map corrections)."""
        t = StageTimer(prepared)
        p = prepared_for(frame, prepared)
        self._feats = None if p is None else p.features
        self._preprocess(frame, prepared)
        self._set_source_intensity(frame, prepared)
        t.lap("preprocess" if prepared is None else None)
        self._stamp_of_frame[frame.index] = frame.timestamp
        if self.T_world_cam is None:  # the world frame, or the pose localised in a loaded map
            T_new = self._first_pose(frame, t)
            if T_new is None:
                return self._not_localised(frame, t)
            status = self._first_status()
            self._mark_tracked(T_new, frame.time_s, status)
            self._fuse(frame, T_new)
            t.lap("fuse")
            self._after_tracking(frame, T_new, True, t)
            self._retire_source()
            return FrameResult(frame.index, frame.timestamp, self.T_world_cam.copy(), True, True, None, t.ms,
                               self.map.n_alive, status=status)
        T_prev = self.T_world_cam
        T_pred = self.predict()
        if relocalise_due(self.cfg.tracking, self.failures_in_a_row):
            loc = self._relocalise(frame, T_prev, t)
        else:
            loc = self._localise(frame, T_prev, T_pred, t)
        tracked, T_new, failure, status = self._fuse_or_count(frame, loc, T_prev, T_pred, t)
        self._after_tracking(frame, T_new, tracked, t)
        self._retire_source()
        res = loc.res
        return FrameResult(frame.index, frame.timestamp, self.T_world_cam.copy(), tracked, tracked,
                           None if res is None else res.reason if tracked else failure, t.ms, self.map.n_alive,
                           res, status)

    def _relocalise(self, frame: RGBDFrame, T_prev: np.ndarray, t: StageTimer) -> _Localised:
        """After too many failures: PnP against every keyframe, then ICP from that pose; else the shape guess."""
        loc = _Localised()
        self.counts["relocalisations_tried"] += 1
        found = self.sparse.relocalise(frame, feats=self._features(frame))
        t.lap("relocalise")
        if found is not None:
            found = (se3.orthonormalize(se3.invert(self._correction(found[1])) @ found[0]), found[1])
            loc.res, loc.failure, loc.T_new = self._icp_from(found[0], np.eye(4))
            t.lap("icp")
            if loc.failure is None and not self.plausible_jump(loc.T_new, frame.time_s):
                loc.failure = "relocalisation_implausible"
            if loc.failure is None:
                self.counts["relocalisations_tracked"] += 1
                self.velocity = np.eye(4)
            elif loc.failure != "relocalisation_implausible" and self.plausible_jump(found[0], frame.time_s):
                loc.guess = found[0]  # ICP failed from a reachable PnP pose: the frame is bridged there
            # a pose refused as out of reach is no bridge either: the frame stays lost at the prediction
        if (loc.res is None or loc.failure is not None) and self.cfg.tracking.relocalise_after_failures > 0:
            shape = self._relocalise_shape(T_prev, frame.time_s)  # no PnP pose (no texture): from the depth alone
            t.lap("relocalise")
            if shape is not None:
                loc.res, loc.failure = shape[0], None
                loc.T_new = se3.orthonormalize(T_prev @ loc.res.T_target_source)
                self.velocity = np.eye(4)
        loc.relocalised = True
        return loc

    def _localise(self, frame: RGBDFrame, T_prev: np.ndarray, T_pred: np.ndarray, t: StageTimer) -> _Localised:
        """ICP from the constant-velocity guess (jointly with the PnP inliers), checked against the PnP pose, and
        retried from the PnP pose when it fails, is degenerate or disagrees."""
        h = self.cfg.hybrid
        loc = _Localised()
        trusted = self.failures_in_a_row == 0 or not h.pnp_when_velocity_untrusted
        match = None
        if self.joint or h.pnp_check or not trusted:
            match = self._pnp_match(frame, T_pred)
            t.lap("pnp")
        if trusted:
            loc.res, loc.failure, loc.T_new = self._icp_from(T_prev, se3.invert(T_prev) @ T_pred, match)
            loc.from_prev = True
            t.lap("icp")
        bad = loc.res is None or loc.failure is not None or loc.res.degenerate
        if match is None and h.pnp_retry and bad:
            match = self._pnp_match(frame, T_pred)
            t.lap("pnp")
        loc.guess = None if match is None else match.T_world_cam
        first_ok = loc.res is not None and loc.failure is None
        if first_ok and loc.guess is not None and h.pnp_check and self._disagrees(loc.T_new, match):
            first_ok = False
            loc.failure = "disagrees_with_pnp"
            self.counts["pnp_disagreements"] += 1
        if loc.guess is not None and h.pnp_retry and (not first_ok or loc.res.degenerate):
            self._retry_from_pnp(loc, match, first_ok, t)
        elif loc.res is None:  # untrusted velocity and no PnP guess: the velocity guess after all
            loc.res, loc.failure, loc.T_new = self._icp_from(T_prev, se3.invert(T_prev) @ T_pred)
            loc.from_prev = True
            t.lap("icp")
        return loc

    def _retry_from_pnp(self, loc: _Localised, match: KeyframeMatch, first_ok: bool, t: StageTimer) -> None:
        """ICP again from the PnP pose; its result replaces ``loc``'s when it is good (or the first one was not)."""
        self.counts["pnp_guesses_tried"] += 1
        r2, f2, T2 = self._icp_from(loc.guess, np.eye(4), match)
        t.lap("icp")
        if f2 is None and self.cfg.hybrid.pnp_check and self._disagrees(T2, match):
            f2 = "disagrees_with_pnp"
        if f2 is None and (not r2.degenerate or not first_ok):
            loc.res, loc.failure, loc.T_new, loc.from_prev = r2, None, T2, False
            self.counts["pnp_guesses_tracked"] += 1
        elif not first_ok:
            loc.res, loc.failure, loc.T_new, loc.from_prev = r2, f2, T2, False

    def _fuse_or_count(self, frame: RGBDFrame, loc: _Localised, T_prev: np.ndarray, T_pred: np.ndarray,
                       t: StageTimer) -> tuple[bool, np.ndarray, str | None, FrameStatus]:
        """A tracked frame updates the velocity and is fused; a failed one is counted and posed at the PnP guess
        (bridged) or the prediction (lost). Returns ``(tracked, T_world_cam, failure, status)``."""
        res, failure, T_new = loc.res, loc.failure, loc.T_new
        tracked = res is not None and failure is None
        if tracked:
            status = (FrameStatus.RELOCALISED if loc.relocalised else
                      FrameStatus.WEAK if res.degenerate else FrameStatus.TRACKED)
            if not relocalise_due(self.cfg.tracking, self.failures_in_a_row):
                step = (self._step_and_pose(T_prev, res)[0] if loc.from_prev
                        else se3.orthonormalize(se3.invert(T_prev) @ T_new))
                # a weak step is ICP's slide along the free directions: not fed back (DenseSlam._velocity_after)
                self.velocity = self._velocity_after(step, status, frame.time_s, res if loc.from_prev else None)
            self._mark_tracked(T_new, frame.time_s, status)
            if res.levels and res.levels[-1].level == 0:
                self._depth_noise_per_frame.append(res.levels[-1].geometric_noise_m)
            self._fuse(frame, T_new)
            t.lap("fuse")
        else:
            failure = failure or "relocalisation_failed"
            status = FrameStatus.BRIDGED if loc.guess is not None else FrameStatus.LOST
            T_new = loc.guess if loc.guess is not None else T_pred
            self.failures += 1
            self.failures_in_a_row += 1
            self.failure_reasons[failure] = self.failure_reasons.get(failure, 0) + 1
            if self.failures_in_a_row >= self.cfg.tracking.max_failures_in_a_row_before_reset_velocity:
                self.velocity = np.eye(4)
        return tracked, T_new, failure, status

    def _after_tracking(self, frame: RGBDFrame, T_new: np.ndarray, tracked: bool, t: StageTimer) -> None:
        """Feed the sparse back end, anchor the frame, apply large pose-graph corrections to the dense state."""
        K = self.sparse.n_keyframes
        sr = None
        if tracked:
            # the graph frame may differ from the dense frame by the last keyframe's pending correction:
            # feed the pose in the graph frame, so the odometry edge is exactly the dense relative motion
            T_feed = T_new if K == 0 else self._correction(K - 1) @ T_new
            # feats None: extracted there if it becomes a keyframe; the source pyramid serves its loop checks when
            # its finest level is computed (the input is not reduced first)
            sr = self.sparse.process(frame, T_world_cam_dense=se3.orthonormalize(T_feed), feats=self._feats,
                                     tracker_pyramid=self.source if self.first_level == 0 else None)
            t.lap("sparse")
            if sr.is_keyframe:
                self._kf_dense.append(T_new)
        anchor = self.sparse.n_keyframes - 1
        if tracked:
            self._fused_frames.append(frame.index)
            self._fused_anchor.append(anchor)
        self._stamps.append(frame.timestamp)
        self._anchor.append(anchor)
        self._T_kf_cam.append(se3.invert(self._kf_dense.poses[anchor]) @ T_new)
        self.T_world_cam = T_new
        if sr is not None and sr.loops_added > 0 and self.cfg.hybrid.loop_correction:
            kf = self.sparse.keyframe_poses()
            C = self._corrections(kf)
            if np.linalg.norm(C[:, :3, 3], axis=1).max() > self.cfg.hybrid.live_correction_min_m:
                self._correct(kf, C)
                t.lap("correct")

    def _corrections(self, kf_new: np.ndarray) -> np.ndarray:
        """``(K, 4, 4)`` each keyframe's correction ``T_new inv(T_dense)`` for the graph poses ``kf_new``."""
        return kf_new @ se3.invert(self._kf_dense.poses)

    def _correct(self, kf_new: np.ndarray, C: np.ndarray | None = None) -> None:
        """Move the surfels and the current pose by each keyframe's correction ``C`` (:meth:`_corrections`)."""
        C = self._corrections(kf_new) if C is None else C
        self.counts["map_corrections"] += 1
        m = self.map
        n = m.size
        if n and not self.frozen:  # localise only: the loaded map never moves
            frames = np.asarray(self._fused_frames, np.int64)
            anchors = np.asarray(self._fused_anchor, np.int64)
            row = np.clip(np.searchsorted(frames, m.first_seen), 0, len(frames) - 1)
            a = anchors[row]
            m.transform_surfels(C[a, :3, :3].astype(np.float32), C[a, :3, 3].astype(np.float32))
        self.T_world_cam = se3.orthonormalize(kf_new[self._anchor[-1]] @ self._T_kf_cam[-1])
        self._kf_dense.poses[:] = kf_new

    def _correction(self, k: int) -> np.ndarray:
        """``C_k = T_kf_graph inv(T_kf_dense)``: maps dense-frame poses near keyframe ``k`` into the graph frame."""
        return self.sparse.keyframe_poses()[k] @ se3.invert(self._kf_dense.poses[k])

    def _pnp_match(self, frame: RGBDFrame, T_pred: np.ndarray) -> KeyframeMatch | None:
        """PnP pose and inliers against the reference keyframe, in the dense frame (the graph frame may have
        moved: the keyframe's pending correction is undone). The coarse match (PnP-RANSAC, sub-pixel inliers, the
        RGB-D refinement with ``hybrid.pnp_rgbd_refine``) serves unless ``hybrid.joint_fine_match``: the pose only
        checks ICP (``pnp_check``, a 5 cm / 5 deg gate), starts it again or measures the joint term's pixel noise,
        and the joint term uses the inliers."""
        C = self._correction(self.sparse.n_keyframes - 1)
        m = self.sparse.match_reference_keyframe(frame, C @ T_pred, feats=self._features(frame),
                                                 coarse=not (self.joint and self.cfg.hybrid.joint_fine_match))
        if m is None:
            return None
        C_inv = se3.invert(self._correction(m.kf_id))
        # inliers on occluding contours (sparse.features.depth_edge_rel, in this frame's depth) are no fixed points:
        # left out of the joint term and the PnP check (in a plain-walled office, cabinet silhouettes against the
        # wall raised the hybrid's frame-to-frame error by 40 %)
        keep = ~on_occluding_contour(frame.depth_m, m.uv_cur, self._contour_cfg)
        return KeyframeMatch(se3.orthonormalize(C_inv @ m.T_world_cam), m.kf_id,
                             se3.transform_points(C_inv, m.points_world[keep]), m.uv_cur[keep])

    def _trusted(self, match: KeyframeMatch) -> bool:
        """Whether ``match`` has the inliers (``hybrid.pnp_trust_min_inliers``, at least one) for its PnP pose to add
        the joint term or check ICP."""
        return len(match.uv_cur) >= max(1, self.cfg.hybrid.pnp_trust_min_inliers)

    def _disagrees(self, T_icp: np.ndarray, match: KeyframeMatch) -> bool:
        """Whether the ICP pose ``T_icp`` and the PnP pose of ``match`` disagree: beyond the metric bounds
        (``hybrid.pnp_check_max_m`` / ``_deg``) and with too few of the PnP inliers consistent with the ICP pose
        (``hybrid.pnp_check_min_inlier_fraction``)."""
        h = self.cfg.hybrid
        if not self._trusted(match):
            return False
        dt, dr = se3.pose_error(T_icp, match.T_world_cam)
        if dt <= h.pnp_check_max_m and dr <= h.pnp_check_max_deg:
            return False
        if h.pnp_check_min_inlier_fraction <= 0:
            return True
        consistent = reprojection_inliers(se3.transform_points(se3.invert(T_icp), match.points_world), match.uv_cur,
                                          self.intr, self.sparse.cfg.features.reprojection_error_px)
        return np.count_nonzero(consistent) < h.pnp_check_min_inlier_fraction * len(consistent)

    def trajectory(self, kf_poses: np.ndarray | None = None) -> Trajectory:
        """Every frame's pose ``T_world_kf T_kf_cam`` with ``kf_poses`` ``(K, 4, 4)`` (default: the graph's)."""
        kf = self.sparse.keyframe_poses() if kf_poses is None else kf_poses
        T = kf[np.asarray(self._anchor)] @ np.asarray(self._T_kf_cam)
        return Trajectory(np.asarray(self._stamps), T)

    def _correction_m(self, kf_new: np.ndarray) -> float:
        """How far (m) the final graph poses ``kf_new`` move the farthest keyframe from its current pose, the first
        keyframe's rigid move taken out."""
        C0 = kf_new[0] @ se3.invert(self._kf_dense.poses[0])
        rel = se3.invert(C0) @ kf_new
        return float(np.linalg.norm(rel[:, :3, 3] - self._kf_dense.poses[:, :3, 3], axis=1).max())

    def _correction_is_noise(self, moved_m: float) -> bool:
        """The refined edges are distrusted, and the final graph poses (the PnP edges') move no keyframe by more than
        ``hybrid.untrusted_min_correction_m`` (``moved_m``: :meth:`_correction_m`; see :class:`HybridConfig`)."""
        return self.sparse.dense_edges_trusted is False and moved_m <= self.cfg.hybrid.untrusted_min_correction_m

    def finish(self) -> SlamResult:
        res = self.sparse.finish()
        kf_final = res.keyframe_poses
        if self.cfg.hybrid.loop_correction and len(self._kf_dense):
            self.counts["final_correction_m"] = self._correction_m(kf_final)
            if self._correction_is_noise(self.counts["final_correction_m"]):
                self.counts["loop_correction_skipped"] = 1
                kf_final = self._kf_dense.poses.copy()
            else:
                self._correct(kf_final)
        if self.cfg.hybrid.loop_correction and self.counts["map_corrections"] > 0 and self._recorder is not None:
            self._recorder.repose(self.trajectory(kf_final))  # the saved keyframes follow the corrected map
        out = self._result({"tracking_failures": self.failures, "tracking_failure_reasons": self.failure_reasons,
                            "photometric": self.photometric, "joint_features": self.joint, **self.counts,
                            "shape_relocalisations_tried": self.relocalisations["tried"],
                            "shape_relocalisations": self.relocalisations["tracked"],
                            "relocalisations_refused": self.relocalisations["refused_implausible"],
                            "weak_frames": self.weak_frames,
                            "depth_noise_m": (float(np.median(self._depth_noise_per_frame))
                                              if self._depth_noise_per_frame else None),
                            # recovered frames by either route, the key every tracker reports
                            "relocalisations": self.counts["relocalisations_tracked"] + self.relocalisations["tracked"],
                            **sparse_metrics(self.sparse, res)})
        # with nothing corrected at all, the frames keep their tracked poses (T_kf T_kf_cam would round them)
        if self.cfg.hybrid.loop_correction and self.counts["map_corrections"] > 0:
            out.trajectory_override = self.trajectory(kf_final)
        out.loop_stamps = loop_stamps(res, self._stamp_of_frame)
        return out
