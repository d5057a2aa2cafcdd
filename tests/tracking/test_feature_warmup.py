"""The feature trackers compile their feature kernels in ``warmup()``, before the timed loop, not on the first
frames."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

_PROBE = """
import json
from surfelslam.kernels import consensus, hamming, keypoint_depth, lk, rgbd_refine
from surfelslam.slam import SlamConfig, build_slam
from surfelslam.types import Intrinsics

kernels = {"hamming": hamming.nearest_mutual_within, "hamming2": hamming.nearest_two,
           "keypoint_depth": keypoint_depth.plane_fit_sums, "rgbd_refine": rgbd_refine.rgbd_refine,
           "lk": lk.track_warped, "consensus": consensus.consistency_matrix}
before = {k: len(f.signatures) for k, f in kernels.items()}
build_slam(Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48), SlamConfig(), "TRACKER").warmup()
print(json.dumps({"before": before, "after": {k: len(f.signatures) for k, f in kernels.items()}}))
"""


# orb's warm-up calls the same feature warm-up as the hybrid's: make test-all (heavy) checks it too
@pytest.mark.parametrize("tracker", ["hybrid", pytest.param("orb", marks=pytest.mark.heavy)])
def test_warmup_compiles_the_feature_kernels(tracker):
    """In a fresh process (no kernel loaded yet), ``warmup()`` loads or compiles the feature kernels (and, through a
    throwaway run, the keyframe and loop-check ones)."""
    out = subprocess.run([sys.executable, "-c", _PROBE.replace("TRACKER", tracker)], capture_output=True, text=True,
                         check=True)
    counts = json.loads(out.stdout.strip().splitlines()[-1])
    assert all(n == 0 for n in counts["before"].values()), counts
    assert all(n >= 1 for n in counts["after"].values()), counts
