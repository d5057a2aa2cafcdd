"""Depth preprocessing for ICP: range clipping, bilateral filter, vertex/normal maps and pyramids.

Pyramid convention
------------------
Level 0 is the input resolution; level ``l + 1`` halves level ``l`` by averaging 2x2 blocks of
camera-frame points (:func:`surfelslam.kernels.preprocess.downsample_vertex`): new pixel ``u'``
covers old pixels ``2u'`` and ``2u' + 1``, whose centres average to ``2u' + 0.5``. With pixel centres at
integer coordinates the level-``l+1`` intrinsics are therefore

    fx' = fx / 2,   fy' = fy / 2,   cx' = (cx - 0.5) / 2,   cy' = (cy - 0.5) / 2,

and the size is ``(H // 2, W // 2)`` (an odd last row / column is dropped). This differs from
:meth:`Intrinsics.scaled`, which describes ``[::2, ::2]`` *sub-sampling* (no half-pixel shift).
Normals of coarse levels are recomputed from the coarse vertex map (depth input) or block-averaged
from the finer normals (:func:`pyramid_from_maps`, for rendered model maps).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surfelslam.config import Config, ordered, setting
from surfelslam.errors import ConfigError
from surfelslam.kernels import preprocess as kp
from surfelslam.types import Intrinsics


@dataclass(frozen=True)
class PreprocessConfig(Config):
    """Depth preprocessing: valid depth range, bilateral filter, vertex/normal pyramid."""

    min_depth_m: float = setting(0.1, unit="m", ge=0, le=100, doc="nearer depths are invalid", user=True)
    max_depth_m: float = setting(5.0, unit="m", gt=0, le=100, doc="farther depths are invalid", user=True)
    bilateral: bool = setting(True, doc="smooth depth with an edge-preserving bilateral filter before "
                              "back-projection", user=True)
    bilateral_radius_px: int = setting(1, unit="px", ge=0, le=20,
                                       doc="half-size of the filter window (a 2r+1 square)")
    bilateral_sigma_px: float = setting(1.5, unit="px", gt=0, le=50, doc="spatial standard deviation of the filter")
    bilateral_sigma_depth_m: float = setting(0.03, unit="m", gt=0, le=10,
                                             doc="range standard deviation; neighbours more than 3 sigma away in "
                                                 "depth get no weight")
    pyramid_levels: int = setting(4, ge=1, le=12, doc="pyramid levels built (1 = full resolution only)")
    normal_max_depth_jump_m: float = setting(
        0.05, unit="m", gt=0, le=10,
        doc="a normal is invalid where a 4-neighbour's depth differs by more than this (level 0; doubled per level)")
    normal_step_px: int = setting(
        2, unit="px", ge=1, le=16,
        doc="normals at the working level from differences this many pixels either side (coarser levels: 1); 2 "
            "spans the staircase a depth sensor's disparity steps make of slanted surfaces, whose 1-pixel normals "
            "point along the optical axis and pin the camera's motion along it")
    pyramid_max_depth_diff_m: float = setting(
        0.05, unit="m", gt=0, le=10,
        doc="2x2 block averaging only merges points within this depth of the block's reference point (level 1; "
            "doubled per level)")

    _depth_range = ordered("min_depth_m", "max_depth_m")


@dataclass
class PyramidLevel:
    """One pyramid level: ``vertex``/``normal`` ``(H, W, 3)`` float32 camera frame (invalid = zeros)."""

    vertex: np.ndarray
    normal: np.ndarray
    intrinsics: Intrinsics


@dataclass
class FramePyramid:
    """Vertex/normal maps at decreasing resolutions; ``levels[0]`` is the finest."""

    levels: list[PyramidLevel]

    def __len__(self) -> int:
        return len(self.levels)

    def __getitem__(self, level: int) -> PyramidLevel:
        return self.levels[level]

    @property
    def intrinsics(self) -> Intrinsics:
        return self.levels[0].intrinsics

    @classmethod
    def empty(cls, intr: Intrinsics, levels: int) -> FramePyramid:
        """Allocate (uninitialised) buffers for ``levels`` levels starting at ``intr``."""
        out = []
        for li in pyramid_intrinsics(intr, levels):
            out.append(PyramidLevel(np.empty((li.height, li.width, 3), np.float32),
                                    np.empty((li.height, li.width, 3), np.float32), li))
        return cls(out)


def halve_intrinsics(intr: Intrinsics) -> Intrinsics:
    """Intrinsics of the 2x2 block-averaged image (see the module docstring)."""
    if intr.width < 2 or intr.height < 2:
        raise ConfigError(f"preprocess: cannot halve an image of {intr.width}x{intr.height} pixels")
    return Intrinsics(intr.fx / 2, intr.fy / 2, (intr.cx - 0.5) / 2, (intr.cy - 0.5) / 2,
                      intr.width // 2, intr.height // 2)


MIN_LEVEL_WIDTH_PX = 8  # level_for_width never halves an image below this width


def level_for_width(width_px: int, max_width_px: int) -> int:
    """Halvings (pyramid level, 0 = input) that bring ``width_px`` to at most ``max_width_px``, never below
    ``MIN_LEVEL_WIDTH_PX`` pixels; ``max_width_px`` 0: level 0."""
    level = 0
    while max_width_px > 0 and width_px > max_width_px and width_px // 2 >= MIN_LEVEL_WIDTH_PX:
        level, width_px = level + 1, width_px // 2
    return level


def pyramid_intrinsics(intr: Intrinsics, levels: int) -> list[Intrinsics]:
    """``[intr, halve(intr), halve(halve(intr)), ...]`` (``levels`` entries)."""
    out = [intr]
    for _ in range(levels - 1):
        out.append(halve_intrinsics(out[-1]))
    return out


def _check_depth(depth_m: np.ndarray, intr: Intrinsics) -> np.ndarray:
    depth_m = np.asarray(depth_m)
    if depth_m.shape != intr.shape:
        raise ConfigError(
            f"preprocess: depth image is {depth_m.shape[::-1]} (W, H) but the intrinsics describe "
            f"{intr.width}x{intr.height}"
        )
    return np.ascontiguousarray(depth_m, dtype=np.float32)


class Preprocessor:
    """Depth -> :class:`FramePyramid`, with scratch buffers kept between frames.

    Example::

        pre = Preprocessor(intr, PreprocessConfig())
        pyr = pre.new_pyramid()          # allocate once
        pre.process(depth_m, out=pyr)    # refill for every frame
    """

    def __init__(self, intr: Intrinsics, cfg: PreprocessConfig | None = None):
        self.cfg = cfg or PreprocessConfig()
        self.intrinsics = intr
        self.level_intrinsics = pyramid_intrinsics(intr, self.cfg.pyramid_levels)
        self._filtered = [np.empty(li.shape, np.float32) for li in self.level_intrinsics]
        self._halved = [np.empty(li.shape, np.float32) for li in self.level_intrinsics[1:]]
        c = self.cfg
        self._spatial, self._lut, self._lut_step = kp.bilateral_tables(
            c.bilateral_radius_px, c.bilateral_sigma_px, c.bilateral_sigma_depth_m
        )

    def new_pyramid(self) -> FramePyramid:
        return FramePyramid.empty(self.intrinsics, self.cfg.pyramid_levels)

    def _filter(self, depth_m: np.ndarray, level: int) -> np.ndarray:
        c = self.cfg
        out = self._filtered[level]
        if c.bilateral:
            kp.bilateral_filter(depth_m, c.min_depth_m, c.max_depth_m, self._spatial, self._lut,
                                self._lut_step, out)
        else:
            np.copyto(out, depth_m)
            out[~((depth_m >= c.min_depth_m) & (depth_m <= c.max_depth_m))] = 0.0
        return out

    def process(self, depth_m: np.ndarray, out: FramePyramid | None = None, first_level: int = 0) -> FramePyramid:
        """Depth ``(H, W)`` float32 metres (0 = invalid) -> pyramid (written into ``out`` if given).

        ``first_level``: the finest level that is computed. With ``first_level = L > 0`` the depth image is
        first halved ``L`` times by 2x2 block averaging (:func:`surfelslam.kernels.preprocess.downsample_depth`:
        the vertex pyramid's depth gate, centred on the block's first valid pixel), then filtered and
        back-projected at level ``L``; the maps of the finer levels are left as they were. This is for a
        pipeline that tracks and fuses at a coarser level than the input (e.g. 640x480 input worked on at
        320x240): the filter, back-projection and normals then cost what they cost at the working resolution.
        """
        c = self.cfg
        pyr = out if out is not None else self.new_pyramid()
        if len(pyr) != c.pyramid_levels or pyr.intrinsics != self.intrinsics:
            raise ConfigError("preprocess: output pyramid does not match this preprocessor's size/levels")
        if not 0 <= first_level < len(pyr):
            raise ConfigError(f"preprocess: first_level must be in [0, {len(pyr)}), got {first_level}")
        depth = _check_depth(depth_m, self.intrinsics)
        for lvl in range(first_level):
            halved = self._halved[lvl]
            kp.downsample_depth(depth, c.min_depth_m, c.max_depth_m, c.pyramid_max_depth_diff_m * 2.0 ** lvl, halved)
            depth = halved
        depth = self._filter(depth, first_level)
        il = self.level_intrinsics[first_level]
        top = pyr[first_level]
        kp.depth_to_vertex(depth, il.fx, il.fy, il.cx, il.cy, c.min_depth_m, c.max_depth_m, top.vertex)
        kp.vertex_normals(top.vertex, c.normal_max_depth_jump_m * 2.0 ** first_level, top.normal, c.normal_step_px)
        for lvl in range(first_level + 1, len(pyr)):
            scale = 2.0 ** (lvl - 1)
            kp.downsample_vertex(pyr[lvl - 1].vertex, c.pyramid_max_depth_diff_m * scale, pyr[lvl].vertex)
            kp.vertex_normals(pyr[lvl].vertex, c.normal_max_depth_jump_m * 2.0 * scale, pyr[lvl].normal, 1)
        return pyr


def build_pyramid(depth_m: np.ndarray, intr: Intrinsics, cfg: PreprocessConfig | None = None) -> FramePyramid:
    """Depth ``(H, W)`` float32 metres (0 = invalid) -> new :class:`FramePyramid`."""
    return Preprocessor(intr, cfg).process(depth_m)


def pyramid_from_maps(
    vertex: np.ndarray,
    normal: np.ndarray,
    intr: Intrinsics,
    levels: int = 3,
    cfg: PreprocessConfig | None = None,
    out: FramePyramid | None = None,
) -> FramePyramid:
    """Pyramid from given vertex/normal maps (e.g. a model rendered in the target camera).

    Args:
        vertex: ``(H, W, 3)`` camera-frame points; ``z <= 0`` marks an invalid pixel.
        normal: ``(H, W, 3)`` unit normals (zeros where unknown).
        levels: number of levels; coarser levels block-average points and normals.
        cfg: only ``pyramid_max_depth_diff_m`` is used.
        out: optional pre-allocated pyramid (from :meth:`FramePyramid.empty`); level 0 is copied into it,
            unless ``vertex`` / ``normal`` already are its level-0 buffers (rendered in place).
    """
    cfg = cfg or PreprocessConfig()
    if vertex.shape != (*intr.shape, 3) or normal.shape != vertex.shape:
        raise ConfigError(
            f"preprocess: vertex {vertex.shape} / normal {normal.shape} maps must be {(*intr.shape, 3)}"
        )
    if levels < 1:
        raise ConfigError(f"preprocess: levels must be >= 1, got {levels}")
    if out is None:
        out = FramePyramid.empty(intr, levels)
    elif len(out) != levels or out.intrinsics != intr:
        raise ConfigError("preprocess: output pyramid does not match the maps' size/levels")
    if vertex is not out[0].vertex:
        np.copyto(out[0].vertex, vertex, casting="same_kind")
    if normal is not out[0].normal:
        np.copyto(out[0].normal, normal, casting="same_kind")
    for lvl in range(1, levels):
        thr = cfg.pyramid_max_depth_diff_m * 2.0 ** (lvl - 1)
        kp.downsample_vertex_normal(out[lvl - 1].vertex, out[lvl - 1].normal, thr, out[lvl].vertex, out[lvl].normal)
    return out
