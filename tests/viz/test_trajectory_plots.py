"""Trajectory and ATE-error figures: fixed margins (no ``tight_layout``) that still hold every label, and valid PNGs
of the figure's size."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.image import imread

from surfelslam.eval.metrics import ate, rpe
from surfelslam.geometry import se3
from surfelslam.types import Trajectory
from surfelslam.viz import style
from surfelslam.viz import trajectory_plots as tp


def _trajectories(offset_m: float, n: int = 60) -> tuple[Trajectory, Trajectory]:
    """A ground truth ``offset_m`` from the origin (wide tick labels when large) and a noisy estimate of it."""
    rng = np.random.default_rng(7)
    t = np.arange(n) / 30.0
    gt = Trajectory(t, np.stack([se3.exp(np.array([0.0, 0.01 * k, 0.0, offset_m + 0.05 * k, offset_m - 0.02 * k,
                                                   0.3 * np.sin(k / 9)])) for k in range(n)]))
    est = Trajectory(t, np.stack([T @ se3.exp(rng.normal(size=6) * 2e-3) for T in gt.T_world_cam]))
    return est, gt


def _drawn(monkeypatch) -> list:
    """The figures the plotting functions save (each is still written)."""
    figures = []
    save = tp.save_figure

    def keep(fig, path):
        figures.append(fig)
        return save(fig, path)

    monkeypatch.setattr(tp, "save_figure", keep)
    return figures


def _inside(fig) -> bool:
    """Every axes' labels, tick labels and title fit within the figure."""
    renderer = fig.canvas.get_renderer()
    box = fig.bbox
    return all(box.x0 - 1 <= b.x0 and b.x1 <= box.x1 + 1 and box.y0 - 1 <= b.y0 and b.y1 <= box.y1 + 1
               for b in (ax.get_tightbbox(renderer) for ax in fig.axes))


@pytest.mark.parametrize("offset_m", [0.0, -123.4])
def test_fixed_layout_keeps_every_label_inside(tmp_path, monkeypatch, offset_m):
    figures = _drawn(monkeypatch)
    est, gt = _trajectories(offset_m)
    a = ate(est, gt)
    tp.plot_trajectory(tmp_path / "trajectory.png", a.est_aligned, gt, "dense: ATE", loops=[(0.1, 1.5)])
    tp.plot_errors(tmp_path / "ate_errors.png", a)
    tp.plot_errors(tmp_path / "ate_rpe.png", a, rpe(est, gt))
    assert len(figures) == 3
    for fig in figures:
        assert fig.get_layout_engine() is None  # no tight_layout pass
        assert _inside(fig)
    for name, size_in in (("trajectory.png", style.TRAJECTORY_FIGSIZE_IN), ("ate_errors.png", style.ERRORS_FIGSIZE_IN),
                          ("ate_rpe.png", style.ERRORS_FIGSIZE_IN)):
        img = imread(tmp_path / name)
        assert img.shape[:2] == (round(size_in[1] * style.DPI), round(size_in[0] * style.DPI))
        assert img.std() > 0.05  # something is drawn
