"""The batch's results table: ``results.csv`` and ``results.md`` (one row per job) and ``ate-<sequence>.png``
(per sequence, ATE RMSE by tracker and configuration); also rebuilt from existing run folders
(:func:`rebuild_rows`, ``surfelslam batch --report DIR``).

The batch also keeps ``batch.json``: every job's row as the batch recorded it (failed ones with their reason),
which the rebuild starts from.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from surfelslam.batch.jobs import JOB_FILE, read_metrics, summary
from surfelslam.errors import ConfigError
from surfelslam.io.atomic import write_text_atomic

MANIFEST = "batch.json"
CSV_NAME = "results.csv"
MD_NAME = "results.md"
#: results.csv's columns, in order
COLUMNS = ("sequence", "tracker", "config", "config_hash", "sets", "status", "ate_rmse_m", "rpe_trans_m_per_frame",
           "rpe_rot_deg_per_frame", "tracking_failures", "lost_segments", "fps", "map_points", "wall_s", "frames",
           "job", "error")


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, list | tuple):
        return "; ".join(str(v) for v in value)
    if isinstance(value, float):
        return "" if math.isnan(value) else repr(value)
    return str(value)


def to_csv(rows: Sequence[dict]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    for r in rows:
        w.writerow([_cell(r.get(c)) for c in COLUMNS])
    return buf.getvalue()


def _fmt(value: Any, scale: float = 1.0, digits: int = 2) -> str:
    if value is None:
        return "-"
    return f"{value * scale:.{digits}f}"


def to_markdown(rows: Sequence[dict]) -> str:
    counts = {s: sum(r["status"] == s for r in rows) for s in ("done", "skipped", "failed", "interrupted")}
    lines = ["# Batch results", "",
             f"{len(rows)} jobs: " + ", ".join(f"{n} {s}" for s, n in counts.items() if n), "",
             "| sequence | tracker | config | hash | --set | status | ATE RMSE [cm] | RPE [mm/frame] | RPE "
             "[deg/frame] | failures | lost segments | FPS | map points | wall [s] | error |",
             "|---|---|---|---|---|---|--:|--:|--:|--:|--:|--:|--:|--:|---|"]
    for r in rows:
        cells = [r["sequence"], r["tracker"], r["config"], f"`{r['config_hash']}`",
                 " ".join(f"`{s}`" for s in r.get("sets") or []) or "-", r["status"],
                 _fmt(r.get("ate_rmse_m"), 100), _fmt(r.get("rpe_trans_m_per_frame"), 1000),
                 _fmt(r.get("rpe_rot_deg_per_frame"), 1, 3), _cell(r.get("tracking_failures")) or "-",
                 _cell(r.get("lost_segments")) or "-", _fmt(r.get("fps"), 1, 1),
                 f"{r['map_points']:,}" if r.get("map_points") is not None else "-", _fmt(r.get("wall_s"), 1, 1),
                 (r.get("error") or "").replace("|", "\\|")]
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    return "\n".join(lines) + "\n"


def plot_ate(rows: Sequence[dict], out_dir: Path) -> list[Path]:
    """One bar plot per sequence: ATE RMSE (cm) of each tracker/config that has one. Returns the files."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    written = []
    by_seq: dict[str, list[dict]] = {}
    for r in rows:
        if r.get("ate_rmse_m") is not None:
            by_seq.setdefault(r["sequence"], []).append(r)
    for seq, rs in by_seq.items():
        labels = [f"{r['tracker']}\n{r['config']}" for r in rs]
        values = [r["ate_rmse_m"] * 100 for r in rs]
        fig, ax = plt.subplots(figsize=(max(4.0, 1.0 + 0.9 * len(rs)), 3.5))
        bars = ax.bar(range(len(rs)), values, color=[f"C{sorted({x['tracker'] for x in rs}).index(r['tracker'])}"
                                                      for r in rs])
        ax.bar_label(bars, fmt="%.2f", fontsize=8)
        ax.set_xticks(range(len(rs)), labels, fontsize=8)
        ax.set_ylabel("ATE RMSE [cm]")
        ax.set_title(f"{seq}: ATE by tracker and configuration")
        fig.tight_layout()
        path = out_dir / f"ate-{seq}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)
    return written


def write_report(out_dir: str | Path, rows: Sequence[dict], plots: bool = True) -> dict[str, Path]:
    """Write ``batch.json``, ``results.csv``, ``results.md`` (and the plots) into ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = list(rows)
    write_text_atomic(out_dir / MANIFEST, json.dumps({"jobs": rows}, indent=2) + "\n")
    write_text_atomic(out_dir / CSV_NAME, to_csv(rows))
    write_text_atomic(out_dir / MD_NAME, to_markdown(rows))
    files = {"csv": out_dir / CSV_NAME, "md": out_dir / MD_NAME}
    if plots:
        for p in plot_ate(rows, out_dir):
            files[p.stem] = p
    return files


def _refreshed(row: dict, folder: Path) -> dict:
    """A manifest row with its metrics re-read from its run folder (when the run is complete)."""
    metrics = read_metrics(folder)
    if not metrics or metrics.get("complete") is not True:
        return row
    keep = {k: row[k] for k in ("job", "sequence", "sequence_path", "tracker", "config", "config_hash",
                                "config_sha256", "sets") if k in row}
    status = row.get("status") if row.get("status") in ("done", "skipped") else "done"
    return summary(keep, metrics, status)


def rebuild_rows(out_dir: str | Path) -> list[dict]:
    """The rows of a batch folder: ``batch.json``'s rows with their metrics re-read from the run folders, then
    any other complete run folder holding a ``job.json`` (status ``done``).

    Raises:
        FileNotFoundError: ``out_dir`` is not a folder.
    """
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise FileNotFoundError(2, "no such batch folder", str(out_dir))
    rows: list[dict] = []
    try:
        manifest = json.loads((out_dir / MANIFEST).read_text()).get("jobs", [])
    except (OSError, ValueError, AttributeError):
        manifest = []
    seen = set()
    for row in manifest:
        if not isinstance(row, dict) or "job" not in row:
            continue
        rows.append(_refreshed(row, out_dir / row["job"]))
        seen.add(row["job"])
    for folder in sorted(p for p in out_dir.iterdir() if p.is_dir() and p.name not in seen):
        try:
            desc = json.loads((folder / JOB_FILE).read_text())
        except (OSError, ValueError):
            continue
        metrics = read_metrics(folder)
        if isinstance(desc, dict) and metrics and metrics.get("complete") is True:
            rows.append(summary(desc, metrics, "done"))
    return rows


def rebuild_report(out_dir: str | Path) -> tuple[list[dict], dict[str, Path]]:
    """``surfelslam batch --report DIR``: ``results.csv`` / ``results.md`` rebuilt from the run folders of
    ``out_dir``, holding its batch lock (never while a batch writes into it). Returns the rows and the files.

    Raises:
        ConfigError: no such folder, or no batch record and no complete run folder in it.
        OutputError: another batch holds the folder.
    """
    from surfelslam.batch.lock import BatchLock

    folder = Path(out_dir)
    if not folder.is_dir():
        raise ConfigError(f"--report {folder}: no such batch folder")
    with BatchLock(folder):
        rows = rebuild_rows(folder)
        if not rows:
            raise ConfigError(f"{folder}: no batch.json and no complete run folders with job.json")
        return rows, write_report(folder, rows)
