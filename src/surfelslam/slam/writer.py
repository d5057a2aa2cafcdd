"""The run writer: the one writer of a run folder.

A run folder holds ``config.toml`` (the whole recipe), ``trajectory.txt`` (TUM; streamed pose by pose while the run
goes, so a killed run keeps every finished frame), ``keyframes.txt`` (TUM, where the tracker saved keyframes),
``trajectory_kitti.txt`` (``--format kitti``), ``map.ply``, ``map.npz`` (surfel trackers: the map a later run
continues from), ``metrics.json`` (written last: its presence marks a complete run) and what the run's report adds.
Everything goes through the run folder policy of :mod:`surfelslam.io.run_folder` (lock, staging folder,
hand-over). ``surfelslam run`` and :meth:`surfelslam.SlamRun.save` both write through :class:`RunWriter`, so the
two give the same files.

The report (evaluation against the ground truth, figures) lives above this layer: the caller passes it in as a
:data:`RunReport` (:func:`surfelslam.viz.run_report.run_report` is the standard one), and the writer calls it once
the trajectory files are in the staging folder, while the map files are written in a background thread, before
``metrics.json`` is written.
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from collections.abc import Callable, Collection
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np

from surfelslam.errors import ConfigError
from surfelslam.io.atomic import write_text_atomic
from surfelslam.io.jsonio import json_default
from surfelslam.io.kitti import write_kitti
from surfelslam.io.run_folder import COMPLETE_MARKER, RunFolder
from surfelslam.io.trajectory import TumAppender, read_tum, write_tum
from surfelslam.slam.map_file import MAP_FILE, write_map_file
from surfelslam.slam.session import RunOutcome
from surfelslam.types import Trajectory

TRAJECTORY_FILE = "trajectory.txt"
CONFIG_FILE = "config.toml"
MAP_PLY_FILE = "map.ply"
#: The keyframes' final poses (TUM; their lines of ``trajectory.txt``), where the tracker saved a map with keyframes.
KEYFRAMES_FILE = "keyframes.txt"
#: The poses in KITTI's format (``--format kitti``), in ``trajectory.txt``'s order.
KITTI_FILE = "trajectory_kitti.txt"
#: The pose formats a run can write: TUM (always, ``trajectory.txt``) and KITTI (also ``trajectory_kitti.txt``).
POSE_FORMATS = ("tum", "kitti")


@dataclass
class RunRecord:
    """What a report sees: the staging folder, the outcome, the metrics so far (the report adds its own keys) and
    the trajectory as written (``(0,)`` poses when none was posed)."""

    folder: Path
    outcome: RunOutcome
    metrics: dict
    trajectory: Trajectory
    ground_truth: Trajectory | None


#: The report step: adds keys to ``record.metrics`` and may write files into ``record.folder``.
RunReport = Callable[[RunRecord], None]


def now_text() -> str:
    """The local time, ISO 8601 to the second (the metrics' ``started`` / ``finished``)."""
    return datetime.now().astimezone().isoformat(timespec="seconds")


class _Background:
    """``fn(*args)`` in a daemon thread; :meth:`join` waits for it and raises its error, if it failed (unless
    ``raise_error`` is False)."""

    def __init__(self, fn: Callable[..., None], *args) -> None:
        self._error: BaseException | None = None

        def run() -> None:
            try:
                fn(*args)
            except BaseException as exc:  # noqa: BLE001 - raised again by join, in the caller's thread
                self._error = exc

        self._thread = threading.Thread(target=run, name="surfelslam-write-map", daemon=True)
        self._thread.start()

    def join(self, raise_error: bool = True) -> None:
        self._thread.join()
        if raise_error and self._error is not None:
            raise self._error


class RunWriter:
    """Write one run into ``out_dir`` (see the module docstring).

    Use: :meth:`check` before anything is done (writes nothing); then ``with writer: stage = writer.open(recipe);
    writer.append_pose(...) ...; metrics = writer.finish(outcome); writer.commit()``. Leaving the ``with`` block
    without :meth:`commit` releases the lock and keeps the staging folder (with its partial trajectory).
    """

    def __init__(self, out_dir: str | Path, *, overwrite: bool = True, report: RunReport | None = None,
                 formats: Collection[str] = ("tum",), started_perf_s: float | None = None):
        unknown = sorted(set(formats) - set(POSE_FORMATS))
        if unknown:
            raise ConfigError(f"--format: unknown {', '.join(unknown)}; known: {', '.join(POSE_FORMATS)}")
        self.formats = frozenset(formats)
        self.out = Path(out_dir)
        self.folder = RunFolder(self.out, overwrite=overwrite)
        self.report = report
        self.started_perf_s = started_perf_s
        self.stage: Path | None = None
        self.recipe = ""
        self.started = ""
        self._poses: TumAppender | None = None

    def check(self) -> None:
        """Refuse an output folder that cannot or may not be written (:meth:`RunFolder.check`)."""
        self.folder.check()

    def open(self, recipe: str) -> Path:
        """Lock ``out_dir``, make the staging folder, write ``config.toml`` and start ``trajectory.txt``; returns
        the staging folder."""
        self.stage = self.folder.open()
        self.started = now_text()
        self.recipe = recipe
        write_text_atomic(self.stage / CONFIG_FILE, recipe)
        self._poses = TumAppender(self.stage / TRAJECTORY_FILE)
        return self.stage

    def append_pose(self, timestamp: float, T_world_cam: np.ndarray) -> None:
        """Stream one pose to ``trajectory.txt``."""
        self._poses.append(timestamp, T_world_cam)

    def finish(self, outcome: RunOutcome, ground_truth: Trajectory | None = None) -> dict:
        """Write the final trajectory, the map, the report's outputs and ``metrics.json``; returns the metrics."""
        streamed = self._close_poses()
        path = self.stage / TRAJECTORY_FILE
        if outcome.result.trajectory_override is not None:
            # a back end (pose graph) corrected the poses: the written trajectory is the optimised one
            write_tum(outcome.trajectory, path)
        elif streamed == 0 and len(outcome.trajectory):  # a session fed frame by frame: nothing was streamed
            with TumAppender(path) as out:
                for t, T in zip(outcome.trajectory.timestamps, outcome.trajectory.T_world_cam, strict=True):
                    out.append(float(t), T)
        self._write_pose_files(outcome)
        metrics = dict(outcome.metrics)
        # the map files (numpy copies and file writes: mostly outside the GIL) are written while the report runs
        maps = _Background(self._write_maps, outcome, metrics.get("sequence") or "")
        try:
            if self.report is not None:
                written = read_tum(path) if len(outcome.trajectory) else outcome.trajectory
                self.report(RunRecord(self.stage, outcome, metrics, written, ground_truth))
        except BaseException:
            maps.join(raise_error=False)  # the report's error (or Ctrl-C) is the one the caller gets
            raise
        maps.join()
        metrics.update(complete=True, started=self.started, finished=now_text(), **self._overhead(outcome))
        write_text_atomic(self.stage / COMPLETE_MARKER, json.dumps(metrics, indent=2, default=json_default) + "\n")
        return metrics

    def _overhead(self, outcome: RunOutcome) -> dict:
        """``startup_s``: from ``started_perf_s`` (the process's start, for ``surfelslam run``) to the start of the
        frames' clock; ``shutdown_s``: from the end of that clock (after the last frame) to now, every output but
        ``metrics.json`` written. ``None`` where not measured (a session fed frame by frame, or no frames)."""
        clock = outcome.clock_perf_s
        if clock is None or self.started_perf_s is None:
            return {"startup_s": None, "shutdown_s": None}
        return {"startup_s": clock[0] - self.started_perf_s, "shutdown_s": time.perf_counter() - clock[1]}

    def _write_pose_files(self, outcome: RunOutcome) -> None:
        """``keyframes.txt`` (this run's keyframes of its saved map, at their final poses) and the other formats."""
        traj = outcome.trajectory
        if "kitti" in self.formats:
            write_kitti(traj, self.stage / KITTI_FILE)
        saved = outcome.result.saved_map
        if saved is None or saved.config_toml or not len(saved.keyframes.timestamp):
            return  # no map saved, or the loaded one as it was (--localize-only): no keyframes of this run
        kf = saved.keyframes
        stamps = kf.timestamp[kf.session == kf.session.max()]
        write_tum(traj.subset(np.isin(traj.timestamps, stamps)), self.stage / KEYFRAMES_FILE)

    def _close_poses(self) -> int:
        poses, self._poses = self._poses, None
        if poses is None:
            return 0
        poses.close()
        return poses.lines

    def _write_maps(self, outcome: RunOutcome, sequence: str) -> None:
        """``map.ply`` and ``map.npz``."""
        outcome.result.write_map(self.stage / MAP_PLY_FILE)
        self._write_saved_map(outcome, sequence)

    def _write_saved_map(self, outcome: RunOutcome, sequence: str) -> None:
        """``map.npz`` (:mod:`surfelslam.slam.map_file`) when the tracker saved a map."""
        saved = outcome.result.saved_map
        if saved is None:
            return
        if not saved.config_toml:  # a map this run made (a localise-only run saves the loaded one as it was)
            saved = dataclasses.replace(saved, config_toml=self.recipe, sequence=sequence)
        write_map_file(self.stage / MAP_FILE, saved)

    def commit(self) -> Path:
        """Hand the staged files over into ``out_dir``; returns ``out_dir``."""
        self.folder.commit()
        return self.out

    def close(self) -> None:
        """Release the lock (a staging folder not committed stays, with what the run wrote)."""
        try:
            self._close_poses()
        finally:
            self.folder.close()

    def __enter__(self) -> RunWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
