"""The run-folder reader: a finished run's trajectory, metrics, settings, map, and the sequence it came from.

:func:`open_run` is the one reader of what :class:`~surfelslam.slam.writer.RunWriter` writes; ``surfelslam mesh``,
``surfelslam rerun`` and ``surfelslam eval`` all read run folders through it, so a run saved from Python
(:meth:`surfelslam.SlamRun.save`) and one written by ``surfelslam run`` read the same. It lives in ``slam/`` (not
``io/``) because a run's settings are a :class:`~surfelslam.slam.config.SlamConfig`.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

from surfelslam.config import load_toml
from surfelslam.datasets.base import DatasetOptions, RGBDSequence
from surfelslam.datasets.registry import open_sequence
from surfelslam.errors import ConfigError, InputError
from surfelslam.io.run_folder import read_run_metrics, read_run_trajectory
from surfelslam.slam.config import SlamConfig
from surfelslam.slam.writer import CONFIG_FILE, MAP_PLY_FILE
from surfelslam.types import Trajectory

#: What a folder that is not a run folder is told it should be.
NOT_A_RUN = "not a folder (expected the --out folder of `surfelslam run`)"


class FinishedRun:
    """A run folder, opened (:func:`open_run`); each file is read when first asked for.

    Attributes:
        folder: the run folder.
    """

    def __init__(self, folder: Path):
        self.folder = folder

    @functools.cached_property
    def metrics(self) -> dict:
        """Its ``metrics.json`` (``{}`` when there is none: an unfinished or copied run)."""
        return read_run_metrics(self.folder)

    @functools.cached_property
    def config(self) -> SlamConfig:
        """Its settings: ``config.toml``, else the defaults with ``metrics.json``'s dataset options."""
        return _run_config(self.folder, self.metrics)

    def trajectory(self) -> Trajectory:
        """``trajectory.txt``; InputError (naming the file) when it is missing or has no poses."""
        return read_run_trajectory(self.folder)

    @property
    def map_path(self) -> Path:
        """The map's point cloud, ``map.ply`` (it may be missing)."""
        return self.folder / MAP_PLY_FILE

    def map_vertices(self) -> dict | None:
        """``map.ply``'s vertex columns (``x``, ``y``, ``z``, normals and colours where written), ``None`` when
        the run has no map."""
        from surfelslam.io.ply import read_ply

        return read_ply(self.map_path) if self.map_path.is_file() else None

    def sequence_path(self, given: Path | None = None, option: str = "--sequence") -> Path:
        """The run's sequence: ``given``, else the one ``metrics.json`` names; InputError (naming ``option``, the
        command's way to give it) when there is none or it is not here."""
        if given is not None:
            return Path(given)
        named = self.metrics.get("sequence")
        if not named:
            raise InputError(self.folder, f"metrics.json names no sequence (is it a complete run?): pass {option} "
                                          "PATH")
        path = Path(named)
        if not path.exists():
            raise InputError(path, f"the run's sequence (named in metrics.json) is not here: pass {option} PATH")
        return path

    def open_sequence(self, given: Path | None = None, option: str = "--sequence", **overrides) -> RGBDSequence:
        """The run's sequence (:meth:`sequence_path`) opened with the run's dataset options, ``overrides``
        (:class:`DatasetOptions` fields; ``None``: the run's) replacing some; ConfigError when it opens at another
        resolution than the run's."""
        path = self.sequence_path(given, option)
        options = dataclasses.replace(self.config.dataset, **{k: v for k, v in overrides.items() if v is not None})
        seq = open_sequence(path, options)
        res = self.metrics.get("resolution")
        if res is not None and [seq.intrinsics.width, seq.intrinsics.height] != list(res):
            raise ConfigError(f"{path} opens at {seq.intrinsics.width}x{seq.intrinsics.height}, the run was "
                              f"{res[0]}x{res[1]}: is it the run's sequence? (else pass the run's --downsample)")
        return seq


def open_run(folder: str | Path) -> FinishedRun:
    """Open the run folder ``folder``: its files are read on demand (InputError naming the file when one is
    unreadable). InputError naming the path when it is not a folder."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, NOT_A_RUN)
    return FinishedRun(folder)


def _run_config(folder: Path, metrics: dict) -> SlamConfig:
    """The run's :class:`SlamConfig`: its ``config.toml``, else the defaults with ``metrics.json``'s dataset
    options."""
    path = folder / CONFIG_FILE
    if path.is_file():
        return load_toml(SlamConfig, path)
    opts = dict(metrics.get("dataset_options") or {})
    if opts.get("intrinsics") is not None:
        opts["intrinsics"] = tuple(float(v) for v in opts["intrinsics"])
    known = {f.name for f in dataclasses.fields(DatasetOptions)}
    return SlamConfig(dataset=DatasetOptions(**{k: v for k, v in opts.items() if k in known}))
