"""Helpers shared by the benchmark scripts: where the real sequences are, one timing rule, ``surfelslam`` commands
in a child process timed from outside (:func:`child_run`), and the Markdown cells and tables of their sections
(:func:`fmt`, :func:`table`)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

import surfelslam

#: The real sequences (``../shared/data`` beside the repository).
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
#: The 7-Scenes sequence the pair and stage benchmarks use.
REDKITCHEN = SHARED_DATA / "7scenes_redkitchen_0000_0499"


#: Tracker rows that are a preset (the package's ``settings/presets/NAME.toml``) rather than a tracker with the
#: defaults.
PRESET_TRACKERS = ("hybrid-full",)
#: Bench-only rows: the defaults with some settings changed (label -> those settings, as in a TOML file).
#: ``hybrid-odometry``: the default hybrid without its loop corrections, the reference of "loop closure never makes
#: the trajectory worse than the odometry alone". ``orb-odometry``: the same reference for orb, which has no such
#: switch: no loop candidates among the older keyframes (neither random nor retrieved; the nearby keyframe edges
#: stay), so that its graph holds no loop edge. Its relocalisation, which retrieves candidates the same way, is off
#: with them: a row of it that lost tracking says so in its failures.
VARIANT_TRACKERS = {"hybrid-odometry": {"tracker": "hybrid", "hybrid": {"loop_correction": False}},
                    "orb-odometry": {"tracker": "orb", "sparse": {"loop": {"n_random": 0, "n_retrieved": 0}}}}
#: The odometry-only variants above: tracker label -> the variant's label (derived, so a new one needs no second entry).
ODOMETRY_VARIANTS = {cfg["tracker"]: label for label, cfg in VARIANT_TRACKERS.items() if label.endswith("-odometry")}
#: Order of the tracker rows in every table (unknown labels last).
TRACKER_ORDER = ("dense", "hybrid", "hybrid-odometry", "hybrid-full", "orb", "orb-odometry", "open3d")
#: Seconds per frame of a tracker row against the dense tracker's on the same sequence: what the budgets assume
#: before a row of that tracker has run (unknown labels: :data:`UNKNOWN_TRACKER_COST`).
TRACKER_COST_VS_DENSE = {"hybrid": 1.5, "hybrid-odometry": 1.5, "hybrid-full": 6.0, "orb": 3.0, "orb-odometry": 2.0,
                         "open3d": 8.0}
UNKNOWN_TRACKER_COST = 5.0
MB = 2.0**20  # bytes per MiB (sizes and peak memory on the page)


def tracker_rank(label: str) -> int:
    """Position of a tracker label in :data:`TRACKER_ORDER` (unknown labels after all of them)."""
    return TRACKER_ORDER.index(label) if label in TRACKER_ORDER else len(TRACKER_ORDER)


def tracker_cost_vs_dense(label: str) -> float:
    """:data:`TRACKER_COST_VS_DENSE` of a label, :data:`UNKNOWN_TRACKER_COST` for others."""
    return TRACKER_COST_VS_DENSE.get(label, UNKNOWN_TRACKER_COST)


def variant_set_options(label: str) -> str:
    """The ``--set`` options that make a :data:`VARIANT_TRACKERS` row from its tracker's defaults (for the page)."""
    def flat(d: dict, prefix: str = "") -> list[str]:
        out = []
        for key, value in d.items():
            if isinstance(value, dict):
                out += flat(value, f"{prefix}{key}.")
            elif prefix or key != "tracker":
                out.append(f"--set {prefix}{key}={str(value).lower() if isinstance(value, bool) else value}")
        return out

    return " ".join(flat(VARIANT_TRACKERS[label]))


def tracker_setup(label: str):
    """``(tracker, SlamConfig)`` of a bench row's tracker label: a tracker with the defaults, a preset of
    :data:`PRESET_TRACKERS` or a variant of :data:`VARIANT_TRACKERS` (its config, whose ``tracker`` it names)."""
    from surfelslam.settings import from_dict, load_config
    from surfelslam.slam import SlamConfig

    if label in VARIANT_TRACKERS:
        cfg = from_dict(SlamConfig, VARIANT_TRACKERS[label], base=SlamConfig())
    elif label in PRESET_TRACKERS:
        cfg = load_config(SlamConfig, label)
    else:
        return label, SlamConfig()
    return cfg.tracker, cfg


def median_ms(fn: Callable[[], object], reps: int) -> float:
    """Median wall time of ``reps`` calls of ``fn``, in milliseconds."""
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000.0 * float(np.median(times))


def fmt(v, nd: int = 1) -> str:
    """One Markdown cell: "–" for None, yes / **NO** for a bool, ``nd`` decimals for a float."""
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "**NO**"
    if isinstance(v, float):
        return f"{v:.{nd}f}"
    return str(v)


def table(header: list[str], rows: list[list]) -> str:
    """A Markdown table of ``header`` and ``rows`` (cells other than strings through :func:`fmt`)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(c) if not isinstance(c, str) else c for c in r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def print_rows(rows: list[dict], cols: list[str] | None = None, nd: int = 1) -> None:
    """Print ``rows`` (dicts) as ``|``-separated lines under a header of ``cols`` (default: the first row's keys);
    floats with ``nd`` decimals (the standalone benchmarks' console output)."""
    cols = list(rows[0]) if cols is None else cols
    print(" | ".join(cols))
    for r in rows:
        print(" | ".join(f"{r[c]:.{nd}f}" if isinstance(r[c], float) else str(r[c]) for c in cols))


def child_env() -> dict[str, str]:
    """The environment of a child ``python -m surfelslam``: this process's, with the ``surfelslam`` package this
    process imported first on ``PYTHONPATH`` (a worktree's ``src``, not whatever the interpreter has installed)."""
    src = str(Path(surfelslam.__file__).resolve().parents[1])
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([src] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    return env


def child_run(args: list[str]) -> dict:
    """``python -m surfelslam ARGS`` in a child process: ``{"wall_s", "cpu_s", "peak_mb", "returncode", "stderr"}``.

    Wall time from before the start to after the exit (what a user waits); CPU and peak resident memory from the
    rusage of that child alone (``os.wait4``; ``ru_maxrss`` is in KiB on Linux)."""
    t0 = time.perf_counter()
    with tempfile.TemporaryFile() as err:
        proc = subprocess.Popen([sys.executable, "-m", "surfelslam", *args], stdout=subprocess.DEVNULL, stderr=err,
                                env=child_env())
        try:
            _, status, ru = os.wait4(proc.pid, 0)
        except BaseException:
            proc.kill()
            raise
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        err.seek(0)
        tail = err.read().decode(errors="replace").strip().splitlines()[-3:]
    return {"wall_s": round(wall, 2), "cpu_s": round(ru.ru_utime + ru.ru_stime, 2),
            "peak_mb": round(ru.ru_maxrss * 1024 / MB, 1), "returncode": proc.returncode, "stderr": " / ".join(tail)}


def cli_tracker_args(label: str) -> list[str]:
    """The ``surfelslam run`` options of a bench row's tracker label (:func:`tracker_setup`'s rows, as a user types
    them): ``--tracker T``, a preset's ``--config NAME``, a variant's ``--set KEY=VALUE`` options."""
    if label in PRESET_TRACKERS:
        return ["--config", label]
    if label in VARIANT_TRACKERS:
        return ["--tracker", VARIANT_TRACKERS[label]["tracker"]] + variant_set_options(label).split()
    return ["--tracker", label]


def machine() -> dict:
    """The CPU, cores, architecture, OS and load average at the start: the page's machine line."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cpu": cpu, "cores": cores, "arch": platform.machine(), "os": f"{platform.system()} {platform.release()}",
            "load_average_at_start": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None}


def git_state() -> dict:
    """The repository's short commit and whether ``src/`` holds uncommitted changes (the page names both)."""
    repo = Path(__file__).resolve().parents[1]
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=repo, capture_output=True, text=True,
                                check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "src"], cwd=repo, capture_output=True,
                               text=True, check=True).stdout.strip() != ""
    except (OSError, subprocess.CalledProcessError):
        return {"commit": None, "src_modified": None}
    return {"commit": commit, "src_modified": dirty}
