"""Shared fixtures: paths to the real sequences in ../shared/data (skipped with a reason when absent).

Plain helpers (the standard camera, ATE, ``shared_sequence``) live in ``tests/helpers.py``.
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))  # `from helpers import ...` in every test folder

from helpers import shared_sequence  # noqa: E402


@pytest.fixture
def sevenscenes_path() -> Path:
    return shared_sequence("7scenes_redkitchen_0000_0499")


def _keep_every_texture_bank() -> None:
    """A synthetic scene's textures take about a second to make. The library keeps the last 4 banks; a test worker
    builds scenes with a dozen seeds and texture styles in turn, so it keeps them all (about 27 MB each)."""
    import surfelslam.synth.scenes as scenes
    from surfelslam.synth.textures import make_texture_bank

    scenes.make_texture_bank = functools.lru_cache(maxsize=32)(make_texture_bank.__wrapped__)


_keep_every_texture_bank()


@pytest.fixture(autouse=True)
def _no_throwaway_warmup_run(request, monkeypatch):
    """The hybrid and orb trackers' ``warmup()`` ends with a throwaway run on synthetic frames
    (:func:`surfelslam.slam.warmup.warm_up_run`, the one patch point), so that a run's timed loop starts with every
    kernel compiled.
    In a test it only costs time (about 0.6 s per run; 46 runs in make test); the kernels compile on first use instead.
    Skipped unless the test is marked ``warmup_run``; that results do not depend on it is tested
    (``tests/slam/test_warmup_run.py``)."""
    if request.node.get_closest_marker("warmup_run") is None:
        import surfelslam.slam.warmup

        monkeypatch.setattr(surfelslam.slam.warmup, "warm_up_run", lambda cfg, tracker: None)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Long work first, so the parallel workers start on the long tests and finish on the short ones instead of one
    worker running a 30 s test at the end while the other is idle: the groups that share a module fixture or a
    cached run (marker ``xdist_group``: one worker runs the whole group, ``make test`` uses ``--dist loadgroup``),
    then the whole-sequence tests (marker ``slow``), then the rest."""
    items.sort(key=lambda item: (item.get_closest_marker("xdist_group") is None,
                                 item.get_closest_marker("slow") is None))


#: s: how long a test's leftover background thread may take to end (a tracker's queued loop checks: well under this)
_BACKGROUND_GRACE_S = 10.0


@pytest.fixture(autouse=True)
def _background_threads_end_with_their_test():
    """A test that leaves a tracker unfinished leaves its background threads (loop checks, the hybrid's worker; stopped
    by its ``finish()``) running into the next tests, where they call whatever those tests patch (a patched function
    then counts calls that are not the test's own): each test finishes the trackers it starts."""
    import threading

    from surfelslam.backend.sparse_slam.loop_checks import LOOP_CHECK_THREAD
    from surfelslam.slam.hybrid import WORKER_THREAD

    background = (LOOP_CHECK_THREAD, WORKER_THREAD)
    before = {t.ident for t in threading.enumerate()}
    yield
    left = [t for t in threading.enumerate() if t.ident not in before and t.name.startswith(background)]
    for t in left:  # a pool whose tracker was collected ends its thread after its queued work: give it that time
        t.join(_BACKGROUND_GRACE_S)
    left = [t.name for t in left if t.is_alive()]
    assert not left, f"background threads left running (finish the tracker): {left}"
