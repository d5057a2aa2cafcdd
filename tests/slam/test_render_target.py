"""The tracking target: the map rendered only as far as ICP can associate it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from surfelslam.slam import SlamConfig
from surfelslam.slam.frontend import TARGET_FAR_SLACK_M, DenseFrontEnd, tracking_render_config
from surfelslam.synth.writer import default_intrinsics


def _plane(x0: float, x1: float, z: float, spacing: float) -> np.ndarray:
    xx, yy = np.meshgrid(np.arange(x0, x1, spacing), np.arange(-5.0, 5.0, spacing))
    return np.column_stack([xx.ravel(), yy.ravel(), np.full(xx.size, z)])


def _target_depth(cfg: SlamConfig) -> np.ndarray:
    """Level-0 depth of the target rendered at the origin: a wall 3 m away on the left half of the view, one 7.5 m
    away on the right half (both facing the camera)."""
    front = DenseFrontEnd(default_intrinsics(160, 120), cfg)
    pos = np.vstack([_plane(-4.0, 0.0, 3.0, 0.02), _plane(0.05, 6.0, 7.5, 0.04)])
    front.map.append(pos, np.tile([0.0, 0.0, -1.0], (len(pos), 1)), np.full((len(pos), 3), 90.0), 1.0, 0.03, 0)
    return front.render_target(np.eye(4))[0].vertex[..., 2]


def test_target_is_not_drawn_beyond_the_source_reach_plus_the_coarsest_gate():
    cfg = SlamConfig()
    far = tracking_render_config(cfg).max_depth_m
    assert far == cfg.preprocess.max_depth_m + max(cfg.icp.dist_thresh_m) + TARGET_FAR_SLACK_M == 6.5
    depth = _target_depth(cfg)
    left, right = depth[:, :70], depth[:, 90:]
    np.testing.assert_allclose(left, 3.0, atol=1e-4)  # the near wall: every pixel
    assert not right.any()  # the far wall lies beyond every association gate: not drawn
    # a source that measures farther (8 m) reaches past render.max_depth_m: the user's cap (8 m) holds, both drawn
    deep = replace(cfg, preprocess=replace(cfg.preprocess, max_depth_m=8.0))
    assert tracking_render_config(deep).max_depth_m == cfg.render.max_depth_m
    np.testing.assert_allclose(_target_depth(deep)[:, 90:], 7.5, atol=1e-4)
    # a nearer user cap stays
    capped = replace(cfg, render=replace(cfg.render, max_depth_m=4.0))
    assert tracking_render_config(capped).max_depth_m == 4.0
