"""What the experiments run (options, frame pairs, the reference assignment's values) and small helpers."""

from __future__ import annotations

import math
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from surfelslam.errors import ConfigError

# The reference assignment's dormant-rule values (surfels older than 20 frames seen in fewer than 15 are removed).
REFERENCE_DORMANT_MAX_AGE_FRAMES = 20
REFERENCE_DORMANT_MIN_HITS = 15
SOLVER_TIMEIT_NUMBER = 10
SOLVER_TIMEIT_REPEAT = 7
SOLVER_PAIR_GATE_M = 0.17

SECTION_TITLES = (
    "## 1. ICP on frame pairs",
    "## 2. Solver comparison",
    "## 3. Fusion with ground-truth poses vs estimated poses",
    "## 4. Dormant-point rule",
    "## 5. Feature odometry on a pair",
    "## 6. Trajectories against ground truth",
)


@dataclass(frozen=True)
class ExperimentOptions:
    """What to run: ``frames`` frames for sections 3, 4 and 6; pairs ``pair_start -> pair_start + gap``."""

    frames: int = 200
    pair_start: int = 10
    pair_gaps: tuple[int, ...] = (40, 90)
    progress: bool = True

    def __post_init__(self) -> None:
        if self.frames < 3:
            raise ConfigError(f"--frames must be >= 3, got {self.frames}")
        if self.pair_start < 0:
            raise ConfigError(f"--pair-start must be >= 0, got {self.pair_start}")
        if not self.pair_gaps or any(g < 1 for g in self.pair_gaps):
            raise ConfigError(f"--pair-gaps must be positive frame gaps, got {self.pair_gaps}")


def choose_pairs(n_frames: int, start: int, gaps: tuple[int, ...]) -> tuple[list[tuple[int, int]], bool]:
    """Frame pairs ``(source, target)`` ``start -> start + gap``; scaled down to fit a short selection.

    Returns ``(pairs, scaled)``; ``pairs`` is empty when the selection has fewer than 2 frames.
    """
    if n_frames < 2:
        return [], False
    if start + max(gaps) < n_frames:
        return [(start, start + g) for g in gaps], False
    s = min(start, n_frames // 10)
    scale = (n_frames - 1 - s) / max(gaps)
    pairs: list[tuple[int, int]] = []
    for g in gaps:
        p = (s, s + max(1, int(g * scale)))
        if p not in pairs:
            pairs.append(p)
    return pairs, True


def fmt_value(x, spec: str = ".2f", none: str = "n/a") -> str:
    """``x`` formatted with ``spec``; ``none`` for ``None`` and non-finite floats."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return none
    return format(x, spec)


def gt_relative(T_wc: np.ndarray, valid: np.ndarray, s: int, t: int) -> np.ndarray | None:
    """Ground-truth ``T_t_s`` (frame ``s`` into frame ``t``), ``None`` when either pose is missing."""
    from surfelslam.geometry import se3

    if not (valid[s] and valid[t]):
        return None
    return se3.invert(T_wc[t]) @ T_wc[s]


def run_tracker(seq_runs, out_dir: Path, cfg, tracker: str, poses: str | None, opts: ExperimentOptions,
                figures: Collection[str] = ()) -> dict:
    """One ordinary run folder (``surfelslam run``) of ``seq_runs`` into ``out_dir``, with the ``figures``
    (:data:`~surfelslam.viz.run_report.RUN_FIGURES`) the report links; returns its metrics."""
    from surfelslam.api import run_sequence

    return run_sequence(seq_runs, out_dir, cfg, tracker, poses=poses, progress=opts.progress, figures=figures)


def ate_of(metrics: dict | None) -> float | None:
    """The ATE RMSE (m) of a run's metrics, ``None`` without an evaluation."""
    if metrics is None or "eval" not in metrics:
        return None
    return float(metrics["eval"]["ate_rmse_m"])
