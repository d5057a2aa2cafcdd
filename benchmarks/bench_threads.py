"""Where a run's CPU goes, thread by thread: the CPU milliseconds per frame of the tracking thread, the reader, the
hybrid's feature worker and the loop checks, for each tracker asked, on one sequence.

Why: on two cores a run whose threads together need more than two cores' worth of CPU per frame is bound by that
sum, not by its tracking thread; the FPS ratio of two trackers then follows their total CPU per frame, and the
stage timings of ``metrics.json`` (wall clock, including the time a thread waits for a core) do not show which
thread to cut. Each thread's CPU time is read from Linux's ``/proc/self/task/<tid>/stat`` (user + system clock
ticks) at the last frame, while every worker is still alive, and named by its Python thread's name. The same
process runs every tracker, one after the other, each in its own run folder; the first run also pays numba's cache
loads (outside the frames: excluded from every figure here, which are counted from the first frame on).

Linux only (``/proc``). Usage: ``.venv/bin/python -m benchmarks.bench_threads SEQ [--tracker T ...] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import threading
import time
from pathlib import Path

from benchmarks.common import print_rows
from surfelslam.backend.sparse_slam.loop_checks import LOOP_CHECK_THREAD
from surfelslam.io.prefetch import READER_THREAD
from surfelslam.slam.hybrid import WORKER_THREAD

TASKS = Path("/proc/self/task")
#: thread name prefix -> the row's column (threads not listed are summed under ``other``)
ROLES = {"MainThread": "tracking", READER_THREAD: "reader", WORKER_THREAD: "features", LOOP_CHECK_THREAD: "loop_checks"}


def thread_cpu_s() -> dict[str, float]:
    """CPU seconds (user + system) so far of each live thread of this process, by role (:data:`ROLES`)."""
    tick_s = 1.0 / os.sysconf("SC_CLK_TCK")
    names = {t.native_id: t.name for t in threading.enumerate()}
    out: dict[str, float] = {}
    for task in TASKS.iterdir():
        try:
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # the thread ended meanwhile
            continue
        cpu_s = (int(fields[11]) + int(fields[12])) * tick_s  # utime and stime: fields 14 and 15 of stat(5)
        name = names.get(int(task.name), "")
        role = next((r for prefix, r in ROLES.items() if name.startswith(prefix)), "other")
        out[role] = out.get(role, 0.0) + cpu_s
    return out


def measure(seq_dir: Path, tracker: str, out_dir: Path) -> dict:
    """One run of ``tracker`` on ``seq_dir`` (no figures): CPU ms per frame by role from its first frame to its
    last, the process's sum, and the run's FPS."""
    from surfelslam.api import open_sequence, run_sequence
    from surfelslam.slam import SlamConfig

    seq = open_sequence(seq_dir)
    marks: dict[str, tuple[dict[str, float], float]] = {}

    def on_frame(_frame, res, _tracker) -> None:
        if "first" not in marks:
            marks["first"] = (thread_cpu_s(), time.process_time())
        if res.index == len(seq) - 1:
            marks["last"] = (thread_cpu_s(), time.process_time())

    metrics = run_sequence(seq, out_dir / tracker, SlamConfig(), tracker, progress=False, figures=False,
                           on_frame=on_frame)
    if "last" not in marks:
        raise SystemExit(f"bench_threads: the last frame of {seq_dir} was not tracked (unreadable?): no measurement")
    (cpu0, proc0), (cpu1, proc1) = marks["first"], marks["last"]
    n = max(len(seq) - 1, 1)
    row = {"tracker": tracker, "frames": len(seq), "fps": round(metrics["fps"], 1)}
    for role in ("tracking", "reader", "features", "loop_checks", "other"):
        row[role] = round((cpu1.get(role, 0.0) - cpu0.get(role, 0.0)) * 1e3 / n, 1)
    row["process"] = round((proc1 - proc0) * 1e3 / n, 1)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("seq", type=Path)
    ap.add_argument("--tracker", action="append", help="tracker to measure (repeatable; default: hybrid, dense)")
    ap.add_argument("--out", type=Path, help="run folders go here (default: a temporary folder)")
    args = ap.parse_args()
    if not TASKS.is_dir():
        raise SystemExit("bench_threads needs Linux's /proc/self/task")
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        rows = [measure(args.seq, t, out) for t in args.tracker or ("hybrid", "dense")]
    print_rows(rows)


if __name__ == "__main__":
    main()
