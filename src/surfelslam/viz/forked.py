"""Figures drawn in forked child processes while this process does other work.

Drawing a figure (matplotlib, PNG encoding) holds the GIL nearly all the time, so a thread does not overlap it with
anything; a forked child does, on another core. A run's report draws its map figures in children while it evaluates
and draws the trajectory figures itself (:mod:`surfelslam.viz.run_report`).

A job runs in a child only where that is safe and useful (:func:`can_fork`): Linux (elsewhere the system's libraries
may not survive a fork), more than one CPU for this process and a CPU to spare (a load average, this process
included, below the CPU count: on a saturated machine a child only adds its start-up to the same share of CPU), and
no other Python thread alive (a lock another thread held at the fork would stay locked in the child). Otherwise,
and for a job whose child failed, the job runs in this process when the ``with`` block ends, so its outputs are the
same and its error is raised here.
"""

from __future__ import annotations

import contextlib
import gc
import os
import signal
import sys
import threading
import warnings
from collections.abc import Callable, Iterator, Sequence

_CHILD_DONE = 0  # the child's exit status when its job returned
_CHILD_FAILED = 1  # ... when it raised (the job is run again in the parent, which raises its error)


def can_fork() -> bool:
    """True when jobs may run in forked children here and now (see the module docstring)."""
    if not (sys.platform.startswith("linux") and hasattr(os, "fork")) or threading.active_count() != 1:
        return False
    cpus = len(os.sched_getaffinity(0))
    return cpus > 1 and os.getloadavg()[0] < cpus


def _fork(job: Callable[[], object]) -> int:
    """Fork a child that runs ``job`` and exits with :data:`_CHILD_DONE` or :data:`_CHILD_FAILED`; the child's pid.

    The child leaves through ``os._exit``: no exit handlers, no flushing of the parent's buffered output."""
    parent = os.getpid()
    freeze = gc.get_freeze_count() == 0  # (else someone froze objects on purpose: left as they are)
    if freeze:
        gc.freeze()  # the child's garbage collections leave the inherited objects alone (no copy of their pages)
    try:
        with warnings.catch_warnings():
            # Python 3.12 warns when forking a process with other threads: here only idle native pools (BLAS, OpenCV)
            warnings.simplefilter("ignore", DeprecationWarning)
            pid = os.fork()
    finally:
        if freeze and os.getpid() == parent:
            gc.unfreeze()
    if pid:
        return pid
    status = _CHILD_FAILED
    try:
        signal.signal(signal.SIGINT, signal.SIG_DFL)  # a Ctrl-C ends the child at once, without a word
        job()
        status = _CHILD_DONE
    except BaseException:  # noqa: BLE001, S110 - the parent runs the job again and raises its error
        pass
    finally:
        os._exit(status)


def _reap(pid: int) -> bool:
    """Wait for the child ``pid``; True when its job was done."""
    _, status = os.waitpid(pid, 0)
    return os.WIFEXITED(status) and os.WEXITSTATUS(status) == _CHILD_DONE


def _kill(pids: Sequence[int]) -> None:
    for pid in pids:
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGKILL)
        with contextlib.suppress(OSError):
            os.waitpid(pid, 0)


@contextlib.contextmanager
def jobs_in_children(jobs: Sequence[Callable[[], object]]) -> Iterator[None]:
    """Run ``jobs`` beside the ``with`` block: each in a forked child when :func:`can_fork`, else here once the block
    is done. Leaving waits for the children; a job whose child failed is run again here (raising its error). When the
    block or the wait raises (a Ctrl-C), the children are killed and reaped first."""
    forked: list[tuple[int, Callable[[], object]]] = []  # (child's pid, its job), not yet reaped
    local = list(jobs)
    try:
        if local and can_fork():
            local, pending = [], local
            for job in pending:
                try:
                    forked.append((_fork(job), job))
                except OSError:  # no process to be had (EAGAIN, ENOMEM): the job runs here
                    local.append(job)
        yield
        while forked:
            pid, job = forked[0]
            done = _reap(pid)
            forked.pop(0)
            if not done:
                local.append(job)
    except BaseException:
        _kill([pid for pid, _ in forked])
        raise
    for job in local:
        job()
