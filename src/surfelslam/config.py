"""The settings machinery's old import path: everything lives in :mod:`surfelslam.settings` (kept because every
subsystem's config module imports ``Config`` and ``setting`` from here)."""

from surfelslam.settings import *  # noqa: F403
from surfelslam.settings import __all__  # noqa: F401
