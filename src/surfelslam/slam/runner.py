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
import time
from collections.abc import Callable, Collection, Sequence
from pathlib import Path
from typing import Any

from surfelslam import settings
from surfelslam.errors import ConfigError
from surfelslam.settings import dumps_toml
from surfelslam.slam import TRACKERS, SlamConfig, poses_for_mapping
from surfelslam.slam.colour_check import colour_is_registered
from surfelslam.slam.saved_map import SavedMap, check_map_options
from surfelslam.slam.session import ProgressSink, Session, track_sequence
from surfelslam.slam.writer import RunReport, RunWriter


# ------------------------------------------------------------------------------------------------ configuration
def parse_set(item: str, cls: type = SlamConfig) -> dict[str, Any]:
    """:func:`surfelslam.settings.parse_set` against :class:`SlamConfig` by default."""
    return settings.parse_set(item, cls)


def apply_sets(cfg: SlamConfig, sets: Sequence[str]) -> SlamConfig:
    """``cfg`` with the ``--set KEY=VALUE`` overrides applied (later ones win)."""
    return settings.apply_sets(cfg, sets)


def load_config(path: str | Path | None = None, sets: Sequence[str] = ()) -> SlamConfig:
    """The defaults, overridden by the TOML file or preset ``path``
    (:func:`surfelslam.settings.resolve_config_path`), overridden by the ``--set`` items."""
    return settings.load_config(SlamConfig, path, sets)


# ------------------------------------------------------------------------------------------------ the run
def run_sequence(seq, out_dir: Path, cfg: SlamConfig, tracker: str | None = None, poses: str | None = None, *,
                 overwrite: bool = True, report: RunReport | None = None,
                 on_start: Callable[[Path], None] | None = None,
                 before_commit: Callable[[Path], None] | None = None,
                 on_frame: Callable[[Any, Any, Any], None] | None = None,
                 on_progress: ProgressSink | None = None,
                 prior_map: SavedMap | None = None, localize_only: bool = False,
                 formats: Collection[str] = ("tum",), started_perf_s: float | None = None) -> dict:
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
    ``started_perf_s``: the ``time.perf_counter()`` the metrics' ``startup_s`` counts from (``surfelslam run``: the
    process's start; default: this call).

    Returns the metrics dict (also written as ``metrics.json``).
    """
    started_perf_s = time.perf_counter() if started_perf_s is None else started_perf_s
    tracker = cfg.tracker if tracker is None else tracker
    if tracker not in TRACKERS:
        raise ConfigError(f"tracker must be one of {', '.join(TRACKERS)}, got {tracker!r}")
    if len(seq) == 0:
        raise ConfigError(f"{seq.root}: the selection has no frames (check --start/--end/--stride)")
    cfg = dataclasses.replace(cfg, tracker=tracker, dataset=seq.options)
    given = poses_for_mapping(seq, poses, cfg) if poses is not None else None
    check_map_options(tracker, prior_map, localize_only, poses)
    writer = RunWriter(out_dir, overwrite=overwrite, report=report, formats=formats, started_perf_s=started_perf_s)
    writer.check()  # nothing written yet; before the colour check, which reads frames
    colour_registered, colour_check = colour_is_registered(seq, cfg.colour_registration)
    session = Session(seq.intrinsics, cfg, tracker, colour_registered=colour_registered,
                      colour_camera=getattr(seq, "colour_camera", None), colour_check=colour_check,
                      prior_map=prior_map, localize_only=localize_only, given_poses=poses, warmup=False)
    with writer:
        stage = writer.open(dumps_toml(cfg))
        if on_start is not None:
            on_start(stage)
        outcome = track_sequence(seq, session, given=given, on_pose=writer.append_pose, on_frame=on_frame,
                                 on_progress=on_progress, warm_up=True)  # the first frames are read meanwhile
        metrics = writer.finish(outcome, seq.ground_truth)
        if before_commit is not None:
            before_commit(stage)
        writer.commit()
    return metrics
