"""Figures of a fused map: shaded surfel splats from a framing camera and from the top.

For pictures only (not the tracking path). The surfels are projected in numpy and splatted as depth-tested
discs (:mod:`surfelslam.kernels.splat`) once per view; each colour mode (normal, confidence, time, RGB) then
just recolours the same index image. Surfels facing away from the viewer are culled, so walls between the
virtual camera and the room's inside do not hide it (the map's normals face the cameras that saw them).
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from matplotlib import colormaps, patheffects
from matplotlib.artist import Artist
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from surfelslam.errors import ConfigError
from surfelslam.kernels.splat import splat_discs
from surfelslam.viz import style
from surfelslam.viz.save import new_figure, save_figure, write_png

COLOUR_MODES = ("normal", "confidence", "time", "rgb")
FIGURE_SIZE_PX = (1600, 1200)
#: the 2x2 panels' placement in the figure (matplotlib's subplot parameters, fractions of the figure)
PANEL_LAYOUT = {"left": 0.01, "right": 0.93, "bottom": 0.02, "top": 0.92, "wspace": 0.12, "hspace": 0.1}
#: (width, height) of one rendered panel: 4:3 at the height a panel of the 1600x1200 figure has (1080 px for two
#: panels and a tenth of one between them), so that it is drawn pixel for pixel, without resampling
IMAGE_SIZE_PX = (686, 514)
BACKGROUND = 1.0  # white
_FULL_SCALE = 255  # an 8-bit channel's value for 1.0
AMBIENT = 0.45  # Lambert shading: brightness of a surfel lit edge-on
FIXED_RADIUS_PX = 1.5  # splat radius of points without a radius (the ORB keyframe cloud)
MAX_RADIUS_PX = 16.0
RADIUS_SCALE = 1.5  # splats drawn larger than the fusion radius: closes the gaps seen at oblique angles
ELEVATION_DEG = 35.0  # the framing camera looks down at the map by this angle
FIT_PERCENTILE = 0.2  # framing ignores this percentage of outlying surfels on each side
MARGIN = 0.04  # fraction of the image kept free on each side
#: surfels of the throwaway figure of :func:`warm_up_map_figures` (a few: it is drawn for its first-use costs)
WARM_UP_SURFELS = 200
_warmed_up = False  # whether this process has drawn the warm-up figure (:func:`warm_up_map_figures`)


def _rotate(R: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """``(N, K)`` float64 ``xyz @ R.T`` for ``R`` ``(K, 3)``, by columns: a BLAS matmul of an ``(N, 3)`` array is
    slower and, with its threads spinning on a busy machine, several times slower."""
    x, y, z = (np.asarray(xyz[:, k], np.float64) for k in range(3))
    return np.column_stack([R[i, 0] * x + R[i, 1] * y + R[i, 2] * z for i in range(len(R))])


def _unit(v) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


@dataclass(frozen=True)
class ViewCamera:
    """A virtual camera: ``p_cam = R_cam_world @ p_world + t_cam_world``; x right, y down, z into the image.

    Perspective (``u = f_px x / z + cx``) unless ``px_per_m`` is set (orthographic: ``u = px_per_m x + cx``).
    """

    R_cam_world: np.ndarray  # (3, 3)
    t_cam_world: np.ndarray  # (3,)
    width: int
    height: int
    cx: float
    cy: float
    f_px: float = 0.0
    px_per_m: float | None = None
    light_cam: np.ndarray = field(default_factory=lambda: _unit([-0.35, -0.6, -0.72]))  # surface -> light

    def to_cam(self, xyz_world: np.ndarray) -> np.ndarray:
        """``(N, 3)`` world points -> ``(N, 3)`` float64 camera-frame points."""
        return _rotate(self.R_cam_world, xyz_world) + self.t_cam_world

    def to_pixels(self, xyz_world: np.ndarray, p_cam: np.ndarray | None = None,
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(N, 3)`` world points (or their ``p_cam``) -> ``(u_px, v_px, depth_m)`` each ``(N,)`` float64."""
        p = self.to_cam(xyz_world) if p_cam is None else p_cam
        if self.px_per_m is not None:
            return self.px_per_m * p[:, 0] + self.cx, self.px_per_m * p[:, 1] + self.cy, p[:, 2]
        z = np.where(p[:, 2] > 1e-9, p[:, 2], 1e-9)
        return self.f_px * p[:, 0] / z + self.cx, self.f_px * p[:, 1] / z + self.cy, p[:, 2]


def _subsample(xyz: np.ndarray, n_max: int = 50_000) -> np.ndarray:
    return np.asarray(xyz[:: max(1, len(xyz) // n_max)], np.float64)


def _range(a: np.ndarray) -> tuple[float, float]:
    lo, hi = np.percentile(a, [FIT_PERCENTILE, 100 - FIT_PERCENTILE]) if len(a) else (-1.0, 1.0)
    return float(lo), float(hi) if hi > lo else float(lo) + 1e-3


def up_axis(position: np.ndarray, poses: np.ndarray | None, normal: np.ndarray | None = None) -> np.ndarray:
    """World 'up' ``(3,)``: a hint, refined by the map's floor / ceiling normals when it has them.

    The hint is minus the cameras' mean y axis (cameras are held roughly upright, but pitched) when they agree,
    else the map's smallest-variance axis signed towards the cameras. The refinement averages the normals
    within a shrinking cone around the hint (floors point up, ceilings down), which removes the pitch.
    """
    pts = _subsample(position)
    if len(pts) == 0:
        return np.array([0.0, 0.0, 1.0]) if poses is None or not len(poses) else _unit(-poses[:, :3, 1].mean(axis=0))
    if poses is not None and len(poses) and np.linalg.norm(poses[:, :3, 1].mean(axis=0)) > 0.5:
        up = -poses[:, :3, 1].mean(axis=0)
    elif len(pts) >= 3:
        up = np.linalg.eigh(np.cov((pts - pts.mean(axis=0)).T))[1][:, 0]
        hint = poses[:, :3, 3].mean(axis=0) - pts.mean(axis=0) if poses is not None and len(poses) else up
        up = up if hint @ up >= 0 else -up
    else:
        up = np.array([0.0, 0.0, 1.0])
    up = up / np.linalg.norm(up)
    nrm = None if normal is None else _subsample(normal)
    if nrm is None or not (np.abs(nrm) > 0).any():
        nrm = _sample_normals(position)
    for cone_deg in (45.0, 30.0, 20.0):
        if nrm is None:
            break
        c = _rotate(up[None], nrm)[:, 0]
        near = np.abs(c) > np.cos(np.radians(cone_deg))
        if near.sum() < max(50, 0.02 * len(nrm)):
            break
        m = (nrm[near] * np.sign(c[near])[:, None]).sum(axis=0)
        up = m / np.linalg.norm(m)
    return up


def _sample_normals(position: np.ndarray, n_sample: int = 4000, k: int = 12) -> np.ndarray | None:
    """Unsigned normals ``(S, 3)`` of a point cloud at ``S <= n_sample`` points (PCA of ``k`` neighbours)."""
    if len(position) < 4 * k:
        return None
    from scipy.spatial import cKDTree

    pts = _subsample(position, 200_000)
    sample = pts[:: max(1, len(pts) // n_sample)]
    nb = pts[cKDTree(pts).query(sample, k=k)[1]]
    nb -= nb.mean(axis=1, keepdims=True)
    return np.linalg.eigh(np.einsum("ski,skj->sij", nb, nb))[1][:, :, 0]


def _horizontal_axes(pts: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The map's major and minor horizontal axes (PCA of the points in the plane normal to ``up``)."""
    a = _unit(np.cross(up, [1.0, 0, 0] if abs(up[0]) < 0.9 else [0, 1.0, 0]))
    b = np.cross(up, a)
    q = _rotate(np.stack([a, b]), pts - pts.mean(axis=0)) if len(pts) > 2 else np.eye(2)
    w = np.linalg.eigh(np.cov(q.T))[1][:, 1]
    major = w[0] * a + w[1] * b
    return major, np.cross(up, major)


def perspective_view(position: np.ndarray, poses: np.ndarray | None, normal: np.ndarray | None = None,
                     width: int | None = None, height: int | None = None, vfov_deg: float = 45.0) -> ViewCamera:
    """A camera behind and above the map, looking along the trajectory's mean viewing direction tilted down by
    ``ELEVATION_DEG``, at the distance where the map fits ``vfov_deg``; focal and principal point then frame
    the map's projection exactly (with ``MARGIN``)."""
    width, height = width or IMAGE_SIZE_PX[0], height or IMAGE_SIZE_PX[1]
    pts = _subsample(position)
    up = up_axis(position, poses, normal)
    look = poses[:, :3, 2].mean(axis=0) if poses is not None and len(poses) else np.zeros(3)
    look = look - (look @ up) * up
    if np.linalg.norm(look) < 0.1:
        look = _horizontal_axes(pts, up)[1]
    look /= np.linalg.norm(look)
    el = np.radians(ELEVATION_DEG)
    fwd = np.cos(el) * look - np.sin(el) * up
    down = -(up - (up @ fwd) * fwd)
    down /= np.linalg.norm(down)
    R = np.stack([np.cross(down, fwd), down, fwd])
    centre = np.median(pts, axis=0) if len(pts) else np.zeros(3)
    q = _rotate(R, pts - centre)
    ty = np.tan(np.radians(vfov_deg) / 2)
    need = np.maximum(np.abs(q[:, 0]) / (ty * width / height), np.abs(q[:, 1]) / ty) - q[:, 2]
    dist = max(float(np.percentile(need, 100 - FIT_PERCENTILE)) if len(q) else 1.0, 0.1)
    z = q[:, 2] + dist
    front = z > 0.05 * dist
    a0, a1 = _range(q[front, 0] / z[front])
    b0, b1 = _range(q[front, 1] / z[front])
    f = min(width * (1 - 2 * MARGIN) / (a1 - a0), height * (1 - 2 * MARGIN) / (b1 - b0))
    t = -R @ (centre - dist * fwd)
    return ViewCamera(R, t, width, height, width / 2 - f * (a0 + a1) / 2, height / 2 - f * (b0 + b1) / 2, f)


def top_view(position: np.ndarray, poses: np.ndarray | None, normal: np.ndarray | None = None,
             width: int | None = None, height: int | None = None) -> ViewCamera:
    """Orthographic camera looking down ``-up``, the map's major horizontal axis along the image's x, scaled so
    the map and the trajectory fit."""
    width, height = width or IMAGE_SIZE_PX[0], height or IMAGE_SIZE_PX[1]
    pts = _subsample(position)
    up = up_axis(position, poses, normal)
    x_axis, _ = _horizontal_axes(pts, up)
    R = np.stack([x_axis, np.cross(-up, x_axis), -up])
    (x0, x1), (y0, y1) = _range((q := _rotate(R, pts))[:, 0]), _range(q[:, 1])
    if poses is not None and len(poses):  # the whole trajectory is drawn, so it must fit
        qt = poses[:, :3, 3] @ R.T
        x0, x1 = min(x0, qt[:, 0].min()), max(x1, qt[:, 0].max())
        y0, y1 = min(y0, qt[:, 1].min()), max(y1, qt[:, 1].max())
    s = min(width * (1 - 2 * MARGIN) / (x1 - x0), height * (1 - 2 * MARGIN) / (y1 - y0))
    return ViewCamera(R, np.zeros(3), width, height, width / 2 - s * (x0 + x1) / 2, height / 2 - s * (y0 + y1) / 2,
                      px_per_m=s, light_cam=_unit([-0.3, -0.4, -0.87]))


def render(cam: ViewCamera, position: np.ndarray, normal: np.ndarray, radius_m: np.ndarray | None = None,
           radius_scale: float = RADIUS_SCALE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Splat the surfels: ``(index (H, W) int32, -1 = background; depth (H, W) float64; shade (N,) float32)``.

    ``radius_m`` ``(N,)`` times ``radius_scale`` sizes each disc; without it every point is ``FIXED_RADIUS_PX``.
    Zero normals (points without one) are never culled and are drawn unshaded.
    """
    p_cam = cam.to_cam(position)
    u, v, z = cam.to_pixels(position, p_cam)
    n = _rotate(cam.R_cam_world, normal)
    has_n = np.einsum("ij,ij->i", n, n) > 0.25
    m_per_px = np.full(len(z), 1.0 / cam.px_per_m) if cam.px_per_m is not None else np.abs(z) / cam.f_px
    facing = (n[:, 2] if cam.px_per_m is not None else np.einsum("ij,ij->i", n, p_cam)) <= 0
    keep = (~has_n | facing) & ((z > 1e-3) | (cam.px_per_m is not None))
    if radius_m is None:
        r_px = np.full(len(z), FIXED_RADIUS_PX)
    else:
        r_px = np.clip(radius_scale * np.asarray(radius_m, np.float64) / m_per_px, 0.5, MAX_RADIUS_PX)
    nz = np.where(np.abs(n[:, 2]) > 0.1, n[:, 2], np.where(n[:, 2] < 0, -0.1, 0.1))
    slope_u = np.where(has_n, -n[:, 0] / nz * m_per_px, 0.0)
    slope_v = np.where(has_n, -n[:, 1] / nz * m_per_px, 0.0)
    idx = np.flatnonzero(keep)
    depth = np.full((cam.height, cam.width), np.inf)
    index = np.full((cam.height, cam.width), -1, np.int32)
    splat_discs(u[idx], v[idx], z[idx], r_px[idx], slope_u[idx], slope_v[idx], (r_px * m_per_px)[idx],
                depth, index)
    hit = index >= 0
    index[hit] = idx[index[hit]]
    lambert = np.abs(_rotate(cam.light_cam[None], n)[:, 0])
    shade = np.where(has_n, AMBIENT + (1 - AMBIENT) * lambert, 1.0).astype(np.float32)
    return index, depth, shade


def point_colours(mode: str, normal: np.ndarray, confidence: np.ndarray, first_seen: np.ndarray,
                  colour: np.ndarray) -> tuple[np.ndarray, ScalarMappable | None, str]:
    """``(N, 3)`` float colours in [0, 1] for a colour mode, the colour bar's mappable (or None) and a note for
    the title when the mode carries no information (no normals, every value equal: uniform grey)."""
    grey = np.full((len(normal), 3), 0.7, np.float32)
    if mode == "normal":
        if not (np.abs(normal) > 0).any():
            return grey, None, "none in this map"
        return np.clip((normal + 1.0) * 0.5, 0, 1), None, ""
    if mode == "rgb":
        return np.clip(np.asarray(colour, np.float32) / 255.0, 0, 1), None, ""
    if mode not in ("confidence", "time"):
        raise ValueError(f"unknown colour mode {mode!r}; known: {COLOUR_MODES}")
    values = np.asarray(confidence if mode == "confidence" else first_seen, np.float64)
    lo, hi = (float(values.min()), float(values.max())) if len(values) else (0.0, 0.0)
    if hi <= lo:
        return grey, None, f"all {lo:g}"
    if mode == "confidence":
        hi = max(float(np.percentile(values, 98)), lo + 1e-6 * (hi - lo))
    sm = ScalarMappable(Normalize(lo, hi), colormaps["viridis" if mode == "confidence" else "plasma"])
    return sm.to_rgba(values)[:, :3].astype(np.float32), sm, ""


def pixel_shade(index: np.ndarray, depth: np.ndarray, shade: np.ndarray) -> np.ndarray:
    """``(H, W)`` float32 brightness: each pixel's surfel shade, darkened along depth edges (outlines)."""
    hit = index >= 0
    out = np.zeros(index.shape, np.float32)
    out[hit] = shade[index[hit]]
    z = np.where(hit, depth, 1e30)  # background: far away (finite, so differences stay finite)
    step = 0.03 * float(np.median(depth[hit])) if hit.any() else 1.0
    edge = np.zeros(index.shape, bool)
    jump_v = ~(np.abs(np.diff(z, axis=0)) <= step)
    jump_u = ~(np.abs(np.diff(z, axis=1)) <= step)
    edge[1:] |= jump_v
    edge[:-1] |= jump_v
    edge[:, 1:] |= jump_u
    edge[:, :-1] |= jump_u
    out[edge & hit] *= 0.7
    return out


def compose(index: np.ndarray, brightness: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """``(H, W, 4)`` uint8 RGBA image, opaque: surfel colours ``(N, 3)`` in [0, 1] times :func:`pixel_shade`, white
    background (8 bits with alpha, as matplotlib draws images: it takes it without a conversion of every pixel)."""
    img = np.full((*index.shape, 4), round(BACKGROUND * _FULL_SCALE), np.uint8)
    hit = index >= 0
    img[hit, :3] = (colours[index[hit]] * (brightness[hit, None] * _FULL_SCALE) + 0.5).astype(np.uint8)
    return img


def _normal_key(cam: ViewCamera, size_px: int = 64) -> np.ndarray:
    """``(S, S, 4)`` RGBA image of a sphere seen by ``cam``, coloured like the normal mode: the colour key."""
    a = (np.arange(size_px) + 0.5) / size_px * 2 - 1
    x, y = np.meshgrid(a, a)
    inside = x * x + y * y < 1
    n_cam = np.stack([x, y, -np.sqrt(np.clip(1 - x * x - y * y, 0, 1))], axis=-1)
    rgba = np.zeros((size_px, size_px, 4), np.float32)
    shade = AMBIENT + (1 - AMBIENT) * np.abs(n_cam @ cam.light_cam)
    rgba[..., :3] = np.clip((n_cam @ cam.R_cam_world + 1) * 0.5, 0, 1) * shade[..., None]
    rgba[..., 3] = inside
    return rgba


class PanelPixels(Artist):
    """An RGBA image ``(H, W, 4)`` uint8 drawn pixel for pixel at the top left corner of its axes (clipped to them),
    under the axes' other artists. The panels are rendered at the size their axes have in the figure
    (:data:`IMAGE_SIZE_PX`), so this is what ``imshow`` draws there, to the pixel, without its resampling pass
    (a tenth of a second of each map figure's drawing, holding the GIL)."""

    def __init__(self, ax, rgba: np.ndarray) -> None:
        super().__init__()
        self._ax = ax
        self._rows_up = np.ascontiguousarray(rgba[::-1])  # the renderer's rows go up from the image's bottom
        self.set_zorder(0)

    def draw(self, renderer) -> None:
        box = self._ax.bbox
        gc = renderer.new_gc()
        gc.set_clip_rectangle(box)
        renderer.draw_image(gc, round(box.x0), round(box.y1) - self._rows_up.shape[0], self._rows_up)
        gc.restore()


def _nice_length_m(span_m: float) -> float:
    """A 1-2-5 length near a fifth of ``span_m``."""
    target = max(span_m / 5, 1e-6)
    base = 10 ** np.floor(np.log10(target))
    return float(base * min((1, 2, 5, 10), key=lambda k: abs(k * base - target)))


_TITLES = {"normal": "by normal (world xyz as RGB)", "confidence": "by confidence",
           "time": "by time (frame first seen)", "rgb": "by colour"}
_BAR_LABELS = {"confidence": "confidence (accumulated weight)", "time": "first seen (frame index)"}


def map_figure(cam: ViewCamera, position: np.ndarray, normal: np.ndarray, colour: np.ndarray,
               confidence: np.ndarray, first_seen: np.ndarray, radius: np.ndarray | None = None,
               trajectory_T_world_cam: np.ndarray | None = None, title: str = "") -> Figure:
    """A 2x2 figure (one panel per colour mode) of one view; the trajectory and a scale bar on orthographic views."""
    index, depth, shade = render(cam, position, normal, radius)
    brightness = pixel_shade(index, depth, shade)
    fig = new_figure((FIGURE_SIZE_PX[0] / style.DPI, FIGURE_SIZE_PX[1] / style.DPI))
    fig.subplots_adjust(**PANEL_LAYOUT)
    fig.suptitle(title, fontsize=style.TITLE_FONTSIZE + 1)
    traj_px = None
    if cam.px_per_m is not None and trajectory_T_world_cam is not None and len(trajectory_T_world_cam):
        traj_px = cam.to_pixels(trajectory_T_world_cam[:, :3, 3])[:2]
    for k, mode in enumerate(COLOUR_MODES):
        ax = fig.add_subplot(2, 2, k + 1)
        colours, sm, note = point_colours(mode, normal, confidence, first_seen, colour)
        ax.add_artist(PanelPixels(ax, compose(index, brightness, colours)))
        panel_title = f"{_TITLES[mode].split(' (')[0]} ({note})" if note else _TITLES[mode]
        ax.set_title(panel_title, fontsize=style.TITLE_FONTSIZE)
        ax.set_xticks([])
        ax.set_yticks([])
        if sm is not None:
            cbar = fig.colorbar(sm, cax=ax.inset_axes((1.015, 0.05, 0.03, 0.9)),
                                extend="max" if mode == "confidence" and confidence.max() > sm.norm.vmax else "neither")
            cbar.set_label(_BAR_LABELS[mode], fontsize=style.LABEL_FONTSIZE)
            cbar.ax.tick_params(labelsize=style.LABEL_FONTSIZE)
        if mode == "normal" and not note:
            key = ax.inset_axes((0.0, 0.0, 0.12, 0.12 * cam.width / cam.height))
            key.imshow(_normal_key(cam))
            key.set_axis_off()
        if traj_px is not None:
            halo = [patheffects.withStroke(linewidth=3.5, foreground="white")]
            ax.plot(*traj_px, color="black", lw=style.LINE_WIDTH, path_effects=halo, label="camera path")
            ax.plot(traj_px[0][0], traj_px[1][0], "o", color=style.START_COLOR, ms=8, mec="white", label="start")
            ax.plot(traj_px[0][-1], traj_px[1][-1], "s", color=style.END_COLOR, ms=8, mec="white", label="end")
            if k == 0:
                ax.legend(loc="best", fontsize=style.LABEL_FONTSIZE, framealpha=0.85)
        if cam.px_per_m is not None:
            length_m = _nice_length_m(cam.width / cam.px_per_m)
            ax.add_artist(AnchoredSizeBar(ax.transData, length_m * cam.px_per_m,
                                          f"{length_m:g} m", "lower right", pad=0.6, sep=4, frameon=True,
                                          size_vertical=3, fontproperties={"size": style.LABEL_FONTSIZE}))
        ax.set_aspect("equal")
        ax.set_xlim(-0.5, cam.width - 0.5)
        ax.set_ylim(cam.height - 0.5, -0.5)
    return fig


def save_map_figures(out_dir: str | Path, position: np.ndarray, normal: np.ndarray, colour: np.ndarray,
                     confidence: np.ndarray, first_seen: np.ndarray, T_world_cam0: np.ndarray,
                     prefix: str = "map", title: str = "", trajectory_T_world_cam: np.ndarray | None = None,
                     radius: np.ndarray | None = None, views: Sequence[str] = ("camera", "top")) -> list[Path]:
    """Write ``{prefix}_camera.png`` (framing perspective view) and ``{prefix}_top.png`` (top view with the
    trajectory), each 2x2 colour modes, or only the ``views`` named. Arrays ``(N, 3)`` / ``(N,)``; ``colour`` RGB
    in [0, 255]; poses ``(M, 4, 4)`` (``T_world_cam0`` alone when no trajectory is given); ``radius`` metres or
    None."""
    out_dir = Path(out_dir)
    poses = np.asarray(trajectory_T_world_cam if trajectory_T_world_cam is not None else T_world_cam0[None])
    poses = poses[np.isfinite(poses).all(axis=(1, 2))]
    position = np.asarray(position, np.float32)
    n = f"{len(position):,} {'surfels' if radius is not None else 'points'}"
    head = f"{title}: " if title else ""
    make = {"camera": lambda: (perspective_view(position, poses, normal),
                               f"{head}view from behind and above the map ({n})"),
            "top": lambda: (top_view(position, poses, normal), f"{head}top view, looking down ({n})")}
    unknown = sorted(set(views) - make.keys())
    if unknown:
        raise ConfigError(f"map figure views: unknown {', '.join(unknown)}; known: {', '.join(make)}")
    written = []
    for name in views:
        cam, fig_title = make[name]()
        fig = map_figure(cam, position, normal, colour, confidence, first_seen, radius, poses, fig_title)
        written.append(save_figure(fig, out_dir / f"{prefix}_{name}.png"))
    return written


def warm_up_map_figures() -> None:
    """Draw a small map figure in memory (nothing is written): the splat kernel is loaded from numba's cache and
    matplotlib's fonts and PNG writer are set up, so that a run's map figures do not pay for them at its end (a run
    calls this in a background thread while it tracks). Once per process: what it sets up stays set up, and a
    process that makes many runs (``surfelslam experiments``, a batch, the tests) paid 0.5 s of drawing for each."""
    global _warmed_up
    if _warmed_up:
        return
    rng = np.random.default_rng(0)
    position = rng.uniform(-1.0, 1.0, (WARM_UP_SURFELS, 3))
    normal = position / np.linalg.norm(position, axis=1, keepdims=True)
    colour = rng.integers(0, 256, (WARM_UP_SURFELS, 3))
    values = np.arange(WARM_UP_SURFELS, dtype=np.float64)
    poses = np.stack([np.eye(4), np.eye(4)])
    poses[1, 0, 3] = 0.5
    cam = top_view(position, poses, normal)
    fig = map_figure(cam, position, normal, colour, values, values, np.full(WARM_UP_SURFELS, 0.01), poses, "warm-up")
    write_png(fig, io.BytesIO())
    _warmed_up = True
