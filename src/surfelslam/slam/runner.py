"""The run of a sequence into a run folder, and the run's configuration.

:func:`run_sequence` is a :class:`~surfelslam.slam.session.Session` over the sequence
(:func:`~surfelslam.slam.session.track_sequence`: frames decoded, and prepared by the tracker, in a background
thread), written by the :class:`~surfelslam.slam.writer.RunWriter`. Everything is checked before anything is
written. It is what ``surfelslam run``, the experiments and the benchmarks call (through
:func:`surfelslam.api.run_sequence`, which adds the evaluation and figures); it prints nothing.

:func:`load_config` builds the run's :class:`SlamConfig` from a TOML file or preset and ``--set KEY=VALUE``
overrides.
"""

from __future__ import annotations

import dataclasses
import difflib
import re
import tomllib
import types
import typing
from collections.abc import Callable, Collection, Sequence
from pathlib import Path
from typing import Any

from surfelslam.config import dumps_toml, from_dict, load_toml
from surfelslam.errors import ConfigError
from surfelslam.slam import TRACKERS, SlamConfig, poses_for_mapping
from surfelslam.slam.colour_check import colour_is_registered
from surfelslam.slam.saved_map import SavedMap, check_map_options
from surfelslam.slam.session import ProgressSink, Session, track_sequence
from surfelslam.slam.writer import RunReport, RunWriter

#: Preset configurations: ``--config NAME`` reads ``configs/NAME.toml`` of the source tree.
PRESETS_DIR = Path(__file__).resolve().parents[3] / "configs"
_PRESET_NAME = re.compile(r"^[A-Za-z0-9_-]+$")


# ------------------------------------------------------------------------------------------------ configuration
def preset_names() -> list[str]:
    """Names of the preset configurations (``configs/*.toml``), sorted."""
    return sorted(p.stem for p in PRESETS_DIR.glob("*.toml")) if PRESETS_DIR.is_dir() else []


def resolve_config_path(config: str | Path) -> Path:
    """The file ``--config`` names: an existing file, else the preset ``configs/<config>.toml`` for a bare name.

    Raises:
        ConfigError: a bare name that is neither a file nor a preset (the message lists the presets).
    """
    path = Path(config)
    if path.exists() or not _PRESET_NAME.match(str(config)):
        return path  # a file (or a path that load_toml reports as missing)
    preset = PRESETS_DIR / f"{config}.toml"
    if preset.is_file():
        return preset
    names = preset_names()
    listed = f"presets: {', '.join(names)}" if names else f"no presets in {PRESETS_DIR}"
    raise ConfigError(f"--config {config}: no such file, and not a preset ({listed})")


def _leaf_paths(cls: type, prefix: str = "") -> list[str]:
    out = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = _unwrap_optional(hints[f.name])
        path = f"{prefix}{f.name}"
        out += _leaf_paths(tp, path + ".") if dataclasses.is_dataclass(tp) else [path]
    return out


def _unwrap_optional(tp: Any) -> Any:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return args[0] if len(args) == 1 else tp
    return tp


def parse_set(item: str, cls: type = SlamConfig) -> dict[str, Any]:
    """``"icp.min_inliers=300"`` -> ``{"icp": {"min_inliers": 300}}``, the key checked against ``cls``.

    The value is read as a TOML value (``300``, ``0.5``, ``true``, ``"text"``, ``[1, 2]``); anything else is taken
    as a bare string (``tracking.photometric=off``).

    Raises:
        ConfigError: not ``KEY=VALUE``, an unknown key (the message names its full path and close matches), or a
            key that is a table.
    """
    key, sep, text = item.partition("=")
    key = key.strip()
    parts = key.split(".")
    if not sep or not all(parts):
        raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. --set icp.min_inliers=300")
    tp: Any = cls
    for i, name in enumerate(parts):
        here = ".".join(parts[:i])
        if not dataclasses.is_dataclass(tp):
            raise ConfigError(f"--set {item}: unknown setting {key} ({here} is a setting, not a table)")
        names = [f.name for f in dataclasses.fields(tp)]
        if name not in names:
            close = difflib.get_close_matches(key, _leaf_paths(cls), n=3, cutoff=0.6)
            hint = f"did you mean {_or_list(close)}?" if close else (
                f"[{here}] has {', '.join(names)}" if here else f"the top level has {', '.join(names)}")
            raise ConfigError(f"--set {item}: unknown setting {key} ({hint})")
        tp = _unwrap_optional(typing.get_type_hints(tp)[name])
    if dataclasses.is_dataclass(tp):
        first = dataclasses.fields(tp)[0].name
        raise ConfigError(f"--set {item}: {key} is a table, not a setting (set its keys, e.g. {key}.{first}=...)")
    try:
        value = tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        value = text.strip()
    nested: dict[str, Any] = {parts[-1]: value}
    for name in reversed(parts[:-1]):
        nested = {name: nested}
    return nested


def _or_list(items: list[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " or " + items[-1]


def _merge(into: dict[str, Any], more: dict[str, Any]) -> dict[str, Any]:
    for k, v in more.items():
        if isinstance(v, dict) and isinstance(into.get(k), dict):
            _merge(into[k], v)
        else:
            into[k] = v
    return into


def apply_sets(cfg: SlamConfig, sets: Sequence[str]) -> SlamConfig:
    """``cfg`` with the ``--set KEY=VALUE`` overrides applied (later ones win)."""
    if not sets:
        return cfg
    merged: dict[str, Any] = {}
    for item in sets:
        _merge(merged, parse_set(item))
    try:
        return from_dict(SlamConfig, merged, base=cfg)
    except ConfigError as exc:
        for item in sets:  # name the override at fault when it fails alone
            try:
                from_dict(SlamConfig, parse_set(item), base=cfg)
            except ConfigError as alone:
                raise ConfigError(f"--set {item}: {alone}") from None
        raise ConfigError(f"--set {' --set '.join(sets)}: {exc}") from None


def load_config(path: str | Path | None = None, sets: Sequence[str] = ()) -> SlamConfig:
    """The defaults, overridden by the TOML file or preset ``path`` (:func:`resolve_config_path`), overridden by
    the ``--set`` items."""
    cfg = SlamConfig() if path is None else load_toml(SlamConfig, resolve_config_path(path))
    return apply_sets(cfg, sets)


# ------------------------------------------------------------------------------------------------ the run
def run_sequence(seq, out_dir: Path, cfg: SlamConfig, tracker: str | None = None, poses: str | None = None, *,
                 overwrite: bool = True, report: RunReport | None = None,
                 on_start: Callable[[Path], None] | None = None,
                 before_commit: Callable[[Path], None] | None = None,
                 on_frame: Callable[[Any, Any, Any], None] | None = None,
                 on_progress: ProgressSink | None = None,
                 prior_map: SavedMap | None = None, localize_only: bool = False,
                 formats: Collection[str] = ("tum",)) -> dict:
    """Run the pipeline on an opened sequence and write every output into ``out_dir``: a :class:`Session`
    over :func:`track_sequence`, written by a :class:`RunWriter`.

    ``tracker`` overrides ``cfg.tracker``. The written ``config.toml`` is ``cfg`` with the tracker and the
    sequence's dataset options: the whole recipe. Everything (tracker, config, ``poses``, ``out_dir``) is checked
    before anything is written; ``out_dir`` holding a previous run is refused unless ``overwrite``. ``report``:
    the evaluation and figures step (:func:`surfelslam.viz.run_report.run_report`; ``None``: neither).
    ``on_start(staging_folder)`` is called once the folder is locked, ``before_commit(staging_folder)`` after every
    output is written, before the hand-over (to add files to the run). ``on_frame(frame, result, tracker)`` is
    called after each frame is tracked (a live viewer; it must return quickly), ``on_progress(done, result)`` after
    each slot of the sequence (a progress bar).

    ``prior_map`` (``--map``): continue from a saved map (``dense``, ``hybrid``); ``localize_only``: track against it
    without changing it. A run in which no frame is localised in it ends normally, with no poses (its metrics'
    ``prior_map`` says why). ``formats``: the pose files besides TUM (``"kitti"``: ``trajectory_kitti.txt``).

    Returns the metrics dict (also written as ``metrics.json``).
    """
    tracker = cfg.tracker if tracker is None else tracker
    if tracker not in TRACKERS:
        raise ConfigError(f"tracker must be one of {', '.join(TRACKERS)}, got {tracker!r}")
    if len(seq) == 0:
        raise ConfigError(f"{seq.root}: the selection has no frames (check --start/--end/--stride)")
    cfg = dataclasses.replace(cfg, tracker=tracker, dataset=seq.options)
    given = poses_for_mapping(seq, poses, cfg) if poses is not None else None
    check_map_options(tracker, prior_map, localize_only, poses)
    writer = RunWriter(out_dir, overwrite=overwrite, report=report, formats=formats)
    writer.check()  # nothing written yet; before the colour check, which reads frames
    colour_registered, colour_check = colour_is_registered(seq, cfg.colour_registration)
    session = Session(seq.intrinsics, cfg, tracker, colour_registered=colour_registered,
                      colour_camera=getattr(seq, "colour_camera", None), colour_check=colour_check,
                      prior_map=prior_map, localize_only=localize_only, given_poses=poses, warmup=False)
    with writer:
        stage = writer.open(dumps_toml(cfg))
        if on_start is not None:
            on_start(stage)
        session.warm_up()
        outcome = track_sequence(seq, session, given=given, on_pose=writer.append_pose, on_frame=on_frame,
                                 on_progress=on_progress)
        metrics = writer.finish(outcome, seq.ground_truth)
        if before_commit is not None:
            before_commit(stage)
        writer.commit()
    return metrics
