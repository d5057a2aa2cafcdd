"""Render a :class:`SurfelMap` into a camera: splatted z-buffer (ICP target) and supersampled index map.

Outputs are in the CAMERA frame (``vertex_cam``, ``normal_cam``), so the projective ICP can use the
rendered view directly as its target. Only surfels of blocks that meet the view frustum are touched
(see :mod:`surfelslam.mapping.surfel_map`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from surfelslam.config import Config, ordered, setting
from surfelslam.errors import ConfigError
from surfelslam.kernels import render as kr
from surfelslam.mapping.surfel_map import SurfelMap
from surfelslam.types import Intrinsics


@dataclass(frozen=True)
class RenderConfig(Config):
    """Rendering the surfel map into a camera (the ICP target)."""

    min_depth_m: float = setting(0.1, unit="m", gt=0, le=100, doc="nearer surfels are not drawn")
    max_depth_m: float = setting(8.0, unit="m", gt=0, le=100,
                                 doc="farther surfels are not drawn; the tracking target stops sooner, where ICP "
                                     "cannot associate: preprocess.max_depth_m + the coarsest icp.dist_thresh_m "
                                     "+ 0.5 m")
    max_splat_radius_px: float = setting(2.0, unit="px", ge=0, le=50, doc="cap of a surfel's footprint radius on "
                                         "screen")
    min_confidence: float = setting(0.0, ge=0, le=1e6,
                                    doc="only surfels with at least this confidence are drawn, except young ones "
                                        "(young_age_frames); 0 draws everything")
    young_age_frames: int = setting(10, unit="frames", ge=0, le=1_000_000,
                                    doc="surfels first seen within this many frames of the latest fused one are drawn "
                                        "whatever their confidence (a young map still renders)")
    cull_backfaces: bool = setting(True, doc="skip surfels whose normal faces away from the camera")
    front_band_rel: float = setting(0.0, unit="fraction of depth", ge=0, le=0.1,
                                    doc="discs within this fraction of the nearest one's depth at a pixel compete by "
                                        "confidence, the most confident is drawn; 0 (default): the nearest. "
                                        "Experimental: better on noisy orbits, worse on textured planes")
    lod_surfels_per_px: float = setting(
        2.0, unit="surfels/px", ge=0, le=1000,
        doc="level of detail: a block of the map whose surfels would crowd more than this many onto each pixel of "
            "its face on screen (far blocks of a floor) draws one of each k of them, k = crowding / this; 0 draws all")
    vertex: str = setting("centre", choices=("centre", "disc"),
                          doc="a pixel's point: the winning surfel's centre, or its disc point on the pixel ray")

    _depth_range = ordered("min_depth_m", "max_depth_m")


@dataclass
class RenderedView:
    """A rendered view, all ``(H, W, ...)``; empty pixels have ``index == -1`` and zeros elsewhere.

    Attributes:
        index: int32 surfel row drawn at each pixel.
        vertex_cam: float32 ``(H, W, 3)`` metres, camera frame (point of the surfel disc on the pixel ray).
        normal_cam: float32 ``(H, W, 3)`` unit normals, camera frame.
        colour: uint8 ``(H, W, 3)`` RGB (``None`` when rendered with ``attributes=False``).
        confidence: float32 ``(H, W)`` (``None`` when rendered with ``attributes=False``).
        n_candidates: surfels that passed block culling (the work done).
    """

    index: np.ndarray
    vertex_cam: np.ndarray
    normal_cam: np.ndarray
    colour: np.ndarray | None
    confidence: np.ndarray | None
    n_candidates: int

    @property
    def depth_m(self) -> np.ndarray:
        """``(H, W)`` float32 rendered depth, 0 where empty."""
        return self.vertex_cam[..., 2]

    @property
    def valid(self) -> np.ndarray:
        return self.index >= 0


@dataclass
class IndexMap:
    """Supersampled index map: ``index`` int32 ``(H*scale, W*scale)``, -1 empty; cell ``(sv, su)`` belongs
    to pixel ``(sv // scale, su // scale)``. ``candidates`` are the culled surfel rows (view into a buffer
    of the map, valid until its next query)."""

    index: np.ndarray
    scale: int
    candidates: np.ndarray


def _world_to_cam(T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    T = np.asarray(T_world_cam, np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"T_world_cam must be (4, 4), got {T.shape}")
    R = T[:3, :3].T.copy()
    t = -R @ T[:3, 3]
    return R, t


def _out_buffer(buf: np.ndarray | None, shape: tuple[int, ...], name: str) -> np.ndarray:
    if buf is None:
        return np.empty(shape, np.float32)
    if buf.shape != shape or buf.dtype != np.float32 or not buf.flags.c_contiguous:
        raise ValueError(f"render: {name} must be a C-contiguous float32 array of shape {shape}, "
                         f"got {buf.dtype} {buf.shape}")
    return buf


def render(
    smap: SurfelMap, T_world_cam: np.ndarray, intr: Intrinsics, cfg: RenderConfig | None = None,
    vertex_out: np.ndarray | None = None, normal_out: np.ndarray | None = None, attributes: bool = True,
    select: Callable[[np.ndarray], np.ndarray] | None = None,
) -> RenderedView:
    """Splat the map into the camera at ``T_world_cam`` (camera-to-world, ``(4, 4)``).

    Each surfel covers the pixels whose rays meet its disc (footprint radius capped at
    ``cfg.max_splat_radius_px``; the nearest pixel of its centre is always covered); the nearest
    intersection wins, or the most confident within ``cfg.front_band_rel`` of its depth. Returns
    camera-frame vertex and normal maps (see :class:`RenderedView`). Blocks of the map that crowd more than
    ``cfg.lod_surfels_per_px`` surfels onto each pixel of their face draw only a share of them (level of detail).

    ``vertex_out`` / ``normal_out``: optional float32 ``(H, W, 3)`` buffers to write the vertex / normal maps
    into (e.g. level 0 of an ICP target pyramid, which :func:`~surfelslam.tracking.preprocess.pyramid_from_maps`
    then does not copy); the view refers to them. ``attributes=False`` skips the colour and confidence
    maps (``None`` in the view): tracking only needs the geometry. ``select``: draws only part of the map, given the
    surfel rows that survive culling (int32 ``(M,)``) it returns those to draw (e.g. the hybrid's inactive map), so
    its cost follows the view, not the map.
    """
    cfg = cfg or RenderConfig()
    H, W = intr.height, intr.width
    R, t = _world_to_cam(T_world_cam)
    cand = smap.visible_candidates(T_world_cam, intr, cfg.min_depth_m, cfg.max_depth_m,
                                   margin_px=cfg.max_splat_radius_px, lod_surfels_per_px=cfg.lod_surfels_per_px)
    if select is not None:
        cand = np.ascontiguousarray(select(cand), np.int32)
    depth = smap.scratch("render_depth", H * W, np.float64).reshape(H, W)
    depth.fill(np.inf)
    index = np.full((H, W), -1, np.int32)
    arr = smap.raw()
    young_from = smap.latest_frame - cfg.young_age_frames + 1 if cfg.min_confidence > 0 else -(2**31)
    kr.splat_zbuffer(
        cand, len(cand), arr["position"], arr["normal"], arr["radius"], arr["confidence"], arr["first_seen"],
        float(cfg.min_confidence), int(young_from), R, t,
        float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy),
        float(cfg.max_splat_radius_px), float(cfg.min_depth_m), float(cfg.max_depth_m), bool(cfg.cull_backfaces),
        float(cfg.front_band_rel), depth, index,
    )
    vertex = _out_buffer(vertex_out, (H, W, 3), "vertex_out")
    normal = _out_buffer(normal_out, (H, W, 3), "normal_out")
    if not attributes:
        kr.fill_geometry(index, depth, arr["position"], arr["normal"], R, t, float(intr.fx), float(intr.fy),
                         float(intr.cx), float(intr.cy), cfg.vertex == "centre", vertex, normal)
        return RenderedView(index, vertex, normal, None, None, len(cand))
    colour = np.empty((H, W, 3), np.uint8)
    conf = np.empty((H, W), np.float32)
    kr.fill_view(index, depth, arr["position"], arr["normal"], arr["colour"], arr["confidence"], R, t,
                 float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy), cfg.vertex == "centre",
                 vertex, normal, colour, conf)
    return RenderedView(index, vertex, normal, colour, conf, len(cand))


def render_index_map(
    smap: SurfelMap, T_world_cam: np.ndarray, intr: Intrinsics, scale: int = 4,
    min_depth_m: float = 0.1, max_depth_m: float = 8.0, cull_backfaces: bool = True,
) -> IndexMap:
    """Keller's supersampled index map: every live surfel in the frustum lands in one cell of an
    ``(H*scale, W*scale)`` grid (no splatting), nearest wins: the ``scale x scale`` cells of an input pixel
    list the surfels that project into that pixel. (Fusion uses the equivalent per-pixel buckets of
    :func:`surfelslam.kernels.fusion.bucket_by_pixel`, which hide no surfel and need no large buffer.)"""
    if scale < 1:
        raise ConfigError(f"render_index_map: scale must be >= 1, got {scale}")
    R, t = _world_to_cam(T_world_cam)
    cand = smap.visible_candidates(T_world_cam, intr, min_depth_m, max_depth_m)
    shape = (intr.height * scale, intr.width * scale)
    depth = np.full(shape, np.inf)
    index = np.full(shape, -1, np.int32)
    arr = smap.raw()
    kr.index_zbuffer(
        cand, len(cand), arr["position"], arr["normal"], R, t,
        float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy), int(scale),
        float(min_depth_m), float(max_depth_m), bool(cull_backfaces), depth, index,
    )
    return IndexMap(index, scale, cand)
