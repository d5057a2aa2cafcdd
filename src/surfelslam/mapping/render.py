"""Render a :class:`SurfelMap` into a camera: splatted z-buffer (ICP target) and supersampled index map.

Outputs are in the CAMERA frame (``vertex_cam``, ``normal_cam``), so the projective ICP can use the
rendered view directly as its target. Only surfels of blocks that meet the view frustum are touched
(see :mod:`surfelslam.mapping.surfel_map`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surfelslam.errors import ConfigError
from surfelslam.kernels import render as kr
from surfelslam.mapping.surfel_map import SurfelMap
from surfelslam.types import Intrinsics


@dataclass
class RenderConfig:
    """Rendering settings.

    ``min_confidence``: only surfels with at least this confidence are drawn (stable surfels), EXCEPT
    surfels first seen within the last ``young_age_frames`` frames of the map's latest fused frame: they
    are drawn regardless, so a young map (or a newly explored region) still renders while it gathers
    confidence. 0 draws everything.
    """

    min_depth_m: float = 0.1
    max_depth_m: float = 8.0
    max_splat_radius_px: float = 2.0  # cap of a surfel's footprint radius on screen
    min_confidence: float = 0.0
    young_age_frames: int = 10
    cull_backfaces: bool = True  # skip surfels whose normal faces away from the camera
    vertex: str = "centre"  # "centre": the winning surfel's centre; "disc": its disc point on the pixel ray

    def __post_init__(self) -> None:
        if not 0 < self.min_depth_m < self.max_depth_m:
            raise ConfigError(
                f"render: need 0 < min_depth_m < max_depth_m, got {self.min_depth_m}, {self.max_depth_m}"
            )
        if self.max_splat_radius_px < 0:
            raise ConfigError(f"render: max_splat_radius_px must be >= 0, got {self.max_splat_radius_px}")
        if self.vertex not in ("centre", "disc"):
            raise ConfigError(f"render: vertex must be 'centre' or 'disc', got {self.vertex!r}")
        if self.young_age_frames < 0:
            raise ConfigError(f"render: young_age_frames must be >= 0, got {self.young_age_frames}")


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
) -> RenderedView:
    """Splat the map into the camera at ``T_world_cam`` (camera-to-world, ``(4, 4)``).

    Each surfel covers the pixels whose rays meet its disc (footprint radius capped at
    ``cfg.max_splat_radius_px``; the nearest pixel of its centre is always covered); the nearest
    intersection wins. Returns camera-frame vertex and normal maps (see :class:`RenderedView`).

    ``vertex_out`` / ``normal_out``: optional float32 ``(H, W, 3)`` buffers to write the vertex / normal maps
    into (e.g. level 0 of an ICP target pyramid, which :func:`~surfelslam.tracking.preprocess.pyramid_from_maps`
    then does not copy); the view refers to them. ``attributes=False`` skips the colour and confidence
    maps (``None`` in the view): tracking only needs the geometry.
    """
    cfg = cfg or RenderConfig()
    H, W = intr.height, intr.width
    R, t = _world_to_cam(T_world_cam)
    cand = smap.visible_candidates(T_world_cam, intr, cfg.min_depth_m, cfg.max_depth_m,
                                   margin_px=cfg.max_splat_radius_px)
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
        depth, index,
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
