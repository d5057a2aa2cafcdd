"""The dense front end: predict, render, ICP, fuse and the motion update, as one component with a public interface.

:class:`DenseFrontEnd` is what the surfel trackers (``dense``, ``hybrid``) hold and drive from their own ``process``:

- frames: :meth:`~DenseFrontEnd.prepare` (another thread), :meth:`~DenseFrontEnd.begin_frame` (the frame's pyramid
  becomes the ICP source), :meth:`~DenseFrontEnd.end_frame` (it becomes the previous frame's);
- tracking: :meth:`~DenseFrontEnd.predict`, :meth:`~DenseFrontEnd.render_target`, :meth:`~DenseFrontEnd.register`
  (ICP of the source against a rendered target), :meth:`~DenseFrontEnd.failure_of` (the failure policy),
  :meth:`~DenseFrontEnd.relocalise_shape`;
- the motion state (:class:`~surfelslam.slam.motion.TrackingState`, ``front.state``) and its updates
  (:mod:`surfelslam.slam.motion`);
- the map: :meth:`~DenseFrontEnd.fuse` into the :class:`~surfelslam.slam.mapper.FusingMapper` it holds
  (``front.mapper``), and with a loaded map the localisation of the first frames (:mod:`.map_localiser`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from concurrent.futures import Future

import numpy as np

from surfelslam.backend.sparse_slam import features_for_width
from surfelslam.mapping.render import RenderConfig, render
from surfelslam.mapping.surfel_map import SurfelMap
from surfelslam.slam.config import SlamConfig
from surfelslam.slam.frame import FrameResult, FrameStatus, PreparedFrame, StageTimer, prepared_for
from surfelslam.slam.map_localiser import NOT_LOCALISED, MapLocaliser, verify_icp
from surfelslam.slam.mapper import FusingMapper
from surfelslam.slam.motion import MotionModel, TrackingState, step_and_pose
from surfelslam.tracking.features import Features
from surfelslam.tracking.geometric import geometric_guess
from surfelslam.tracking.icp import ICPResult, ICPStatus, ReprojectionTerm, icp, icp_failure, photometric_term
from surfelslam.tracking.photometric import (
    IntensityPyramid,
    PhotometricTerm,
    colour_switch,
    intensity_from_rgb,
    intensity_pyramid,
)
from surfelslam.tracking.preprocess import FramePyramid, level_for_width, pyramid_from_maps
from surfelslam.types import ColourCamera, Intrinsics, RGBDFrame

#: metres beyond the source's reach + the coarsest ICP gate that the tracking target still draws: a correction of the
#: prediction the tracker accepts (a few cm, some degrees) moves a source point's depth in the rendered view by up to
#: ~0.3 m (6 deg at a 5 m image corner)
TARGET_FAR_SLACK_M = 0.5


def tracking_render_config(cfg: SlamConfig) -> RenderConfig:
    """``cfg.render`` with its far limit cut to what ICP can associate: a model point farther than the source's
    ``preprocess.max_depth_m`` plus the coarsest ``icp.dist_thresh_m`` (plus :data:`TARGET_FAR_SLACK_M`) lies beyond
    every association gate from any source point on its ray. On a floor most of the frustum's surfels are farther
    rooms; they cost render time and can only pull the photometric term to the wrong surface."""
    reach = cfg.preprocess.max_depth_m + max(cfg.icp.dist_thresh_m) + TARGET_FAR_SLACK_M
    if not cfg.render.min_depth_m < reach < cfg.render.max_depth_m:
        return cfg.render
    return dataclasses.replace(cfg.render, max_depth_m=reach)


class DenseFrontEnd:
    """Frame-to-model dense tracking against a surfel map, and fusion into it (see the module docstring).

    ``colour_registered``: the sequence's colour and depth pixels see the same rays (``tracking.photometric``).
    ``colour_camera``: the sequence's separate colour camera, if known. ``features_of``: the ORB features of a frame
    for the saved map and the map localisation (default: extracted by the mapper); ``features_later``: a future of
    them for the saved map, or ``None`` (see :class:`FusingMapper`). ``tracker_name``: written into
    the saved map.
    """

    def __init__(self, intr: Intrinsics, cfg: SlamConfig, colour_registered: bool = True,
                 colour_camera: ColourCamera | None = None,
                 features_of: Callable[[RGBDFrame], Features] | None = None, tracker_name: str = "",
                 features_later: Callable[[RGBDFrame], Future | None] | None = None):
        self.intr = intr
        self.cfg = cfg
        self.photometric = cfg.icp.photometric_weight > 0 and colour_switch(cfg.tracking.photometric,
                                                                            colour_registered)
        self._src_intensity: IntensityPyramid | None = None
        self._tgt_intensity: IntensityPyramid | None = None
        self.track_level = level_for_width(intr.width, cfg.tracking.max_width_px)
        self.mapper = FusingMapper(intr, cfg, min_levels=self.track_level + cfg.icp.levels,
                                   track_level=self.track_level, colour_camera=colour_camera,
                                   features_of=features_of, tracker_name=tracker_name, features_later=features_later)
        level_intrinsics = self.mapper.pre.level_intrinsics
        self.target = FramePyramid.empty(level_intrinsics[self.track_level], len(level_intrinsics) - self.track_level)
        self.state = TrackingState()
        self.motion = MotionModel(cfg.tracking, cfg.icp, self.state)
        self._localiser: MapLocaliser | None = None  # with a loaded map, until the first frame is localised
        self.render_cfg = tracking_render_config(cfg)

    @property
    def map(self) -> SurfelMap:
        """The surfel map (the mapper's; replaced when a loaded map is refused)."""
        return self.mapper.map

    # ---- frames
    def source_intensity(self, frame: RGBDFrame) -> IntensityPyramid:
        """The frame's intensity pyramid on the tracking levels' grid (2x2 block means down to the tracking
        level, then ``icp.levels`` levels)."""
        pyr = intensity_pyramid(intensity_from_rgb(frame.rgb), self.track_level + self.cfg.icp.levels,
                                gradients=False)
        return IntensityPyramid(pyr.intensity[self.track_level:])

    def prepare(self, frame: RGBDFrame) -> PreparedFrame:
        """Preprocessing (and the intensity pyramid when tracking photometrically), for another thread."""
        p = self.mapper.prepare(frame)
        if self.photometric:
            t0 = time.perf_counter()
            p.intensity = self.source_intensity(frame)
            p.timings_ms["preprocess"] += (time.perf_counter() - t0) * 1e3
        return p

    def discard(self, prepared: PreparedFrame | None) -> None:
        """A prepared frame that will not be processed: its pyramid goes back to the pool."""
        self.mapper.discard(prepared)

    def begin_frame(self, frame: RGBDFrame, prepared: PreparedFrame | None = None) -> None:
        """Make the frame the ICP source: its pyramid (and intensity pyramid), prepared or computed here."""
        self.mapper.preprocess(frame, prepared)
        if not self.photometric:
            return
        p = prepared_for(frame, prepared)
        self._src_intensity = p.intensity if p is not None and p.intensity is not None else \
            self.source_intensity(frame)

    def end_frame(self) -> None:
        """End of a frame: its pyramid becomes the previous frame's (:meth:`FusingMapper.retire_source`)."""
        self.mapper.retire_source()

    @property
    def track_source(self) -> FramePyramid:
        """The current frame's pyramid from the tracking level down (what ICP registers)."""
        return self.at_track_level(self.mapper.source)

    def full_source(self) -> FramePyramid | None:
        """The current frame's whole pyramid when its finest level is computed (the input is not reduced first),
        else ``None``."""
        return self.mapper.source if self.mapper.first_level == 0 else None

    def at_track_level(self, pyr: FramePyramid) -> FramePyramid:
        """The levels of ``pyr`` from the tracking level down (views, no copy)."""
        return FramePyramid(pyr.levels[self.track_level:])

    # ---- tracking
    def predict(self) -> np.ndarray:
        """Constant-velocity prediction of ``T_world_cam`` ``(4, 4)`` for the next frame."""
        T = self.state.T_world_cam
        assert T is not None
        if not self.cfg.tracking.constant_velocity:
            return T.copy()
        return T @ self.state.velocity

    def render_target(self, T_world_cam: np.ndarray) -> FramePyramid:
        """The map rendered at ``T_world_cam`` at the tracking resolution, straight into the target pyramid's
        level 0 (geometry, and the intensity pyramid of the rendered colour when tracking photometrically)."""
        lvl0 = self.target[0]
        view = render(self.map, T_world_cam, lvl0.intrinsics, self.render_cfg, vertex_out=lvl0.vertex,
                      normal_out=lvl0.normal, attributes=self.photometric)
        if self.photometric:
            self._tgt_intensity = intensity_pyramid(intensity_from_rgb(view.colour, view.valid), self.cfg.icp.levels,
                                                    gradients=True)
        return pyramid_from_maps(view.vertex_cam, view.normal_cam, lvl0.intrinsics, len(self.target),
                                 self.cfg.preprocess, out=self.target)

    def photometric_term(self) -> PhotometricTerm | None:
        """The joint photometric term of the current source against the last rendered target (or ``None``)."""
        if not self.photometric or self._src_intensity is None or self._tgt_intensity is None:
            return None
        return photometric_term(self._src_intensity, self._tgt_intensity, self.cfg.icp)

    def register(self, target: FramePyramid, T_init: np.ndarray,
                 reprojection: ReprojectionTerm | None = None, levels: int | None = None) -> ICPResult:
        """ICP of the current source against ``target`` (the last :meth:`render_target`) from ``T_init``
        (``T_target_source``, ``(4, 4)``), with the photometric term and an optional reprojection term; ``levels``:
        only that many of the finest pyramid levels (``None``: ``icp.levels``)."""
        cfg = self.cfg.icp
        if levels is not None and levels < cfg.levels:
            cfg = dataclasses.replace(cfg, levels=levels)
        return icp(self.track_source, target, T_init=T_init, cfg=cfg, reprojection=reprojection,
                   photometric=self.photometric_term())

    def register_frame_to_frame(self, T_init: np.ndarray) -> ICPResult:
        """ICP of the current source against the previous frame's pyramid (geometry only) from ``T_init``."""
        return icp(self.track_source, self.at_track_level(self.mapper.previous), T_init=T_init, cfg=self.cfg.icp)

    def failure_of(self, res: ICPResult) -> str | None:
        """Why ``res`` cannot be used (an :class:`~surfelslam.tracking.icp.ICPStatus` value), or ``None``.

        A degenerate result (one plane, two planes, a corridor) is usable when ``tracking.fuse_weak_frames`` is on
        and everything else about it holds: ICP kept the prediction along the weak directions
        (``icp.weak_direction_ratio``) and registered the frame along the others, so the pose and the map stay
        updated where the view constrains them instead of freezing until the view improves.
        """
        failure = icp_failure(res)
        if failure == ICPStatus.TOO_FEW_INLIERS and self._sees_unmapped_space(res):
            return None
        if failure != ICPStatus.DEGENERATE or not self.cfg.tracking.fuse_weak_frames:
            return failure
        icfg = self.cfg.icp
        usable = (icfg.weak_direction_ratio > 0 and res.levels[-1].stop not in (ICPStatus.TOO_FEW_INLIERS,
                                                                               ICPStatus.SOLVER)
                  and res.inlier_fraction >= icfg.min_inlier_fraction
                  and res.motion_m <= icfg.max_translation_m and res.motion_deg <= icfg.max_rotation_deg)
        return None if usable else failure

    def _sees_unmapped_space(self, res: ICPResult) -> bool:
        """Whether ``res`` failed on its inlier fraction only because much of the view lies outside the map (a room
        seen for the first time through a doorway): the finest level kept its inlier count, and the inliers are
        ``icp.min_inlier_fraction`` of the source points that land on the rendered model. Such a frame is tracked and
        fused, so the map grows into the new space; refusing it would leave the map, and every later frame, short."""
        fine = res.levels[-1]
        return (fine.stop not in (ICPStatus.TOO_FEW_INLIERS, ICPStatus.SOLVER, ICPStatus.MAX_ITERATIONS)
                and not res.degenerate
                and fine.overlap_inlier_fraction >= self.cfg.icp.min_inlier_fraction
                and res.motion_m <= self.cfg.icp.max_translation_m and res.motion_deg <= self.cfg.icp.max_rotation_deg)

    def relocalise_shape(self, T_world_render: np.ndarray | None = None,
                         time_s: float | None = None) -> tuple[ICPResult, np.ndarray] | None:
        """The current source against the map rendered at ``T_world_render`` (default: the last tracked pose),
        from the shape-feature guess: ``(ICP result, T_world_render)`` when ICP from the guess succeeds and, given
        the frame's time ``time_s`` (s), the pose is reachable from the last tracked one
        (:meth:`MotionModel.plausible_jump`); else ``None``."""
        reloc = self.state.relocalisations
        reloc["tried"] += 1
        T_ref = self.state.T_world_last_tracked if T_world_render is None else T_world_render
        target = self.render_target(T_ref)
        src = self.track_source
        g = geometric_guess(src[0].vertex, src[0].normal, target[0].vertex, target[0].normal,
                            self.cfg.tracking.shape_guess)
        if g.T_target_source is None:
            return None
        res = self.register(target, g.T_target_source)
        if icp_failure(res) is not None:
            return None
        if time_s is not None and not self.motion.plausible_jump(step_and_pose(T_ref, res)[1], time_s):
            return None
        reloc["tracked"] += 1
        return res, T_ref

    # ---- the map
    def fuse(self, frame: RGBDFrame, T_world_cam: np.ndarray) -> None:
        """Fuse the current frame at ``T_world_cam`` ``(4, 4)`` (nothing in a localise-only run)."""
        self.mapper.fuse(frame, T_world_cam)

    def use_prior_map(self, saved, localize_only: bool = False) -> None:
        """Continue from the saved map ``saved`` (:meth:`FusingMapper.use_prior_map`); the first frames are localised
        in it (:mod:`surfelslam.slam.map_localiser`)."""
        self.mapper.use_prior_map(saved, localize_only)
        self._localiser = MapLocaliser(saved.keyframes, self.intr, features_for_width(self.cfg.sparse, self.intr.width),
                                       self.cfg.map_reuse)

    def first_pose(self, frame: RGBDFrame, t: StageTimer) -> np.ndarray | None:
        """The first frame's pose: the identity (it defines the world frame), or with a loaded map its verified pose
        in it (``None``: not localised yet)."""
        if self._localiser is None:
            return np.eye(4)
        rep = self.mapper.prior_report
        if not self.mapper.frozen and rep["frames_tried"] >= self.cfg.map_reuse.localise_max_frames:
            # not localised in localise_max_frames frames: a map of another place, or no overlap. Refused, not
            # forced: this frame starts a new map (a localise-only run has none to start and keeps trying)
            self._localiser = None
            self.mapper.start_new_map()
            rep["new_map_frame_at"] = int(frame.index)
            return np.eye(4)
        rep["frames_tried"] += 1
        T = self._localise_in_map(frame)
        t.lap("localise")
        return T

    def _localise_in_map(self, frame: RGBDFrame) -> np.ndarray | None:
        """Place recognition and PnP against the loaded keyframes, then ICP against the loaded surfels rendered at
        each PnP pose (most inliers first); the first pose that passes :func:`verify_icp`, or ``None``."""
        rep = self.mapper.prior_report
        guesses = self._localiser.guesses(self.mapper.keyframe_features(frame))
        reason = "no_keyframe_verified_by_pnp"
        for g in guesses:
            target = self.render_target(g.T_world_cam)
            res = self.register(target, np.eye(4))
            why = verify_icp(res, self.cfg.map_reuse)
            if why is None:
                self._localiser = None
                rep.update(localised=True, frame=int(frame.index), timestamp=float(frame.timestamp),
                           keyframe=int(g.kf_id), pnp_inliers=g.n_inliers,
                           icp_inlier_fraction=float(res.inlier_fraction), icp_rmse_m=float(res.rmse_m))
                rep.pop("last_failure", None)
                return step_and_pose(g.T_world_cam, res)[1]
            reason = why
        rep["last_failure"] = reason
        return None

    def first_status(self) -> FrameStatus:
        """The first posed frame's status: relocalised when it was localised in a loaded map, else tracked."""
        rep = self.mapper.prior_report
        return FrameStatus.RELOCALISED if rep is not None and rep["localised"] else FrameStatus.TRACKED

    def not_localised(self, frame: RGBDFrame, t: StageTimer) -> FrameResult:
        """A frame before the run is localised in the loaded map: lost, not fused, no pose written."""
        self.end_frame()
        self.motion.count_not_localised(NOT_LOCALISED)
        return FrameResult(index=frame.index, timestamp=frame.timestamp, T_world_cam=np.eye(4), tracked=False,
                           fused=False, reason=NOT_LOCALISED, timings_ms=t.ms, map_points=self.map.n_alive,
                           status=FrameStatus.LOST, posed=False)
