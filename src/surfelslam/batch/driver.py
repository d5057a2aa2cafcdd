"""A whole batch: skip the finished jobs, warm the kernels once, run the rest on an executor, write the table."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from surfelslam.batch.executors import Executor, LocalExecutor
from surfelslam.batch.jobs import Job, is_complete, one_line, skipped_row, summary
from surfelslam.batch.lock import BatchLock
from surfelslam.batch.report import write_report


@dataclasses.dataclass
class BatchResult:
    rows: list[dict]
    files: dict[str, Path]
    interrupted: bool = False

    def count(self, status: str) -> int:
        return sum(r["status"] == status for r in self.rows)


def warm_parts(jobs: Sequence[Job]) -> tuple[str, ...]:
    """The :mod:`surfelslam.warmup` parts the jobs' trackers use (:func:`surfelslam.slam.warmup.parts_for`)."""
    from surfelslam.slam.warmup import parts_for  # when used, as the warm-up itself: no trackers loaded at import

    return parts_for(j.tracker for j in jobs)


def run_batch(jobs: Sequence[Job], out_root: str | Path, executor: Executor | None = None,
              on_result: Callable[[Job, dict[str, Any]], None] | None = None, warmup: bool = True,
              plots: bool = True) -> BatchResult:
    """Run ``jobs`` (from :func:`~surfelslam.batch.spec.expand_jobs`) and write the results table into
    ``out_root``.

    A job whose folder holds a complete run of the same config is ``skipped`` (its row read from its
    ``metrics.json``). Before the others are dispatched the JIT kernels are compiled (or loaded) once here
    (``warmup``), so that the workers load numba's cache instead of each compiling it. ``on_result(job, row)`` is
    called for each job as it is settled (skipped ones first). A KeyboardInterrupt, or the executor failing (a
    cluster that cannot be joined), still writes the table (the jobs not finished: ``interrupted``, with the
    reason) and then propagates. One batch at a time writes into ``out_root`` (:class:`~.lock.BatchLock`: a second
    one raises OutputError), so ``results.csv`` agrees with the run folders.
    """
    executor = LocalExecutor() if executor is None else executor
    out_root = Path(out_root)
    out_root.mkdir(parents=True, exist_ok=True)
    with BatchLock(out_root):
        return _run_locked(jobs, out_root, executor, on_result, warmup, plots)


def _run_locked(jobs: Sequence[Job], out_root: Path, executor: Executor,
                on_result: Callable[[Job, dict[str, Any]], None] | None, warmup: bool, plots: bool) -> BatchResult:
    """:func:`run_batch` once ``out_root``'s batch lock is held."""
    rows: dict[str, dict] = {}

    def settle(job: Job, row: dict) -> None:
        rows[job.name] = row
        if on_result is not None:
            on_result(job, row)

    todo = []
    for job in jobs:
        if is_complete(job):
            settle(job, skipped_row(job))
        else:
            todo.append(job)
    interrupted = False
    reason = "the batch was interrupted before this job finished"
    try:
        if todo and warmup:
            from surfelslam.warmup import warm

            warm(*warm_parts(todo))
        executor.run(todo, settle)
    except KeyboardInterrupt:
        interrupted = True
        raise
    except Exception as exc:  # the executor itself failed (no cluster, the cluster lost): say so in the table
        reason = f"the batch stopped before this job finished: {one_line(exc)}"
        raise
    finally:
        ordered = [rows.get(j.name) or summary(j.describe(), None, "interrupted", reason) for j in jobs]
        files = write_report(out_root, ordered, plots=plots and not interrupted)
    return BatchResult(ordered, files, interrupted)
