"""Keyframes: features for matching and a voxel-filtered coloured cloud for the map."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surfelslam.config import Config, ordered, setting
from surfelslam.geometry.camera import backproject
from surfelslam.geometry.se3 import transform_points
from surfelslam.kernels.voxel import voxel_filter
from surfelslam.tracking.features import Features
from surfelslam.types import Intrinsics, RGBDFrame


@dataclass(frozen=True)
class KeyframeMapConfig(Config):
    """Keyframe clouds and the sparse trackers' final voxel-filtered map."""

    voxel_size_m: float = setting(0.02, unit="m", ge=0.001, le=10,
                                  doc="voxel edge of the per-keyframe and the final voxel-grid filter", user=True)
    min_depth_m: float = setting(0.0, unit="m", ge=0, le=100, doc="nearer pixels are not mapped")
    max_depth_m: float = setting(4.0, unit="m", gt=0, le=100, doc="farther pixels are not mapped", user=True)
    pixel_stride: int = setting(2, unit="px", ge=1, le=64,
                                doc="keyframe depth is sampled every s pixels before filtering")

    _depth_range = ordered("min_depth_m", "max_depth_m")


@dataclass
class Keyframe:
    """A keyframe.

    Attributes:
        kf_id: index in the keyframe list and pose-graph node id.
        frame_index, timestamp: the frame it was made from.
        features: its ORB features (with 3D points in its camera frame).
        cloud_xyz_cam: ``(M, 3)`` float32 voxel-filtered points in its camera frame (m).
        cloud_rgb: ``(M, 3)`` uint8 colours.
    """

    kf_id: int
    frame_index: int
    timestamp: float
    features: Features
    cloud_xyz_cam: np.ndarray
    cloud_rgb: np.ndarray


def keyframe_cloud(frame: RGBDFrame, intr: Intrinsics, cfg: KeyframeMapConfig,
                   rgb: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame coloured cloud of a frame: ``(xyz (M, 3) float32, rgb (M, 3) uint8)``, voxel-filtered.

    ``rgb``: ``(H, W, 3)`` uint8 colour of each depth pixel (default ``frame.rgb``)."""
    s = cfg.pixel_stride
    vtx = backproject(frame.depth_m, intr)[::s, ::s].reshape(-1, 3)
    rgb = (frame.rgb if rgb is None else rgb)[::s, ::s].reshape(-1, 3)
    z = vtx[:, 2]
    keep = (z > cfg.min_depth_m) & (z <= cfg.max_depth_m)
    xyz, col, _ = voxel_filter(vtx[keep], rgb[keep], cfg.voxel_size_m)
    return xyz, col


def joined_clouds(kfs: list[Keyframe], poses_world_kf: np.ndarray,
                  voxel_size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The keyframes' clouds in the world frame (``poses_world_kf (K, 4, 4)``), joined and voxel-filtered:
    ``(xyz (M, 3) f32, rgb (M, 3) u8)``."""
    if not kfs:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    n = sum(len(k.cloud_xyz_cam) for k in kfs)
    xyz = np.empty((n, 3), np.float32)
    rgb = np.empty((n, 3), np.uint8)
    i = 0
    for k, T in zip(kfs, poses_world_kf, strict=True):
        m = len(k.cloud_xyz_cam)
        xyz[i : i + m] = transform_points(T, k.cloud_xyz_cam.astype(np.float64))
        rgb[i : i + m] = k.cloud_rgb
        i += m
    out_xyz, out_rgb, _ = voxel_filter(xyz, rgb, voxel_size_m)
    return out_xyz, out_rgb
