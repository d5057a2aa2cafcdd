"""A run's start-up imports what tracking needs and no more: the evaluation (evo), the figures (matplotlib) and the
mesh's TSDF are imported at the run's end or in the background while it tracks, never by ``import surfelslam.api``."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

#: modules a run needs only at its end (or for options not taken)
LATE = ("surfelslam.eval.metrics", "evo.core.metrics", "evo.core.lie_algebra", "scipy.spatial", "matplotlib",
        "surfelslam.viz.map_figures", "surfelslam.mapping.mesh")


def test_importing_the_api_does_not_import_what_only_the_end_of_a_run_needs():
    code = f"import json, sys, surfelslam.api; print(json.dumps([m for m in {LATE!r} if m in sys.modules]))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert json.loads(out.strip().splitlines()[-1]) == []


def test_the_evaluation_names_are_imported_on_first_use():
    import surfelslam.eval as ev
    from surfelslam.eval import metrics
    from surfelslam.eval.protocol import DEFAULT_MAX_DIFF_S

    assert ev.evaluate is metrics.evaluate and ev.AteResult is metrics.AteResult
    assert metrics.DEFAULT_MAX_DIFF_S == DEFAULT_MAX_DIFF_S == 0.02
    with pytest.raises(AttributeError, match="not_a_name"):
        ev.not_a_name  # noqa: B018
