"""Where the hybrid tracker puts a frame: ICP from the velocity guess, PnP guesses and checks, relocalisation.

:class:`HybridLocaliser` drives the dense front end (:class:`~surfelslam.slam.frontend.DenseFrontEnd`) with the sparse
back end's PnP poses (stages 1 and 2 of :mod:`surfelslam.slam.hybrid`); it decides nothing about fusing.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass

import numpy as np

from surfelslam.backend.sparse_slam import KeyframeMatch, SparseSlam, features_for_width
from surfelslam.geometry import se3
from surfelslam.slam.config import HybridConfig, SlamConfig
from surfelslam.slam.frame import StageTimer
from surfelslam.slam.frontend import DenseFrontEnd
from surfelslam.slam.hybrid_anchors import KeyframeAnchors
from surfelslam.slam.motion import step_and_pose
from surfelslam.tracking.features import (
    Features,
    on_occluding_contour,
    reprojection_inliers,
    reprojection_spread_px,
    to_grey,
)
from surfelslam.tracking.icp import ICPResult, ReprojectionTerm
from surfelslam.types import Intrinsics, RGBDFrame

#: failure of a relocalised pose the camera could not have reached in the time since the last tracked frame
IMPLAUSIBLE = "relocalisation_implausible"
#: failure of an ICP pose that disagrees with the PnP pose
DISAGREES = "disagrees_with_pnp"
#: failure of an ICP pose that moved the motion prediction farther than the camera could (MotionModel.jumped)
JUMPED = "implausible_correction"
#: pyramid levels of the retry of a jumped registration: the two finest, whose correspondence gates
#: (``icp.dist_thresh_m``, 0.1 and 0.2 m by default) keep ICP in the prediction's basin; the coarser ones (0.4 and 1 m)
#: are where a view of plain walls slid 35 cm from a prediction 3 cm off
FINE_RETRY_LEVELS = 2


@dataclass
class Localised:
    """Where localising one frame ended: the kept ICP result, its failure (``None``: usable), its pose, the PnP or
    relocalisation guess, and whether the result was tracked against the map rendered at the previous pose."""

    res: ICPResult | None = None
    failure: str | None = None
    T_new: np.ndarray | None = None
    guess: np.ndarray | None = None
    from_prev: bool = False
    relocalised: bool = False  # the result comes from a relocalisation (after too many failures)
    guess_trusted: bool = False  # the guess is a PnP pose with hybrid.pnp_trust_min_inliers inliers


def joint_term_weight(h: HybridConfig, finest_robust_scale_m: float, depth_noise_m: float) -> float:
    """Weight (m^2) of a unit feature residual in the joint term: ``hybrid.joint_weight`` point-to-plane pairs whose
    residual is ``hybrid.joint_weight_unit``: the finest robust scale, or ``depth_noise_m``, the depth noise the last
    tracked frame's ICP measured (the scale until one was measured, ``depth_noise_m`` 0)."""
    unit_m = depth_noise_m if h.joint_weight_unit == "depth_noise" and depth_noise_m > 0 else finest_robust_scale_m
    return h.joint_weight * unit_m**2


class HybridLocaliser:
    """ICP of the current frame guided by PnP against the keyframes (see the module docstring).

    Args:
        front: the dense front end (its source is the current frame).
        sparse: the sparse back end (PnP against the reference keyframe, relocalisation against all).
        anchors: the keyframes' dense poses (the graph frame's pending corrections are undone with them).
        joint: whether ICP has the inliers' reprojection terms (``hybrid.joint_features``).
        features_of: the current frame's ORB features (extracted at most once per frame).
        worker: where the frame's match runs while the main thread renders the map (the main thread waits for it
            before ICP: results do not depend on the timing).
    """

    def __init__(self, front: DenseFrontEnd, sparse: SparseSlam, anchors: KeyframeAnchors, cfg: SlamConfig,
                 intr: Intrinsics, joint: bool, features_of: Callable[[RGBDFrame], Features], worker: Executor):
        self.front = front
        self.sparse = sparse
        self.anchors = anchors
        self.cfg = cfg
        self.intr = intr
        self.joint = joint
        self._features_of = features_of
        self._contour_cfg = features_for_width(cfg.sparse, intr.width).features
        # finest-level point-to-plane noise of every tracked frame (the last weighs the joint term)
        self.depth_noise_per_frame: list[float] = []
        self._worker = worker
        self.counts = {"pnp_guesses_tried": 0, "pnp_guesses_tracked": 0, "relocalisations_tried": 0,
                       "relocalisations_tracked": 0, "pnp_disagreements": 0, "pnp_unsupported": 0,
                       "unconverged_slides": 0, "fine_retries_tried": 0, "fine_retries_tracked": 0}

    def record_noise(self, res: ICPResult) -> None:
        """Keep a tracked frame's finest-level depth noise (when its finest ICP level is the input's)."""
        if res.levels and res.levels[-1].level == 0:
            self.depth_noise_per_frame.append(res.levels[-1].geometric_noise_m)

    def icp_from(self, T_render: np.ndarray, T_init_rel: np.ndarray, match: KeyframeMatch | None = None,
                 match_of: Callable[[], KeyframeMatch | None] | None = None):
        """ICP of the current source against the map rendered at ``T_render``, jointly with ``match``'s
        reprojection terms when ``hybrid.joint_features`` is on; returns (res, failure, T). ``match_of``: a match
        to wait for instead, once the map is rendered (one found alongside the rendering)."""
        front = self.front
        target = front.render_target(T_render)
        if match_of is not None:
            match = match_of()
        term = self._reprojection_term(T_render, match)
        res = front.register(target, se3.orthonormalize(T_init_rel), reprojection=term)
        return res, front.failure_of(res), step_and_pose(T_render, res)[1]

    def _reprojection_term(self, T_render: np.ndarray, match: KeyframeMatch | None) -> ReprojectionTerm | None:
        h = self.cfg.hybrid
        if match is None or not self.joint or h.joint_weight == 0 or not self.trusted(match):
            return None
        pts_t = se3.transform_points(se3.invert(T_render), match.points_world)
        sigma = max(h.joint_sigma_px, self._match_spread_px(match))
        noise = self.depth_noise_per_frame[-1] if self.depth_noise_per_frame else 0.0
        return ReprojectionTerm(pts_t, match.uv_cur, self.intr, sigma, h.joint_huber,
                                joint_term_weight(h, self.cfg.icp.finest_robust_scale_m, noise))

    def _match_spread_px(self, match: KeyframeMatch) -> float:
        """Robust spread (px) of the inliers' reprojection residuals at the PnP pose: the data's own pixel noise
        (larger where colour and depth are misregistered or keypoints are poorly localised)."""
        X = se3.transform_points(se3.invert(match.T_world_cam), match.points_world)
        return reprojection_spread_px(X, match.uv_cur, self.intr)

    def relocalise(self, frame: RGBDFrame, T_prev: np.ndarray, t: StageTimer) -> Localised:
        """After too many failures: PnP against every keyframe, then ICP from that pose; else the shape guess."""
        front = self.front
        loc = Localised()
        self.counts["relocalisations_tried"] += 1
        found = self.sparse.relocalise(frame, feats=self._features_of(frame))
        t.lap("relocalise")
        if found is not None:
            found = (se3.orthonormalize(se3.invert(self.anchors.correction(found[1])) @ found[0]), found[1])
            loc.res, loc.failure, loc.T_new = self.icp_from(found[0], np.eye(4))
            t.lap("icp")
            if loc.failure is None and not front.motion.plausible_jump(loc.T_new, frame.time_s):
                loc.failure = IMPLAUSIBLE
            if loc.failure is None:
                self.counts["relocalisations_tracked"] += 1
                front.state.velocity = np.eye(4)
            elif loc.failure != IMPLAUSIBLE and front.motion.plausible_jump(found[0], frame.time_s):
                loc.guess = found[0]  # ICP failed from a reachable PnP pose: the frame is bridged there
            # a pose refused as out of reach is no bridge either: the frame stays lost at the prediction
        if (loc.res is None or loc.failure is not None) and self.cfg.tracking.relocalise_after_failures > 0:
            shape = front.relocalise_shape(T_prev, frame.time_s)  # no PnP pose (no texture): from the depth alone
            t.lap("relocalise")
            if shape is not None:
                loc.res, loc.failure = shape[0], None
                loc.T_new = se3.orthonormalize(T_prev @ loc.res.T_target_source)
                front.state.velocity = np.eye(4)
        loc.relocalised = True
        return loc

    def localise(self, frame: RGBDFrame, T_prev: np.ndarray, T_pred: np.ndarray, t: StageTimer) -> Localised:
        """ICP from the constant-velocity guess (jointly with the PnP inliers), checked against the PnP pose, and
        retried from the PnP pose when it fails, is degenerate or disagrees."""
        h = self.cfg.hybrid
        loc = Localised()
        trusted = self.front.state.failures_in_a_row == 0 or not h.pnp_when_velocity_untrusted
        match = None
        if not trusted:
            match = self.pnp_match(frame, T_pred)
            t.lap("pnp")
        if trusted:
            T_init_rel = se3.invert(T_prev) @ T_pred
            if self.joint or h.pnp_check:  # the match is found while the map is rendered (both release the GIL)
                pending = self._worker.submit(self.pnp_match, frame, T_pred)
                loc.res, loc.failure, loc.T_new = self.icp_from(T_prev, T_init_rel, match_of=pending.result)
                match = pending.result()
            else:
                loc.res, loc.failure, loc.T_new = self.icp_from(T_prev, T_init_rel)
            loc.from_prev = True
            t.lap("icp")
            motion = self.front.motion
            if loc.failure is None and motion.jumped(loc.res, frame.time_s):
                loc.failure = JUMPED
            elif loc.failure is None and motion.slid_unconverged(loc.res):
                loc.failure = JUMPED
                self.counts["unconverged_slides"] += 1
            if loc.failure == JUMPED:
                self._fine_retry(loc, T_prev, T_init_rel, match, frame.time_s)
                t.lap("icp")
        bad = loc.res is None or loc.failure is not None or loc.res.degenerate
        if match is None and h.pnp_retry and bad:
            match = self.pnp_match(frame, T_pred)
            t.lap("pnp")
        loc.guess = None if match is None else match.T_world_cam
        loc.guess_trusted = match is not None and self.trusted(match)
        first_ok = loc.res is not None and loc.failure is None
        if first_ok and loc.guess is not None and h.pnp_check and self.disagrees(loc.T_new, match):
            first_ok = False
            loc.failure = DISAGREES
            self.counts["pnp_disagreements"] += 1
        if loc.guess is not None and h.pnp_retry and (not first_ok or loc.res.degenerate):
            self._retry_from_pnp(loc, match, first_ok, T_pred, frame.time_s, t)
        elif loc.res is None:  # untrusted velocity and no PnP guess: the velocity guess after all
            loc.res, loc.failure, loc.T_new = self.icp_from(T_prev, se3.invert(T_prev) @ T_pred)
            loc.from_prev = True
            t.lap("icp")
        return loc

    def _fine_retry(self, loc: Localised, T_prev: np.ndarray, T_init_rel: np.ndarray, match: KeyframeMatch | None,
                    time_s: float) -> None:
        """A registration from the prediction that jumped (or slid) is retried from the prediction against the same
        rendered map at the :data:`FINE_RETRY_LEVELS` finest levels only: the coarse levels' wide correspondence
        gates can carry ICP into another basin where the view constrains it weakly (plain walls, a corridor), the
        fine ones cannot. Its result replaces ``loc``'s when it is usable, within the jump bound and not a slide;
        else the frame stays a jump (held, or retried from the PnP pose)."""
        self.counts["fine_retries_tried"] += 1
        front = self.front
        res = front.register(front.target, se3.orthonormalize(T_init_rel),
                             reprojection=self._reprojection_term(T_prev, match), levels=FINE_RETRY_LEVELS)
        if (front.failure_of(res) is None and not front.motion.jumped(res, time_s)
                and not front.motion.slid_unconverged(res)):
            loc.res, loc.failure, loc.T_new = res, None, step_and_pose(T_prev, res)[1]
            self.counts["fine_retries_tracked"] += 1

    def _retry_from_pnp(self, loc: Localised, match: KeyframeMatch, first_ok: bool, T_pred: np.ndarray,
                        time_s: float, t: StageTimer) -> None:
        """ICP again from the PnP pose; its result replaces ``loc``'s when it is good (or the first one was not).

        A result beyond :meth:`MotionModel.jumped`'s bound of the prediction ``T_pred`` (at ``time_s``) is a jump
        (held at the prediction) unless the PnP pose supports it (:meth:`_supports`): ICP from a PnP pose of a few
        inliers, itself centimetres off, converged 12 cm from the truth on a floor and was fused as tracked."""
        self.counts["pnp_guesses_tried"] += 1
        r2, f2, T2 = self.icp_from(loc.guess, np.eye(4), match)
        t.lap("icp")
        # after a jump the PnP pose is the evidence: ICP from it must agree with it
        if f2 is None and (self.cfg.hybrid.pnp_check or loc.failure == JUMPED) and self.disagrees(T2, match):
            f2 = DISAGREES
        if f2 is None and not self.front.motion.within_reach(T_pred, T2, time_s) and not self._supports(match, T2):
            f2 = JUMPED
            self.counts["pnp_unsupported"] += 1
        if f2 is None and (not r2.degenerate or not first_ok):
            loc.res, loc.failure, loc.T_new, loc.from_prev = r2, None, T2, False
            self.counts["pnp_guesses_tracked"] += 1
        elif not first_ok and loc.failure != JUMPED:  # a jump with no better pose from PnP stays one (held)
            loc.res, loc.failure, loc.T_new, loc.from_prev = r2, f2, T2, False

    def _supports(self, match: KeyframeMatch, T: np.ndarray) -> bool:
        """Whether ``match`` is evidence for the pose ``T`` of ICP from its PnP pose: the PnP pose is trusted
        (:meth:`trusted`) and ``T`` stays within the metric bounds of it (``hybrid.pnp_check_max_m`` / ``_deg``).
        Unlike :meth:`disagrees`, inliers that still reproject under ``T`` are no evidence: on a floor ICP from a
        288-inlier PnP pose 4 mm from the truth converged 5.2 cm away, and most of the inliers reprojected there."""
        h = self.cfg.hybrid
        dt, dr = se3.pose_error(T, match.T_world_cam)
        return self.trusted(match) and dt <= h.pnp_check_max_m and dr <= h.pnp_check_max_deg

    def pnp_match(self, frame: RGBDFrame, T_pred: np.ndarray) -> KeyframeMatch | None:
        """PnP pose and inliers against the reference keyframe, in the dense frame (the graph frame may have
        moved: the keyframe's pending correction is undone). The coarse match (PnP-RANSAC, sub-pixel inliers, the
        RGB-D refinement with ``hybrid.pnp_rgbd_refine``) serves unless ``hybrid.joint_fine_match``: the pose only
        checks ICP (``pnp_check``, a 5 cm / 5 deg gate), starts it again or measures the joint term's pixel noise,
        and the joint term uses the inliers."""
        C = self.anchors.correction(self.sparse.n_keyframes - 1)
        m = self._tracked_match(frame, C @ T_pred)
        if m is None:
            m = self.sparse.match_reference_keyframe(frame, C @ T_pred, feats=self._features_of(frame),
                                                     coarse=not (self.joint and self.cfg.hybrid.joint_fine_match))
        if m is None:
            return None
        C_inv = se3.invert(self.anchors.correction(m.kf_id))
        # inliers on occluding contours (sparse.features.depth_edge_rel, in this frame's depth) are no fixed points:
        # left out of the joint term and the PnP check (in a plain-walled office, cabinet silhouettes against the
        # wall raised the hybrid's frame-to-frame error by 40 %)
        keep = ~on_occluding_contour(frame.depth_m, m.uv_cur, self._contour_cfg)
        return KeyframeMatch(se3.orthonormalize(C_inv @ m.T_world_cam), m.kf_id,
                             se3.transform_points(C_inv, m.points_world[keep]), m.uv_cur[keep])

    @property
    def tracks_features(self) -> bool:
        """Whether the reference keyframe's points are tracked into each frame (``hybrid.frame_features``) rather
        than matched with the frame's own ORB features (also when the joint term asks for the fine match)."""
        h = self.cfg.hybrid
        return h.frame_features == "tracked" and not (self.joint and h.joint_fine_match)

    def _tracked_match(self, frame: RGBDFrame, T_pred_graph: np.ndarray) -> KeyframeMatch | None:
        """With ``hybrid.frame_features = "tracked"`` (and no fine match asked for): the reference keyframe's points
        tracked into the frame from the prediction ``T_pred_graph`` (graph frame), when at least
        ``hybrid.pnp_trust_min_inliers`` are found; else ``None`` (the frame's ORB features are then matched)."""
        if not self.tracks_features:
            return None
        m = self.sparse.track_reference_keyframe(to_grey(frame.rgb), T_pred_graph)
        return m if m is not None and self.trusted(m) else None

    def trusted(self, match: KeyframeMatch) -> bool:
        """Whether ``match`` has the inliers (``hybrid.pnp_trust_min_inliers``, at least one) for its PnP pose to add
        the joint term or check ICP."""
        return len(match.uv_cur) >= max(1, self.cfg.hybrid.pnp_trust_min_inliers)

    def disagrees(self, T_icp: np.ndarray, match: KeyframeMatch) -> bool:
        """Whether the ICP pose ``T_icp`` and the PnP pose of ``match`` disagree: beyond the metric bounds
        (``hybrid.pnp_check_max_m`` / ``_deg``) and with too few of the PnP inliers consistent with the ICP pose
        (``hybrid.pnp_check_min_inlier_fraction``)."""
        h = self.cfg.hybrid
        if not self.trusted(match):
            return False
        dt, dr = se3.pose_error(T_icp, match.T_world_cam)
        if dt <= h.pnp_check_max_m and dr <= h.pnp_check_max_deg:
            return False
        if h.pnp_check_min_inlier_fraction <= 0:
            return True
        consistent = reprojection_inliers(se3.transform_points(se3.invert(T_icp), match.points_world), match.uv_cur,
                                          self.intr, self.sparse.cfg.features.reprojection_error_px)
        return np.count_nonzero(consistent) < h.pnp_check_min_inlier_fraction * len(consistent)
