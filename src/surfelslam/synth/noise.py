"""Kinect-v1-like sensor noise for rendered frames.

Depth (in this order): dropouts at grazing angles (from the rendered normals), axial Gaussian noise with
sigma growing with depth squared (Nguyen, Izadi, Lovell, 3DIMPVT 2012), optionally a fixed low-frequency disparity
error (``disparity_distortion_px``: off in ``"kinect"``, on in ``"kinect-distorted"``), disparity quantisation
(structured light: ``disparity = baseline * focal / z`` in 1/8 pixel steps), the valid range, dropouts at
depth discontinuities and random small holes. The distortion mimics uncalibrated Kinect v1 depth (Smisek,
Jancosek, Pajdla 2011; Herrera, Kannala, Heikkila, PAMI 2012: a per-pixel disparity offset, so a depth error
that grows with z^2) by a radial bowl: the offset grows with the squared distance from the image centre.
Colour: a slight Gaussian blur and Gaussian pixel noise.
ICL-NUIM's synthetic sensor noise (Handa, Whelan, McDonald, Davison, ICRA 2014, after Barron and Malik) is the
same chain with other settings (``"icl"`` in :func:`surfelslam.synth.writer.noise_config`): the depth is first
looked up at per-pixel Gaussian offsets (``lateral_jitter_px``, bilinear, so edges mix), then the disparity gets
Gaussian noise (``disparity_sigma_px``) and is rounded to the sensor's steps; no axial noise, holes or dropouts.
Every random draw comes from the generator passed in; :func:`frame_rng` makes it from ``(seed, frame)``
so that any frame can be regenerated on its own.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from surfelslam.config import Config, ordered, setting
from surfelslam.types import Intrinsics

_REFERENCE_WIDTH_PX = 640  # hole sizes and the disparity focal length refer to a 640-pixel-wide sensor image


@dataclass(frozen=True)
class KinectNoiseConfig(Config):
    """Kinect-like depth and colour noise of the synthetic sequences (axial noise, disparity steps, holes, edges)."""

    min_depth_m: float = setting(0.4, unit="m", ge=0, le=100, doc="nearer -> invalid (0)")
    max_depth_m: float = setting(4.5, unit="m", gt=0, le=100, doc="farther -> invalid (0)")
    axial_sigma_base_m: float = setting(0.0012, unit="m", ge=0, le=1,
                                        doc="sigma_z(z) = base + quad * (z - offset)^2")
    axial_sigma_quad_per_m: float = setting(0.0019, unit="1/m", ge=0, le=1, doc="quad of that rule")
    axial_sigma_offset_m: float = setting(0.4, unit="m", ge=0, le=100, doc="offset of that rule")
    baseline_m: float = setting(0.075, unit="m", gt=0, le=10, doc="projector-camera baseline (Kinect v1)")
    disparity_focal_px: float | None = setting(
        None, unit="px", gt=0, le=1e6,
        doc="focal length of the disparity camera; none: the image's |fx| scaled to a 640-pixel width")
    disparity_step_px: float = setting(0.125, unit="px", ge=0, le=100, doc="disparity quantisation step; 0 = off")
    disparity_sigma_px: float = setting(0.0, unit="px", ge=0, le=100,
                                        doc="Gaussian noise on the disparity before its quantisation; 0 = off")
    lateral_jitter_px: float = setting(
        0.0, unit="px", ge=0, le=10,
        doc="look each depth up (bilinear) at a Gaussian offset of this sigma, for a 640-pixel-wide image; 0 = off")
    disparity_distortion_px: float = setting(
        0.0, unit="px", ge=-100, le=100,
        doc="fixed disparity error at the image corners, growing with r^2 from the centre; positive = nearer; 0 = off")
    grazing_angle_deg: float = setting(78.0, unit="deg", gt=0, le=90, doc="drop pixels whose ray-normal angle "
                                       "exceeds this")
    edge_jump_rel: float = setting(0.04, unit="fraction", ge=0, le=10,
                                   doc="a neighbour differing by more than this fraction of z marks an edge")
    edge_dropout_prob: float = setting(0.5, ge=0, le=1, doc="probability of dropping an edge pixel")
    holes_per_frame_mean: float = setting(6.0, ge=0, le=10_000, doc="Poisson mean of random holes per frame")
    hole_radius_min_px: int = setting(2, unit="px", ge=0, le=1000, doc="smallest hole radius (for a 640-pixel-wide "
                                      "image)")
    hole_radius_max_px: int = setting(7, unit="px", ge=0, le=1000, doc="largest hole radius")
    rgb_blur_sigma_px: float = setting(0.5, unit="px", ge=0, le=50, doc="colour blur; 0 = off")
    rgb_noise_sigma: float = setting(2.0, unit="grey levels", ge=0, le=255, doc="Gaussian noise on 0..255 "
                                     "intensities")

    _depth_range = ordered("min_depth_m", "max_depth_m")
    _hole_radii = ordered("hole_radius_min_px", "hole_radius_max_px", strict=False)


def frame_rng(seed: int, frame_index: int) -> np.random.Generator:
    """The random generator of frame ``frame_index`` of a sequence generated with ``seed``."""
    return np.random.default_rng([int(seed), int(frame_index), 0x5EED])


def axial_sigma_m(depth_m: np.ndarray, cfg: KinectNoiseConfig) -> np.ndarray:
    """Axial (depth) noise standard deviation in metres at each depth."""
    return cfg.axial_sigma_base_m + cfg.axial_sigma_quad_per_m * (depth_m - cfg.axial_sigma_offset_m) ** 2


@functools.lru_cache(maxsize=8)
def _unit_rays(fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> np.ndarray:
    """``(H, W, 3)`` float32 unit viewing rays (cached per camera; read-only)."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    rays = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    rays.setflags(write=False)
    return rays


@functools.lru_cache(maxsize=8)
def _radial_r2(cx: float, cy: float, width: int, height: int) -> np.ndarray:
    """``(H, W)`` float32 squared distance from the principal point, 1 at the farthest image corner (read-only)."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    r2 = (u - cx) ** 2 + (v - cy) ** 2
    r2 /= r2.max()
    r2.setflags(write=False)
    return r2


def ray_normal_cos(normal_cam: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """``(H, W)`` ``|cos|`` of the angle between each pixel's viewing ray and the normal ``(H, W, 3)``."""
    rays = _unit_rays(intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height)
    return np.abs(np.einsum("hwc,hwc->hw", normal_cam, rays))


def disparity_focal_px(intr: Intrinsics, cfg: KinectNoiseConfig) -> float:
    """Focal length (px) used for the disparity quantisation."""
    if cfg.disparity_focal_px is not None:
        return cfg.disparity_focal_px
    return abs(intr.fx) * _REFERENCE_WIDTH_PX / intr.width


def noisy_depth(
    depth_m: np.ndarray, normal_cam: np.ndarray, intr: Intrinsics, cfg: KinectNoiseConfig, rng: np.random.Generator
) -> np.ndarray:
    """Exact depth ``(H, W)`` (0 = none) -> Kinect-like depth ``(H, W)`` float32 (0 = invalid)."""
    d = depth_m.astype(np.float32)
    valid = d > 0
    valid &= ray_normal_cos(normal_cam, intr) >= np.float32(np.cos(np.radians(cfg.grazing_angle_deg)))
    z = d if cfg.lateral_jitter_px <= 0 else _jittered(d, cfg.lateral_jitter_px * intr.width / _REFERENCE_WIDTH_PX,
                                                       rng)
    valid &= z > 0
    sigma = axial_sigma_m(d, cfg).astype(np.float32)
    z = z + rng.standard_normal(d.shape, dtype=np.float32) * sigma
    bf = cfg.baseline_m * disparity_focal_px(intr, cfg)
    if cfg.disparity_distortion_px != 0:
        offset = _radial_r2(intr.cx, intr.cy, intr.width, intr.height) * np.float32(cfg.disparity_distortion_px / bf)
        z = np.where(z > 0, 1.0 / (1.0 / np.where(z > 0, z, np.float32(1.0)) + offset), z).astype(np.float32)
    if cfg.disparity_step_px > 0:
        zpos = z > 0
        disp_steps = np.float32(bf / cfg.disparity_step_px) / np.where(zpos, z, np.float32(np.inf))
        if cfg.disparity_sigma_px > 0:
            disp_steps += rng.standard_normal(d.shape, dtype=np.float32) * np.float32(
                cfg.disparity_sigma_px / cfg.disparity_step_px)
        disp_steps = np.round(disp_steps)
        ok = disp_steps > 0
        z = np.where(ok, np.float32(bf / cfg.disparity_step_px) / np.where(ok, disp_steps, 1.0), 0.0)
        z = z.astype(np.float32)
    valid &= (z >= cfg.min_depth_m) & (z <= cfg.max_depth_m)
    # depth discontinuities (on the exact depth): largest jump to a 4-neighbour
    dh = np.abs(d[:, 1:] - d[:, :-1])
    dv = np.abs(d[1:, :] - d[:-1, :])
    jump = np.zeros_like(d)
    jump[:, 1:] = dh
    np.maximum(jump[:, :-1], dh, out=jump[:, :-1])
    np.maximum(jump[1:, :], dv, out=jump[1:, :])
    np.maximum(jump[:-1, :], dv, out=jump[:-1, :])
    edge = jump > cfg.edge_jump_rel * d
    valid &= ~(edge & (rng.random(d.shape, dtype=np.float32) < cfg.edge_dropout_prob))
    # random holes: small filled discs
    n_holes = int(rng.poisson(cfg.holes_per_frame_mean))
    if n_holes > 0:
        scale = intr.width / _REFERENCE_WIDTH_PX
        mask = np.zeros(d.shape, np.uint8)
        cu = rng.integers(0, intr.width, n_holes)
        cv_ = rng.integers(0, intr.height, n_holes)
        rad = rng.integers(cfg.hole_radius_min_px, cfg.hole_radius_max_px + 1, n_holes)
        for a, b, r in zip(cu, cv_, rad, strict=True):  # a few holes per frame, not pixels
            cv2.circle(mask, (int(a), int(b)), max(1, int(round(r * scale))), 1, -1)
        valid &= mask == 0
    return np.where(valid, z, np.float32(0.0)).astype(np.float32)


def _jittered(depth_m: np.ndarray, sigma_px: float, rng: np.random.Generator) -> np.ndarray:
    """``(H, W)`` depth looked up bilinearly at Gaussian offsets (``sigma_px``) from each pixel; 0 where the lookup
    touches a pixel without depth (so no depth is mixed with a hole)."""
    h, w = depth_m.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    u += rng.standard_normal((h, w), dtype=np.float32) * np.float32(sigma_px)
    v += rng.standard_normal((h, w), dtype=np.float32) * np.float32(sigma_px)
    z = cv2.remap(depth_m, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    full = cv2.remap((depth_m > 0).astype(np.float32), u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.where(full >= np.float32(1.0), z, np.float32(0.0)).astype(np.float32)


def noisy_rgb(rgb: np.ndarray, cfg: KinectNoiseConfig, rng: np.random.Generator) -> np.ndarray:
    """``(H, W, 3)`` uint8 -> blurred, noisy ``(H, W, 3)`` uint8."""
    img = rgb
    if cfg.rgb_blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), cfg.rgb_blur_sigma_px, borderType=cv2.BORDER_REFLECT)
    noise = rng.standard_normal(img.shape, dtype=np.float32)
    noise *= np.float32(cfg.rgb_noise_sigma)
    noise += img
    noise += np.float32(0.5)
    np.clip(noise, 0, 255, out=noise)
    return noise.astype(np.uint8)
