"""RGB-D sequence readers. Open any supported folder with :func:`open_sequence`.

Layouts (see :mod:`surfelslam.datasets.registry` for the detection order): ``7scenes``, ``synthetic``,
``icl``, ``tum``, ``folder``.
"""

from surfelslam.datasets.base import DatasetOptions, FrameEntry, RGBDSequence
from surfelslam.datasets.registry import (
    LAYOUTS,
    check_depth_scale,
    describe,
    detect_layout,
    open_sequence,
    require_ground_truth,
)

__all__ = [
    "LAYOUTS",
    "DatasetOptions",
    "FrameEntry",
    "RGBDSequence",
    "check_depth_scale",
    "describe",
    "detect_layout",
    "open_sequence",
    "require_ground_truth",
]
