"""Figure creation and atomic PNG saving shared by every plot (no pyplot global state)."""

from __future__ import annotations

from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from surfelslam.io.atomic import atomic_open
from surfelslam.viz import style

_OPAQUE = 255  # alpha of a fully opaque pixel in Agg's RGBA buffer


def new_figure(figsize_in: tuple[float, float]) -> Figure:
    """A Figure bound to an Agg canvas (independent of pyplot and of the global backend)."""
    fig = Figure(figsize=figsize_in, dpi=style.DPI)
    FigureCanvasAgg(fig)
    return fig


def write_png(fig: Figure, fh: BinaryIO) -> None:
    """Render ``fig`` at :data:`style.DPI <surfelslam.viz.style.DPI>` and write it as PNG to ``fh``.

    An opaque figure (every figure of ours: white background) is written as RGB, not RGBA: the same pixels, a
    quarter less to compress (a 1600x1200 map figure encodes in about 0.07 s less). OpenCV encodes it: unlike
    Pillow's PNG writer it releases the GIL, so that figures drawn in threads side by side encode in parallel."""
    canvas = fig.canvas if isinstance(fig.canvas, FigureCanvasAgg) else FigureCanvasAgg(fig)
    fig.set_dpi(style.DPI)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())  # (H, W, 4) uint8
    opaque = bool((rgba[..., 3] == _OPAQUE).all())
    pixels = cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGR if opaque else cv2.COLOR_RGBA2BGRA)  # OpenCV's channel order
    ok, png = cv2.imencode(".png", pixels, [cv2.IMWRITE_PNG_COMPRESSION, style.PNG_COMPRESS_LEVEL])
    if not ok:
        raise ValueError(f"OpenCV could not encode a {pixels.shape} figure as PNG")
    fh.write(png.tobytes())


def save_figure(fig: Figure, path: str | Path) -> Path:
    """:func:`write_png` to ``path`` via a temp file + rename (never a half-written PNG)."""
    with atomic_open(path, "wb") as fh:
        write_png(fig, fh)
    return Path(path)
