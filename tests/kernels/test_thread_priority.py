"""The worker threads' lower CPU priority: it lowers the calling thread's, and only that thread's."""

from __future__ import annotations

import sys
from concurrent.futures import ThreadPoolExecutor

import pytest

from surfelslam.backend.sparse_slam import loop_checks
from surfelslam.errors import FrameError
from surfelslam.io import prefetch
from surfelslam.kernels import threads

from helpers import thread_nice


def _nice_in_worker(nice_increment: int) -> tuple[int, int]:
    """``(nice before, nice after)`` in a pool thread given ``lower_thread_priority(nice_increment)``."""
    with ThreadPoolExecutor(max_workers=1) as pool:
        before = pool.submit(thread_nice).result()
    with ThreadPoolExecutor(max_workers=1, initializer=threads.lower_thread_priority,
                            initargs=(nice_increment,)) as pool:
        after = pool.submit(thread_nice).result()
    return before, after


@pytest.mark.skipif(sys.platform != "linux", reason="nice is per thread on Linux only")
def test_lower_thread_priority_lowers_the_worker_and_not_the_caller():
    main_before = thread_nice()
    before, after = _nice_in_worker(5)
    assert after == min(before + 5, 19)
    assert thread_nice() == main_before
    assert _nice_in_worker(0)[1] == before  # no increment: unchanged


@pytest.mark.skipif(sys.platform != "linux", reason="nice is per thread on Linux only")
def test_reader_and_loop_checks_run_below_the_tracking_thread():
    assert 0 < prefetch.READER_NICE < loop_checks.LOOP_CHECK_NICE <= 19
    seen = {}

    class Seq(list):
        def __getitem__(self, i):
            seen["nice"] = thread_nice()
            raise FrameError(None, "unreadable", i)  # the reader reports it as the slot's error

    reader = prefetch.FrameReader(Seq([0]), ahead=1)
    with reader:
        list(reader.frames())
    assert seen["nice"] == min(thread_nice() + prefetch.READER_NICE, 19)


def test_lower_thread_priority_does_nothing_off_linux(monkeypatch):
    calls = []
    monkeypatch.setattr(threads.sys, "platform", "darwin")
    monkeypatch.setattr(threads.os, "setpriority", lambda *a: calls.append(a), raising=False)
    threads.lower_thread_priority(5)
    assert calls == []  # on macOS a thread id given to setpriority would name another process
