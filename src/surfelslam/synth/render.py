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


_BOX_EDGES = np.array([(i, i | b) for b in (1, 2, 4) for i in range(8) if not i & b])  # (12, 2) corner pairs


def primitive_pixel_bounds(scene: Scene, T_world_cam: np.ndarray, intr: Intrinsics, near_m: float) -> np.ndarray:
    """Conservative pixel bounds ``(P, 4)`` = ``umin, umax, vmin, vmax`` of each primitive.

    A primitive lies inside its bounding box; the part of the box in front of the near plane is the
    convex hull of its corners in front plus the points where its edges cross the near plane, so the
    bounds of those points' projections contain the primitive's image. Entirely hidden -> empty bounds.
    """
    R = T_world_cam[:3, :3]
    t = T_world_cam[:3, 3]
    corners_w = np.einsum("pij,pkj->pki", scene.prim_R, _local_corners(scene)) + scene.prim_center[:, None, :]
    pc = (corners_w - t) @ R  # (P, 8, 3) camera frame
    a = pc[:, _BOX_EDGES[:, 0]]  # (P, 12, 3)
    b = pc[:, _BOX_EDGES[:, 1]]
    za, zb = a[..., 2], b[..., 2]
    crosses = (za - near_m) * (zb - near_m) < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(crosses, (near_m - za) / np.where(crosses, zb - za, 1.0), 0.0)
    cross_pts = a + f[..., None] * (b - a)
    cross_pts[..., 2] = near_m
    pts = np.concatenate([pc, cross_pts], axis=1)  # (P, 20, 3)
    use = np.concatenate([pc[..., 2] > near_m, crosses], axis=1)
    # points exactly on the near plane (crossings) have z = near_m > 0, so projection is safe
    zs = np.where(use, np.maximum(pts[..., 2], near_m), 1.0)
    u = intr.fx * pts[..., 0] / zs + intr.cx
    v = intr.fy * pts[..., 1] / zs + intr.cy
    big = 1e12
    bbox = np.empty((scene.n_primitives, 4))
    bbox[:, 0] = np.where(use, u, big).min(axis=1) - BBOX_MARGIN_PX
    bbox[:, 1] = np.where(use, u, -big).max(axis=1) + BBOX_MARGIN_PX
    bbox[:, 2] = np.where(use, v, big).min(axis=1) - BBOX_MARGIN_PX
    bbox[:, 3] = np.where(use, v, -big).max(axis=1) + BBOX_MARGIN_PX
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
