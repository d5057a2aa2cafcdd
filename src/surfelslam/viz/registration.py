"""Before/after figures of a pairwise registration: source cloud red, target cloud green."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from surfelslam.viz import style
from surfelslam.viz.save import new_figure, save_figure

SOURCE_COLOR = "#d62728"  # red
TARGET_COLOR = "#2ca02c"  # green
REGISTRATION_FIGSIZE_IN = (7.0, 6.0)
MAX_POINTS_PER_CLOUD = 12000
POINT_SIZE = 0.4
VIEW_ELEVATION_DEG = 30.0  # a 3/4 view from above, beside the target camera
VIEW_AZIMUTH_DEG = -60.0
SUBSAMPLE_SEED = 0


def subsample(points: np.ndarray, max_points: int = MAX_POINTS_PER_CLOUD, seed: int = SUBSAMPLE_SEED) -> np.ndarray:
    """A deterministic random subset of at most ``max_points`` rows of ``points (N, 3)``."""
    if len(points) <= max_points:
        return points
    idx = np.random.default_rng(seed).choice(len(points), max_points, replace=False)
    return points[np.sort(idx)]


def plot_registration(source_pts_tgt: np.ndarray, target_pts: np.ndarray, path: str | Path, title: str) -> Path:
    """Scatter both clouds (already in the target camera frame) from a fixed viewpoint; save a PNG.

    Args:
        source_pts_tgt: ``(N, 3)`` source points mapped into the target camera frame.
        target_pts: ``(M, 3)`` target points (target camera frame).
    """
    fig = new_figure(REGISTRATION_FIGSIZE_IN)
    ax = fig.add_subplot(projection="3d")
    s = subsample(np.asarray(source_pts_tgt))
    t = subsample(np.asarray(target_pts))
    # plot (x, z, -y): x right, depth away from the viewer, camera "up" upwards
    ax.scatter(t[:, 0], t[:, 2], -t[:, 1], s=POINT_SIZE, c=TARGET_COLOR, depthshade=False, label="target",
               linewidths=0)
    ax.scatter(s[:, 0], s[:, 2], -s[:, 1], s=POINT_SIZE, c=SOURCE_COLOR, depthshade=False, label="source",
               linewidths=0)
    both = np.concatenate([s, t]) if len(s) and len(t) else (s if len(s) else t)
    if len(both):
        lo = np.percentile(both, 1, axis=0)
        hi = np.percentile(both, 99, axis=0)
        c = (lo + hi) / 2
        r = float(np.max(hi - lo)) / 2 or 1.0
        ax.set_xlim(c[0] - r, c[0] + r)
        ax.set_ylim(c[2] - r, c[2] + r)
        ax.set_zlim(-c[1] - r, -c[1] + r)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=VIEW_ELEVATION_DEG, azim=VIEW_AZIMUTH_DEG)
    ax.set_xlabel("x (m)", fontsize=style.LABEL_FONTSIZE)
    ax.set_ylabel("z (m)", fontsize=style.LABEL_FONTSIZE)
    ax.set_zlabel("-y (m)", fontsize=style.LABEL_FONTSIZE)
    ax.set_title(title, fontsize=style.TITLE_FONTSIZE)
    ax.legend(loc="upper right", markerscale=12, fontsize=style.LABEL_FONTSIZE)
    return save_figure(fig, path)


def save_registration(out: Path, report, figures: bool = True) -> list[Path]:
    """Write a registered pair (:class:`~surfelslam.eval.pair_registration.PairReport`) into ``out``:
    ``registration.json``, and ``before.png`` and ``after.png`` when ``figures``; returns the files written."""
    import json

    from surfelslam.geometry import se3
    from surfelslam.io.atomic import write_text_atomic

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = [out / "registration.json"]
    write_text_atomic(written[0], json.dumps(report.result, indent=2) + "\n")
    if not figures:
        return written
    p_src, p_tgt = report.pyramids
    res, source, target = report.registration.icp, report.result["source"], report.result["target"]
    src_pts = p_src[0].vertex[p_src[0].vertex[..., 2] > 0]
    tgt_pts = p_tgt[0].vertex[p_tgt[0].vertex[..., 2] > 0]
    written.append(plot_registration(src_pts, tgt_pts, out / "before.png", f"before: source {source} (red), target "
                                     f"{target} (green), identity"))
    written.append(plot_registration(se3.transform_points(res.T_target_source, src_pts.astype(np.float64)), tgt_pts,
                                     out / "after.png", f"after ICP: {res.inliers} inliers, RMSE "
                                                        f"{1000 * res.rmse_m:.1f} mm"))
    return written
