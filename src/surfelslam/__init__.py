"""surfelslam: dense RGB-D SLAM (projective ICP + point-based fusion) with a sparse ORB back end.

The public API (:mod:`surfelslam.api`): :func:`open_sequence`, :class:`Slam` (``track`` / ``finish``), :class:`SlamRun`,
:func:`register`, :func:`evaluate`, :func:`load_map`, :class:`SlamConfig`, and the types :class:`Intrinsics`,
:class:`RGBDFrame`, :class:`Trajectory`. The API names are imported on first use, so ``import surfelslam`` (and the
command line's start-up) stays fast: nothing but the error types is imported up front.
"""

import time

from surfelslam.errors import SurfelSlamError

#: ``time.perf_counter()`` when the package was first imported: for the ``surfelslam`` command, the process's start
#: (less the interpreter's own start-up); ``surfelslam run`` counts ``metrics.json``'s ``startup_s`` from it.
IMPORTED_PERF_S = time.perf_counter()

__version__ = "0.1.0"

_API = {"Intrinsics": "surfelslam.types", "RGBDFrame": "surfelslam.types", "Trajectory": "surfelslam.types",
        "open_sequence": "surfelslam.api", "Slam": "surfelslam.api", "SlamRun": "surfelslam.api",
        "register": "surfelslam.api", "evaluate": "surfelslam.api", "load_map": "surfelslam.api",
        "SlamConfig": "surfelslam.slam.config", "TRACKERS": "surfelslam.slam"}

__all__ = ["SurfelSlamError", *_API]


def __getattr__(name: str):
    if name in _API:
        import importlib

        value = getattr(importlib.import_module(_API[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'surfelslam' has no attribute {name!r}")
