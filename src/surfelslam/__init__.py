"""surfelslam: dense RGB-D SLAM (projective ICP + point-based fusion) with a sparse ORB back end."""

from surfelslam.errors import SurfelSlamError
from surfelslam.types import Intrinsics, RGBDFrame, Trajectory

__all__ = ["Intrinsics", "RGBDFrame", "SurfelSlamError", "Trajectory"]
__version__ = "0.1.0"
