"""Colour re-timing: the colour image as the colour camera would have seen it at the *depth* image's capture time.

Sensors that do not expose colour and depth at the same instant (TUM's Kinect: the two stamps of a frame differ by
up to 20 ms; at 0.5 m/s that is 1 cm of motion) give each frame two poses. ICP estimates the depth camera's; a
photometric term measures the colour camera's. Where the offset differs between the two frames of a registration
(jitter, or the same offset under acceleration) the joint estimate is pulled off the depth pose by the difference.
Re-timing removes it: with the depth camera's velocity at its capture stamp (a body twist per second), the colour
camera's pose at the colour stamp is ``T_world_depth @ exp(offset_s * twist)``, so a surface point ``p`` seen at
depth pixel ``u`` was imaged by the colour camera at ``project(T_colour_depth @ p)``, with
``T_colour_depth = exp(-offset_s * twist)``. :func:`retime_intensity` samples the colour (intensity) image there
for every valid depth pixel, giving an intensity image on the depth grid at the depth time.

Used by pairwise registration (``surfelslam register``); the velocity comes from the frame's ICP with its
neighbours (:func:`surfelslam.tracking.registration.colour_timing`).

Not used by the frame-to-model trackers: there the offsets of consecutive frames are nearly equal and the map's
colours, fused from such frames, carry the same shift as the frame's, so the two cancel; re-timing the frames but
not the map's colours would make it worse (``benchmarks/bench_hybrid.py`` measures colour taken before depth).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from surfelslam.config import Config, ordered, setting
from surfelslam.errors import ConfigError
from surfelslam.geometry import se3
from surfelslam.geometry.camera import backproject, pixel_grid, project
from surfelslam.types import Intrinsics

RETIME_MODES = ("auto", "off")


@dataclass(frozen=True)
class RetimeConfig(Config):
    """When colour is re-timed to its depth image's time (a constant-velocity model over the offset)."""

    mode: str = setting("auto", choices=RETIME_MODES,
                        doc="auto: where a frame's colour and depth stamps differ by at least min_offset_s; off")
    min_offset_s: float = setting(0.001, unit="s", ge=0, le=10, doc="smaller colour - depth offsets are left alone")
    max_offset_s: float = setting(0.05, unit="s", ge=0, le=10,
                                  doc="larger offsets are not re-timed (frames paired across a gap)")
    max_velocity_lag_s: float = setting(0.015, unit="s", ge=0, le=10,
                                        doc="the velocity used must be measured within this of the middle of the "
                                            "colour - depth interval")

    _offset_range = ordered("min_offset_s", "max_offset_s", strict=False)

    def applies(self, offset_s: float) -> bool:
        """Whether a frame whose colour stamp minus depth stamp is ``offset_s`` is re-timed."""
        return self.mode == "auto" and self.min_offset_s <= abs(offset_s) <= self.max_offset_s


@dataclass(frozen=True)
class ColourTiming:
    """A frame's colour capture relative to its depth capture.

    Attributes:
        offset_s: colour stamp minus depth stamp (s); negative when colour was taken first.
        twist_per_s: ``(6,)`` body twist ``(omega rad/s, v m/s)`` of the depth camera at the depth stamp
            (:func:`twist_from_pose`).
    """

    offset_s: float
    twist_per_s: np.ndarray

    @property
    def T_colour_depth(self) -> np.ndarray:
        """``(4, 4)``: maps depth-camera points (at the depth stamp) into the colour camera at the colour stamp."""
        return se3.exp(-self.offset_s * np.asarray(self.twist_per_s, dtype=np.float64))


def twist_from_pose(T_b_a: np.ndarray, dt_s: float) -> np.ndarray:
    """``(6,)`` constant body twist per second of camera ``a`` that reaches camera ``b`` after ``dt_s`` seconds.

    ``T_b_a``: ``(4, 4)`` maps points of camera ``a`` into camera ``b`` (an ICP ``T_target_source`` with ``a`` the
    source); ``dt_s = t_b - t_a`` (may be negative). With ``T_world_b = T_world_a @ exp(dt_s * twist)``.
    """
    if not np.isfinite(dt_s) or dt_s == 0:
        raise ConfigError(f"twist_from_pose: the two captures must be at different times (dt = {dt_s} s)")
    return se3.log(se3.invert(T_b_a)) / dt_s


def colour_pixel_maps(depth_m: np.ndarray, intr: Intrinsics,
                      T_colour_depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each depth pixel's point was imaged by the colour camera.

    Args:
        depth_m: ``(H, W)`` depth in metres (0 = invalid).
        intr: intrinsics of the depth grid (the colour image shares them).
        T_colour_depth: ``(4, 4)`` (:attr:`ColourTiming.T_colour_depth`).

    Returns:
        ``(map_u, map_v, seen)``: ``(H, W)`` float32 colour-image coordinates (the pixel itself where the point is
        invalid) and ``(H, W)`` bool, False where a valid point falls behind the colour camera or more than half a
        pixel outside its image.
    """
    h, w = depth_m.shape
    if (intr.width, intr.height) != (w, h):
        raise ConfigError(f"colour re-timing: intrinsics are for {intr.width}x{intr.height}, images are {w}x{h}")
    ok = depth_m > 0
    u, v = pixel_grid(intr, np.float64)  # float64: an unmoved point maps onto its own pixel exactly
    uc, vc, zc = project(se3.transform_points(T_colour_depth, backproject(depth_m, intr, np.float64)), intr)
    map_u = np.where(ok, uc, u)
    map_v = np.where(ok, vc, v)
    # within half a pixel of the image: the edge pixel (replicated); farther out: unseen
    inside = (zc > 0) & (map_u > -0.5) & (map_u < w - 0.5) & (map_v > -0.5) & (map_v < h - 0.5)
    return map_u.astype(np.float32), map_v.astype(np.float32), ~ok | inside


def retime_intensity(intensity: np.ndarray, depth_m: np.ndarray, intr: Intrinsics,
                     T_colour_depth: np.ndarray) -> np.ndarray:
    """Intensity on the depth grid as the colour camera saw it at the depth stamp.

    Args:
        intensity: ``(H, W)`` float32 in [0, 1] (NaN = invalid), captured by the colour camera at its own stamp,
            registered to the depth grid (pixel ``u`` of both sees the same ray when the cameras coincide).
        depth_m: ``(H, W)`` float32 metres (0 = invalid) at the depth stamp.
        intr: intrinsics of both images.
        T_colour_depth: ``(4, 4)`` (:attr:`ColourTiming.T_colour_depth`).

    Returns:
        ``(H, W)`` float32: at each valid depth pixel the intensity bilinearly sampled where its point projects
        into the colour image (NaN where it falls outside or behind the camera); elsewhere the input unchanged.
    """
    if intensity.shape != depth_m.shape:
        raise ConfigError(f"retime_intensity: intensity is {intensity.shape}, depth is {depth_m.shape}")
    map_u, map_v, seen = colour_pixel_maps(depth_m, intr, T_colour_depth)
    out = cv2.remap(np.ascontiguousarray(intensity, dtype=np.float32), map_u, map_v, cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    out[~seen] = np.nan
    return out

