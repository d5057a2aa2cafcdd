"""Helpers shared by the benchmark scripts: where the real sequences are, and one timing rule."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

#: The real sequences (``../shared/data`` beside the repository).
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
#: The 7-Scenes sequence the pair and stage benchmarks use.
REDKITCHEN = SHARED_DATA / "7scenes_redkitchen_0000_0499"


#: Tracker rows that are a preset (``configs/NAME.toml``) rather than a tracker with the defaults.
PRESET_TRACKERS = ("hybrid-full",)
PRESETS = Path(__file__).resolve().parents[1] / "configs"


def tracker_setup(label: str):
    """``(tracker, SlamConfig)`` of a bench row's tracker label: a tracker with the defaults, or a preset of
    :data:`PRESET_TRACKERS` (its config, whose ``tracker`` it names)."""
    from surfelslam.config import load_toml
    from surfelslam.slam import SlamConfig

    if label not in PRESET_TRACKERS:
        return label, SlamConfig()
    cfg = load_toml(SlamConfig, PRESETS / f"{label}.toml")
    return cfg.tracker, cfg


def median_ms(fn: Callable[[], object], reps: int) -> float:
    """Median wall time of ``reps`` calls of ``fn``, in milliseconds."""
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000.0 * float(np.median(times))
