"""Preprocessing into reused buffers and fusion into a surfel map: the component every surfel tracker holds.

:class:`FusingMapper` owns the frame pyramids (a pool shared with the preparing thread), the surfel map, fusion and
the saved map (its keyframe recorder and a loaded map to continue from). The dense front end
(:mod:`surfelslam.slam.frontend`) and the given-pose mapper (:mod:`surfelslam.slam.given`) each hold one.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import replace

import cv2
import numpy as np

from surfelslam.backend.sparse_slam import features_for_width
from surfelslam.errors import ConfigError
from surfelslam.geometry.camera import ColourRegistrationConfig, colour_at_depth_pixels
from surfelslam.mapping.fusion import fuse
from surfelslam.mapping.surfel_map import SurfelMap
from surfelslam.slam.config import SlamConfig, apply_compute
from surfelslam.slam.frame import PreparedFrame, SlamResult, prepared_for
from surfelslam.slam.map_keyframes import KeyframeRecorder, depth_step_for_width
from surfelslam.slam.saved_map import SavedMap, chain_graph
from surfelslam.tracking.features import Features, extract
from surfelslam.tracking.preprocess import (
    FramePyramid,
    Preprocessor,
    level_for_width,
)
from surfelslam.types import ColourCamera, Intrinsics, RGBDFrame, Trajectory


class FusingMapper:
    """Preprocessing into reused buffers, fusion into a surfel map, and the saved map.

    Args:
        min_levels: pyramid levels the holder needs at least (tracking levels included).
        track_level: the pyramid level tracking starts from (``None``: no tracking); finer levels are never computed.
        colour_camera: a separate colour camera (colour not registered to depth): the map's colours are sampled
            through it.
        features_of: the ORB features of a frame that becomes a saved keyframe (a holder with features of its own
            passes its own; default: extracted here).
        features_later: a future of those features, for the saved keyframes only (a holder with a worker thread
            passes it; default: ``features_of``), or ``None`` when the frame has none at hand: it is then not saved,
            a later frame is (:meth:`KeyframeRecorder.observe`).
        tracker_name: the tracker's name, written into the saved map.
    """

    def __init__(self, intr: Intrinsics, cfg: SlamConfig, min_levels: int = 1, track_level: int | None = None,
                 colour_camera: ColourCamera | None = None,
                 features_of: Callable[[RGBDFrame], Features] | None = None, tracker_name: str = "",
                 features_later: Callable[[RGBDFrame], Future | None] | None = None):
        apply_compute(cfg.compute)
        self.intr = intr
        self.cfg = cfg
        # a separate colour camera (colour not registered to depth): the map's colours are sampled through it
        self.colour_camera = colour_camera
        self.fuse_level = level_for_width(intr.width, cfg.fusion.max_width_px)
        levels = max(cfg.preprocess.pyramid_levels, min_levels, self.fuse_level + 1)
        self.pre = Preprocessor(intr, replace(cfg.preprocess, pyramid_levels=levels))
        self._pre_ahead: Preprocessor | None = None  # the preparing thread's own (scratch buffers)
        self._pool: list[FramePyramid] = []  # free source pyramids (grows to what is in flight, then reused)
        self._pool_lock = threading.Lock()
        # finer pyramid levels are never used, so never computed
        self.first_level = self.fuse_level if track_level is None else min(self.fuse_level, track_level)
        self.source = self._acquire()
        self.previous: FramePyramid | None = None  # the last frame's pyramid (kept, not copied)
        self._rgb_fuse: np.ndarray | None = None  # the prepared fusion colour of the current frame
        self.map = SurfelMap(cfg.map)
        self.n_fused = 0
        # the saved map (map.npz): keyframes recorded as frames are fused; a loaded map to continue from
        self._map_feature_cfg = features_for_width(cfg.sparse, intr.width).features
        self.prior: SavedMap | None = None
        self.frozen = False  # localise only: the map is never changed
        self.prior_report: dict | None = None  # metrics of the loaded map (``prior_map`` in metrics.json)
        self._features_of = self.map_features if features_of is None else features_of
        self._features_later = features_later
        self.tracker_name = tracker_name
        self._recorder = self._new_recorder() if cfg.map_reuse.save else None

    def _new_recorder(self, prior: SavedMap | None = None) -> KeyframeRecorder:
        mr = self.cfg.map_reuse
        step = depth_step_for_width(self.intr.width, mr.keyframe_depth_max_width_px)
        return KeyframeRecorder(mr.keyframe_motion, step, self._features_later or self._features_of,
                                None if prior is None else prior.keyframes)

    def map_features(self, frame: RGBDFrame) -> Features:
        """ORB features of a frame, extracted with the saved map's settings."""
        return extract(frame.rgb, frame.depth_m, self.intr, self._map_feature_cfg)

    def keyframe_features(self, frame: RGBDFrame) -> Features:
        """The features the saved keyframes and the map localisation use (``features_of``, or :meth:`map_features`)."""
        return self._features_of(frame)

    @property
    def saves_map(self) -> bool:
        """Whether a map is saved at the end of the run (``map_reuse.save``)."""
        return self._recorder is not None

    def start_new_map(self) -> None:
        """Drop the loaded map (the first frames were not localised in it): an empty map, keyframes from scratch."""
        self.prior = None
        self.map = SurfelMap(self.cfg.map)
        if self._recorder is not None:
            self._recorder = self._new_recorder()

    def repose_keyframes(self, trajectory: Trajectory) -> None:
        """Give the saved keyframes their poses in ``trajectory`` (the loop-corrected one); nothing without saving."""
        if self._recorder is not None:
            self._recorder.repose(trajectory)

    def use_prior_map(self, saved: SavedMap, localize_only: bool = False) -> None:
        """Continue from ``saved`` (before the first frame): its surfels become the map (their frame indices shifted
        below this run's: ``first_seen`` / ``last_seen`` <= -1), its keyframes come first in this run's saved map.
        ``localize_only``: the map is never changed (nothing is fused) and the saved map is ``saved`` itself."""
        if self.map.size or self.n_fused:
            raise ValueError("use_prior_map: the tracker has already mapped frames")
        surfels = dict(saved.surfels)
        if saved.n_surfels:
            offset = int(surfels["last_seen"].max()) + 1
            for name in ("first_seen", "last_seen"):
                surfels[name] = (surfels[name].astype(np.int64) - offset).astype(np.int32)
        self.map.load(surfels)
        self.prior = saved
        self.frozen = localize_only
        self.prior_report = {"surfels": saved.n_surfels, "keyframes": len(saved.keyframes),
                             "localize_only": localize_only, "localised": False, "frames_tried": 0}
        if self._recorder is not None:
            self._recorder = self._new_recorder(saved)

    def saved_map(self) -> SavedMap | None:
        """The map to save at the end of the run (``None`` with ``map_reuse.save`` off)."""
        if self._recorder is None:
            return None
        if self.frozen and self.prior is not None:
            return self.prior
        kfs = self._recorder.keyframes()
        edges, rel = chain_graph(kfs.T_world_kf)
        m = self.map
        surfels = {"position": m.position, "normal": m.normal, "colour": m.colour, "confidence": m.confidence,
                   "radius": m.radius, "first_seen": m.first_seen, "last_seen": m.last_seen, "hits": m.hits}
        return SavedMap(surfels, kfs, edges, rel, self.intr, self.tracker_name)

    @property
    def pooled_pyramids(self) -> int:
        """Free source pyramids kept for reuse (at most what was ever in flight at once)."""
        with self._pool_lock:
            return len(self._pool)

    def _acquire(self) -> FramePyramid:
        with self._pool_lock:
            if self._pool:
                return self._pool.pop()
        return self.pre.new_pyramid()

    def _release(self, pyr: FramePyramid | None) -> None:
        if pyr is not None:
            with self._pool_lock:
                self._pool.append(pyr)

    def check_size(self, frame: RGBDFrame) -> None:
        if frame.depth_m.shape != self.intr.shape:
            raise ConfigError(
                f"frame {frame.index}: depth is {frame.depth_m.shape[1]}x{frame.depth_m.shape[0]}, "
                f"expected {self.intr.width}x{self.intr.height}"
            )

    def _fuse_rgb(self, frame: RGBDFrame) -> np.ndarray:
        rgb = frame_colour_at_depth(frame, self.intr, self.colour_camera, self.cfg.colour_registration)
        return rgb if self.fuse_level == 0 else block_average_rgb(rgb, self.fuse_level)

    def prepare(self, frame: RGBDFrame) -> PreparedFrame:
        """The frame-only work of :meth:`process`, for another thread to do ahead (one such thread at a time).

        Raises what :meth:`process` would raise for this frame (e.g. :class:`ConfigError` for a wrong size).
        """
        c0, t0 = time.thread_time(), time.perf_counter()
        self.check_size(frame)
        if self._pre_ahead is None:
            self._pre_ahead = Preprocessor(self.intr, self.pre.cfg)
        pyr = self._acquire()
        self._pre_ahead.process(frame.depth_m, out=pyr, first_level=self.first_level)
        rgb = self._fuse_rgb(frame)
        ms = {"preprocess": (time.perf_counter() - t0) * 1e3}
        return PreparedFrame(frame, pyr, rgb, None, ms, (time.thread_time() - c0) * 1e3)

    def discard(self, prepared: PreparedFrame | None) -> None:
        """A prepared frame that will not be processed (skipped): its pyramid goes back to the pool."""
        if prepared is not None and prepared.pyramid is not None:
            self._release(prepared.pyramid)
            prepared.pyramid = None

    def preprocess(self, frame: RGBDFrame, prepared: PreparedFrame | None = None) -> FramePyramid:
        """Make the frame's pyramid the current source (the prepared one, or computed here)."""
        prepared = prepared_for(frame, prepared)
        if prepared is not None and prepared.pyramid is not None:
            self.source, prepared.pyramid = prepared.pyramid, None
            self._rgb_fuse = prepared.rgb_fuse
            return self.source
        self.check_size(frame)
        if self.source is self.previous:
            self.source = self._acquire()
        self._rgb_fuse = None
        return self.pre.process(frame.depth_m, out=self.source, first_level=self.first_level)

    def retire_source(self) -> None:
        """End of a frame: its pyramid becomes ``previous``; the one before goes back to the pool."""
        if self.previous is not self.source:
            self._release(self.previous)
        self.previous = self.source

    def fuse(self, frame: RGBDFrame, T_world_cam: np.ndarray) -> None:
        """Fuse the current source (the frame's pyramid, :meth:`preprocess`) at ``T_world_cam`` ``(4, 4)``, and
        record a saved keyframe when due; nothing in a localise-only run."""
        if self.frozen:
            return  # localise only: the loaded map stays as it is
        lvl = self.source[self.fuse_level]
        rgb = self._rgb_fuse if self._rgb_fuse is not None else self._fuse_rgb(frame)
        fuse(self.map, lvl.vertex, lvl.normal, rgb, T_world_cam, lvl.intrinsics, frame.index, self.cfg.fusion)
        self.n_fused += 1
        if self._recorder is not None:
            self._recorder.observe(frame, T_world_cam)

    def result(self, extra: dict) -> SlamResult:
        """End of the run: the compacted map, ``frames_fused`` then ``extra`` (and ``prior_map``) as metrics."""
        self.map.compact()
        if self.prior_report is not None:
            extra = {**extra, "prior_map": dict(self.prior_report)}
        return SlamResult(self.map.n_alive, {"frames_fused": self.n_fused, **extra}, self.map,
                          saved_map=self.saved_map())


def frame_colour_at_depth(frame: RGBDFrame, intr: Intrinsics, cam: ColourCamera | None,
                          cfg: ColourRegistrationConfig) -> np.ndarray:
    """``(H, W, 3)`` uint8 colour of each depth pixel: ``frame.rgb`` itself, or sampled through ``cam`` (when given
    and ``cfg.enabled``)."""
    if cam is None or not cfg.enabled:
        return frame.rgb
    return colour_at_depth_pixels(frame.rgb, frame.depth_m, intr, cam, cfg.fallback_depth_m)


def block_average_rgb(rgb: np.ndarray, levels: int) -> np.ndarray:
    """``(H, W, 3)`` uint8 colour averaged over ``2^levels`` square blocks, matching the pyramid's geometry
    (an odd last row / column is dropped at each halving)."""
    for _ in range(levels):
        h, w = rgb.shape[0] // 2, rgb.shape[1] // 2
        rgb = cv2.resize(rgb[: 2 * h, : 2 * w], (w, h), interpolation=cv2.INTER_AREA)
    return rgb
