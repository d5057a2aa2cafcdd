"""Preset configurations: ``--config NAME`` reads the package's ``settings/presets/NAME.toml``.

The presets are package data (``pyproject.toml``: ``[tool.setuptools.package-data]``), found with
:mod:`importlib.resources`, so that they work the same from a source tree, an editable install and a wheel.
"""

from __future__ import annotations

import importlib.resources
import re
from importlib.resources.abc import Traversable
from pathlib import Path

from surfelslam.errors import ConfigError

#: The folder of preset files inside this package.
PRESETS_FOLDER = "presets"
#: A bare ``--config`` value that may name a preset (anything else is a path).
_PRESET_NAME = re.compile(r"^[A-Za-z0-9_-]+$")


def presets_dir() -> Traversable:
    """The packaged folder of presets (``surfelslam/settings/presets``)."""
    return importlib.resources.files(__package__) / PRESETS_FOLDER


def preset_names() -> list[str]:
    """Names of the preset configurations (``settings/presets/*.toml``), sorted."""
    folder = presets_dir()
    if not folder.is_dir():
        return []
    return sorted(p.name.removesuffix(".toml") for p in folder.iterdir() if p.name.endswith(".toml"))


def resolve_config_path(config: str | Path) -> Path | Traversable:
    """The file ``--config`` names: an existing file, else the packaged preset ``<config>.toml`` for a bare name.

    Raises:
        ConfigError: a bare name that is neither a file nor a preset (the message lists the presets).
    """
    path = Path(config)
    if path.exists() or not _PRESET_NAME.match(str(config)):
        return path  # a file (or a path that load_toml reports as missing)
    preset = presets_dir() / f"{config}.toml"
    if preset.is_file():
        return preset
    names = preset_names()
    listed = f"presets: {', '.join(names)}" if names else "no presets installed"
    raise ConfigError(f"--config {config}: no such file, and not a preset ({listed})")
