"""Jobs run in forked child processes beside the caller's work (viz.forked): where they ran, a failed child's job run
again here, and the children killed when the caller's work is interrupted."""

from __future__ import annotations

import gc
import os
import threading
import time

import pytest

from surfelslam.viz import forked

linux_only = pytest.mark.skipif(not hasattr(os, "fork") or not hasattr(os, "sched_getaffinity"),
                                reason="forked jobs need os.fork (Linux)")
LONG_JOB_S = 60.0  # a child still running this long after the test was not killed


def _write_pid(path):
    def job():
        path.write_text(str(os.getpid()))
    return job


@linux_only
def test_jobs_run_in_children_while_the_block_runs(tmp_path, monkeypatch):
    monkeypatch.setattr(forked, "can_fork", lambda: True)
    with forked.jobs_in_children([_write_pid(tmp_path / "a"), _write_pid(tmp_path / "b")]):
        here = os.getpid()
    pids = {int((tmp_path / n).read_text()) for n in "ab"}
    assert len(pids) == 2 and here not in pids
    assert gc.get_freeze_count() == 0  # frozen for the fork only (the children's collections skip the parent's)


def test_without_fork_the_jobs_run_here_after_the_block(tmp_path, monkeypatch):
    monkeypatch.setattr(forked, "can_fork", lambda: False)
    order = []
    with forked.jobs_in_children([lambda: order.append("job")]):
        order.append("block")
    assert order == ["block", "job"]


def test_no_fork_while_another_thread_runs():
    stop = threading.Event()
    other = threading.Thread(target=stop.wait)
    other.start()
    try:
        assert not forked.can_fork()
    finally:
        stop.set()
        other.join()


@linux_only
def test_no_fork_on_a_saturated_machine(monkeypatch):
    """A load average of the CPU count or more: a child would only share the same CPU time (the jobs run here)."""
    cpus = len(os.sched_getaffinity(0))
    monkeypatch.setattr(forked.threading, "active_count", lambda: 1)  # (a test worker may run threads of its own)
    monkeypatch.setattr(forked.os, "getloadavg", lambda: (float(cpus), 0.0, 0.0))
    assert not forked.can_fork()
    monkeypatch.setattr(forked.os, "getloadavg", lambda: (cpus - 1.0, 0.0, 0.0))
    assert forked.can_fork() == (cpus > 1)


@linux_only
def test_a_job_whose_child_failed_runs_again_here(tmp_path, monkeypatch):
    monkeypatch.setattr(forked, "can_fork", lambda: True)
    parent = os.getpid()

    def fails_in_a_child():
        if os.getpid() != parent:
            raise OSError("no space left on device")
        (tmp_path / "done").write_text("here")

    def always_fails():
        raise ValueError("a bad figure")

    with forked.jobs_in_children([fails_in_a_child]):
        pass
    assert (tmp_path / "done").read_text() == "here"
    with pytest.raises(ValueError, match="a bad figure"), forked.jobs_in_children([always_fails]):
        pass


@linux_only
def test_an_interrupted_block_kills_and_reaps_the_children(tmp_path, monkeypatch):
    monkeypatch.setattr(forked, "can_fork", lambda: True)
    started = tmp_path / "pid"

    def long_job():
        started.write_text(str(os.getpid()))
        time.sleep(LONG_JOB_S)

    with pytest.raises(KeyboardInterrupt), forked.jobs_in_children([long_job]):
        while not started.exists() or not started.read_text():
            time.sleep(0.01)
        raise KeyboardInterrupt
    with pytest.raises(ChildProcessError):  # killed and already reaped: no such child any more
        os.waitpid(int(started.read_text()), os.WNOHANG)
    with pytest.raises(ProcessLookupError):
        os.kill(int(started.read_text()), 0)
