"""Joint geometric + photometric ICP: the dense intensity term added to every Gauss-Newton iteration.

Point-to-plane ICP leaves a pose free along directions the geometry barely constrains (a wall, a shelf front
parallel to it): small biases there move the estimate by millimetres per frame, which add up. Texture does
constrain them. :class:`PhotometricTerm` adds, for every source pixel, the difference between the target
intensity where the pixel's point lands and its own intensity (kernel and maths:
:mod:`surfelslam.kernels.photometric`), weighted against the point-to-plane pairs as
``icp.photometric_weight`` says. Only for colour registered to depth (``RGBDSequence.colour_registered``):
with an unregistered colour camera (7-Scenes) the intensity at a depth pixel belongs to another ray.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from surfelslam.errors import ConfigError
from surfelslam.kernels import photometric as kph

PHOTOMETRIC_MODES = ("auto", "on", "off")


def colour_switch(mode: str, colour_registered: bool) -> bool:
    """An ``auto | on | off`` switch of a colour-based term: ``auto`` is on only where colour is registered to
    depth (``RGBDSequence.colour_registered``; with separate cameras a depth pixel's colour belongs to another
    ray)."""
    return mode == "on" or (mode == "auto" and colour_registered)


@dataclass
class IntensityPyramid:
    """Intensity ``(H_l, W_l)`` float32 in [0, 1] (NaN = invalid) per level, finest first, on the depth pyramid's
    grid (2x2 block means, :mod:`surfelslam.tracking.preprocess` convention); ``packed``: ``(H_l, W_l, 3)``
    ``(I, gx, gy)`` with its gradients (intensity per pixel) when built for a target, else an empty list."""

    intensity: list[np.ndarray]
    packed: list[np.ndarray] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.intensity)


def intensity_pyramid(intensity: np.ndarray, levels: int, gradients: bool) -> IntensityPyramid:
    """Pyramid of ``levels`` levels from ``(H, W)`` float32 intensity (NaN = invalid)."""
    imgs = [np.ascontiguousarray(intensity, dtype=np.float32)]
    for _ in range(levels - 1):
        imgs.append(kph.halve_intensity(imgs[-1]))
    pyr = IntensityPyramid(imgs)
    if gradients:
        pyr.packed = [kph.pack_target(img) for img in imgs]
    return pyr


#: the mask passed to the one-pass kernel when there is none (it is not read then)
_NO_MASK = np.ones((1, 1), np.bool_)


def intensity_from_rgb(rgb: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """``(H, W, 3)`` uint8 -> ``(H, W)`` float32 intensity in [0, 1]; NaN where ``valid`` is False."""
    if rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3 and (valid is None
                                                                           or valid.shape == rgb.shape[:2]):
        mask = _NO_MASK if valid is None else np.ascontiguousarray(valid, dtype=np.bool_)
        return kph.intensity_from_rgb_u8(np.ascontiguousarray(rgb), mask, valid is not None)
    img = kph.intensity_from_rgb(rgb)
    if valid is not None:
        img[~valid] = np.nan
    return img


@dataclass
class PhotometricTerm:
    """The photometric pairs of one registration (passed to :func:`surfelslam.tracking.icp.icp`).

    Attributes:
        source: intensity pyramid of the source frame, on the source vertex pyramid's grid.
        target: intensity pyramid of the target view, with gradients, on the target vertex pyramid's grid.
        sigma: intensity noise (intensity units, [0, 1] scale): residuals are measured in units of it.
        huber: Huber threshold of the residual, in units of ``sigma``.
        weight: a residual of ``sigma`` costs as much as this many point-to-plane pairs with a residual of the
            level's robust scale (``icp.finest_robust_scale_m`` at the finest level, ``icp.robust_scale_m``
            above it).
        brightness_offset: re-estimate a global brightness offset (target - source) at every iteration
            (auto-exposure).
        offset: the current offset estimate (intensity units).
    """

    source: IntensityPyramid
    target: IntensityPyramid
    sigma: float
    huber: float
    weight: float
    brightness_offset: bool = True
    offset: float = 0.0
    pairs: int = 0  # pairs used in the last accumulation

    def __post_init__(self) -> None:
        if not self.target.packed:
            raise ConfigError("photometric term: the target pyramid needs gradients (intensity_pyramid(..., True))")
        if not (self.sigma > 0 and self.huber > 0 and self.weight >= 0):
            raise ConfigError(f"photometric term: need sigma > 0, huber > 0, weight >= 0; got {self.sigma}, "
                              f"{self.huber}, {self.weight}")
        self._aux = np.zeros(kph.N_AUX)

    def add_to(self, stats: np.ndarray, T: np.ndarray, level: int, src_vertex: np.ndarray, tgt_vertex: np.ndarray,
               fx: float, fy: float, cx: float, cy: float, dist_thresh_m: float, robust_scale_m: float,
               src_stride: int) -> None:
        """Add the level's photometric pairs at ``T`` (``T_target_source``) to ``stats`` (ICP layout)."""
        if level >= len(self.source) or level >= len(self.target):
            return
        w = self.weight * robust_scale_m * robust_scale_m
        kph.accumulate_photometric(src_vertex, self.source.intensity[level], tgt_vertex, self.target.packed[level], T,
                                   fx, fy, cx, cy, dist_thresh_m, self.sigma, self.huber, w, self.offset, stats,
                                   self._aux, src_stride)
        self.pairs = int(self._aux[2])
        if self.brightness_offset and self._aux[0] > 0:
            self.offset = float(self._aux[1] / self._aux[0])  # Huber-weighted mean of I_t - I_s
