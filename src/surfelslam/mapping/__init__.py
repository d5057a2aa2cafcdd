"""Point-based fusion: the surfel map, its rendering and the per-frame fusion."""

from surfelslam.mapping.fusion import FusionConfig, FusionStats, fuse, pixel_weights
from surfelslam.mapping.render import IndexMap, RenderConfig, RenderedView, render, render_index_map
from surfelslam.mapping.surfel_map import MapConfig, SurfelMap

__all__ = [
    "FusionConfig", "FusionStats", "IndexMap", "MapConfig", "RenderConfig", "RenderedView", "SurfelMap",
    "fuse", "pixel_weights", "render", "render_index_map",
]
