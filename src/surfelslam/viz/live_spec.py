"""Where the live view goes and how much it logs: ``--viewer spawn|connect[=ADDR]|serve|save=FILE`` parsed into a
:class:`ViewerSpec`, and the viewer's settings (:class:`LiveViewerConfig`). The logging itself is
:mod:`surfelslam.viz.live`, which re-exports these (one import for callers)."""

from __future__ import annotations

from dataclasses import dataclass

from surfelslam.config import Config, setting
from surfelslam.errors import ConfigError

MODES = ("spawn", "connect", "serve", "save")
#: Default Rerun gRPC address for ``connect`` without one.
DEFAULT_CONNECT = "rerun+http://127.0.0.1:9876/proxy"


@dataclass(frozen=True)
class ViewerSpec:
    """Where the live view goes: ``mode`` one of :data:`MODES`; ``target``: the file (``save``), the address
    (``connect``, ``None``: the local viewer), else ``None``."""

    mode: str
    target: str | None = None

    def describe(self) -> str:
        return {"spawn": "a spawned Rerun viewer", "connect": f"the Rerun viewer at {self.url()}",
                "serve": "a served Rerun web viewer", "save": f"the recording {self.target}"}[self.mode]

    def url(self) -> str:
        """The gRPC URL of ``connect``: ``host:port`` becomes ``rerun+http://host:port/proxy``."""
        t = self.target
        if not t:
            return DEFAULT_CONNECT
        return t if "://" in t else f"rerun+http://{t}/proxy"


def parse_viewer(text: str) -> ViewerSpec:
    """``spawn``, ``connect``, ``connect=HOST:PORT`` (or a ``rerun+http://`` URL), ``serve`` or ``save=FILE``.

    Raises:
        ConfigError: anything else (the message lists the forms).
    """
    mode, sep, target = text.strip().partition("=")
    mode = mode.strip().lower()
    forms = "spawn, connect, connect=HOST:PORT, serve or save=FILE.rrd"
    if mode not in MODES:
        raise ConfigError(f"--viewer {text!r}: expected {forms}")
    target = target.strip() or None
    if mode == "save" and target is None:
        raise ConfigError(f"--viewer {text!r}: save needs a file, e.g. save=run.rrd")
    if mode in ("spawn", "serve") and sep:
        raise ConfigError(f"--viewer {text!r}: {mode} takes no value (expected {forms})")
    return ViewerSpec(mode, target)


@dataclass(frozen=True)
class LiveViewerConfig(Config):
    """How much the live viewer logs, and how far it may fall behind tracking."""

    images_every: int = setting(5, unit="frames", ge=1, le=1_000_000,
                                doc="log the colour and depth images every N frames")
    map_every: int = setting(30, unit="frames", ge=1, le=1_000_000, doc="log a map snapshot every N frames")
    path_every: int = setting(10, unit="frames", ge=1, le=1_000_000,
                              doc="send the camera poses, plots and path in batches of N frames")
    map_max_points: int = setting(100_000, unit="points", ge=1, le=100_000_000,
                                  doc="a map snapshot is subsampled to at most this many points")
    queue_size: int = setting(8, unit="items", ge=1, le=10_000,
                              doc="pending log items; when full, images and map snapshots are dropped, not waited for")
