"""`surfelslam eval` on degenerate input: one line and exit 2, never a traceback; it never replaces a run's files and
plots the estimate's time span."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from evo.core.geometry import GeometryException
from faultkit import assert_one_line, cli, no_temp_files

from surfelslam.errors import EvaluationError, SurfelSlamError
from surfelslam.eval import metrics
from surfelslam.io.trajectory import read_tum, write_tum
from surfelslam.tools.eval import EVAL_FILES, within_span
from surfelslam.types import Trajectory


@pytest.fixture
def gt(synth_seq):
    return read_tum(synth_seq / "groundtruth.txt")


def _est(tmp_path, traj: Trajectory, name: str = "est.txt"):
    path = tmp_path / name
    write_tum(traj, path)
    return path


def test_all_estimate_stamps_equal(synth_seq, tmp_path, gt):
    path = tmp_path / "est.txt"
    path.write_text("".join(f"5.0 {0.1 * i} 0 0 0 0 0 1\n" for i in range(5)))
    assert_one_line(cli("eval", path, synth_seq, "--no-plots"), 2, str(path), "duplicate timestamp 5.000000",
                    "(lines 1 and 2)")


def test_estimate_that_never_moves(synth_seq, tmp_path, gt):
    path = _est(tmp_path, Trajectory(gt.timestamps, np.tile(np.eye(4), (len(gt), 1, 1))))
    assert_one_line(cli("eval", path, synth_seq, "--no-plots"), 2, f"{path} vs {synth_seq}",
                    "the estimate does not move", "at least two directions")
    assert not (tmp_path / "eval.json").exists()


def test_estimate_along_one_line(synth_seq, tmp_path, gt):
    T = np.tile(np.eye(4), (len(gt), 1, 1))
    T[:, 0, 3] = np.linspace(0, 0.3, len(gt))
    path = _est(tmp_path, Trajectory(gt.timestamps, T))
    assert_one_line(cli("eval", path, synth_seq, "--no-plots"), 2, "the estimate moves along one straight line")


def test_too_few_associated_poses(synth_seq, tmp_path, gt):
    path = _est(tmp_path, gt.subset(slice(0, 2)))
    assert_one_line(cli("eval", path, synth_seq / "groundtruth.txt", "--no-plots"), 2, str(path),
                    "only 2 estimate/ground-truth pose pairs")


@pytest.mark.parametrize("value", ["-1", "nan", "inf"])
def test_max_diff_out_of_domain(synth_seq, tmp_path, gt, value):
    path = _est(tmp_path, gt)
    assert_one_line(cli("eval", path, synth_seq, "--max-diff", value, "--no-plots"), 2, "--max-diff",
                    "finite number of seconds >= 0")


def test_eval_never_replaces_a_runs_files(synth_seq, tmp_path, gt):
    run = tmp_path / "run"
    run.mkdir()
    write_tum(gt, run / "trajectory.txt")
    own = {name: f"run's {name}".encode() for name in ("trajectory.png", "ate_errors.png", "metrics.json")}
    for name, data in own.items():
        (run / name).write_bytes(data)
    old = os.umask(0o022)
    try:
        res = cli("eval", run, synth_seq)  # a run folder as EST: its trajectory.txt, outputs beside it
    finally:
        os.umask(old)
    assert res.exit_code == 0, res.output
    for name, data in own.items():
        assert (run / name).read_bytes() == data, name
    for name in EVAL_FILES.values():
        assert (run / name).is_file() and (run / name).stat().st_mode & 0o777 == 0o644
    assert set(EVAL_FILES.values()).isdisjoint({"trajectory.png", "ate_errors.png", "metrics.json", "map.ply",
                                                "config.toml", "trajectory.txt"})
    assert json.loads((run / "eval.json").read_text())["n_pairs"] == len(gt)
    assert no_temp_files(run)


def test_plots_cover_the_estimate_span():
    t = np.arange(0, 100, 0.1)
    gt = Trajectory(t, np.tile(np.eye(4), (len(t), 1, 1)))
    est = gt.subset((t >= 10) & (t <= 20))
    span = within_span(gt, est, 0.02)
    assert span.timestamps[0] == pytest.approx(10.0) and span.timestamps[-1] == pytest.approx(20.0)
    far = Trajectory(np.array([500.0, 501.0]), np.tile(np.eye(4), (2, 1, 1)))
    assert len(within_span(gt, far, 0.02)) == len(gt)  # nothing inside: the whole ground truth


def test_library_errors_are_typed(gt):
    still = Trajectory(gt.timestamps, np.tile(np.eye(4), (len(gt), 1, 1)))
    with pytest.raises(EvaluationError, match="does not move") as err:
        metrics.evaluate(still, gt)
    assert isinstance(err.value, SurfelSlamError) and isinstance(err.value, ValueError)
    assert isinstance(err.value, GeometryException)  # callers that fall back to another alignment catch this
    with pytest.raises(EvaluationError, match="max_diff must be a finite number"):
        metrics.evaluate(gt, gt, -1.0)
