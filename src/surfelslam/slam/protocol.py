"""The interface every tracker implements (the registry that builds one by name: :mod:`surfelslam.slam.registry`).

A tracker turns frames into poses and a map: ``prepare`` (frame-only work another thread may do ahead),
``discard`` (a prepared frame skipped), ``process`` (one frame), ``finish`` (the end-of-run result, whose trajectory
is final for every tracker), ``warmup`` (JIT compilation, excluded from timings) and ``use_prior_map`` (continue
from a saved map). A new tracker is one module whose class is decorated with
:func:`~surfelslam.slam.registry.register_tracker` plus one import line in :mod:`surfelslam.slam`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol, runtime_checkable

import numpy as np

from surfelslam.slam.frame import FrameResult, PreparedFrame, SlamResult
from surfelslam.slam.saved_map import SavedMap
from surfelslam.types import RGBDFrame


@runtime_checkable
class Tracker(Protocol):
    """One tracker (``dense``, ``orb``, ``hybrid``) or mapper (``given``) behind the run loop: every method and
    attribute the run loop calls."""

    #: the name it is registered under (set by :func:`register_tracker`)
    name: str

    def warmup(self) -> None:
        """Compile (or load from numba's cache) the kernels the tracker uses."""

    def use_prior_map(self, saved: SavedMap, localize_only: bool = False) -> None:
        """Before the first frame: continue from the saved map ``saved`` (``localize_only``: never change it).
        Trackers without a surfel map raise :class:`ConfigError`."""

    def prepare(self, frame: RGBDFrame) -> PreparedFrame:
        """Frame-only work, safe to run in one other thread while :meth:`process` runs."""

    def discard(self, prepared: PreparedFrame | None) -> None:
        """A prepared frame that will not be processed (skipped): its buffers go back to the tracker."""

    def process(self, frame: RGBDFrame, prepared: PreparedFrame | None = None,
                T_world_cam: np.ndarray | None = None) -> FrameResult:
        """Track (and map) one frame; ``prepared`` is :meth:`prepare`'s output for this very frame, if any.
        ``T_world_cam`` ``(4, 4)``: the frame's given pose, required by the ``given`` mapper; the trackers, which
        compute their own, raise ``ValueError`` when given one."""

    def finish(self) -> SlamResult:
        """End the run: back-end optimisation, the final trajectory and the map."""


TrackerFactory = Callable[..., Tracker]
