"""The SLAM pipelines, as a list of stages.

Dense frame-to-model SLAM (:class:`DenseSlam`), per frame:

1. ``preprocess``: depth -> bilateral filter -> vertex/normal pyramid (source).
2. ``predict``: constant-velocity guess of the new pose.
3. ``render``: the surfel map rendered at the previous pose -> vertex/normal pyramid (target).
4. ``track``: coarse-to-fine projective point-to-plane ICP, source -> target, from the prediction.
5. ``fuse``: on success, the frame is fused into the map at the tracked pose (merge, add, remove);
   on failure the frame is not fused, it is counted, and the pose is the prediction.

Mapping with given poses (:class:`GivenPoseMapper`) runs ``preprocess`` and ``fuse`` only.
Library code: no printing, no file reading (``write_map`` is the one output hook the CLI calls).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from surfelslam.errors import ConfigError, GroundTruthError
from surfelslam.geometry import se3
from surfelslam.mapping.fusion import FusionConfig, fuse
from surfelslam.mapping.render import RenderConfig, render
from surfelslam.mapping.surfel_map import MapConfig, SurfelMap
from surfelslam.tracking.icp import ICPConfig, ICPResult, icp
from surfelslam.tracking.preprocess import FramePyramid, PreprocessConfig, Preprocessor, pyramid_from_maps
from surfelslam.types import Intrinsics, RGBDFrame, Trajectory

TRACKERS = ("dense",)


@dataclass
class IOConfig:
    """Reading: ``prefetch_frames`` frames are decoded ahead in a background thread (0 = synchronous)."""

    prefetch_frames: int = 3


@dataclass
class TrackingConfig:
    """Frame-to-model tracking policy.

    Attributes:
        constant_velocity: predict each pose by repeating the last inter-frame motion (else: last pose).
        frame_to_frame_init: first register the frame to the previous frame (from the prediction), then
            refine against the model from there (costs one more ICP; helps under fast motion).
        max_failures_in_a_row_before_reset_velocity: after this many failed frames in a row the velocity is
            reset to zero (the prediction stops extrapolating).
    """

    constant_velocity: bool = True
    max_failures_in_a_row_before_reset_velocity: int = 3
    frame_to_frame_init: bool = False


@dataclass
class GivenPosesConfig:
    """Mapping with given poses: a frame takes the pose whose timestamp is nearest, within ``max_dt_s``."""

    max_dt_s: float = 0.02


@dataclass
class SlamConfig:
    """Every setting of a run; saved as ``config.toml`` next to the outputs."""

    io: IOConfig = field(default_factory=IOConfig)
    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)
    icp: ICPConfig = field(default_factory=ICPConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    map: MapConfig = field(default_factory=MapConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    given_poses: GivenPosesConfig = field(default_factory=GivenPosesConfig)

    def __post_init__(self) -> None:
        if self.preprocess.pyramid_levels < self.icp.levels:
            raise ConfigError(
                f"config: preprocess.pyramid_levels ({self.preprocess.pyramid_levels}) must be >= icp.levels "
                f"({self.icp.levels})"
            )


@dataclass
class FrameResult:
    """What the pipeline did with one frame."""

    index: int
    timestamp: float
    T_world_cam: np.ndarray
    tracked: bool
    fused: bool
    reason: str | None
    timings_ms: dict[str, float]
    map_points: int
    icp: ICPResult | None = None


@dataclass
class SlamResult:
    """End of a run: the map and summary numbers (the per-frame poses were already streamed)."""

    map_points: int
    metrics: dict
    surfel_map: SurfelMap | None = None
    trajectory_override: Trajectory | None = None
    loop_stamps: list[tuple[float, float]] | None = None

    def map_arrays(self) -> dict[str, np.ndarray] | None:
        if self.surfel_map is None:
            return None
        m = self.surfel_map
        return {"position": m.position, "normal": m.normal, "colour": m.colour,
                "confidence": m.confidence, "first_seen": m.first_seen}

    def write_map(self, path: str | Path) -> None:
        if self.surfel_map is not None:
            from surfelslam.io.ply import write_ply

            write_ply(path, self.surfel_map)


class _Timer:
    def __init__(self) -> None:
        self.ms: dict[str, float] = {}
        self._t = time.perf_counter()

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.ms[stage] = self.ms.get(stage, 0.0) + (now - self._t) * 1e3
        self._t = now


class _FusingMapper:
    """What the dense pipelines share: preprocessing into reused buffers, and fusion into a surfel map."""

    def __init__(self, intr: Intrinsics, cfg: SlamConfig):
        self.intr = intr
        self.cfg = cfg
        self.pre = Preprocessor(intr, cfg.preprocess)
        self.source = self.pre.new_pyramid()
        self.map = SurfelMap(cfg.map)
        self.n_fused = 0

    def _preprocess(self, frame: RGBDFrame) -> FramePyramid:
        if frame.depth_m.shape != self.intr.shape:
            raise ConfigError(
                f"frame {frame.index}: depth is {frame.depth_m.shape[1]}x{frame.depth_m.shape[0]}, "
                f"expected {self.intr.width}x{self.intr.height}"
            )
        return self.pre.process(frame.depth_m, out=self.source)

    def _fuse(self, frame: RGBDFrame, T_world_cam: np.ndarray) -> None:
        lvl0 = self.source[0]
        fuse(self.map, lvl0.vertex, lvl0.normal, frame.rgb, T_world_cam, self.intr, frame.index, self.cfg.fusion)
        self.n_fused += 1

    def warmup(self) -> None:
        """Compile (or load from numba's cache) every kernel on a tiny synthetic scene; excluded from FPS."""
        warm_up(self.cfg)

    def _result(self, extra: dict) -> SlamResult:
        self.map.compact()
        return SlamResult(self.map.n_alive, {"frames_fused": self.n_fused, **extra}, self.map)


class DenseSlam(_FusingMapper):
    """Frame-to-model dense SLAM: track each frame against the map rendered at the previous pose, then fuse."""

    def __init__(self, intr: Intrinsics, cfg: SlamConfig):
        super().__init__(intr, cfg)
        self.target = self.pre.new_pyramid()
        self.previous = self.pre.new_pyramid()  # the last frame's pyramid (buffers swapped, not copied)
        self.T_world_cam: np.ndarray | None = None
        self.velocity = np.eye(4)  # T_prev_cur of the last good step
        self.failures = 0
        self.failures_in_a_row = 0
        self.failure_reasons: dict[str, int] = {}

    def predict(self) -> np.ndarray:
        """Constant-velocity prediction of ``T_world_cam`` for the next frame."""
        assert self.T_world_cam is not None
        if not self.cfg.tracking.constant_velocity:
            return self.T_world_cam.copy()
        return self.T_world_cam @ self.velocity

    def render_target(self, T_world_cam: np.ndarray) -> FramePyramid:
        view = render(self.map, T_world_cam, self.intr, self.cfg.render)
        return pyramid_from_maps(view.vertex_cam, view.normal_cam, self.intr, len(self.target),
                                 self.cfg.preprocess, out=self.target)

    def process(self, frame: RGBDFrame) -> FrameResult:
        t = _Timer()
        self._preprocess(frame)
        t.lap("preprocess")
        if self.T_world_cam is None:  # the first frame defines the world frame
            self.T_world_cam = np.eye(4)
            self._fuse(frame, self.T_world_cam)
            t.lap("fuse")
            self.source, self.previous = self.previous, self.source
            return FrameResult(frame.index, frame.timestamp, self.T_world_cam.copy(), True, True, None, t.ms,
                               self.map.n_alive)
        T_prev = self.T_world_cam
        T_pred = self.predict()
        T_init = se3.orthonormalize(se3.invert(T_prev) @ T_pred)
        target = self.render_target(T_prev)
        t.lap("render")
        if self.cfg.tracking.frame_to_frame_init:
            f2f = icp(self.source, self.previous, T_init=T_init, cfg=self.cfg.icp)
            if icp_failure(f2f) is None:
                T_init = f2f.T_target_source
        res = icp(self.source, target, T_init=T_init, cfg=self.cfg.icp)
        t.lap("icp")
        failure = icp_failure(res)
        if failure is None:
            self.velocity = se3.orthonormalize(res.T_target_source)
            T_new = se3.orthonormalize(T_prev @ self.velocity)
            self.failures_in_a_row = 0
            self._fuse(frame, T_new)
            t.lap("fuse")
        else:
            T_new = T_pred
            self.failures += 1
            self.failures_in_a_row += 1
            self.failure_reasons[failure] = self.failure_reasons.get(failure, 0) + 1
            if self.failures_in_a_row >= self.cfg.tracking.max_failures_in_a_row_before_reset_velocity:
                self.velocity = np.eye(4)
        self.T_world_cam = T_new
        self.source, self.previous = self.previous, self.source
        return FrameResult(frame.index, frame.timestamp, T_new.copy(), failure is None, failure is None,
                           res.reason, t.ms, self.map.n_alive, res)

    def finish(self) -> SlamResult:
        return self._result({"tracking_failures": self.failures, "tracking_failure_reasons": self.failure_reasons})


_WARMUP_INTRINSICS = Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)


def warm_up(cfg: SlamConfig) -> None:
    """Run two frames of a tilted-plane-and-bump scene through a throwaway :class:`DenseSlam`.

    Numba compiles for argument types, not sizes, so a 64x48 frame compiles everything a real run uses.
    """
    intr = _WARMUP_INTRINSICS
    v, u = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float32)
    depth = 1.5 + 0.004 * u + 0.002 * v + 0.1 * np.exp(-((u - 32) ** 2 + (v - 24) ** 2) / 60.0)
    rgb = np.zeros((intr.height, intr.width, 3), np.uint8)
    slam = DenseSlam(intr, cfg)
    for i in range(2):
        slam.process(RGBDFrame(i, i / 30.0, rgb, depth.astype(np.float32)))


def icp_failure(res: ICPResult) -> str | None:
    """Category of a tracking failure, or ``None`` when the result can be used.

    Running out of iterations at the finest level is *not* a failure (the estimate is still refined);
    too few inliers, an unsolvable or degenerate system, and implausible motion are.
    """
    if res.converged:
        return None
    if res.degenerate:
        return "degenerate"
    stop = res.levels[-1].stop if res.levels else "solver"
    if stop in ("too_few_inliers", "solver"):
        return stop
    if res.reason and res.reason.startswith("implausible"):
        return "implausible_motion"
    return None


class GivenPoseMapper(_FusingMapper):
    """Fuse frames at given poses (ground truth or a trajectory file); no tracking."""

    def process(self, frame: RGBDFrame, T_world_cam: np.ndarray) -> FrameResult:
        t = _Timer()
        self._preprocess(frame)
        t.lap("preprocess")
        self._fuse(frame, T_world_cam)
        t.lap("fuse")
        return FrameResult(frame.index, frame.timestamp, np.asarray(T_world_cam).copy(), True, True, None, t.ms,
                           self.map.n_alive)

    def finish(self) -> SlamResult:
        return self._result({})


def build_slam(intr: Intrinsics, cfg: SlamConfig, tracker: str):
    """The pipeline object for ``tracker`` (``dense`` ..., or ``given`` for mapping with given poses)."""
    if tracker == "dense":
        return DenseSlam(intr, cfg)
    if tracker == "given":
        return GivenPoseMapper(intr, cfg)
    raise ConfigError(f"unknown tracker {tracker!r}; known: {', '.join(TRACKERS)}")


def poses_for_mapping(seq, poses: str, cfg: SlamConfig) -> dict[int, np.ndarray]:
    """Pose of each selected frame (position -> ``T_world_cam``) from ``'gt'`` or a TUM trajectory file.

    Frames with no pose within ``cfg.given_poses.max_dt_s`` are absent from the dict (skipped, counted).
    """
    if poses == "gt":
        if seq.ground_truth is None:
            raise GroundTruthError(seq.root, "--poses gt: this sequence has no ground truth")
        traj = seq.ground_truth
    else:
        traj = Trajectory.read_tum(poses)
    T, valid = traj.lookup(seq.timestamps, cfg.given_poses.max_dt_s)
    if not valid.any():
        src = "ground truth" if poses == "gt" else poses
        raise GroundTruthError(seq.root, f"no frame has a pose in {src} within {cfg.given_poses.max_dt_s} s")
    return {int(i): T[i] for i in np.flatnonzero(valid)}
