"""Trajectory and error figures (matplotlib Figure objects on the Agg canvas; no pyplot state).

PNG files are written atomically: rendered to a temp file in the target folder, then ``os.replace``d.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.collections import LineCollection

from surfelslam.eval.metrics import AteResult, RpeResult
from surfelslam.types import Trajectory
from surfelslam.viz import style
from surfelslam.viz.save import new_figure, save_figure

AXIS_NAMES = ("x", "y", "z")


def top_view_axes(gt_positions: np.ndarray) -> tuple[int, int]:
    """The two axes (indices into x, y, z) with the largest spread of ``(N, 3)`` positions, ascending."""
    spread = np.ptp(np.asarray(gt_positions, dtype=np.float64).reshape(-1, 3), axis=0)
    a, b = sorted(np.argsort(-spread, kind="stable")[:2].tolist())
    return a, b


def _nearest_indices(timestamps: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Index of the timestamp nearest each query time; ``timestamps`` ascending ``(N,)``."""
    hi = np.clip(np.searchsorted(timestamps, query), 1, len(timestamps) - 1)
    lo = hi - 1
    return np.where(np.abs(timestamps[hi] - query) < np.abs(timestamps[lo] - query), hi, lo)


def plot_trajectory(
    path: str | Path,
    est_aligned: Trajectory,
    gt: Trajectory | None,
    title: str,
    loops: Sequence[tuple[float, float]] | None = None,
) -> Path:
    """Top view (the two axes of largest GT spread) of GT vs estimate, plus x, y, z against time.

    Args:
        path: output PNG.
        est_aligned: estimate, already in the GT frame (e.g. ``T_align @ T_world_cam``).
        gt: ground truth, or None (then the top view uses the estimate's spread).
        title: figure title.
        loops: optional ``(t_i, t_j)`` timestamp pairs (seconds); each is drawn as a line between the
            estimate positions nearest those times.
    """
    est_p = est_aligned.positions
    ref_p = gt.positions if gt is not None and len(gt) else est_p
    a, b = top_view_axes(ref_p)
    t0_candidates = [est_aligned.timestamps[0]] if len(est_aligned) else []
    if gt is not None and len(gt):
        t0_candidates.append(gt.timestamps[0])
    t0 = min(t0_candidates) if t0_candidates else 0.0

    fig = new_figure(style.TRAJECTORY_FIGSIZE_IN)
    grid = fig.add_gridspec(3, 2, width_ratios=(1.1, 1.0), **style.TRAJECTORY_LAYOUT)
    ax_top = fig.add_subplot(grid[:, 0])
    if gt is not None and len(gt):
        ax_top.plot(gt.positions[:, a], gt.positions[:, b], style.GT_LINESTYLE, color=style.GT_COLOR,
                    lw=style.LINE_WIDTH, label="ground truth")
    ax_top.plot(est_p[:, a], est_p[:, b], color=style.EST_COLOR, lw=style.LINE_WIDTH, label="estimate")
    if len(est_p):
        ax_top.scatter(est_p[:1, a], est_p[:1, b], s=style.MARKER_SIZE * 2, color=style.START_COLOR,
                       zorder=3, label="start")
        ax_top.scatter(est_p[-1:, a], est_p[-1:, b], s=style.MARKER_SIZE * 2, color=style.END_COLOR,
                       zorder=3, label="end")
    if loops and len(est_aligned) >= 2:
        pairs = np.asarray(loops, dtype=np.float64).reshape(-1, 2)
        ii = _nearest_indices(est_aligned.timestamps, pairs[:, 0])
        jj = _nearest_indices(est_aligned.timestamps, pairs[:, 1])
        segments = np.stack([est_p[ii][:, [a, b]], est_p[jj][:, [a, b]]], axis=1)
        edges = LineCollection(segments, colors=style.LOOP_COLOR, linewidths=style.THIN_LINE_WIDTH,
                               label=f"loop edges ({len(segments)})")
        ax_top.add_collection(edges)
    ax_top.set_xlabel(f"{AXIS_NAMES[a]} [m]", fontsize=style.LABEL_FONTSIZE)
    ax_top.set_ylabel(f"{AXIS_NAMES[b]} [m]", fontsize=style.LABEL_FONTSIZE)
    ax_top.set_aspect("equal", adjustable="datalim")
    ax_top.grid(alpha=style.GRID_ALPHA)
    ax_top.legend(fontsize=style.LABEL_FONTSIZE, loc="best")
    ax_top.set_title(f"top view ({AXIS_NAMES[a]}-{AXIS_NAMES[b]})", fontsize=style.LABEL_FONTSIZE)

    for k in range(3):
        ax = fig.add_subplot(grid[k, 1])
        if gt is not None and len(gt):
            ax.plot(gt.timestamps - t0, gt.positions[:, k], style.GT_LINESTYLE, color=style.GT_COLOR,
                    lw=style.THIN_LINE_WIDTH)
        ax.plot(est_aligned.timestamps - t0, est_p[:, k], color=style.EST_COLOR, lw=style.THIN_LINE_WIDTH)
        ax.set_ylabel(f"{AXIS_NAMES[k]} [m]", fontsize=style.LABEL_FONTSIZE)
        ax.grid(alpha=style.GRID_ALPHA)
        ax.tick_params(labelsize=style.LABEL_FONTSIZE)
        if k < 2:
            ax.tick_params(labelbottom=False)
        else:
            ax.set_xlabel("time [s]", fontsize=style.LABEL_FONTSIZE)
    fig.suptitle(title, fontsize=style.TITLE_FONTSIZE)
    return save_figure(fig, path)


def plot_errors(
    path: str | Path, ate_result: AteResult, rpe_result: RpeResult | None = None, title: str = ""
) -> Path:
    """ATE translation error over time (with its RMSE), and the RPE translation error if given."""
    n_rows = 2 if rpe_result is not None else 1
    fig = new_figure(style.ERRORS_FIGSIZE_IN)
    fig.subplots_adjust(**style.ERRORS_LAYOUT)
    axes = [fig.add_subplot(n_rows, 1, k + 1) for k in range(n_rows)]
    t0 = ate_result.timestamps[0] if ate_result.n_pairs else 0.0
    ax = axes[0]
    ax.plot(ate_result.timestamps - t0, ate_result.errors_m, color=style.ERROR_COLOR, lw=style.LINE_WIDTH,
            label="ATE")
    ax.axhline(ate_result.rmse_m, color=style.GT_COLOR, ls=style.GT_LINESTYLE, lw=style.THIN_LINE_WIDTH,
               label=f"RMSE {ate_result.rmse_m:.4f} m")
    ax.set_ylabel("ATE [m]", fontsize=style.LABEL_FONTSIZE)
    ax.legend(fontsize=style.LABEL_FONTSIZE, loc="upper left")
    if rpe_result is not None:
        unit = "frame" if rpe_result.delta_unit == "frames" else "s"
        label = f"RPE trans (delta {rpe_result.delta:g} {unit})"
        ax2 = axes[1]
        ax2.plot(rpe_result.timestamps - t0, rpe_result.trans_errors_m, color=style.SECONDARY_COLOR,
                 lw=style.THIN_LINE_WIDTH, label=f"{label}, RMSE {rpe_result.trans_rmse_m:.4f} m")
        ax2.set_ylabel("RPE trans [m]", fontsize=style.LABEL_FONTSIZE)
        ax2.legend(fontsize=style.LABEL_FONTSIZE, loc="upper left")
    for ax in axes:
        ax.grid(alpha=style.GRID_ALPHA)
        ax.tick_params(labelsize=style.LABEL_FONTSIZE)
    axes[-1].set_xlabel("time [s]", fontsize=style.LABEL_FONTSIZE)
    fig.suptitle(title or f"ATE over time ({ate_result.n_pairs} poses)", fontsize=style.TITLE_FONTSIZE)
    return save_figure(fig, path)
