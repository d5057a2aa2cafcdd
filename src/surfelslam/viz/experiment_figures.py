"""Figures of ``surfelslam experiments``: feature matches side by side and several trajectories against GT."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.collections import LineCollection

from surfelslam.types import Trajectory
from surfelslam.viz import style
from surfelslam.viz.save import new_figure, save_figure
from surfelslam.viz.trajectory_plots import top_view_axes

KEPT_COLOR = "#2ca02c"  # green
REJECTED_COLOR = "#d62728"  # red
MATCH_LINE_WIDTH = 0.6
MATCH_LINE_ALPHA = 0.7
MATCHES_FIG_WIDTH_IN = 12.0
TRAJ_FIGSIZE_IN = (7.0, 6.0)
TRACKER_COLORS = ("#1f77b4", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf")


def plot_matches(path: str | Path, img_a: np.ndarray, img_b: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray,
                 kept: np.ndarray, title: str) -> Path:
    """Two images side by side with one line per match: kept matches green, rejected ones red.

    Args:
        img_a, img_b: ``(H, W, 3)`` uint8 RGB (or ``(H, W)`` grey) images of the same height.
        uv_a, uv_b: ``(M, 2)`` pixel coordinates ``(u, v)`` of the matched keypoints in each image.
        kept: ``(M,)`` bool, True for a match kept by the distance filter.
    """
    if img_a.shape[0] != img_b.shape[0]:
        raise ValueError(f"images must have the same height, got {img_a.shape} and {img_b.shape}")
    both = np.concatenate([np.atleast_3d(img_a), np.atleast_3d(img_b)], axis=1)
    if both.shape[2] == 1:
        both = np.repeat(both, 3, axis=2)
    h, w2 = both.shape[:2]
    fig = new_figure((MATCHES_FIG_WIDTH_IN, MATCHES_FIG_WIDTH_IN * h / w2 + 0.6))
    ax = fig.add_subplot(1, 1, 1)
    ax.imshow(both, interpolation="nearest")
    off = float(img_a.shape[1])
    kept = np.asarray(kept, bool)
    segs = np.stack([np.asarray(uv_a, float), np.asarray(uv_b, float) + [off, 0.0]], axis=1)  # (M, 2, 2)
    # rejected matches drawn last, on top
    for mask, colour, label in ((kept, KEPT_COLOR, "kept"), (~kept, REJECTED_COLOR, "rejected")):
        if mask.any():
            ax.add_collection(LineCollection(segs[mask], colors=colour, linewidths=MATCH_LINE_WIDTH,
                                             alpha=MATCH_LINE_ALPHA, label=f"{label} ({int(mask.sum())})"))
            ax.scatter(segs[mask][:, :, 0].ravel(), segs[mask][:, :, 1].ravel(), s=3, c=colour, linewidths=0)
    ax.set_xlim(0, w2)
    ax.set_ylim(h, 0)
    ax.set_axis_off()
    ax.set_title(title, fontsize=style.TITLE_FONTSIZE)
    if len(segs):
        ax.legend(loc="lower right", fontsize=style.LABEL_FONTSIZE)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_trajectories(path: str | Path, estimates: dict[str, Trajectory], gt: Trajectory | None,
                      title: str) -> Path:
    """Top view (the two axes of largest GT spread) of several aligned estimates and the ground truth.

    Args:
        estimates: name -> trajectory already in the GT frame (e.g. ``AteResult.est_aligned``).
        gt: ground truth (dashed), or None.
    """
    ref = gt.positions if gt is not None and len(gt) else (
        np.concatenate([e.positions for e in estimates.values()]) if estimates else np.zeros((1, 3)))
    a, b = top_view_axes(ref)
    fig = new_figure(TRAJ_FIGSIZE_IN)
    ax = fig.add_subplot(1, 1, 1)
    if gt is not None and len(gt):
        ax.plot(gt.positions[:, a], gt.positions[:, b], style.GT_LINESTYLE, color=style.GT_COLOR,
                lw=style.LINE_WIDTH, label="ground truth")
    for k, (name, est) in enumerate(estimates.items()):
        p = est.positions
        ax.plot(p[:, a], p[:, b], color=TRACKER_COLORS[k % len(TRACKER_COLORS)], lw=style.LINE_WIDTH, label=name)
    axis = ("x", "y", "z")
    ax.set_xlabel(f"{axis[a]} (m)", fontsize=style.LABEL_FONTSIZE)
    ax.set_ylabel(f"{axis[b]} (m)", fontsize=style.LABEL_FONTSIZE)
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=style.LABEL_FONTSIZE)
    ax.set_title(title, fontsize=style.TITLE_FONTSIZE)
    fig.tight_layout()
    return save_figure(fig, path)
