"""The interface every tracker implements (the registry that builds one by name: :mod:`surfelslam.slam.registry`).

A tracker turns frames into poses and a map: ``prepare`` (frame-only work another thread may do ahead),
``process`` (one frame), ``finish`` (the end-of-run result, whose trajectory is final for every tracker) and
``warmup`` (JIT compilation, excluded from timings).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol, runtime_checkable

from surfelslam.slam.frame import FrameResult, PreparedFrame, SlamResult
from surfelslam.types import RGBDFrame


@runtime_checkable
class Tracker(Protocol):
    """One tracker (``dense``, ``orb``, ``hybrid``) or mapper (``given``) behind the run loop."""

    def warmup(self) -> None:
        """Compile (or load from numba's cache) the kernels the tracker uses."""

    def prepare(self, frame: RGBDFrame) -> PreparedFrame:
        """Frame-only work, safe to run in one other thread while :meth:`process` runs."""

    def process(self, frame: RGBDFrame, prepared: PreparedFrame | None = None) -> FrameResult:
        """Track (and map) one frame; ``prepared`` is :meth:`prepare`'s output for this very frame, if any."""

    def finish(self) -> SlamResult:
        """End the run: back-end optimisation, the final trajectory and the map."""


TrackerFactory = Callable[..., Tracker]
