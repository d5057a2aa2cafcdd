"""The run loop: a sequence through a tracker into a run folder.

:func:`run_sequence` reads frames (decoded, and prepared by the tracker, in a background thread), tracks them,
streams the trajectory to ``trajectory.txt`` and writes ``config.toml``, ``metrics.json``, ``map.ply`` and the
figures. Everything is checked before anything is written, and the outputs go through the run folder policy of
:mod:`surfelslam.io.run_folder` (lock, staging folder, hand-over). It is what ``surfelslam run``, the experiments
and the benchmarks call; it prints nothing.

:func:`load_config` builds the run's :class:`SlamConfig` from a TOML file or preset and ``--set KEY=VALUE``
overrides.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import re
import time
import tomllib
import types
import typing
from collections.abc import Callable, Collection, Sequence
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from surfelslam.config import dumps_toml, from_dict, load_toml
from surfelslam.errors import ConfigError
from surfelslam.io.atomic import write_text_atomic
from surfelslam.io.jsonio import json_default
from surfelslam.io.map_file import MAP_FILE, write_map_file
from surfelslam.io.prefetch import prefetch_frames
from surfelslam.io.run_folder import RunFolder
from surfelslam.io.trajectory import TumAppender
from surfelslam.kernels.threads import concurrent_launch_safe, parallel_enabled
from surfelslam.slam import TRACKERS, SlamConfig, build_slam, poses_for_mapping
from surfelslam.slam.colour_check import colour_is_registered
from surfelslam.slam.saved_map import SavedMap, check_map_options
from surfelslam.slam.segments import segments_report, tracking_segments

#: Preset configurations: ``--config NAME`` reads ``configs/NAME.toml`` of the source tree.
PRESETS_DIR = Path(__file__).resolve().parents[3] / "configs"
_PRESET_NAME = re.compile(r"^[A-Za-z0-9_-]+$")
#: The PNGs a run writes: the trajectory and its ATE errors (with ground truth), the map's two views.
RUN_FIGURES = frozenset({"trajectory", "ate_errors", "map_camera", "map_top"})
#: Unpaired images listed (with their reasons) in ``metrics.json``; ``frames_unpaired`` counts them all.
UNPAIRED_IN_METRICS = 10


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


def one_line(text: str) -> str:
    """``text`` with its line breaks written as ``\\n`` / ``\\r``: a message quoting a ``--set`` item stays one line."""
    return text.replace("\r", "\\r").replace("\n", "\\n")


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
            raise ConfigError(f"--set {one_line(item)}: unknown setting {one_line(key)} ({here} is a setting, "
                              "not a table)")
        names = [f.name for f in dataclasses.fields(tp)]
        if name not in names:
            close = difflib.get_close_matches(key, _leaf_paths(cls), n=3, cutoff=0.6)
            hint = f"did you mean {_or_list(close)}?" if close else (
                f"[{here}] has {', '.join(names)}" if here else f"the top level has {', '.join(names)}")
            raise ConfigError(f"--set {one_line(item)}: unknown setting {one_line(key)} ({hint})")
        tp = _unwrap_optional(typing.get_type_hints(tp)[name])
    if dataclasses.is_dataclass(tp):
        first = dataclasses.fields(tp)[0].name
        raise ConfigError(f"--set {one_line(item)}: {key} is a table, not a setting (set its keys, e.g. "
                          f"{key}.{first}=...)")
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
                raise ConfigError(f"--set {one_line(item)}: {alone}") from None
        raise ConfigError(f"--set {one_line(' --set '.join(sets))}: {exc}") from None


def load_config(path: str | Path | None = None, sets: Sequence[str] = ()) -> SlamConfig:
    """The defaults, overridden by the TOML file or preset ``path`` (:func:`resolve_config_path`), overridden by
    the ``--set`` items."""
    cfg = SlamConfig() if path is None else load_toml(SlamConfig, resolve_config_path(path))
    return apply_sets(cfg, sets)


def _now() -> str:
    return datetime.now().astimezone().isoformat(timespec="seconds")


# ------------------------------------------------------------------------------------------------ the run
def run_sequence(seq, out_dir: Path, cfg: SlamConfig, tracker: str | None = None, poses: str | None = None,
                 progress: bool = True, figures: bool | Collection[str] = True, *, overwrite: bool = True,
                 on_start: Callable[[Path], None] | None = None,
                 before_commit: Callable[[Path], None] | None = None,
                 on_frame: Callable[[Any, Any, Any], None] | None = None,
                 prior_map: SavedMap | None = None, localize_only: bool = False) -> dict:
    """Run the pipeline on an opened sequence and write every output into ``out_dir``.

    ``tracker`` overrides ``cfg.tracker``. The written ``config.toml`` is ``cfg`` with the tracker and the
    sequence's dataset options: the whole recipe. Everything (tracker, config, ``poses``, ``out_dir``) is checked
    before anything is written; ``out_dir`` holding a previous run is refused unless ``overwrite`` (the default
    here; ``surfelslam run`` passes its ``--overwrite``). The run writes into ``out_dir/.partial-<pid>/`` and hands
    its files over at the end (:mod:`surfelslam.io.run_folder`). ``on_start(staging_folder)`` is called once the
    folder is locked, ``before_commit(staging_folder)`` after every output is written, before the hand-over (to
    add files to the run). ``on_frame(frame, result, tracker)`` is called on the tracking thread after each frame
    is tracked (a live viewer: :mod:`surfelslam.viz.live`; it must return quickly).

    ``prior_map`` (``--map``, :func:`surfelslam.io.map_file.read_map_file`): continue from a saved map: the first
    frames are localised in it, then tracking and fusion go on in its frame (``dense`` and ``hybrid``).
    ``localize_only``: track against it without changing it. With ``map_reuse.save`` (the default) the run saves its
    map as ``map.npz``.

    ``figures``: every PNG of :data:`RUN_FIGURES` (True), none (False), or those named (a caller that links only
    some of them, as the experiments report does).

    Returns the metrics dict (also written as ``metrics.json``).
    """
    figures = _figures_wanted(figures)
    tracker = cfg.tracker if tracker is None else tracker
    if tracker not in TRACKERS:
        raise ConfigError(f"tracker must be one of {', '.join(TRACKERS)}, got {tracker!r}")
    if len(seq) == 0:
        raise ConfigError(f"{seq.root}: the selection has no frames (check --start/--end/--stride)")
    cfg = dataclasses.replace(cfg, tracker=tracker, dataset=seq.options)
    recipe = dumps_toml(cfg)
    given = poses_for_mapping(seq, poses, cfg) if poses is not None else None
    check_map_options(tracker, prior_map, localize_only, poses)
    folder = RunFolder(out_dir, overwrite=overwrite)
    folder.check()  # nothing written yet; before the colour check, which reads frames
    colour_registered, colour_check = colour_is_registered(seq, cfg.colour_registration)
    slam = build_slam(seq.intrinsics, cfg, tracker if given is None else "given", colour_registered=colour_registered,
                      colour_camera=getattr(seq, "colour_camera", None))
    if prior_map is not None:
        slam.use_prior_map(prior_map, localize_only)
    with folder:
        stage = folder.open()
        started = _now()
        if on_start is not None:
            on_start(stage)
        write_text_atomic(stage / "config.toml", recipe)
        metrics = _run(seq, stage, cfg, slam, tracker, given, poses, progress, figures, on_frame, recipe)
        metrics["colour_check"] = colour_check
        if colour_check is not None and not colour_check["registered"]:
            metrics["warnings"].append(
                f"colour does not line up with depth (mean edge distance {colour_check['edge_distance_same_pixel_px']}"
                f" px at the same pixel, {colour_check['edge_distance_fitted_px']} px through a fitted colour camera):"
                " taken as not registered, colour terms under auto are off (colour_registration.check)")
        metrics.update(complete=True, started=started, finished=_now())
        write_text_atomic(stage / "metrics.json", json.dumps(metrics, indent=2, default=json_default) + "\n")
        if before_commit is not None:
            before_commit(stage)
        folder.commit()
    return metrics


def _run(seq, out_dir: Path, cfg: SlamConfig, slam, tracker: str, given, poses: str | None, progress: bool,
         figures: frozenset[str], on_frame: Callable[[Any, Any, Any], None] | None = None, recipe: str = "") -> dict:
    """The loop proper, writing into the staging folder ``out_dir``; everything but ``metrics.json``."""
    t_warm = time.perf_counter()
    slam.warmup()
    warmup_s = time.perf_counter() - t_warm
    # the warm-up ran the kernels, so numba's threading layer is known: with parallel kernels on a layer that
    # cannot launch from two threads at once, frames are prepared in the main thread (same results, slower)
    prepare_in_reader = cfg.io.prepare_in_reader and concurrent_launch_safe()

    skipped: list[dict] = []
    stage_ms: dict[str, list[float]] = {"read": []}
    frame_ms: list[float] = []
    statuses: list[tuple[int, float, str, str | None]] = []  # per frame: index, stamp, status, reason
    n_done = 0
    bar = tqdm(total=len(seq), unit="frame", disable=not progress, dynamic_ncols=True, leave=False)
    t_start = time.perf_counter()
    try:
        with TumAppender(out_dir / "trajectory.txt") as traj_out:
            prepare = slam.prepare if prepare_in_reader else None
            for item in prefetch_frames(seq, ahead=cfg.io.prefetch_frames, prepare=prepare):
                t0 = time.perf_counter()
                if item.error is not None:
                    skipped.append({"position": item.position, "reason": str(item.error)})
                    bar.update(1)
                    continue
                frame = item.frame
                if given is not None:
                    T_given = given.get(item.position)
                    if T_given is None:
                        slam.discard(item.prepared)  # its pyramid back to the pool
                        skipped.append({"position": item.position, "reason": "no pose within max_dt"})
                        bar.update(1)
                        continue
                    res = slam.process(frame, T_world_cam=T_given, prepared=item.prepared)
                else:
                    res = slam.process(frame, prepared=item.prepared)
                if res.posed:  # frames not yet localised in a loaded map have no pose
                    traj_out.append(frame.timestamp, res.T_world_cam)
                if on_frame is not None:
                    on_frame(frame, res, slam)
                statuses.append((res.index, res.timestamp, res.status, res.reason))
                n_done += 1
                stage_ms["read"].append(item.read_ms)
                for k, v in res.timings_ms.items():
                    stage_ms.setdefault(k, []).append(v)
                frame_ms.append((time.perf_counter() - t0) * 1e3)
                bar.update(1)
                if n_done % 10 == 0:
                    el = time.perf_counter() - t_start
                    bar.set_postfix(fps=f"{n_done / max(el, 1e-9):.1f}", pts=f"{res.map_points:,}")
    finally:
        bar.close()
    wall_s = time.perf_counter() - t_start
    result = slam.finish()
    if result.trajectory_override is not None:
        # A back end (pose graph) corrected the poses: the written trajectory is the optimised one.
        result.trajectory_override.write_tum(out_dir / "trajectory.txt")

    metrics = {
        "sequence": str(seq.root),
        "layout": seq.layout,
        "tracker": tracker if given is None else f"given:{poses}",
        "frames": len(seq),
        "frames_processed": n_done,
        "frames_skipped": len(skipped),
        "skipped": skipped,
        "frames_unpaired": len(seq.unpaired),
        "unpaired": [{"file": str(u.file), "timestamp": u.timestamp, "reason": u.reason}
                     for u in seq.unpaired[:UNPAIRED_IN_METRICS]],
        "warnings": list(seq.warnings),
        "resolution": [seq.intrinsics.width, seq.intrinsics.height],
        "downsample": seq.options.downsample,
        "dataset_options": dataclasses.asdict(seq.options),
        "fps": n_done / wall_s if wall_s > 0 else 0.0,
        "wall_s": wall_s,
        "warmup_s": warmup_s,
        "parallel_kernels": parallel_enabled(),
        "prepare_in_reader": bool(prepare_in_reader and cfg.io.prefetch_frames > 0),
        "ms_per_frame": _stats(frame_ms),
        "stage_ms": {k: _stats(v) for k, v in stage_ms.items()},
        "map_points": result.map_points,
        "compression_ratio": result.map_points / max(n_done * seq.intrinsics.width * seq.intrinsics.height, 1),
        **result.metrics,
        **segments_report(tracking_segments(statuses)),
    }
    if result.loop_stamps:
        # keyframe timestamps (s) of each accepted loop edge, for viewers (`surfelslam rerun`)
        metrics["loop_edges"] = [[float(a), float(b)] for a, b in result.loop_stamps]
    if seq.ground_truth is not None and n_done >= 3:
        from surfelslam.eval.metrics import evaluate
        from surfelslam.types import Trajectory

        est = Trajectory.read_tum(out_dir / "trajectory.txt")
        try:
            metrics["eval"] = evaluate(est, seq.ground_truth)
        except Exception as exc:  # noqa: BLE001 - evaluation problems must not lose the run's outputs
            metrics["eval_error"] = str(exc)
    result.write_map(out_dir / "map.ply")
    _write_saved_map(result, out_dir, recipe, str(seq.root))
    if figures:
        _write_figures(out_dir, seq, result, metrics, figures)
    return metrics


def _write_saved_map(result, out_dir: Path, recipe: str, sequence: str) -> None:
    """``map.npz`` (:mod:`surfelslam.io.map_file`) when the tracker saved a map."""
    saved = result.saved_map
    if saved is None:
        return
    if not saved.config_toml:  # a map this run made (a localise-only run saves the loaded one as it was)
        saved = dataclasses.replace(saved, config_toml=recipe, sequence=sequence)
    write_map_file(out_dir / MAP_FILE, saved)


def _stats(v: list[float]) -> dict:
    if not v:
        return {"mean": 0.0, "median": 0.0, "p95": 0.0}
    a = np.asarray(v)
    return {"mean": float(a.mean()), "median": float(np.median(a)), "p95": float(np.percentile(a, 95))}


def _figures_wanted(figures: bool | Collection[str]) -> frozenset[str]:
    if isinstance(figures, bool):
        return RUN_FIGURES if figures else frozenset()
    wanted = frozenset(figures)
    if not wanted <= RUN_FIGURES:
        raise ConfigError(f"figures: unknown {', '.join(sorted(wanted - RUN_FIGURES))}; known: "
                          f"{', '.join(sorted(RUN_FIGURES))}")
    return wanted


def _write_figures(out_dir: Path, seq, result, metrics: dict, wanted: frozenset[str]) -> None:
    from surfelslam.types import Trajectory
    from surfelslam.viz.map_figures import save_map_figures

    est = Trajectory.read_tum(out_dir / "trajectory.txt")
    if "eval" in metrics and wanted & {"trajectory", "ate_errors"}:
        from surfelslam.eval.metrics import ate
        from surfelslam.viz.trajectory_plots import plot_errors, plot_trajectory

        a = ate(est, seq.ground_truth)
        if "trajectory" in wanted:
            plot_trajectory(out_dir / "trajectory.png", a.est_aligned, a.gt,
                            title=f"{metrics['tracker']}: ATE RMSE {a.rmse_m * 100:.2f} cm", loops=result.loop_stamps)
        if "ate_errors" in wanted:
            plot_errors(out_dir / "ate_errors.png", a)
    views = tuple(v for v in ("camera", "top") if f"map_{v}" in wanted)
    cloud = result.map_arrays() if views else None
    if cloud is not None and len(cloud["position"]) and len(est):
        save_map_figures(out_dir, cloud["position"], cloud["normal"], cloud["colour"], cloud["confidence"],
                         cloud["first_seen"], est.T_world_cam[0], title=f"{metrics['tracker']} map",
                         trajectory_T_world_cam=est.T_world_cam, radius=cloud.get("radius"), views=views)
