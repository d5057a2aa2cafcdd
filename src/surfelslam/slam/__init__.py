"""The SLAM pipelines: one module per tracker behind one interface (:mod:`surfelslam.slam.protocol`).

- ``dense`` (:mod:`.dense`): frame-to-model projective ICP against the surfel map, then fusion.
- ``hybrid`` (:mod:`.hybrid`): dense tracking with the sparse ORB back end alongside (PnP guesses and checks,
  relocalisation, loop closure that corrects the trajectory and the map).
- ``orb`` (:mod:`.orb`): sparse ORB + PnP keyframe SLAM with depth odometry; the map is the keyframe cloud.
- ``given`` (:mod:`.given`): mapping with given poses, no tracking.

:mod:`.runner` is the run loop (source -> tracker -> writers); :mod:`.config` holds every setting.
"""

from __future__ import annotations

# isort: off
# one import line per tracker module: importing it registers the tracker (this order is --tracker's listing)
from surfelslam.slam import dense  # noqa: F401
from surfelslam.slam import orb  # noqa: F401
from surfelslam.slam import hybrid  # noqa: F401
from surfelslam.slam import given  # noqa: F401
# isort: on
from surfelslam.slam.config import DEFAULT_TRACKER, SlamConfig
from surfelslam.slam.dense import DenseSlam
from surfelslam.slam.frame import FrameResult, PreparedFrame, SlamResult
from surfelslam.slam.given import GivenPoseMapper, poses_for_mapping
from surfelslam.slam.hybrid import HybridSlam
from surfelslam.slam.orb import OrbSlam
from surfelslam.slam.protocol import Tracker
from surfelslam.slam.registry import build_tracker, register_tracker, registered
from surfelslam.slam.warmup import warm_up_dense, warm_up_tracker

# the trackers a user picks with ``--tracker`` (``given`` is chosen by ``--poses``)
TRACKERS: tuple[str, ...] = tuple(n for n in registered() if n != "given")


def build_slam(intr, cfg: SlamConfig, tracker: str, colour_registered: bool = True, colour_camera=None) -> Tracker:
    """The tracker object for ``tracker`` (see :func:`~surfelslam.slam.registry.build_tracker`)."""
    return build_tracker(tracker, intr, cfg, colour_registered, colour_camera)


__all__ = [
    "DEFAULT_TRACKER", "TRACKERS", "DenseSlam", "FrameResult", "GivenPoseMapper", "HybridSlam", "OrbSlam",
    "PreparedFrame", "SlamConfig", "SlamResult", "Tracker", "build_slam", "build_tracker", "poses_for_mapping",
    "register_tracker", "warm_up_dense", "warm_up_tracker",
]
