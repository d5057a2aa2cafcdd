"""The session: one tracker fed frame by frame, with the run's bookkeeping. The one frame loop.

:class:`Session` owns what every driver of a tracker needs: the checks (tracker name, ``--map`` options), the
tracker's set-up (prior map, warm-up), the per-frame statuses and skipped frames, the timing statistics, and at the
end the run's outcome (:class:`RunOutcome`: final trajectory, map, metrics with the tracking-segments report).
``surfelslam run`` (:func:`track_sequence` over an opened sequence) and :class:`surfelslam.Slam` (frame by frame)
are both a Session, so their trajectories and metrics are the same. It prints and writes nothing.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from surfelslam.errors import ConfigError
from surfelslam.io.prefetch import FrameReader
from surfelslam.kernels.threads import concurrent_launch_safe, parallel_enabled
from surfelslam.slam import TRACKERS, SlamConfig, build_slam
from surfelslam.slam.frame import FrameResult, PreparedFrame, SlamResult
from surfelslam.slam.saved_map import SavedMap, check_map_options
from surfelslam.slam.segments import segments_report, tracking_segments
from surfelslam.types import ColourCamera, Intrinsics, RGBDFrame, Trajectory

#: Unpaired images listed (with their reasons) in the metrics; ``frames_unpaired`` counts them all.
UNPAIRED_IN_METRICS = 10
#: The given-poses tracker (``--poses``): mapping at known poses, no tracking.
GIVEN_TRACKER = "given"

#: ``on_pose(timestamp_s, T_world_cam (4, 4))``: a posed frame, in order (the run writer streams it to disk).
PoseSink = Callable[[float, np.ndarray], None]
#: ``on_progress(frames_done, result or None)``: after each slot of the sequence (``None``: a skipped frame).
ProgressSink = Callable[[int, FrameResult | None], None]


@dataclass
class RunOutcome:
    """What a session produced.

    Attributes:
        trajectory: every posed frame's final pose (the back end's optimised one when there is a back end).
        result: the tracker's end-of-run result (map, saved map, loop stamps).
        metrics: the run's numbers (``metrics.json`` without the writer's fields: evaluation, start/end times).
        frames: the per-frame results in order.
        clock_perf_s: the ``time.perf_counter()`` stamps at which the FPS clock started (before the first frame
            was read) and stopped (after the last frame): ``metrics["wall_s"]`` apart; ``None`` without frames.
    """

    trajectory: Trajectory
    result: SlamResult
    metrics: dict
    frames: list[FrameResult] = field(default_factory=list, repr=False)
    clock_perf_s: tuple[float, float] | None = None


def _stats(v: list[float]) -> dict:
    if not v:
        return {"mean": 0.0, "median": 0.0, "p95": 0.0}
    a = np.asarray(v)
    return {"mean": float(a.mean()), "median": float(np.median(a)), "p95": float(np.percentile(a, 95))}


def colour_warning(check: dict | None) -> str | None:
    """The run's warning when the colour check found colour not registered to depth (``None`` otherwise)."""
    if check is None or check["registered"]:
        return None
    return (f"colour does not line up with depth (mean edge distance {check['edge_distance_same_pixel_px']}"
            f" px at the same pixel, {check['edge_distance_fitted_px']} px through a fitted colour camera):"
            " taken as not registered, colour terms under auto are off (colour_registration.check)")


class Session:
    """One tracker, fed frame by frame, with the run's bookkeeping (see the module docstring).

    Args:
        intrinsics: the depth camera; frames must have its size.
        cfg: the settings; ``cfg.tracker`` names the tracker unless ``tracker`` is given.
        tracker: one of :data:`~surfelslam.slam.TRACKERS`.
        colour_registered, colour_camera: the sequence's colour (see :func:`~surfelslam.slam.build_slam`).
        colour_check: the pre-run colour registration report (recorded in the metrics), if one was made.
        prior_map, localize_only: continue from a saved map (``dense``, ``hybrid``), optionally without changing it.
        given_poses: the label of the given poses (``"gt"`` or a file): then frames are mapped at the poses passed
            to :meth:`track` (tracker ``given``) and ``tracker`` is recorded as ``given:<label>``.
        warmup: compile the kernels now (timed apart as ``warmup_s``), else on the first frame.
    """

    def __init__(self, intrinsics: Intrinsics, cfg: SlamConfig, tracker: str | None = None, *,
                 colour_registered: bool = True, colour_camera: ColourCamera | None = None,
                 colour_check: dict | None = None, prior_map: SavedMap | None = None,
                 localize_only: bool = False, given_poses: str | None = None, warmup: bool = True):
        tracker = cfg.tracker if tracker is None else tracker
        if tracker not in TRACKERS:
            raise ConfigError(f"tracker must be one of {', '.join(TRACKERS)}, got {tracker!r}")
        check_map_options(tracker, prior_map, localize_only, given_poses)
        self.intrinsics = intrinsics
        self.config = dataclasses.replace(cfg, tracker=tracker)
        self.tracker_name = tracker
        self.label = tracker if given_poses is None else f"given:{given_poses}"
        self.colour_check = colour_check
        self.tracker = build_slam(intrinsics, self.config, tracker if given_poses is None else GIVEN_TRACKER,
                                  colour_registered=colour_registered, colour_camera=colour_camera)
        if prior_map is not None:
            self.tracker.use_prior_map(prior_map, localize_only)
        self.warmup_s = 0.0
        if warmup:
            self.warm_up()
        self.frames: list[FrameResult] = []
        self.skipped: list[dict] = []
        self.stage_ms: dict[str, list[float]] = {"read": []}
        self.frame_ms: list[float] = []
        self._t_start: float | None = None
        self._wall_s: float | None = None
        self.finished = False

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) the tracker's kernels; timed apart from the frames (``warmup_s``)."""
        t0 = time.perf_counter()
        self.tracker.warmup()
        self.warmup_s += time.perf_counter() - t0

    # ---------------------------------------------------------------------------------------------- frames
    def start_clock(self) -> None:
        """Start the wall clock of the FPS (else the first :meth:`track` or :meth:`skip` starts it)."""
        if self._t_start is None:
            self._t_start = time.perf_counter()

    def track(self, frame: RGBDFrame, prepared: PreparedFrame | None = None, T_world_cam: np.ndarray | None = None,
              read_ms: float | None = None) -> FrameResult:
        """Track (and map) one frame; ``T_world_cam``: its given pose (``given_poses`` sessions only);
        ``read_ms``: the time its reading took (reported as the ``read`` stage)."""
        if self.finished:
            raise ConfigError("the session is finished; start a new one")
        self.start_clock()
        t0 = time.perf_counter()
        res = self.tracker.process(frame, prepared=prepared, T_world_cam=T_world_cam)
        self.frames.append(res)
        if read_ms is not None:
            self.stage_ms["read"].append(read_ms)
        for k, v in res.timings_ms.items():
            self.stage_ms.setdefault(k, []).append(v)
        self.frame_ms.append((time.perf_counter() - t0) * 1e3)
        return res

    def skip(self, position: int, reason: str, prepared: PreparedFrame | None = None) -> None:
        """Record a frame that is not tracked (unreadable, no given pose); its prepared work goes back to the pool."""
        self.start_clock()
        if prepared is not None:
            self.tracker.discard(prepared)
        self.skipped.append({"position": position, "reason": reason})

    # ---------------------------------------------------------------------------------------------- the end
    def finish(self, seq=None) -> RunOutcome:
        """End the session: the back end runs, and the final trajectory, map and metrics are returned.

        ``seq``: the sequence the frames came from, for its fields of the metrics (:func:`sequence_metrics`).
        """
        if self.finished:
            raise ConfigError("the session is finished already")
        self.finished = True
        t_end = time.perf_counter()
        wall_s = 0.0 if self._t_start is None else t_end - self._t_start
        result = self.tracker.finish()
        trajectory = result.trajectory_override
        if trajectory is None:
            posed = [r for r in self.frames if r.posed]
            trajectory = Trajectory(np.array([r.timestamp for r in posed], np.float64),
                                    np.array([r.T_world_cam for r in posed], np.float64).reshape(-1, 4, 4))
        metrics = self._metrics(seq, result, wall_s, len(trajectory))
        clock = None if self._t_start is None else (self._t_start, t_end)
        return RunOutcome(trajectory, result, metrics, self.frames, clock)

    def _metrics(self, seq, result: SlamResult, wall_s: float, poses: int) -> dict:
        n_done = len(self.frames)
        width, height = self.intrinsics.width, self.intrinsics.height
        statuses = [(r.index, r.timestamp, r.status, r.reason) for r in self.frames]
        metrics = {
            **sequence_metrics(seq, self.intrinsics, n_done + len(self.skipped)),
            "tracker": self.label,
            "frames_processed": n_done,
            "frames_skipped": len(self.skipped),
            "skipped": self.skipped,
            "poses_written": poses,
            # frames with no pose (before the run was localised in a loaded map), each with its reason
            "unposed": [{"frame": int(r.index), "timestamp": float(r.timestamp), "reason": r.reason}
                        for r in self.frames if not r.posed],
            "fps": n_done / wall_s if wall_s > 0 else 0.0,
            "wall_s": wall_s,
            "warmup_s": self.warmup_s,
            "parallel_kernels": parallel_enabled(),
            "prepare_in_reader": False,  # track_sequence says when frames were prepared in its reader thread
            "ms_per_frame": _stats(self.frame_ms),
            "stage_ms": {k: _stats(v) for k, v in self.stage_ms.items()},
            "map_points": result.map_points,
            "compression_ratio": result.map_points / max(n_done * width * height, 1),
            **result.metrics,
            **segments_report(tracking_segments(statuses)),
            "loop_edges": [[float(a), float(b)] for a, b in (result.loop_stamps or [])],
            "colour_check": self.colour_check,
        }
        warning = colour_warning(self.colour_check)
        if warning is not None:
            metrics["warnings"].append(warning)
        return metrics


def sequence_metrics(seq, intrinsics: Intrinsics, frames: int) -> dict:
    """The metrics' fields about the input: the sequence's folder, layout, selection, unpaired images, warnings
    and dataset options (``None`` / empty where the frames did not come from an opened sequence, or it lacks them:
    a sequence-like object may have only frames, intrinsics and a layout)."""
    root = getattr(seq, "root", None)
    options = getattr(seq, "options", None)
    unpaired = list(getattr(seq, "unpaired", ()))
    return {
        "sequence": None if root is None else str(root),
        "layout": getattr(seq, "layout", None),
        "frames": frames if seq is None else len(seq),
        "frames_unpaired": len(unpaired),
        "unpaired": [{"file": str(u.file), "timestamp": u.timestamp, "reason": u.reason}
                     for u in unpaired[:UNPAIRED_IN_METRICS]],
        "warnings": list(getattr(seq, "warnings", ())),
        "resolution": [intrinsics.width, intrinsics.height],
        "downsample": 1 if options is None else options.downsample,
        "dataset_options": None if options is None else dataclasses.asdict(options),
    }


def track_sequence(seq, session: Session, *, given: Mapping[int, np.ndarray] | None = None,
                   on_pose: PoseSink | None = None, on_frame: Callable[[Any, Any, Any], None] | None = None,
                   on_progress: ProgressSink | None = None, warm_up: bool = False) -> RunOutcome:
    """Every frame of ``seq`` through ``session``, read (and prepared) ahead in a background thread.

    ``warm_up``: run :meth:`Session.warm_up` first, while the reader thread already decodes the first frames.

    ``given``: position -> ``T_world_cam`` for a ``given_poses`` session (a frame without one is skipped).
    ``on_pose`` gets each posed frame as it is tracked, ``on_frame(frame, result, tracker)`` each tracked frame (a
    live viewer; it must return quickly), ``on_progress`` each slot. Returns :meth:`Session.finish`'s outcome, whose
    metrics also say whether frames were prepared in the reader thread.
    """
    cfg = session.config
    with FrameReader(seq, ahead=cfg.io.prefetch_frames) as reader:
        if warm_up:
            session.warm_up()
        return _track_frames(reader, session, given, on_pose, on_frame, on_progress)


def _track_frames(reader: FrameReader, session: Session, given, on_pose, on_frame, on_progress) -> RunOutcome:
    """:func:`track_sequence`'s loop, the session warmed up: the frames of ``reader`` through ``session``."""
    cfg = session.config
    # the warm-up ran the kernels, so numba's threading layer is known: with parallel kernels on a layer that
    # cannot launch from two threads at once, frames are prepared in the main thread (same results, slower)
    prepare_in_reader = cfg.io.prepare_in_reader and concurrent_launch_safe()
    prepare = session.tracker.prepare if prepare_in_reader else None
    session.start_clock()
    done = 0
    for item in reader.frames(prepare):
        res = None
        T_given = None if given is None else given.get(item.position)
        if item.error is not None:
            session.skip(item.position, str(item.error))
        elif given is not None and T_given is None:
            session.skip(item.position, "no pose within max_dt", item.prepared)
        else:
            res = session.track(item.frame, item.prepared, T_given, item.read_ms)
            if res.posed and on_pose is not None:  # frames not yet localised in a loaded map have no pose
                on_pose(item.frame.timestamp, res.T_world_cam)
            if on_frame is not None:
                on_frame(item.frame, res, session.tracker)
            done += 1
        if on_progress is not None:
            on_progress(done, res)
    outcome = session.finish(reader.seq)
    outcome.metrics["prepare_in_reader"] = bool(prepare_in_reader and reader.ahead > 0)
    return outcome
