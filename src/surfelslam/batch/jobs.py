"""One batch job: a sequence x a tracker x a configuration, run into its own run folder.

The folder is ``<out>/<sequence>-<tracker>-<hash8>``: ``hash`` is the sha256 of the job's ``config.toml`` (the
whole recipe: settings, tracker and dataset options), so a changed setting gives a new folder and an unchanged
one finds its finished run (:func:`is_complete`). :func:`run_job` is the one code path of every executor: it runs
the job through :func:`surfelslam.slam.runner.run_sequence` (the library runner of ``surfelslam run``) and returns
the job's summary row (:func:`summary`); besides the run's own files it writes ``job.json`` (the job's
description, for ``surfelslam batch --report``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
from pathlib import Path
from typing import Any

from surfelslam.config import dumps_toml
from surfelslam.errors import SurfelSlamError
from surfelslam.slam import SlamConfig

JOB_FILE = "job.json"
STATUSES = ("done", "skipped", "failed", "interrupted")
_UNSAFE = re.compile(r"[^A-Za-z0-9_.+-]+")


@dataclasses.dataclass(frozen=True)
class Job:
    """One run of a batch. ``config`` has the job's tracker and dataset options set (it is what ``config.toml``
    will hold); ``config_hash`` is the sha256 of its TOML text."""

    sequence: str  # the sequence path, as every worker will read it
    tracker: str
    config: SlamConfig
    config_name: str
    sets: tuple[str, ...]
    config_hash: str
    out_root: str

    @property
    def short_hash(self) -> str:
        return self.config_hash[:8]

    @property
    def sequence_name(self) -> str:
        return sequence_name(self.sequence)

    @property
    def name(self) -> str:
        """The run folder's name: ``<sequence>-<tracker>-<hash8>``."""
        return f"{self.sequence_name}-{self.tracker}-{self.short_hash}"

    @property
    def folder(self) -> Path:
        return Path(self.out_root) / self.name

    def describe(self) -> dict[str, Any]:
        """The job as ``job.json`` holds it (and as a results row starts)."""
        return {"job": self.name, "sequence": self.sequence_name, "sequence_path": self.sequence,
                "tracker": self.tracker, "config": self.config_name, "config_hash": self.short_hash,
                "config_sha256": self.config_hash, "sets": list(self.sets)}


def sequence_name(path: str | Path) -> str:
    """A sequence's short name: its folder name (a bag file: its name without the suffix), made path-safe."""
    p = Path(str(path).rstrip("/\\"))
    name = p.stem if p.suffix.lower() in (".bag", ".mcap", ".db3") else p.name
    return _UNSAFE.sub("_", name) or "sequence"


def config_text(cfg: SlamConfig) -> str:
    """The job's ``config.toml`` text (what :func:`run_sequence` writes for it)."""
    return dumps_toml(cfg)


def config_sha256(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def make_job(sequence: str | Path, tracker: str, cfg: SlamConfig, config_name: str, sets: tuple[str, ...],
             out_root: str | Path) -> Job:
    cfg = dataclasses.replace(cfg, tracker=tracker)
    return Job(str(sequence), tracker, cfg, config_name, tuple(sets), config_sha256(config_text(cfg)),
               str(out_root))


# ------------------------------------------------------------------------------------------------ run folders
def read_metrics(folder: Path) -> dict | None:
    try:
        data = json.loads((folder / "metrics.json").read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def folder_config_sha256(folder: Path) -> str | None:
    try:
        return config_sha256((folder / "config.toml").read_text())
    except OSError:
        return None


def is_complete(job: Job) -> bool:
    """The job's folder holds a complete run (``metrics.json`` with ``complete: true``) of the same config
    (``config.toml``'s sha256 is the job's hash)."""
    metrics = read_metrics(job.folder)
    return bool(metrics and metrics.get("complete") is True and folder_config_sha256(job.folder) == job.config_hash)


# ------------------------------------------------------------------------------------------------ results
def summary(description: dict[str, Any], metrics: dict | None, status: str, error: str = "") -> dict[str, Any]:
    """A results row: the job's description, its status and the run's headline metrics (empty when none)."""
    row = dict(description)
    row.update(status=status, error=error, ate_rmse_m=None, rpe_trans_m_per_frame=None,
               rpe_rot_deg_per_frame=None, tracking_failures=None, lost_segments=None, fps=None, map_points=None,
               wall_s=None, frames=None)
    if metrics:
        ev = metrics.get("eval") or {}
        row.update(ate_rmse_m=ev.get("ate_rmse_m"), rpe_trans_m_per_frame=ev.get("rpe_trans_rmse_m_per_frame"),
                   rpe_rot_deg_per_frame=ev.get("rpe_rot_rmse_deg_per_frame"),
                   tracking_failures=metrics.get("tracking_failures"), lost_segments=metrics.get("lost_segments"),
                   fps=metrics.get("fps"), map_points=metrics.get("map_points"), wall_s=metrics.get("wall_s"),
                   frames=metrics.get("frames_processed"))
        if not error and "eval" not in metrics and metrics.get("eval_error"):
            row["error"] = f"no ATE: {metrics['eval_error']}"
    return row


def one_line(exc: BaseException) -> str:
    """An exception as one line; unexpected ones keep their type name."""
    text = " ".join(str(exc).split()) or "(no message)"
    return text if isinstance(exc, SurfelSlamError) else f"{type(exc).__name__}: {text}"


def run_job(job: Job) -> dict[str, Any]:
    """Run ``job`` into its folder and return its results row (status ``done``).

    Bad input (a :class:`SurfelSlamError`: missing or unreadable sequence, bad settings) gives a ``failed`` row
    at once: retrying would fail the same way. Anything else (a crash, an I/O error) propagates, so that the
    executor retries the job.
    """
    from surfelslam.api import run_sequence
    from surfelslam.datasets import open_sequence

    description = job.describe()
    try:
        seq = open_sequence(Path(job.sequence), job.config.dataset)
        metrics = run_sequence(
            seq, job.folder, job.config, job.tracker, progress=False, figures=False, overwrite=True,
            before_commit=lambda stage: (stage / JOB_FILE).write_text(json.dumps(description, indent=2) + "\n"))
    except SurfelSlamError as exc:
        return summary(description, None, "failed", one_line(exc))
    return summary(description, metrics, "done")


def skipped_row(job: Job) -> dict[str, Any]:
    """The row of a job whose complete run is already there (:func:`is_complete`)."""
    return summary(job.describe(), read_metrics(job.folder), "skipped")
