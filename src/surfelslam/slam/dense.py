"""Dense frame-to-model SLAM (tracker ``dense``).

Dense frame-to-model SLAM (:class:`DenseSlam`), per frame:

1. ``preprocess``: depth -> (2x2 block averaging down to the working level) -> optional bilateral filter ->
   vertex/normal pyramid (source).
2. ``predict``: constant-velocity guess of the new pose.
3. ``render``: the surfel map rendered at the previous pose -> vertex/normal pyramid (target).
4. ``track``: coarse-to-fine projective point-to-plane ICP, source -> target, from the prediction.
5. ``fuse``: on success, the frame is fused into the map at the tracked pose (merge, add, remove);
   on failure the frame is not fused, it is counted, and the pose is the prediction.
   ``relocalise``: after ``tracking.relocalise_after_failures`` failed frames in a row, a failed frame is
   registered to the map rendered at the last tracked pose from the shape-feature guess
   (:mod:`surfelslam.tracking.geometric`), and tracked and fused when ICP from it succeeds.

Working resolution: tracking (render + ICP) and fusion run at the finest pyramid level that is at most
``tracking.max_width_px`` / ``fusion.max_width_px`` wide (default 320 for both). 320x240 input is worked on
as it is; 640x480 input is first block-averaged 2x2 (which also halves the depth noise), so its map has the
density of a 320x240 map (one surfel per 2x2 input pixels; ~7 mm apart at 2 m, about Open3D's default
5.9 mm voxel) and a frame costs about what a 320x240 frame costs. Set both to 0 to work at full resolution
(a 4x denser map, about 4x the time).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from surfelslam.backend.sparse_slam import features_for_width
from surfelslam.geometry import se3
from surfelslam.mapping.render import render
from surfelslam.mapping.surfel_map import SurfelMap
from surfelslam.slam.config import SlamConfig
from surfelslam.slam.frame import FrameResult, FrameStatus, PreparedFrame, SlamResult, StageTimer, prepared_for
from surfelslam.slam.map_localiser import NOT_LOCALISED, MapLocaliser, verify_icp
from surfelslam.slam.mapper import FusingMapper
from surfelslam.slam.registry import register_tracker
from surfelslam.tracking.geometric import geometric_guess
from surfelslam.tracking.icp import ICPResult, ICPStatus, icp, icp_failure, photometric_term, weak_projector
from surfelslam.tracking.photometric import (
    IntensityPyramid,
    PhotometricTerm,
    colour_switch,
    intensity_from_rgb,
    intensity_pyramid,
)
from surfelslam.tracking.preprocess import (
    FramePyramid,
    level_for_width,
    pyramid_from_maps,
)
from surfelslam.types import ColourCamera, Intrinsics, RGBDFrame


@register_tracker("dense")
class DenseSlam(FusingMapper):
    """Frame-to-model dense SLAM: track each frame against the map rendered at the previous pose, then fuse.

    ``colour_registered``: the sequence's colour and depth pixels see the same rays (``tracking.photometric``).
    ``colour_camera``: the sequence's separate colour camera, if known (the map's colours are sampled through it).
    """

    def __init__(self, intr: Intrinsics, cfg: SlamConfig, colour_registered: bool = True,
                 colour_camera: ColourCamera | None = None):
        mode = cfg.tracking.photometric
        self.photometric = cfg.icp.photometric_weight > 0 and colour_switch(mode, colour_registered)
        self._src_intensity: IntensityPyramid | None = None
        self._tgt_intensity: IntensityPyramid | None = None
        self.track_level = level_for_width(intr.width, cfg.tracking.max_width_px)
        super().__init__(intr, cfg, min_levels=self.track_level + cfg.icp.levels, track_level=self.track_level,
                         colour_camera=colour_camera)
        track_intr = self.pre.level_intrinsics[self.track_level]
        self.target = FramePyramid.empty(track_intr, len(self.pre.level_intrinsics) - self.track_level)
        self.T_world_cam: np.ndarray | None = None
        self.T_world_last_tracked: np.ndarray | None = None  # pose of the last tracked (fused) frame
        self.velocity = np.eye(4)  # T_prev_cur of the last good step
        self._v_tracked, self._t_v_tracked = np.eye(4), 0.0  # the last fully tracked step and its time (s)
        self.failures = 0
        self.failures_in_a_row = 0
        self.failure_reasons: dict[str, int] = {}
        self.relocalisations = {"tried": 0, "tracked": 0, "refused_implausible": 0}
        self.t_last_tracked = 0.0  # time (s) of the last tracked frame
        self.weak_frames = 0  # frames registered with weak directions held at the prediction
        self._localiser: MapLocaliser | None = None  # with a loaded map, until the first frame is localised

    def predict(self) -> np.ndarray:
        """Constant-velocity prediction of ``T_world_cam`` for the next frame."""
        assert self.T_world_cam is not None
        if not self.cfg.tracking.constant_velocity:
            return self.T_world_cam.copy()
        return self.T_world_cam @ self.velocity

    def render_target(self, T_world_cam: np.ndarray) -> FramePyramid:
        """The map rendered at ``T_world_cam`` at the tracking resolution, straight into the target pyramid's
        level 0 (geometry, and the intensity pyramid of the rendered colour when tracking photometrically)."""
        lvl0 = self.target[0]
        view = render(self.map, T_world_cam, lvl0.intrinsics, self.cfg.render, vertex_out=lvl0.vertex,
                      normal_out=lvl0.normal, attributes=self.photometric)
        if self.photometric:
            self._tgt_intensity = intensity_pyramid(intensity_from_rgb(view.colour, view.valid), self.cfg.icp.levels,
                                                    gradients=True)
        return pyramid_from_maps(view.vertex_cam, view.normal_cam, lvl0.intrinsics, len(self.target),
                                 self.cfg.preprocess, out=self.target)

    def source_intensity(self, frame: RGBDFrame) -> IntensityPyramid:
        """The frame's intensity pyramid on the tracking levels' grid (2x2 block means down to the tracking
        level, then ``icp.levels`` levels)."""
        pyr = intensity_pyramid(intensity_from_rgb(frame.rgb), self.track_level + self.cfg.icp.levels,
                                gradients=False)
        return IntensityPyramid(pyr.intensity[self.track_level:])

    def prepare(self, frame: RGBDFrame) -> PreparedFrame:
        """Preprocessing (and the intensity pyramid when tracking photometrically), for another thread."""
        p = super().prepare(frame)
        if self.photometric:
            t0 = time.perf_counter()
            p.intensity = self.source_intensity(frame)
            p.timings_ms["preprocess"] += (time.perf_counter() - t0) * 1e3
        return p

    def _set_source_intensity(self, frame: RGBDFrame, prepared: PreparedFrame | None) -> None:
        if not self.photometric:
            return
        p = prepared_for(frame, prepared)
        self._src_intensity = p.intensity if p is not None and p.intensity is not None else \
            self.source_intensity(frame)

    def photometric_term(self) -> PhotometricTerm | None:
        """The joint photometric term of the current source against the last rendered target (or ``None``)."""
        if not self.photometric or self._src_intensity is None or self._tgt_intensity is None:
            return None
        return photometric_term(self._src_intensity, self._tgt_intensity, self.cfg.icp)

    @property
    def track_source(self) -> FramePyramid:
        """The current frame's pyramid from the tracking level down (what ICP registers)."""
        return self._at_track_level(self.source)

    def _at_track_level(self, pyr: FramePyramid) -> FramePyramid:
        """The levels of ``pyr`` from the tracking level down (views, no copy)."""
        return FramePyramid(pyr.levels[self.track_level:])

    def process(self, frame: RGBDFrame, prepared: PreparedFrame | None = None) -> FrameResult:
        """Track ``frame`` and fuse it; ``prepared``: optional :meth:`prepare` output for this frame."""
        t = StageTimer(prepared)
        self._preprocess(frame, prepared)
        self._set_source_intensity(frame, prepared)
        t.lap("preprocess" if prepared is None else None)
        if self.T_world_cam is None:  # the first frame defines the world frame (or is localised in a loaded map)
            T_first = self._first_pose(frame, t)
            if T_first is None:
                return self._not_localised(frame, t)
            self.T_world_cam = T_first
            self.T_world_last_tracked = self.T_world_cam.copy()
            self.t_last_tracked = frame.time_s
            self._fuse(frame, self.T_world_cam)
            t.lap("fuse")
            self._retire_source()
            return FrameResult(frame.index, frame.timestamp, self.T_world_cam.copy(), True, True, None, t.ms,
                               self.map.n_alive, status=self._first_status())
        T_prev = self.T_world_cam
        T_pred = self.predict()
        T_init = se3.orthonormalize(se3.invert(T_prev) @ T_pred)
        target = self.render_target(T_prev)
        t.lap("render")
        if self.cfg.tracking.frame_to_frame_init:
            f2f = icp(self.track_source, self._at_track_level(self.previous), T_init=T_init,
                      cfg=self.cfg.icp)
            if icp_failure(f2f) is None:
                T_init = f2f.T_target_source
        res = icp(self.track_source, target, T_init=T_init, cfg=self.cfg.icp, photometric=self.photometric_term())
        t.lap("icp")
        failure = self.failure_of(res)
        status = FrameStatus.WEAK if failure is None and res.degenerate else FrameStatus.TRACKED
        T_ref = T_prev
        n_reloc = self.cfg.tracking.relocalise_after_failures
        if failure is not None and n_reloc > 0 and self.failures_in_a_row >= n_reloc:
            found = self._relocalise_shape(time_s=frame.time_s)
            t.lap("relocalise")
            if found is not None:
                res, failure, T_ref = found[0], None, found[1]
                status = FrameStatus.RELOCALISED
        if failure is None:
            step, T_new = self._step_and_pose(T_ref, res)
            self.velocity = self._velocity_after(step, status, frame.time_s, res)
            self._mark_tracked(T_new, frame.time_s, status)
            self._fuse(frame, T_new)
            t.lap("fuse")
        else:
            T_new = T_pred
            status = FrameStatus.LOST
            self.failures += 1
            self.failures_in_a_row += 1
            self.failure_reasons[failure] = self.failure_reasons.get(failure, 0) + 1
            if self.failures_in_a_row >= self.cfg.tracking.max_failures_in_a_row_before_reset_velocity:
                self.velocity = self._v_tracked = np.eye(4)
        self.T_world_cam = T_new
        self._retire_source()
        return FrameResult(frame.index, frame.timestamp, T_new.copy(), failure is None, failure is None,
                           res.reason, t.ms, self.map.n_alive, res, status)

    # ---- a loaded map: the first frames are localised in it before tracking starts (map_localiser.py)
    def use_prior_map(self, saved, localize_only: bool = False) -> None:
        """Continue from the saved map ``saved`` (:meth:`FusingMapper.use_prior_map`); the first frames are localised
        in it (:mod:`surfelslam.slam.map_localiser`)."""
        super().use_prior_map(saved, localize_only)
        self._localiser = MapLocaliser(saved.keyframes, self.intr, features_for_width(self.cfg.sparse, self.intr.width),
                                       self.cfg.map_reuse)

    def _first_pose(self, frame: RGBDFrame, t: StageTimer) -> np.ndarray | None:
        """The first frame's pose: the identity (it defines the world frame), or with a loaded map its verified pose
        in it (``None``: not localised yet)."""
        if self._localiser is None:
            return np.eye(4)
        rep = self.prior_report
        if not self.frozen and rep["frames_tried"] >= self.cfg.map_reuse.localise_max_frames:
            # not localised in localise_max_frames frames: a map of another place, or no overlap. Refused, not
            # forced: this frame starts a new map (a localise-only run has none to start and keeps trying)
            self._localiser = None
            self.prior = None
            self.map = SurfelMap(self.cfg.map)
            if self._recorder is not None:
                self._recorder = self._new_recorder()
            rep["new_map_frame_at"] = int(frame.index)
            return np.eye(4)
        rep["frames_tried"] += 1
        T = self._localise_in_map(frame)
        t.lap("localise")
        return T

    def _localise_in_map(self, frame: RGBDFrame) -> np.ndarray | None:
        """Place recognition and PnP against the loaded keyframes, then ICP against the loaded surfels rendered at
        each PnP pose (most inliers first); the first pose that passes :func:`verify_icp`, or ``None``."""
        rep = self.prior_report
        guesses = self._localiser.guesses(self._map_features(frame))
        reason = "no_keyframe_verified_by_pnp"
        for g in guesses:
            target = self.render_target(g.T_world_cam)
            res = icp(self.track_source, target, T_init=np.eye(4), cfg=self.cfg.icp,
                      photometric=self.photometric_term())
            why = verify_icp(res, self.cfg.map_reuse)
            if why is None:
                self._localiser = None
                rep.update(localised=True, frame=int(frame.index), timestamp=float(frame.timestamp),
                           keyframe=int(g.kf_id), pnp_inliers=g.n_inliers,
                           icp_inlier_fraction=float(res.inlier_fraction), icp_rmse_m=float(res.rmse_m))
                rep.pop("last_failure", None)
                return self._step_and_pose(g.T_world_cam, res)[1]
            reason = why
        rep["last_failure"] = reason
        return None

    def _first_status(self) -> FrameStatus:
        return FrameStatus.RELOCALISED if self.prior_report is not None and self.prior_report["localised"] \
            else FrameStatus.TRACKED

    def _not_localised(self, frame: RGBDFrame, t: StageTimer) -> FrameResult:
        """A frame before the run is localised in the loaded map: lost, not fused, no pose written."""
        self._retire_source()
        self.failures += 1
        self.failure_reasons[NOT_LOCALISED] = self.failure_reasons.get(NOT_LOCALISED, 0) + 1
        return FrameResult(frame.index, frame.timestamp, np.eye(4), False, False, NOT_LOCALISED, t.ms,
                           self.map.n_alive, status=FrameStatus.LOST, posed=False)

    def failure_of(self, res: ICPResult) -> str | None:
        """Why ``res`` cannot be used (an :class:`~surfelslam.tracking.icp.ICPStatus` value), or ``None``.

        A degenerate result (one plane, two planes, a corridor) is usable when ``tracking.fuse_weak_frames`` is on
        and everything else about it holds: ICP kept the prediction along the weak directions
        (``icp.weak_direction_ratio``) and registered the frame along the others, so the pose and the map stay
        updated where the view constrains them instead of freezing until the view improves.
        """
        failure = icp_failure(res)
        if failure != ICPStatus.DEGENERATE or not self.cfg.tracking.fuse_weak_frames:
            return failure
        icfg = self.cfg.icp
        usable = (icfg.weak_direction_ratio > 0 and res.levels[-1].stop not in (ICPStatus.TOO_FEW_INLIERS,
                                                                               ICPStatus.SOLVER)
                  and res.inlier_fraction >= icfg.min_inlier_fraction
                  and res.motion_m <= icfg.max_translation_m and res.motion_deg <= icfg.max_rotation_deg)
        return None if usable else failure

    def _damp_frozen(self, step: np.ndarray, res: ICPResult | None) -> np.ndarray:
        """``step`` with its part along the directions the finest ICP level of ``res`` left at the prediction (solution
        remapping) moved only ``tracking.frozen_velocity_gain`` of the way from the current velocity: there the step
        is the prediction plus what the coarser levels did, not a measurement of the finest one."""
        g = self.cfg.tracking.frozen_velocity_gain
        fine = res.levels[-1] if res is not None and res.levels else None
        if g >= 1 or fine is None or fine.level != 0 or not fine.frozen_directions or res.normal_matrix is None:
            return step
        P = weak_projector(res.normal_matrix, res.mean_depth_m, self.cfg.icp.weak_direction_ratio)
        if P is None:
            return step
        delta = se3.log(self.velocity @ se3.invert(step))  # left difference, as ICP's: velocity = exp(delta) step
        return se3.orthonormalize(se3.exp((1 - g) * (P @ delta)) @ step)

    def _velocity_after(self, step: np.ndarray, status: FrameStatus, t_s: float,
                        res: ICPResult | None = None) -> np.ndarray:
        """The velocity (``T_prev_cur`` per frame, ``(4, 4)``) after a registered frame at time ``t_s`` whose step
        was ``step`` (``res``: its ICP result against the map rendered at the previous pose, if it was).

        A tracked frame: its step, damped along frozen directions (:meth:`_damp_frozen`). A relocalised frame has no
        known velocity (identity). A weak frame's step is known only along the directions the view constrains, so it
        is not used: the velocity of the last fully tracked frame goes on, fading by
        ``exp(-(t_s - t_tracked) / tracking.weak_velocity_decay_s)`` (a walk down a corridor keeps going; a weak step
        never feeds the next prediction, so ICP's slide along a free direction cannot build up speed)."""
        if status is FrameStatus.TRACKED:
            step = self._damp_frozen(step, res)
            self._v_tracked, self._t_v_tracked = step, t_s
            return step
        tau_s = self.cfg.tracking.weak_velocity_decay_s
        if status is not FrameStatus.WEAK or tau_s <= 0:
            self._v_tracked = np.eye(4)
            return np.eye(4)
        keep = float(np.exp(-max(t_s - self._t_v_tracked, 0.0) / tau_s))
        return se3.exp(keep * se3.log(self._v_tracked))

    def _mark_tracked(self, T_world_cam: np.ndarray, time_s: float, status: FrameStatus) -> None:
        """Bookkeeping of a registered frame: the last tracked pose and time, the failure streak, weak counts."""
        self.T_world_last_tracked = T_world_cam.copy()
        self.t_last_tracked = time_s
        self.failures_in_a_row = 0
        if status is FrameStatus.WEAK:
            self.weak_frames += 1

    def plausible_jump(self, T_world_new: np.ndarray, time_s: float) -> bool:
        """Whether a relocalised pose is reachable from the last tracked one in the time since it
        (``tracking.relocalise_max_speed_m_s`` / ``_max_rate_deg_s`` plus a slack): a relocalisation that would
        move the camera faster than a hand-held or robot camera moves is refused rather than followed."""
        tc = self.cfg.tracking
        if self.T_world_last_tracked is None:
            return True
        dt_s = max(time_s - self.t_last_tracked, 0.0)
        d_m, d_deg = se3.pose_error(T_world_new, self.T_world_last_tracked)
        ok = (d_m <= tc.relocalise_slack_m + tc.relocalise_max_speed_m_s * dt_s
              and d_deg <= tc.relocalise_slack_deg + tc.relocalise_max_rate_deg_s * dt_s)
        if not ok:
            self.relocalisations["refused_implausible"] += 1
        return ok

    @staticmethod
    def _step_and_pose(T_ref: np.ndarray, res: ICPResult) -> tuple[np.ndarray, np.ndarray]:
        """``(step, T_world_cam)``: the ICP motion ``res.T_target_source`` re-projected onto SE(3) and the pose it
        gives from the render pose ``T_ref`` (both ``(4, 4)``). One formula for the dense and the hybrid
        trackers, so that their trajectories agree to the last bit where the hybrid adds nothing (real-data
        tracking amplifies rounding differences to about 0.5 % ATE)."""
        step = se3.orthonormalize(res.T_target_source)
        return step, se3.orthonormalize(T_ref @ step)

    def _relocalise_shape(self, T_world_render: np.ndarray | None = None,
                          time_s: float | None = None) -> tuple[ICPResult, np.ndarray] | None:
        """The current source against the map rendered at ``T_world_render`` (default: the last tracked pose),
        from the shape-feature guess: ``(ICP result, T_world_render)`` when ICP from the guess succeeds and, given
        the frame's time ``time_s`` (s), the pose is reachable from the last tracked one (:meth:`plausible_jump`);
        else ``None``."""
        self.relocalisations["tried"] += 1
        T_ref = self.T_world_last_tracked if T_world_render is None else T_world_render
        target = self.render_target(T_ref)
        src = self.track_source
        g = geometric_guess(src[0].vertex, src[0].normal, target[0].vertex, target[0].normal,
                            self.cfg.tracking.shape_guess)
        if g.T_target_source is None:
            return None
        res = icp(src, target, T_init=g.T_target_source, cfg=self.cfg.icp, photometric=self.photometric_term())
        if icp_failure(res) is not None:
            return None
        if time_s is not None and not self.plausible_jump(self._step_and_pose(T_ref, res)[1], time_s):
            return None
        self.relocalisations["tracked"] += 1
        return res, T_ref

    def finish(self) -> SlamResult:
        return self._result({"tracking_failures": self.failures, "tracking_failure_reasons": self.failure_reasons,
                             "relocalisations_tried": self.relocalisations["tried"],
                             "relocalisations": self.relocalisations["tracked"],
                             "relocalisations_refused": self.relocalisations["refused_implausible"],
                             "weak_frames": self.weak_frames,
                             "photometric": self.photometric})

    def warmup(self) -> None:
        """Compile (or load from numba's cache) every kernel on a tiny synthetic scene; excluded from FPS."""
        warm_up(self.cfg)


_WARMUP_INTRINSICS = Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)


def warm_up(cfg: SlamConfig) -> None:
    """Run two frames of a tilted-plane-and-bump scene through a throwaway :class:`DenseSlam`.

    Numba compiles for argument types, not sizes, so a 64x48 frame compiles everything a real run uses.
    """
    intr = _WARMUP_INTRINSICS
    v, u = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float32)
    depth = 1.5 + 0.004 * u + 0.002 * v + 0.1 * np.exp(-((u - 32) ** 2 + (v - 24) ** 2) / 60.0)
    rgb = np.zeros((intr.height, intr.width, 3), np.uint8)
    slam = DenseSlam(intr, replace(cfg, map_reuse=replace(cfg.map_reuse, save=False)))
    for i in range(2):
        slam.process(RGBDFrame(i, i / 30.0, rgb, depth.astype(np.float32)))
