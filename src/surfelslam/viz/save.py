"""Figure creation and atomic PNG saving shared by every plot (no pyplot global state)."""

from __future__ import annotations

from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from surfelslam.io.atomic import atomic_open
from surfelslam.viz import style


def new_figure(figsize_in: tuple[float, float]) -> Figure:
    """A Figure bound to an Agg canvas (independent of pyplot and of the global backend)."""
    fig = Figure(figsize=figsize_in, dpi=style.DPI)
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig: Figure, path: str | Path) -> Path:
    """Render ``fig`` to PNG at ``path`` via a temp file + rename (never a half-written PNG)."""
    if fig.canvas is None or not isinstance(fig.canvas, FigureCanvasAgg):
        FigureCanvasAgg(fig)
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=style.DPI, pil_kwargs={"compress_level": style.PNG_COMPRESS_LEVEL})
    return Path(path)
