"""Compile (or load from numba's cache) the feature side's kernels before a run's timed loop.

A tracker that matches features (hybrid, orb) would otherwise compile its Hamming, keypoint-depth, consensus,
Lucas-Kanade and RGB-D refinement kernels on its first frames, inside the loop whose frame rate it reports: on a
fresh install the first run then reports a fraction of its real FPS.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from surfelslam.kernels import hamming
from surfelslam.tracking.features.config import FeatureConfig
from surfelslam.tracking.features.depth import keypoint_depth
from surfelslam.tracking.features.extract import extract
from surfelslam.tracking.features.motion import estimate_motion
from surfelslam.tracking.features.refine import refine_rgbd
from surfelslam.types import Intrinsics

_INTR = Intrinsics(130.0, 130.0, 79.5, 59.5, 160, 120)  # a small camera: numba compiles for types, not sizes
_DEPTH_M = 1.5  # the scene: a textured plane facing the camera at this distance
_SHIFT_PX = 3  # the second view: the texture moved sideways by this much
_BLOCK_PX = 4  # texture block size (corners for ORB)
_GUIDED_RADIUS_PX = 8.0  # the guided match's radius when the config has it off (its kernel is compiled too)


def block_texture(height: int, width: int, block_px: int = _BLOCK_PX) -> np.ndarray:
    """``(height, width, 3)`` uint8 grey blocks of random levels (fixed seed): corners everywhere for ORB."""
    blocks = np.random.default_rng(0).integers(0, 256, (height // block_px, width // block_px)).astype(np.uint8)
    grey = cv2.resize(blocks, (width, height), interpolation=cv2.INTER_NEAREST)
    return np.repeat(grey[:, :, None], 3, axis=2)


def warm_up_features(cfg: FeatureConfig) -> None:
    """Run extraction, guided and brute-force matching, PnP with the consensus test and the refinements on two views
    of a synthetic textured plane, and the keypoint-depth and RGB-D refinement kernels directly (they run only
    after PnP succeeds). Nothing is kept."""
    h, w = _INTR.height, _INTR.width
    rgb = block_texture(h, w)
    depth_m = np.full((h, w), _DEPTH_M, np.float32)
    ref = extract(rgb, depth_m, _INTR, cfg)
    cur = extract(np.roll(rgb, _SHIFT_PX, axis=1), depth_m, _INTR, cfg)
    T_cur_ref = np.eye(4)
    T_cur_ref[0, 3] = _SHIFT_PX * _DEPTH_M / _INTR.fx
    guided = replace(cfg, guided_radius_px=cfg.guided_radius_px or _GUIDED_RADIUS_PX)
    estimate_motion(ref, cur, _INTR, guided, T_cur_ref, min_consistent=cfg.min_inliers)
    estimate_motion(ref, cur, _INTR, cfg)
    if ref.descriptors.dtype == np.uint8:  # ORB: the place-recognition query (nearest two of a keyframe database)
        hamming.nearest_two_words(hamming.as_words(cur.descriptors), hamming.as_words(ref.descriptors))
    uv = np.column_stack([np.linspace(20.0, 140.0, 12), np.linspace(20.0, 100.0, 12)])
    z = keypoint_depth(depth_m, uv, cfg)
    pts = np.column_stack([(uv[:, 0] - _INTR.cx) / _INTR.fx * z, (uv[:, 1] - _INTR.cy) / _INTR.fy * z, z])
    refine_rgbd(np.eye(4), pts, uv, 1.0 / z, _INTR, cfg, with_information=True)
