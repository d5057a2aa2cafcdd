"""What a tracker returns: per-frame results, frame-only work done ahead, the end-of-run result.

Work that depends on the frame alone (the ``preprocess`` stage, the fusion colour image and, for the
trackers with a sparse part, ORB extraction) can be done ahead, in the reader thread: ``prepare(frame)``
returns a :class:`PreparedFrame` that ``process(frame, prepared)`` then uses instead of doing it again. The
results are the same either way (bit-identical trajectories); on 2 cores it overlaps that work with the
map stages of the previous frame. ``prepare`` may run in one other thread while ``process`` runs (it has
its own scratch buffers; pyramids come from a lock-protected pool).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

import numpy as np

from surfelslam.mapping.surfel_map import SurfelMap
from surfelslam.slam.saved_map import SavedMap
from surfelslam.tracking.features import Features
from surfelslam.tracking.icp import ICPResult
from surfelslam.tracking.photometric import (
    IntensityPyramid,
)
from surfelslam.tracking.preprocess import (
    FramePyramid,
)
from surfelslam.types import RGBDFrame, Trajectory


class FrameStatus(StrEnum):
    """How a frame's pose was obtained."""

    TRACKED = "tracked"  # registered to the map (or the keyframes) and fused
    WEAK = "weak"  # registered along the directions the view constrains, the prediction along the others; fused
    RELOCALISED = "relocalised"  # registered after a loss, from a verified relocalisation guess; fused
    HELD = "held"  # the registration jumped implausibly from the motion prediction: the pose is the prediction; not
    # fused (a short weak stretch, e.g. a doorway whose view constrains little)
    BRIDGED = "bridged"  # not registered: the pose comes from the features (PnP) alone; not fused
    LOST = "lost"  # not registered: the pose is the motion prediction; not fused


@dataclass(kw_only=True)
class FrameResult:
    """What the pipeline did with one frame (``status``: :class:`FrameStatus`; derived from ``tracked`` if not
    given). Built with keyword arguments only."""

    index: int
    timestamp: float
    T_world_cam: np.ndarray
    tracked: bool
    fused: bool
    reason: str | None
    timings_ms: dict[str, float]
    map_points: int
    icp: ICPResult | None = None
    status: FrameStatus | None = None
    posed: bool = True  # False: the frame has no pose at all (not yet localised in a loaded map); not written

    def __post_init__(self) -> None:
        if self.status is None:
            self.status = FrameStatus.TRACKED if self.tracked else FrameStatus.LOST


def refuse_given_pose(tracker: str, T_world_cam: np.ndarray | None) -> None:
    """Raise ``ValueError`` when a tracker that computes its own poses is given one (``process(T_world_cam=...)`` is
    for the ``given`` mapper)."""
    if T_world_cam is not None:
        raise ValueError(f"tracker {tracker!r} computes its own poses: a given pose is for the 'given' mapper")


@dataclass
class PreparedFrame:
    """Per-frame work that needs the frame alone, done ahead of :meth:`process` (see the module docstring).

    Attributes:
        frame: the frame it was prepared from (``process`` checks it is given the same object).
        pyramid: the source vertex/normal pyramid (a pool buffer, owned by the pipeline from then on), or
            ``None`` for trackers without one.
        rgb_fuse: ``(h, w, 3)`` uint8 colour at the fusion level, or ``None``.
        features: ORB features of the frame (trackers with a sparse part), or ``None``.
        timings_ms: wall ms per stage spent preparing (reported as that stage's time).
        cpu_ms: CPU time of the preparing thread for this frame (ms).
        intensity: the frame's intensity pyramid at the tracking level (photometric tracking), or ``None``.
    """

    frame: RGBDFrame
    pyramid: FramePyramid | None = None
    rgb_fuse: np.ndarray | None = None
    features: Features | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    cpu_ms: float = 0.0
    intensity: IntensityPyramid | None = None


def prepared_for(frame: RGBDFrame, prepared: PreparedFrame | None) -> PreparedFrame | None:
    """``prepared`` when it was made from this very frame, else ``None`` (the work is then done in ``process``)."""
    return prepared if prepared is not None and prepared.frame is frame else None


@dataclass
class SlamResult:
    """End of a run: the map and summary numbers (the per-frame poses were already streamed)."""

    map_points: int
    metrics: dict
    surfel_map: SurfelMap | None = None
    trajectory_override: Trajectory | None = None
    loop_stamps: list[tuple[float, float]] | None = None
    points_xyz: np.ndarray | None = None  # (M, 3) float32 world points (sparse map), when there is no surfel map
    points_rgb: np.ndarray | None = None  # (M, 3) uint8
    saved_map: SavedMap | None = None  # the map to save for a later run (map.npz), surfel trackers

    def map_arrays(self) -> dict[str, np.ndarray] | None:
        """The map as arrays (position, normal, colour, confidence, first_seen; plus radius for a surfel map),
        or None without a map."""
        if self.surfel_map is None:
            if self.points_xyz is None:
                return None
            n = len(self.points_xyz)
            return {"position": self.points_xyz, "normal": np.zeros((n, 3), np.float32),
                    "colour": self.points_rgb.astype(np.float32), "confidence": np.ones(n, np.float32),
                    "first_seen": np.zeros(n, np.int32)}
        m = self.surfel_map
        return {"position": m.position, "normal": m.normal, "colour": m.colour,
                "confidence": m.confidence, "first_seen": m.first_seen, "radius": m.radius}

    def write_map(self, path: str | Path) -> None:
        if self.surfel_map is not None:
            from surfelslam.io.ply import write_ply

            write_ply(path, self.surfel_map)
        elif self.points_xyz is not None:
            from surfelslam.io.ply import write_points_ply

            write_points_ply(path, self.points_xyz, self.points_rgb)


class StageTimer:
    def __init__(self, prepared: PreparedFrame | None = None) -> None:
        self.ms: dict[str, float] = {} if prepared is None else dict(prepared.timings_ms)
        self._t = time.perf_counter()

    def lap(self, stage: str | None) -> None:
        """Add the time since the last lap to ``stage`` (``None``: not counted)."""
        now = time.perf_counter()
        if stage is None:
            self._t = now
            return
        self.ms[stage] = self.ms.get(stage, 0.0) + (now - self._t) * 1e3
        self._t = now
