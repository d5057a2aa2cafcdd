"""Image decoding with clear errors (OpenCV). Colour is returned RGB, depth as the raw integer image."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from surfelslam.errors import FrameError


def read_rgb(path: str | Path) -> np.ndarray:
    """Colour image -> ``(H, W, 3)`` uint8 RGB. Grey images are replicated to 3 channels."""
    path = Path(path)
    if not path.is_file():
        raise FrameError(path, "colour image not found")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FrameError(path, "cannot decode colour image (corrupt or not an image)")
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.dtype != np.uint8:
        raise FrameError(path, f"unsupported colour image type {img.dtype}")
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth_raw(path: str | Path) -> np.ndarray:
    """Depth image -> ``(H, W)`` array of raw units (uint16 for PNG, float for EXR/TIFF)."""
    path = Path(path)
    if not path.is_file():
        raise FrameError(path, "depth image not found")
    img = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FrameError(path, "cannot decode depth image (corrupt or not an image)")
    if img.ndim != 2:
        raise FrameError(path, f"depth image must have one channel, got {img.shape[2]}")
    if img.dtype == np.uint8:
        raise FrameError(path, "depth image is 8-bit; expected 16-bit PNG (raw units)")
    return img


def write_png_rgb(path: str | Path, rgb: np.ndarray) -> None:
    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise FrameError(path, "cannot write colour image")


def write_png_depth(path: str | Path, depth_raw_u16: np.ndarray) -> None:
    if not cv2.imwrite(str(path), depth_raw_u16.astype(np.uint16)):
        raise FrameError(path, "cannot write depth image")
