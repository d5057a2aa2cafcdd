"""Mapping with given poses (ground truth or a trajectory file): preprocessing and fusion, no tracking."""

from __future__ import annotations

import numpy as np

from surfelslam.errors import GroundTruthError
from surfelslam.io.trajectory import read_tum
from surfelslam.mapping.surfel_map import SurfelMap
from surfelslam.slam.config import SlamConfig
from surfelslam.slam.frame import FrameResult, PreparedFrame, SlamResult, StageTimer
from surfelslam.slam.mapper import FusingMapper
from surfelslam.slam.registry import register_tracker
from surfelslam.slam.warmup import warm_up_tracker
from surfelslam.types import ColourCamera, Intrinsics, RGBDFrame


@register_tracker("given")
class GivenPoseMapper:
    """Fuse frames at given poses (ground truth or a trajectory file); no tracking. The work is the
    :class:`~surfelslam.slam.mapper.FusingMapper`'s (``self.mapper``)."""

    def __init__(self, intr: Intrinsics, cfg: SlamConfig, colour_registered: bool = True,
                 colour_camera: ColourCamera | None = None):
        del colour_registered  # nothing is tracked
        self.intr = intr
        self.cfg = cfg
        self.mapper = FusingMapper(intr, cfg, colour_camera=colour_camera, tracker_name=self.name)

    @property
    def map(self) -> SurfelMap:
        """The surfel map."""
        return self.mapper.map

    @property
    def pooled_pyramids(self) -> int:
        """Free source pyramids kept for reuse (:attr:`FusingMapper.pooled_pyramids`)."""
        return self.mapper.pooled_pyramids

    def warmup(self) -> None:
        """Compile (or load from numba's cache) the preprocessing and fusion kernels; excluded from FPS."""
        warm_up_tracker(self)

    def prepare(self, frame: RGBDFrame) -> PreparedFrame:
        """Preprocessing and the fusion colour, for another thread to do ahead."""
        return self.mapper.prepare(frame)

    def discard(self, prepared: PreparedFrame | None) -> None:
        """A prepared frame that will not be processed (no pose for it): its pyramid goes back to the pool."""
        self.mapper.discard(prepared)

    def use_prior_map(self, saved, localize_only: bool = False) -> None:
        """Continue from the saved map ``saved`` (:meth:`FusingMapper.use_prior_map`)."""
        self.mapper.use_prior_map(saved, localize_only)

    def process(self, frame: RGBDFrame, prepared: PreparedFrame | None = None,
                T_world_cam: np.ndarray | None = None) -> FrameResult:
        """Fuse ``frame`` at its given pose ``T_world_cam`` ``(4, 4)`` (required)."""
        if T_world_cam is None:
            raise ValueError("the 'given' mapper needs each frame's pose: process(frame, T_world_cam=...)")
        t = StageTimer(prepared)
        self.mapper.preprocess(frame, prepared)
        t.lap("preprocess" if prepared is None else None)
        self.mapper.fuse(frame, T_world_cam)
        t.lap("fuse")
        self.mapper.retire_source()
        return FrameResult(index=frame.index, timestamp=frame.timestamp, T_world_cam=np.asarray(T_world_cam).copy(),
                           tracked=True, fused=True, reason=None, timings_ms=t.ms, map_points=self.map.n_alive)

    def finish(self) -> SlamResult:
        """End of the run: the compacted map."""
        return self.mapper.result({})


def poses_for_mapping(seq, poses: str, cfg: SlamConfig) -> dict[int, np.ndarray]:
    """Pose of each selected frame (position -> ``T_world_cam``) from ``'gt'`` or a TUM trajectory file.

    Frames with no pose within ``cfg.given_poses.max_dt_s`` are absent from the dict (skipped, counted).
    """
    if poses == "gt":
        if seq.ground_truth is None:
            raise GroundTruthError(seq.root, "--poses gt: this sequence has no ground truth")
        traj = seq.ground_truth
    else:
        traj = read_tum(poses)
    T, valid = traj.lookup(seq.timestamps, cfg.given_poses.max_dt_s)
    if not valid.any():
        src = "ground truth" if poses == "gt" else poses
        raise GroundTruthError(seq.root, f"no frame has a pose in {src} within {cfg.given_poses.max_dt_s} s")
    return {int(i): T[i] for i in np.flatnonzero(valid)}
