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
#: Bench-only rows: the defaults with some settings changed (label -> those settings, as in a TOML file).
#: ``hybrid-odometry``: the default hybrid without its loop corrections, the reference of "loop closure never makes
#: the trajectory worse than the odometry alone".
VARIANT_TRACKERS = {"hybrid-odometry": {"tracker": "hybrid", "hybrid": {"loop_correction": False}}}


def tracker_setup(label: str):
    """``(tracker, SlamConfig)`` of a bench row's tracker label: a tracker with the defaults, a preset of
    :data:`PRESET_TRACKERS` or a variant of :data:`VARIANT_TRACKERS` (its config, whose ``tracker`` it names)."""
    from surfelslam.config import from_dict, load_toml
    from surfelslam.slam import SlamConfig

    if label in VARIANT_TRACKERS:
        cfg = from_dict(SlamConfig, VARIANT_TRACKERS[label], base=SlamConfig())
    elif label in PRESET_TRACKERS:
        cfg = load_toml(SlamConfig, PRESETS / f"{label}.toml")
    else:
        return label, SlamConfig()
    return cfg.tracker, cfg


def median_ms(fn: Callable[[], object], reps: int) -> float:
    """Median wall time of ``reps`` calls of ``fn``, in milliseconds."""
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000.0 * float(np.median(times))
