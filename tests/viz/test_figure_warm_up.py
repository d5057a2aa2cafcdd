"""The run's figures warmed while it tracks (viz.run_report.preload_figure_modules): nothing is written, and the
figures drawn afterwards are byte for byte those drawn without it."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

from surfelslam.viz import map_figures as mf
from surfelslam.viz.run_report import preload_figure_modules


def _figures(out_dir) -> dict[str, bytes]:
    rng = np.random.default_rng(3)
    pos = rng.uniform(-1, 1, (300, 3)).astype(np.float32)
    normal = pos / np.linalg.norm(pos, axis=1, keepdims=True)
    conf, seen = rng.uniform(1, 20, 300), rng.integers(0, 50, 300)
    written = mf.save_map_figures(out_dir, pos, normal, rng.integers(0, 256, (300, 3)), conf, seen, np.eye(4),
                                  radius=np.full(300, 0.01))
    return {p.name: p.read_bytes() for p in written}


def test_warming_writes_nothing_and_changes_no_figure(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    before = _figures(tmp_path / "before")
    preload_figure_modules(True)
    preload_figure_modules(False)  # no figures wanted: nothing to do
    after = _figures(tmp_path / "after")
    assert sorted(before) == ["map_camera.png", "map_top.png"] and min(len(b) for b in before.values()) > 10_000
    assert after == before
    assert sorted(os.listdir(tmp_path)) == ["after", "before"]


def test_the_map_figures_are_warmed_once_per_process(monkeypatch):
    drawn = []
    map_figure = mf.map_figure
    monkeypatch.setattr(mf, "map_figure", lambda *a, **k: drawn.append(1) or map_figure(*a, **k))
    monkeypatch.setattr(mf, "_warmed_up", False)  # as in a fresh process
    mf.warm_up_map_figures()
    mf.warm_up_map_figures()
    assert drawn == [1]


def test_preload_runs_at_the_short_switch_interval_and_restores_it(monkeypatch):
    """While the report's modules load beside the tracking, the GIL changes hands every 0.5 ms (not every 5 ms): a
    tracking thread back from a kernel waits that long at most. The interval is back afterwards."""
    import sys

    from surfelslam import api

    seen = []
    monkeypatch.setattr(api, "preload_figure_modules", lambda figures: seen.append(sys.getswitchinterval()))
    before = sys.getswitchinterval()
    with api.preloading(True, None) as on_slot:
        on_slot(1, None)
    assert seen == [api.PRELOAD_SWITCH_INTERVAL_S] and api.PRELOAD_SWITCH_INTERVAL_S == 0.0005
    assert sys.getswitchinterval() == before == 0.005


@pytest.mark.skipif(sys.platform != "linux", reason="nice is per thread on Linux only")
def test_preload_runs_below_the_tracking_thread(monkeypatch):
    """The preload thread's imports are wanted at the run's end: it runs PRELOAD_NICE levels below the thread that
    started it, which keeps its own priority."""
    from surfelslam import api

    from helpers import thread_nice as nice

    seen = []
    monkeypatch.setattr(api, "preload_figure_modules", lambda figures: seen.append(nice()))
    mine = nice()
    with api.preloading(True, None) as on_slot:
        on_slot(1, None)
    assert seen == [min(mine + api.PRELOAD_NICE, 19)] and nice() == mine and api.PRELOAD_NICE > 0


def test_overlapping_preloads_restore_the_interval_from_before_the_first(monkeypatch):
    """Two runs in threads of one process, the second preload still loading when the first ends: the interval stays
    short until the second is done, and then the one from before both is back."""
    import sys
    import threading

    from surfelslam import api

    inside = {name: threading.Event() for name in ("first", "second")}
    release = {name: threading.Event() for name in ("first", "second")}

    def held(name):
        inside[name].set()
        release[name].wait(10)

    monkeypatch.setattr(api, "preload_figure_modules", held)
    before = sys.getswitchinterval()
    threads = {name: threading.Thread(target=api._preload_politely, args=(name,)) for name in inside}
    for name in ("first", "second"):
        threads[name].start()
        inside[name].wait(10)
    release["first"].set()
    threads["first"].join(10)
    assert sys.getswitchinterval() == api.PRELOAD_SWITCH_INTERVAL_S  # the second is still loading
    release["second"].set()
    threads["second"].join(10)
    assert sys.getswitchinterval() == before == 0.005
