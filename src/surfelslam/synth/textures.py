"""Procedural textures for the synthetic scenes (deterministic from a seed).

Every texture is a square ``(S, S, 3)`` uint8 RGB image that tiles a surface at ``texel_m`` metres per
texel. Patterns combine a coarse structure (checker, stripes/planks, blobs, rectangles) with value noise
at several scales and high-contrast small marks, so ORB finds corners at every pyramid level.

Style ``"plain"`` (:data:`TEXTURE_STYLES`) paints the walls, ceiling, rug, fabric, cabinets and metal in nearly
uniform colours (a faint low-frequency shade, +-2 % detail), as in real rooms and ICL-NUIM's living room; only
wood, books and posters keep their structure. Keypoints then cluster on a few objects and large parts of the
view are texture-less, the case where feature tracking and photometric terms are weak.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from surfelslam.config import Config, check, setting

TEXTURE_KINDS = ("wallpaper", "wood", "plaster", "checker", "blobs", "fabric", "books", "metal", "poster")
TEXTURE_STYLES = ("rich", "plain")
# style "plain": each of these kinds becomes a flat paint of this colour (RGB); the others keep their pattern
_PLAIN_PAINT = {
    "wallpaper": (226, 218, 200),  # cream wall
    "plaster": (232, 232, 228),  # white ceiling / wall
    "checker": (170, 160, 150),  # grey-beige rug / floor covering
    "blobs": (205, 210, 215),  # pale grey cabinet
    "fabric": (95, 110, 140),  # blue-grey upholstery
    "metal": (150, 152, 156),  # brushed metal without marks
}
_PLAIN_SHADE = 0.06  # +- fraction of the low-frequency shading of a plain paint
_PLAIN_DETAIL = 0.02  # +- fraction of its fine-scale detail


@dataclass(frozen=True)
class TextureConfig(Config):
    """Procedural textures of the synthetic scenes."""

    size_px: int = setting(1024, unit="texels", ge=2, le=16384,
                           doc="texture side, a power of two (the renderer wraps with a bit mask)")
    texel_m: float = setting(0.004, unit="m", gt=0, le=10, doc="metres per texel")
    style: str = setting("rich", choices=TEXTURE_STYLES,
                         doc="rich (texture everywhere) or plain (flat paint but for wood, books and posters)")

    @check
    def _power_of_two(self) -> str | None:
        """size_px is a power of two."""
        if self.size_px & (self.size_px - 1):
            return f"size_px must be a power of two, got {self.size_px}"
        return None


def value_noise(rng: np.random.Generator, size_px: int, cell_px: int) -> np.ndarray:
    """``(S, S)`` float32 smooth noise in [0, 1]: a random grid of ``S / cell_px`` cells, bicubic upsampled."""
    n = max(2, size_px // cell_px + 1)
    grid = rng.random((n, n), dtype=np.float32)
    up = cv2.resize(grid, (size_px, size_px), interpolation=cv2.INTER_CUBIC)
    return np.clip(up, 0.0, 1.0)


def fractal_noise(rng: np.random.Generator, size_px: int, cells_px: tuple[int, ...]) -> np.ndarray:
    """Sum of value-noise octaves (one per cell size, amplitude proportional to cell size), in [0, 1]."""
    acc = np.zeros((size_px, size_px), np.float32)
    total = 0.0
    for c in cells_px:
        w = float(c) ** 0.5
        acc += w * value_noise(rng, size_px, c)
        total += w
    acc /= total
    # stretch to about +-2.3 standard deviations (cheaper than percentiles, same effect)
    mean = float(acc.mean())
    std = max(float(acc.std()), 1e-6)
    return np.clip((acc - mean) / (4.6 * std) + 0.5, 0.0, 1.0)


def _mix(c0, c1, t: np.ndarray) -> np.ndarray:
    """``c0 + (c1 - c0) t`` per pixel: ``(S, S)`` weights -> ``(S, S, 3)`` colours (float32 for float32 ``t``).

    One channel plane at a time: broadcasting over a last axis of 3 makes numpy's inner loops 3 long (about 5x
    slower); the values are the same."""
    c0 = np.asarray(c0, np.float32)
    c1 = np.asarray(c1, np.float32)
    d = c1 - c0
    out = np.empty(np.shape(t) + (3,), np.result_type(c0, t))
    for k in range(3):
        np.multiply(t, d[k], out=out[..., k])
        out[..., k] += c0[k]
    return out


def _add_rgb(img: np.ndarray, rgb) -> np.ndarray:
    """``img + rgb`` for ``(S, S, 3)`` ``img`` and ``(3,)`` ``rgb``, in place, a channel plane at a time (see
    :func:`_mix`); returns ``img``."""
    for k in range(3):
        img[..., k] += rgb[k]
    return img


def _scale(img: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``img * w[..., None]`` for ``(S, S, 3)`` ``img`` and weights broadcastable to ``(S, S)``, in place, a
    channel plane at a time (see :func:`_mix`); returns ``img``."""
    for k in range(3):
        img[..., k] *= w
    return img


def _speckle(rng: np.random.Generator, img: np.ndarray, n: int, radius_px: tuple[int, int], palette) -> None:
    """Draw ``n`` small filled discs of palette colours (high-contrast corners for ORB), in place."""
    s = img.shape[0]
    xs = rng.integers(0, s, n)
    ys = rng.integers(0, s, n)
    rs = rng.integers(radius_px[0], radius_px[1] + 1, n)
    cs = rng.integers(0, len(palette), n)
    for x, y, r, c in zip(xs, ys, rs, cs, strict=True):
        cv2.circle(img, (int(x), int(y)), int(r), tuple(float(v) for v in palette[c]), -1, cv2.LINE_8)


def _rects(rng: np.random.Generator, img: np.ndarray, n: int, size_px: tuple[int, int], palette) -> None:
    s = img.shape[0]
    for _ in range(n):
        x, y = (int(v) for v in rng.integers(0, s, 2))
        w, h = (int(v) for v in rng.integers(size_px[0], size_px[1] + 1, 2))
        c = palette[int(rng.integers(0, len(palette)))]
        cv2.rectangle(img, (x, y), (x + w, y + h), tuple(float(v) for v in c), -1, cv2.LINE_8)


def plain_texture(kind: str, rng: np.random.Generator, size_px: int) -> np.ndarray:
    """A nearly uniform paint ``(S, S, 3)`` uint8 RGB standing in for ``kind`` (style ``"plain"``)."""
    s = size_px
    tint = (rng.random(3).astype(np.float32) - 0.5) * 20.0
    shade = fractal_noise(rng, s, (128, 256)) - 0.5
    detail = fractal_noise(rng, s, (4, 16)) - 0.5
    gain = 1.0 + 2.0 * _PLAIN_SHADE * shade + 2.0 * _PLAIN_DETAIL * detail
    img = (np.asarray(_PLAIN_PAINT[kind], np.float32) + tint) * gain[..., None]
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def make_texture(kind: str, rng: np.random.Generator, size_px: int, style: str = "rich") -> np.ndarray:
    """One texture ``(S, S, 3)`` uint8 RGB of the given kind (see :data:`TEXTURE_KINDS`) and style
    (:data:`TEXTURE_STYLES`)."""
    if style == "plain" and kind in _PLAIN_PAINT:
        return plain_texture(kind, rng, size_px)
    s = size_px
    base = rng.random(3).astype(np.float32) * 60.0  # per-texture tint so each scene looks different
    detail = fractal_noise(rng, s, (4, 16, 64))
    if kind == "wallpaper":
        t = fractal_noise(rng, s, (8, 32, 128, 256))
        img = _add_rgb(_mix((200, 180, 150), (110, 80, 60), t), base * 0.5)
        v = np.arange(s, dtype=np.float32)
        stripes = (np.sin(v * 2 * np.pi / 48.0) > 0.6).astype(np.float32)[None, :]
        _scale(img, 1.0 - 0.35 * stripes)
        _speckle(rng, img, 900, (2, 9), [(40, 30, 30), (240, 230, 210), (150, 40, 40), (30, 60, 120)])
    elif kind == "plaster":
        t = fractal_noise(rng, s, (4, 16, 64, 256))
        img = _mix((225, 225, 215), (120, 125, 130), t)
        _speckle(rng, img, 700, (2, 7), [(60, 60, 70), (250, 250, 245), (90, 110, 80)])
    elif kind == "wood":
        grain = fractal_noise(rng, s, (4, 32))
        plank_px = int(rng.integers(40, 70))
        u = np.arange(s)[None, :] % plank_px
        seam = (u < 2).astype(np.float32)
        plank_id = np.arange(s)[None, :] // plank_px
        plank_tone = (np.sin(plank_id * 12.9898) * 43758.5453) % 1.0
        v = np.arange(s, dtype=np.float32)[:, None]
        rings = 0.5 + 0.5 * np.sin(v / 6.0 + 8.0 * grain)
        t = np.clip(0.45 * rings + 0.35 * plank_tone + 0.2 * grain, 0, 1)
        img = _scale(_add_rgb(_mix((190, 140, 90), (90, 55, 30), t), base * 0.3), 1.0 - 0.7 * seam)
        _speckle(rng, img, 400, (1, 4), [(40, 25, 10), (220, 180, 130)])
    elif kind == "checker":
        cell = int(rng.integers(24, 48))
        yy, xx = np.mgrid[0:s, 0:s]
        chk = ((xx // cell + yy // cell) % 2).astype(np.float32)
        img = _add_rgb(_mix((235, 230, 220), (35, 40, 60), chk), base * 0.4)
        _speckle(rng, img, 500, (2, 8), [(200, 40, 30), (30, 150, 60), (240, 200, 40)])
    elif kind == "blobs":
        img = _mix((210, 200, 190), (150, 140, 130), fractal_noise(rng, s, (32, 128)))
        palette = [(200, 50, 40), (40, 90, 180), (240, 190, 30), (30, 30, 30), (250, 250, 250), (40, 150, 80)]
        _speckle(rng, img, 40, (30, 70), palette)
        _speckle(rng, img, 300, (8, 20), palette)
        _speckle(rng, img, 2000, (2, 6), palette)
    elif kind == "fabric":
        t = fractal_noise(rng, s, (4, 8, 64))
        yy, xx = np.mgrid[0:s, 0:s]
        weave = (((xx // 6) + (yy // 6)) % 2).astype(np.float32)
        img = _add_rgb(_mix((60, 90, 140), (150, 170, 200), 0.6 * t + 0.4 * weave), base * 0.5)
        _speckle(rng, img, 600, (2, 6), [(230, 220, 200), (20, 20, 40), (180, 60, 60)])
    elif kind == "books":
        img = np.full((s, s, 3), 50.0, np.float32)
        palette = [(160, 30, 30), (30, 60, 140), (220, 200, 60), (30, 110, 60), (230, 230, 220), (90, 50, 30)]
        x = 0
        while x < s:
            w = int(rng.integers(8, 28))
            c = np.asarray(palette[int(rng.integers(0, len(palette)))], np.float32)
            img[:, x : x + w] = c
            img[:, x + w - 1 : x + w] = 15.0
            x += w
        _rects(rng, img, 500, (3, 10), [(250, 250, 240), (10, 10, 10), (200, 170, 60)])
    elif kind == "metal":
        t = fractal_noise(rng, s, (2, 8, 128))
        img = _mix((90, 95, 100), (200, 205, 210), t)
        _rects(rng, img, 200, (4, 16), [(40, 40, 45), (230, 230, 235)])
    elif kind == "poster":
        img = _mix((240, 240, 235), (200, 190, 180), fractal_noise(rng, s, (64,)))
        palette = [(200, 30, 30), (20, 40, 120), (20, 20, 20), (240, 180, 0), (0, 130, 120)]
        _rects(rng, img, 150, (10, 80), palette)
        _speckle(rng, img, 400, (3, 12), palette)
    else:
        raise ValueError(f"unknown texture kind {kind!r}; known: {TEXTURE_KINDS}")
    img = _scale(img, 0.8 + 0.4 * detail)  # fine-scale detail everywhere
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


@functools.lru_cache(maxsize=4)
def make_texture_bank(kinds: tuple[str, ...], seed: int, cfg: TextureConfig = TextureConfig()) -> np.ndarray:
    """Textures ``(T, S, S, 3)`` uint8 RGB, one per kind, deterministic from ``seed``.

    Cached (a few banks): the result is read-only and shared between scenes built with the same seed.
    """
    out = np.empty((len(kinds), cfg.size_px, cfg.size_px, 3), np.uint8)
    for i, kind in enumerate(kinds):
        rng = np.random.default_rng([seed, i, 7919])
        out[i] = make_texture(kind, rng, cfg.size_px, cfg.style)
    out.setflags(write=False)
    return out
