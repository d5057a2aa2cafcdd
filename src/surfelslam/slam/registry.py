"""The tracker registry: ``@register_tracker("name")`` on a tracker class makes it buildable by name.

A new tracker is one module whose class is decorated with :func:`register_tracker` plus one import line in
:mod:`surfelslam.slam`. At run time this module imports only the error types, so that the tracker modules, the
settings (``slam/config.py`` checks ``tracker`` against :func:`registered`) and the run loop all import it without
a cycle.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from surfelslam.errors import ConfigError

if TYPE_CHECKING:  # annotations only: the settings import this module
    from surfelslam.slam.config import SlamConfig
    from surfelslam.slam.protocol import Tracker
    from surfelslam.types import ColourCamera, Intrinsics

_REGISTRY: dict[str, type] = {}


def register_tracker(name: str) -> Callable[[type], type]:
    """Class decorator: make the tracker class buildable as ``name`` (``build_tracker(name, ...)``)."""

    def deco(cls: type) -> type:
        if name in _REGISTRY:
            raise ValueError(f"tracker {name!r} is registered twice")
        _REGISTRY[name] = cls
        cls.name = name
        return cls

    return deco


def registered() -> dict[str, type]:
    """``{name: class}`` of every registered tracker, in registration order."""
    return dict(_REGISTRY)


def build_tracker(name: str, intr: Intrinsics, cfg: SlamConfig, colour_registered: bool = True,
                  colour_camera: ColourCamera | None = None) -> Tracker:
    """The tracker registered as ``name``.

    ``colour_registered``: the sequence's colour and depth pixels see the same rays (photometric and feature terms
    are used only then, by default). ``colour_camera``: the sequence's separate colour camera, if known: the maps'
    colours are sampled through it (``colour_registration``); tracking is unaffected.
    """
    cls = _REGISTRY.get(name)
    if cls is None:
        raise ConfigError(f"unknown tracker {name!r}; known: {', '.join(_REGISTRY)}")
    return cls(intr, cfg, colour_registered=colour_registered, colour_camera=colour_camera)
