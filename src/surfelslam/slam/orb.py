"""Sparse keyframe SLAM (tracker ``orb``).

Sparse SLAM (:class:`OrbSlam`, tracker ``orb``) wraps :class:`surfelslam.backend.SparseSlam`: ORB/PnP
odometry against the last keyframe, loop closure, pose graph; the map is the voxel-filtered keyframe cloud
and the written trajectory is the optimised one.
"""

from __future__ import annotations

import time
from functools import partial

import numpy as np

from surfelslam.backend.dense_edges import DenseEdgeRefiner
from surfelslam.backend.sparse_slam import (
    SparseSlam,
)
from surfelslam.errors import ConfigError
from surfelslam.slam.config import SlamConfig
from surfelslam.slam.frame import (
    FrameResult,
    FrameStatus,
    PreparedFrame,
    SlamResult,
    StageTimer,
    prepared_for,
    refuse_given_pose,
)
from surfelslam.slam.mapper import frame_colour_at_depth
from surfelslam.slam.registry import register_tracker
from surfelslam.slam.warmup import warm_up_tracker
from surfelslam.types import ColourCamera, Intrinsics, RGBDFrame

#: the reason a frame posed by the depth odometry alone gives (its weak segments name it)
DEPTH_ONLY_REASON = "depth alone: too few verified features"


def sparse_metrics(sparse: SparseSlam, res) -> dict:
    """The sparse back end's part of ``metrics.json`` (keyframes, loops, edge counts, the refined edges' gate)."""
    return {
        "keyframes": int(len(res.keyframe_indices)),
        "loops_found": len(res.loops_found),
        "loops_accepted": len(res.loops_accepted),
        "nearby_edges": int(res.n_nearby_edges),
        "reinitialisations": int(sparse.n_reinitialisations),
        "lost_frames_placed": int(sparse.n_lost_placed),
        "sparse_rejected": dict(res.rejected),
        **sparse.edge_counts,
        **sparse.dense_edge_stats(),
    }


def loop_stamps(res, stamp_of_frame: dict[int, float]) -> list[tuple[float, float]]:
    kf_frames = res.keyframe_indices
    return [(stamp_of_frame[int(kf_frames[i])], stamp_of_frame[int(kf_frames[j])]) for i, j, _ in res.loops_accepted]


@register_tracker("orb")
class OrbSlam:
    """Tracker ``orb``: :class:`SparseSlam` behind the pipeline interface (``process`` / ``finish`` / ``warmup``).

    No surfel map: the map is the voxel-filtered keyframe cloud, and the trajectory written at the end is
    the pose-graph-optimised one (``SlamResult.trajectory_override``). With ``orb.depth_odometry`` (default) each
    frame's depth is registered to the reference keyframe's as well, and with ``orb.loop_icp`` the keyframe
    edges are refined by ICP behind a trust gate (:class:`OrbConfig`).
    """

    def __init__(self, intr: Intrinsics, cfg: SlamConfig, colour_registered: bool = True,
                 colour_camera: ColourCamera | None = None):
        self.intr = intr
        self.cfg = cfg
        cloud_rgb = None if colour_camera is None else partial(frame_colour_at_depth, intr=intr, cam=colour_camera,
                                                               cfg=cfg.colour_registration)
        oc = cfg.orb
        store = None
        if oc.loop_icp.enabled or oc.depth_odometry.enabled:  # the keyframes' depth is kept for either
            store = DenseEdgeRefiner(intr, cfg.preprocess, oc.loop_icp)
        self.sparse = SparseSlam(intr, cfg.sparse, cloud_rgb=cloud_rgb, edge_refiner=store,
                                 refine_edges=oc.loop_icp.enabled, depth_odometry=oc.depth_odometry,
                                 colour_registered=colour_registered,
                                 relocalise_after_failures=cfg.tracking.relocalise_after_failures)
        self._stamp_of_frame: dict[int, float] = {}
        self.failures = 0
        self.relocalisations = 0
        self.weak_frames = 0  # frames posed by the depth odometry alone (features too few to verify)

    def warmup(self) -> None:
        """Compile the feature side's kernels, the preprocessing and ICP kernels when depth is used, and run a
        throwaway run (keyframes, loop checks); excluded from FPS (:mod:`surfelslam.slam.warmup`)."""
        warm_up_tracker(self)

    def prepare(self, frame: RGBDFrame) -> PreparedFrame:
        """ORB extraction and the depth pyramid, for another thread to do ahead (see :meth:`DenseSlam.prepare`)."""
        c0, t0 = time.thread_time(), time.perf_counter()
        feats = self.sparse.features(frame)
        t1 = time.perf_counter()
        timings = {"orb_extract": (t1 - t0) * 1e3}
        pyr = self.sparse.depth_pyramid(frame)
        if pyr is not None:
            timings["preprocess"] = (time.perf_counter() - t1) * 1e3
        return PreparedFrame(frame, pyramid=pyr, features=feats, timings_ms=timings,
                             cpu_ms=(time.thread_time() - c0) * 1e3)

    def discard(self, prepared: PreparedFrame | None) -> None:
        """A prepared frame that will not be processed: nothing to give back (its buffers are its own)."""

    def use_prior_map(self, saved, localize_only: bool = False) -> None:
        """Saved maps are surfel maps: refused (:func:`~surfelslam.slam.saved_map.check_map_options` says so first)."""
        raise ConfigError("--map is not supported with --tracker orb (its map is a keyframe cloud, not surfels)")

    def process(self, frame: RGBDFrame, prepared: PreparedFrame | None = None,
                T_world_cam: np.ndarray | None = None) -> FrameResult:
        """Match the frame to the reference keyframe (PnP, depth odometry) and feed the keyframe back end."""
        refuse_given_pose(self.name, T_world_cam)
        t = StageTimer(prepared)
        p = prepared_for(frame, prepared)
        feats = None if p is None else p.features
        r = self.sparse.process(frame, feats=feats, depth_pyramid=None if p is None else p.pyramid)
        t.lap("orb")
        self._stamp_of_frame[frame.index] = frame.timestamp
        if not r.ok:
            self.failures += 1
        self.relocalisations += int(r.relocalised)
        weak = r.ok and r.depth_only  # along the directions the depth leaves free, the pose is the prediction
        self.weak_frames += int(weak)
        return FrameResult(index=frame.index, timestamp=frame.timestamp, T_world_cam=r.T_world_cam.copy(),
                           tracked=r.ok or r.relocalised, fused=False, reason=DEPTH_ONLY_REASON if weak else r.reason,
                           timings_ms=t.ms, map_points=self.sparse.n_keyframes,
                           status=FrameStatus.WEAK if weak else None)

    def finish(self) -> SlamResult:
        """End of the run: the optimised trajectory, the keyframe cloud and the back end's counts."""
        res = self.sparse.finish()
        metrics = {"tracking_failures": self.failures,
                   "tracking_failure_reasons": dict(res.rejected),
                   "relocalisations": self.relocalisations,
                   "weak_frames": self.weak_frames,
                   "depth_odometry": dict(self.sparse.depth_counts) if self.sparse.uses_depth else None,
                   **sparse_metrics(self.sparse, res)}
        return SlamResult(len(res.map_xyz), metrics, None, trajectory_override=res.trajectory,
                          loop_stamps=loop_stamps(res, self._stamp_of_frame),
                          points_xyz=res.map_xyz, points_rgb=res.map_rgb)
