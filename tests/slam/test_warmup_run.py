"""The trackers' throwaway warm-up run leaves no trace in a run's results (which lets tests/conftest.py skip it)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

import surfelslam.slam.warmup
from surfelslam.slam import SlamConfig, build_slam
from tracker_helpers import INTR, room_frames

pytestmark = pytest.mark.warmup_run

N_FRAMES = 10  # fast motion: three or four keyframes, loop checks run


@pytest.fixture(scope="module")
def frames():
    return room_frames("fast", N_FRAMES)[0]


@pytest.mark.parametrize("tracker", ["hybrid", pytest.param("orb", marks=pytest.mark.heavy)])  # orb: make test-all
def test_the_warmup_run_changes_no_result(tracker, frames, monkeypatch):
    """The same frames give bit-identical poses whether ``warmup()`` ran its throwaway run first or not, and it did
    run: a tracker's state never leaks from that run into the next."""
    calls = []
    real = surfelslam.slam.warmup.warm_up_run
    poses = []
    for warm in (True, False):
        run = (lambda cfg, t: calls.append(t) or real(cfg, t)) if warm else (lambda cfg, t: None)
        monkeypatch.setattr(surfelslam.slam.warmup, "warm_up_run", run)
        slam = build_slam(INTR, SlamConfig(), tracker)
        slam.warmup()
        live = np.stack([slam.process(f).T_world_cam for f in frames])
        res = slam.finish()
        poses.append(live if res.trajectory_override is None else res.trajectory_override.T_world_cam)
    assert calls == [tracker]
    assert slam.sparse.n_keyframes >= 3
    assert np.array_equal(poses[0], poses[1])


def _loaded_signatures() -> dict[str, int]:
    """Every numba dispatcher with at least one compiled (or cache-loaded) signature -> how many it has."""
    import gc

    from numba.core.registry import CPUDispatcher

    return {f"{d.py_func.__module__}.{d.py_func.__qualname__}": len(d.overloads) for d in gc.get_objects()
            if isinstance(d, CPUDispatcher) and d.overloads}


def test_the_hybrid_short_warmup_run_loads_what_the_full_one_does():
    """The hybrid's throwaway run is short (``_RUN_FRAMES_BY_TRACKER``): after its warm-up, the full-length run of
    the other trackers reaches no numba kernel signature it did not load."""
    w = surfelslam.slam.warmup
    assert w._RUN_FRAMES_BY_TRACKER["hybrid"] < w._RUN_FRAMES
    slam = build_slam(INTR, SlamConfig(), "hybrid")
    slam.warmup()
    before = _loaded_signatures()
    tracker = build_slam(w._RUN_INTR, w._no_map_saving(SlamConfig()), "hybrid")
    for frame in w._run_frames(w._RUN_FRAMES):
        tracker.process(frame)
    tracker.finish()
    assert len(before) > 20
    assert _loaded_signatures() == before


#: numba kernels a long hybrid run reaches late (a keyframe database past ``exact_below_descriptors``, the map edges'
#: geometry-only render, a stack of rotations): the warm-up must compile them, or a first run stalls mid-run
LATE_KERNELS = ("surfelslam.kernels.hamming_hash:hash_keys", "surfelslam.kernels.hamming_hash:insert_rows",
                "surfelslam.kernels.hamming_hash:seal_rows", "surfelslam.kernels.hamming_hash:nearest_two_hashed",
                "surfelslam.geometry.so3_kernels:log_scales",
                "surfelslam.geometry.so3_kernels:markley_many", "surfelslam.kernels.render:fill_geometry")


def test_the_hybrids_warmup_compiles_what_a_long_run_reaches_late():
    """In a fresh process (no other test's calls), after the hybrid's ``warmup()`` each late kernel holds a compiled
    signature (compiled, or loaded from numba's cache)."""
    code = f"""
import importlib, json
from surfelslam.slam import SlamConfig, build_slam
from surfelslam.types import Intrinsics
build_slam(Intrinsics(262.5, 262.5, 159.5, 119.5, 320, 240), SlamConfig(), "hybrid").warmup()
out = {{}}
for name in {LATE_KERNELS!r}:
    module, fn = name.split(":")
    kernel = getattr(importlib.import_module(module), fn)
    out[name] = len(getattr(kernel, "serial", kernel).signatures)  # a dual kernel: its serial compilation
print(json.dumps(out))
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    compiled = json.loads(proc.stdout.strip().splitlines()[-1])
    assert all(n >= 1 for n in compiled.values()), compiled
