"""Trajectory evaluation (ATE, RPE) with evo.

The names are imported on first use (PEP 562): :mod:`surfelslam.eval.metrics` imports evo and scipy.spatial (about
0.05 s of CPU once scipy.linalg is loaded), which a run needs only at its end, and :mod:`surfelslam.eval.protocol`'s
defaults must not pull them in.
"""

import importlib

_METRICS_NAMES = ("AteResult", "RpeResult", "associate", "ate", "evaluate", "evaluate_all", "rpe", "summary")

__all__ = list(_METRICS_NAMES)


def __getattr__(name: str):
    if name in _METRICS_NAMES:
        value = getattr(importlib.import_module("surfelslam.eval.metrics"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'surfelslam.eval' has no attribute {name!r}")
