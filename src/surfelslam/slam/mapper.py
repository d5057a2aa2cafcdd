"""Preprocessing into reused buffers and fusion into a surfel map: what the surfel trackers share."""

from __future__ import annotations

import threading
import time
from dataclasses import replace

import cv2
import numpy as np

from surfelslam.errors import ConfigError
from surfelslam.geometry.camera import ColourRegistrationConfig, colour_at_depth_pixels
from surfelslam.mapping.fusion import fuse
from surfelslam.mapping.surfel_map import SurfelMap
from surfelslam.slam.config import SlamConfig, apply_compute
from surfelslam.slam.frame import PreparedFrame, SlamResult, prepared_for
from surfelslam.tracking.preprocess import (
    FramePyramid,
    Preprocessor,
    level_for_width,
)
from surfelslam.types import ColourCamera, Intrinsics, RGBDFrame


class FusingMapper:
    """What the dense pipelines share: preprocessing into reused buffers, and fusion into a surfel map."""

    def __init__(self, intr: Intrinsics, cfg: SlamConfig, min_levels: int = 1, track_level: int | None = None,
                 colour_camera: ColourCamera | None = None):
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

    def _acquire(self) -> FramePyramid:
        with self._pool_lock:
            if self._pool:
                return self._pool.pop()
        return self.pre.new_pyramid()

    def _release(self, pyr: FramePyramid | None) -> None:
        if pyr is not None:
            with self._pool_lock:
                self._pool.append(pyr)

    def _check_size(self, frame: RGBDFrame) -> None:
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
        self._check_size(frame)
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

    def _preprocess(self, frame: RGBDFrame, prepared: PreparedFrame | None = None) -> FramePyramid:
        """Make the frame's pyramid the current source (the prepared one, or computed here)."""
        prepared = prepared_for(frame, prepared)
        if prepared is not None and prepared.pyramid is not None:
            self.source, prepared.pyramid = prepared.pyramid, None
            self._rgb_fuse = prepared.rgb_fuse
            return self.source
        self._check_size(frame)
        if self.source is self.previous:
            self.source = self._acquire()
        self._rgb_fuse = None
        return self.pre.process(frame.depth_m, out=self.source, first_level=self.first_level)

    def _retire_source(self) -> None:
        """End of a frame: its pyramid becomes ``previous``; the one before goes back to the pool."""
        if self.previous is not self.source:
            self._release(self.previous)
        self.previous = self.source

    def _fuse(self, frame: RGBDFrame, T_world_cam: np.ndarray) -> None:
        lvl = self.source[self.fuse_level]
        rgb = self._rgb_fuse if self._rgb_fuse is not None else self._fuse_rgb(frame)
        fuse(self.map, lvl.vertex, lvl.normal, rgb, T_world_cam, lvl.intrinsics, frame.index, self.cfg.fusion)
        self.n_fused += 1

    def _result(self, extra: dict) -> SlamResult:
        self.map.compact()
        return SlamResult(self.map.n_alive, {"frames_fused": self.n_fused, **extra}, self.map)



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
