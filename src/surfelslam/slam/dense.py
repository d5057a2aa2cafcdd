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

import numpy as np

from surfelslam.geometry import se3
from surfelslam.mapping.surfel_map import SurfelMap
from surfelslam.slam.config import SlamConfig
from surfelslam.slam.frame import (
    FrameResult,
    FrameStatus,
    PreparedFrame,
    SlamResult,
    StageTimer,
    refuse_given_pose,
)
from surfelslam.slam.frontend import DenseFrontEnd
from surfelslam.slam.motion import step_and_pose
from surfelslam.slam.registry import register_tracker
from surfelslam.slam.warmup import warm_up_tracker
from surfelslam.tracking.icp import ICPResult, icp_failure
from surfelslam.types import ColourCamera, Intrinsics, RGBDFrame


@register_tracker("dense")
class DenseSlam:
    """Frame-to-model dense SLAM: track each frame against the map rendered at the previous pose, then fuse.

    ``colour_registered``: the sequence's colour and depth pixels see the same rays (``tracking.photometric``).
    ``colour_camera``: the sequence's separate colour camera, if known (the map's colours are sampled through it).
    The work is the front end's (:class:`~surfelslam.slam.frontend.DenseFrontEnd`, ``self.front``); this class
    orders it per frame.
    """

    def __init__(self, intr: Intrinsics, cfg: SlamConfig, colour_registered: bool = True,
                 colour_camera: ColourCamera | None = None):
        self.intr = intr
        self.cfg = cfg
        self.front = DenseFrontEnd(intr, cfg, colour_registered, colour_camera, tracker_name=self.name)

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

    def warmup(self) -> None:
        """Compile (or load from numba's cache) every kernel on a tiny synthetic scene; excluded from FPS."""
        warm_up_tracker(self)

    def prepare(self, frame: RGBDFrame) -> PreparedFrame:
        """Preprocessing (and the intensity pyramid when tracking photometrically), for another thread."""
        return self.front.prepare(frame)

    def discard(self, prepared: PreparedFrame | None) -> None:
        """A prepared frame that will not be processed (skipped): its pyramid goes back to the pool."""
        self.front.discard(prepared)

    def use_prior_map(self, saved, localize_only: bool = False) -> None:
        """Continue from the saved map ``saved``; the first frames are localised in it (before the first frame)."""
        self.front.use_prior_map(saved, localize_only)

    def process(self, frame: RGBDFrame, prepared: PreparedFrame | None = None,
                T_world_cam: np.ndarray | None = None) -> FrameResult:
        """Track ``frame`` and fuse it; ``prepared``: optional :meth:`prepare` output for this frame."""
        refuse_given_pose(self.name, T_world_cam)
        front, s = self.front, self.front.state
        t = StageTimer(prepared)
        front.begin_frame(frame, prepared)
        t.lap("preprocess" if prepared is None else None)
        if s.T_world_cam is None:  # the first frame defines the world frame (or is localised in a loaded map)
            return self._first_frame(frame, t)
        T_prev = s.T_world_cam
        T_pred = front.predict()
        res, failure, status, T_ref = self._track(frame, T_prev, T_pred, t)
        if failure is None:
            step, T_new = step_and_pose(T_ref, res)
            # a correction of the prediction beyond any change of velocity (after a gap: the prediction was stale) is
            # taken as the pose, but the step across it is no velocity to go on with
            jump = status is not FrameStatus.RELOCALISED and front.motion.jumped(res, frame.time_s)
            s.velocity = front.motion.velocity_after(step, status, frame.time_s, res, measured=not jump)
            front.motion.mark_tracked(T_new, frame.time_s, status)
            front.fuse(frame, T_new)
            t.lap("fuse")
        else:
            T_new = T_pred
            status = FrameStatus.LOST
            front.motion.count_failure(failure)
        s.T_world_cam = T_new
        front.end_frame()
        return FrameResult(index=frame.index, timestamp=frame.timestamp, T_world_cam=T_new.copy(),
                           tracked=failure is None, fused=failure is None, reason=res.reason, timings_ms=t.ms,
                           map_points=self.map.n_alive, icp=res, status=status)

    def _track(self, frame: RGBDFrame, T_prev: np.ndarray, T_pred: np.ndarray, t: StageTimer
               ) -> tuple[ICPResult, str | None, FrameStatus, np.ndarray]:
        """ICP against the map rendered at ``T_prev`` from the prediction ``T_pred`` (refined frame to frame first
        with ``tracking.frame_to_frame_init``); after too many failures in a row, a failed frame is relocalised by
        shape. Returns ``(ICP result, failure or None, status, render pose of the result)``."""
        front = self.front
        T_init = se3.orthonormalize(se3.invert(T_prev) @ T_pred)
        target = front.render_target(T_prev)
        t.lap("render")
        if self.cfg.tracking.frame_to_frame_init:
            f2f = front.register_frame_to_frame(T_init)
            if icp_failure(f2f) is None:
                T_init = f2f.T_target_source
        res = front.register(target, T_init)
        t.lap("icp")
        failure = front.failure_of(res)
        status = FrameStatus.WEAK if failure is None and res.degenerate else FrameStatus.TRACKED
        n_reloc = self.cfg.tracking.relocalise_after_failures
        if failure is not None and n_reloc > 0 and front.state.failures_in_a_row >= n_reloc:
            found = front.relocalise_shape(time_s=frame.time_s)
            t.lap("relocalise")
            if found is not None:
                return found[0], None, FrameStatus.RELOCALISED, found[1]
        return res, failure, status, T_prev

    def _first_frame(self, frame: RGBDFrame, t: StageTimer) -> FrameResult:
        """The first posed frame: the world frame, or its pose localised in a loaded map (none yet: not posed)."""
        front = self.front
        T_first = front.first_pose(frame, t)
        if T_first is None:
            return front.not_localised(frame, t)
        status = front.first_status()
        front.state.T_world_cam = T_first
        front.motion.mark_tracked(T_first, frame.time_s, status)
        front.fuse(frame, T_first)
        t.lap("fuse")
        front.end_frame()
        return FrameResult(index=frame.index, timestamp=frame.timestamp, T_world_cam=T_first.copy(), tracked=True,
                           fused=True, reason=None, timings_ms=t.ms, map_points=self.map.n_alive, status=status)

    def finish(self) -> SlamResult:
        """End of the run: the compacted map and the tracking counts."""
        s = self.front.state
        return self.front.mapper.result({
            "tracking_failures": s.failures, "tracking_failure_reasons": s.failure_reasons,
            "relocalisations_tried": s.relocalisations["tried"],
            "relocalisations": s.relocalisations["tracked"],
            "relocalisations_refused": s.relocalisations["refused_implausible"],
            "weak_frames": s.weak_frames,
            "photometric": self.photometric})

