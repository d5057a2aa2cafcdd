"""A throwaway run of a tracker on a few synthetic frames, so that ``warmup()`` compiles (or loads from numba's cache)
every kernel a real run uses before its timed loop: keyframes, loop checks, edge refinement, the joint ICP term,
map compaction, not only the per-frame dense path.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from surfelslam.slam.registry import build_tracker
from surfelslam.tracking.features.warmup import block_texture
from surfelslam.types import Intrinsics, RGBDFrame

# numba compiles for types, not sizes; wider than the 320 px working width, so that the reduced-input paths run too
_INTR = Intrinsics(130.0, 130.0, 175.5, 63.5, 352, 128)
_FRAMES = 18  # five or six keyframes at the default spacing, with nearby loop checks
_SHIFT_PX = 3  # the camera moves sideways by this much of the image per frame


def _frames() -> list[RGBDFrame]:
    """A textured plane at 1.5 m with a bump (the depth constrains ICP), passing sideways across the view."""
    h, w = _INTR.height, _INTR.width
    rgb = block_texture(h, w)
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    depth_m = (1.5 - 0.15 * np.exp(-((u - w / 2) ** 2 + (v - h / 2) ** 2) / 300.0)).astype(np.float32)
    return [RGBDFrame(k, k / 30.0, np.roll(rgb, -_SHIFT_PX * k, axis=1), np.roll(depth_m, -_SHIFT_PX * k, axis=1))
            for k in range(_FRAMES)]


def warm_up_run(cfg, tracker: str) -> None:
    """Run ``tracker`` with ``cfg`` (map saving off) on :func:`_frames` and finish; nothing is kept."""
    slam = build_tracker(tracker, _INTR, replace(cfg, map_reuse=replace(cfg.map_reuse, save=False)))
    for frame in _frames():
        slam.process(frame)
    slam.finish()
