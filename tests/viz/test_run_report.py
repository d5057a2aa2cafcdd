"""The run's report (viz.run_report): its figure jobs run side by side, every one to its end, and the first failure
(in the jobs' order) is the caller's; the evaluation's figures come from the evaluation the metrics got."""

from __future__ import annotations

import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from surfelslam.eval.metrics import evaluate
from surfelslam.eval.run_eval import evaluate_run
from surfelslam.geometry import se3
from surfelslam.slam.writer import RunRecord
from surfelslam.types import Trajectory
from surfelslam.viz.run_report import run_concurrently, trajectory_figure_jobs


def test_jobs_run_side_by_side():
    """The first job waits for the second one: it can only finish if the second runs meanwhile."""
    second_ran = threading.Event()
    done = []
    run_concurrently([lambda: done.append(second_ran.wait(timeout=30)), lambda: second_ran.set()])
    assert done == [True]


def test_every_job_runs_and_the_first_failure_is_raised():
    ran = []

    def job(k: int, error: Exception | None):
        def run():
            ran.append(k)
            if error is not None:
                raise error
        return run

    with pytest.raises(ValueError, match="second"):
        run_concurrently([job(0, None), job(1, ValueError("second")), job(2, KeyError("third")), job(3, None)])
    assert sorted(ran) == [0, 1, 2, 3]
    run_concurrently([])  # nothing to do


def _record(tmp_path: Path, n: int = 40) -> RunRecord:
    rng = np.random.default_rng(4)
    t = np.arange(n) / 30.0
    gt = Trajectory(t, np.stack([se3.exp(np.concatenate([0.02 * k * np.ones(3), [0.05 * k, 0.01 * k * k, 0.0]]))
                                 for k in range(n)]))
    est = Trajectory(t, np.stack([T @ se3.exp(rng.normal(size=6) * 1e-3) for T in gt.T_world_cam]))
    outcome = SimpleNamespace(result=SimpleNamespace(loop_stamps=None))
    return RunRecord(tmp_path, outcome, {"frames_processed": n, "tracker": "dense"}, est, gt)


def test_the_evaluation_is_made_once_for_the_metrics_and_the_figures(tmp_path):
    record = _record(tmp_path)
    ate = evaluate_run(record)
    assert record.metrics["eval"] == evaluate(record.trajectory, record.ground_truth)
    assert ate.rmse_m == record.metrics["eval"]["ate_rmse_m"]
    jobs = trajectory_figure_jobs(record, frozenset({"trajectory", "ate_errors", "map_top"}), ate)
    run_concurrently(jobs)
    assert len(jobs) == 2 and {p.name for p in tmp_path.iterdir()} == {"trajectory.png", "ate_errors.png"}
    assert trajectory_figure_jobs(record, frozenset({"trajectory"}), None) == []  # no evaluation: no figure
