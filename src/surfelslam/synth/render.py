"""Ray-cast rendering of a :class:`~surfelslam.synth.scenes.Scene` (numba, no OpenGL).

``render(scene, T_world_cam, intr)`` returns exact colour, z-depth, camera-frame normals and primitive
ids. Colour is texture albedo x (ambient + diffuse x Lambert) with one point light; no shadows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surfelslam.kernels.raycast import render_kernel
from surfelslam.synth.scenes import PRIM_QUAD, Scene
from surfelslam.types import Intrinsics

NEAR_M = 1e-3  # near clipping depth
BBOX_MARGIN_PX = 1.0  # safety margin around each primitive's projected bounding box


@dataclass
class RenderOutput:
    """One rendered view.

    Attributes:
        rgb: ``(H, W, 3)`` uint8 RGB (black where no surface).
        depth_m: ``(H, W)`` float32 z-depth in metres (0 = no surface).
        normal_cam: ``(H, W, 3)`` float32 unit normals in the camera frame, facing the camera (0 = none).
        prim_id: ``(H, W)`` int32 index of the visible primitive (-1 = none).
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    normal_cam: np.ndarray
    prim_id: np.ndarray


def _local_corners(scene: Scene) -> np.ndarray:
    """``(P, 8, 3)`` corners of each primitive's local bounding box."""
    s = scene.prim_size.copy()  # cylinders store (r, r, h) and spheres (r, r, r): already box half-sizes
    s[scene.prim_type == PRIM_QUAD, 2] = 0.0
    signs = np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)], np.float64)
    return s[:, None, :] * signs[None, :, :]


def primitive_pixel_bounds(scene: Scene, T_world_cam: np.ndarray, intr: Intrinsics, near_m: float) -> np.ndarray:
    """Conservative pixel bounds ``(P, 4)`` = ``umin, umax, vmin, vmax`` of each primitive.

    A primitive lies inside the convex hull of its bounding-box corners, so when all corners are in front
    of the camera its image lies inside the bounds of the projected corners. Primitives with a corner at
    or behind ``near_m`` get the whole image.
    """
    R = T_world_cam[:3, :3]
    t = T_world_cam[:3, 3]
    corners_w = np.einsum("pij,pkj->pki", scene.prim_R, _local_corners(scene)) + scene.prim_center[:, None, :]
    pc = (corners_w - t) @ R  # (P, 8, 3) camera frame
    z = pc[..., 2]
    front = np.all(z > near_m, axis=1)
    zs = np.where(z > near_m, z, 1.0)
    u = intr.fx * pc[..., 0] / zs + intr.cx
    v = intr.fy * pc[..., 1] / zs + intr.cy
    big = 1e9
    bbox = np.empty((scene.n_primitives, 4))
    bbox[:, 0] = np.where(front, u.min(axis=1) - BBOX_MARGIN_PX, -big)
    bbox[:, 1] = np.where(front, u.max(axis=1) + BBOX_MARGIN_PX, big)
    bbox[:, 2] = np.where(front, v.min(axis=1) - BBOX_MARGIN_PX, -big)
    bbox[:, 3] = np.where(front, v.max(axis=1) + BBOX_MARGIN_PX, big)
    behind = np.all(z <= near_m, axis=1)
    bbox[behind] = (1.0, -1.0, 1.0, -1.0)  # empty: entirely behind the camera
    return bbox


def render(
    scene: Scene, T_world_cam: np.ndarray, intr: Intrinsics, near_m: float = NEAR_M, out: RenderOutput | None = None
) -> RenderOutput:
    """Render ``scene`` seen from ``T_world_cam`` ``(4, 4)`` with intrinsics ``intr``.

    Pass ``out`` (a previous result of the same size) to reuse its buffers.
    """
    T = np.asarray(T_world_cam, np.float64)
    R = np.ascontiguousarray(T[:3, :3])
    t = np.ascontiguousarray(T[:3, 3])
    H, W = intr.height, intr.width
    if out is None or out.depth_m.shape != (H, W):
        out = RenderOutput(
            np.empty((H, W, 3), np.uint8), np.empty((H, W), np.float32),
            np.empty((H, W, 3), np.float32), np.empty((H, W), np.int32),
        )
    prim_M = np.ascontiguousarray(np.einsum("pji,jk->pik", scene.prim_R, R))
    prim_o = np.ascontiguousarray(np.einsum("pji,pj->pi", scene.prim_R, t[None, :] - scene.prim_center))
    bbox = primitive_pixel_bounds(scene, T, intr, near_m)
    render_kernel(
        R, t, float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy),
        scene.prim_type, scene.prim_R, prim_M, prim_o, scene.prim_size, bbox, scene.prim_tex,
        scene.prim_uv_offset_m, scene.textures, float(scene.texel_m), scene.light_pos_world,
        float(scene.ambient), float(scene.diffuse), float(near_m),
        out.rgb, out.depth_m, out.normal_cam, out.prim_id,
    )
    return out
