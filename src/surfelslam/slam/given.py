"""Mapping with given poses (ground truth or a trajectory file): preprocessing and fusion, no tracking."""

from __future__ import annotations

import numpy as np

from surfelslam.errors import GroundTruthError
from surfelslam.io.trajectory import read_tum
from surfelslam.slam.config import SlamConfig
from surfelslam.slam.dense import warm_up
from surfelslam.slam.frame import FrameResult, PreparedFrame, SlamResult, StageTimer
from surfelslam.slam.mapper import FusingMapper
from surfelslam.slam.registry import register_tracker
from surfelslam.types import ColourCamera, Intrinsics, RGBDFrame


@register_tracker("given")
class GivenPoseMapper(FusingMapper):
    """Fuse frames at given poses (ground truth or a trajectory file); no tracking."""

    def __init__(self, intr: Intrinsics, cfg: SlamConfig, colour_registered: bool = True,
                 colour_camera: ColourCamera | None = None):
        del colour_registered  # nothing is tracked
        super().__init__(intr, cfg, colour_camera=colour_camera)

    def process(self, frame: RGBDFrame, T_world_cam: np.ndarray, prepared: PreparedFrame | None = None
                ) -> FrameResult:
        t = StageTimer(prepared)
        self._preprocess(frame, prepared)
        t.lap("preprocess" if prepared is None else None)
        self._fuse(frame, T_world_cam)
        t.lap("fuse")
        self._retire_source()
        return FrameResult(frame.index, frame.timestamp, np.asarray(T_world_cam).copy(), True, True, None, t.ms,
                           self.map.n_alive)

    def warmup(self) -> None:
        """Compile (or load from numba's cache) the preprocessing and fusion kernels; excluded from FPS."""
        warm_up(self.cfg)

    def finish(self) -> SlamResult:
        return self._result({})



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
