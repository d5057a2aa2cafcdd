"""``surfelslam batch`` on Ray: the ATEs of separate ``surfelslam run`` calls, declared resources, numba's cache in
the workers, a killed worker retried, failures kept with their reason, resume without dispatching, Ctrl-C.

One small local Ray (2 CPUs) for one test that checks everything needing a cluster (its start-up is most of the
time); the 3 tiny synthetic sequences of conftest.py x the default tracker (hybrid: the dense and the feature
kernels). Faults are injected by the task function (a wrapper of ``run_job``, pickled by value into the workers)
through marker files, never by timing: a worker SIGKILLs itself on its first attempt, the next attempt finds the
marker. The cluster's test is ``heavy``: it runs in ``make test-all``, not in ``make test`` (Ray's start alone takes
about 9 s of CPU, the whole test about 29 s: more than the 5-minute budget of ``make test`` can spare on a slow
host); the one-line reasons of worker deaths are checked in ``make test``.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import os
import signal
import sys
from collections import Counter
from pathlib import Path

import pytest
from typer.testing import CliRunner

from surfelslam.batch import expand_jobs, inline_spec, load_spec, run_batch
from surfelslam.batch.executors import (
    CPUS_PER_JOB,
    RayExecutor,
    memory_estimate,
    ray_failure_reason,
)
from surfelslam.batch.jobs import config_sha256, is_complete, run_job

# find_spec, not an import: collecting this file must not cost every test worker Ray's import (about a second)
pytestmark = pytest.mark.skipif(importlib.util.find_spec("ray") is None,
                                reason="Ray is not installed (the [batch] extra)")

RAY_CPUS = 2  # the local test cluster: one 2-CPU job at a time, as on a 2-core machine
TRACKERS = ("hybrid",)


# ------------------------------------------------------------------------------------------------ task functions
# Run in the Ray workers (pickled by value: the workers cannot import this test module).
def _inspect(job):
    """run_job, plus what the worker saw: its pid, the resources Ray gave the task, numba's cache counters."""
    import ray
    from numba.core.registry import CPUDispatcher

    row = run_job(job)
    hits, misses = Counter(), Counter()
    for module in [m for name, m in sys.modules.items() if name.startswith("surfelslam")]:
        for obj in list(vars(module).values()):
            if isinstance(obj, CPUDispatcher):
                hits.update(obj.stats.cache_hits)
                misses.update(obj.stats.cache_misses)
    row.update(_pid=os.getpid(), _resources=ray.get_runtime_context().get_assigned_resources(),
               _cache_hits=sum(hits.values()), _cache_misses=sum(misses.values()))
    return row


def _faulty(job, marker_dir, plan):
    """run_job with the fault ``plan[job.name]`` injected; every attempt appends a line to the job's marker file.

    ``kill-once``: the worker SIGKILLs itself on the first attempt; ``kill``: on every attempt; ``raise``: every
    attempt raises. Other jobs run normally."""
    marker = Path(marker_dir) / f"{job.name}.attempts"
    with marker.open("a") as f:
        f.write(f"{os.getpid()}\n")
    attempt = len(marker.read_text().splitlines())
    fault = plan.get(job.name)
    if fault == "kill" or (fault == "kill-once" and attempt == 1):
        os.kill(os.getpid(), signal.SIGKILL)
    if fault == "raise":
        raise RuntimeError("disk on fire")
    return run_job(job)


# ------------------------------------------------------------------------------------------------ the cluster's test
@pytest.fixture
def ray_cluster():
    """A local Ray (its start-up is most of this module's time), shut down after the test."""
    import ray

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("RAY_USAGE_STATS_ENABLED", "0")
        ray.init("local", num_cpus=RAY_CPUS, include_dashboard=False, log_to_driver=False,
                 logging_level=logging.WARNING)
        ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
        try:
            yield ray
        finally:
            ray.cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
            ray.shutdown()


@pytest.mark.slow
@pytest.mark.heavy
def test_batch_on_ray(ray_cluster, tiny_seqs, tmp_path):
    """Everything that needs the cluster, in one test: with pytest-xdist (``make test``) separate tests could land
    on both workers, and each would start its own Ray. Each part is one of issue 38's "done when" items."""
    spec_file = tmp_path / "spec.toml"  # 3 sequences x hybrid
    spec_file.write_text(f"sequences = {json.dumps([str(s) for s in tiny_seqs])}\n"
                         f"trackers = {json.dumps(TRACKERS)}\n")
    separate = _separate_runs(tiny_seqs, tmp_path / "separate")
    # after the separate runs: numba's on-disk cache holds every kernel the jobs use
    out = tmp_path / "batch"
    jobs = expand_jobs(load_spec(spec_file), out)
    rows = run_batch(jobs, out, RayExecutor(retries=0, task=_inspect), warmup=False).rows

    _check_the_ates_of_separate_runs(jobs, rows, separate)
    _check_declared_resources_and_cached_kernels(jobs, rows)
    _check_rerun_skips_every_finished_job(spec_file, out, rows)
    _check_killed_worker_is_retried_and_a_failing_job_keeps_its_reason(tiny_seqs, separate, tmp_path / "faults")
    _check_interrupt_cancels_the_rest_and_keeps_the_finished_run(tiny_seqs, tmp_path / "interrupt")


def _separate_runs(seqs, root: Path) -> dict[tuple[str, str], dict]:
    """(sequence, tracker) -> metrics.json and config.toml sha256 of a separate ``surfelslam run``."""
    from surfelslam.cli import app

    out = {}
    for seq in seqs:
        for tracker in TRACKERS:
            run_dir = root / f"{seq.name}-{tracker}"
            res = CliRunner().invoke(app, ["run", str(seq), "--tracker", tracker, "--out", str(run_dir),
                                           "--no-figures", "--no-progress"])
            assert res.exit_code == 0, res.output
            out[seq.name, tracker] = {"metrics": json.loads((run_dir / "metrics.json").read_text()),
                                      "config_sha256": config_sha256((run_dir / "config.toml").read_text())}
    return out


def _check_the_ates_of_separate_runs(jobs, rows, separate) -> None:
    assert [(Path(j.sequence).name, j.tracker) for j in jobs] == [
        (room, t) for room in ("roomA", "roomB", "roomC") for t in TRACKERS]
    assert [r["status"] for r in rows] == ["done"] * len(jobs)
    for job, row in zip(jobs, rows, strict=True):
        ref = separate[Path(job.sequence).name, job.tracker]
        assert ref["config_sha256"] == job.config_hash  # the same recipe as `surfelslam run SEQ --tracker T`
        assert row["ate_rmse_m"] == ref["metrics"]["eval"]["ate_rmse_m"]
        assert row["rpe_trans_m_per_frame"] == ref["metrics"]["eval"]["rpe_trans_rmse_m_per_frame"]
        assert row["map_points"] == ref["metrics"]["map_points"]
        assert row["frames"] == ref["metrics"]["frames_processed"] > 0
        assert 0 < row["ate_rmse_m"] < 0.05
        assert row["_pid"] != os.getpid()  # it ran in a Ray worker


def _check_declared_resources_and_cached_kernels(jobs, rows) -> None:
    for job, row in zip(jobs, rows, strict=True):
        assert row["_resources"]["CPU"] == CPUS_PER_JOB
        assert row["_resources"]["memory"] == memory_estimate(job)
        # every kernel the worker needed was loaded from numba's on-disk cache, none compiled
        assert row["_cache_misses"] == 0 and row["_cache_hits"] > 0, row


def _check_rerun_skips_every_finished_job(spec_file: Path, out: Path, first_rows) -> None:
    """``surfelslam batch SPEC --executor ray`` over the finished batch: every job skipped, nothing dispatched
    (a dispatched job would be ``done``), the same ATEs."""
    from surfelslam.cli import app

    res = CliRunner().invoke(app, ["batch", str(spec_file), "--out", str(out), "--executor", "ray", "--no-warmup"])
    assert res.exit_code == 0, res.output
    assert "executor: ray" in res.stdout and f"{len(first_rows)} skipped ->" in res.stdout and "done" not in res.stdout
    again = json.loads((out / "batch.json").read_text())["jobs"]
    assert [r["status"] for r in again] == ["skipped"] * len(first_rows)
    assert [r["ate_rmse_m"] for r in again] == [r["ate_rmse_m"] for r in first_rows]


def _check_killed_worker_is_retried_and_a_failing_job_keeps_its_reason(seqs, separate, root: Path) -> None:
    out, markers = root / "out", root / "markers"
    markers.mkdir(parents=True)
    jobs = expand_jobs(inline_spec(seqs[:2], TRACKERS[0]), out)
    plan = {jobs[0].name: "kill-once", jobs[1].name: "raise"}

    def task(job):  # a local function: pickled by value with its closure
        return _faulty(job, str(markers), plan)

    rows = run_batch(jobs, out, RayExecutor(retries=1, task=task), warmup=False, plots=False).rows
    attempts = {j.name: (markers / f"{j.name}.attempts").read_text().split() for j in jobs}
    assert [len(attempts[j.name]) for j in jobs] == [2, 2]
    assert attempts[jobs[0].name][0] != attempts[jobs[0].name][1]  # the killed worker's retry ran in a new one
    assert rows[0]["status"] == "done" and is_complete(jobs[0])
    assert rows[0]["ate_rmse_m"] == separate["roomA", TRACKERS[0]]["metrics"]["eval"]["ate_rmse_m"]
    assert rows[1]["status"] == "failed" and not is_complete(jobs[1])
    assert rows[1]["error"] == "RuntimeError: disk on fire (after 2 attempts)"
    table = (out / "results.md").read_text()
    assert "1 done, 1 failed" in table and "disk on fire" in table


def _check_interrupt_cancels_the_rest_and_keeps_the_finished_run(seqs, root: Path) -> None:
    out = root / "out"
    jobs = expand_jobs(inline_spec(seqs, "dense"), out)

    def stop_after_first(job, row):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_batch(jobs, out, RayExecutor(retries=0), on_result=stop_after_first, warmup=False)
    rows = json.loads((out / "batch.json").read_text())["jobs"]
    finished = [r["job"] for r in rows if r["status"] == "done"]
    assert len(finished) == 1 and [r["status"] for r in rows].count("interrupted") == 2
    assert is_complete(next(j for j in jobs if j.name == finished[0]))


# ------------------------------------------------------------------------------------------------ no cluster needed
def test_worker_deaths_become_one_line_reasons():
    import ray.exceptions as rex

    assert ray_failure_reason(rex.WorkerCrashedError()) == "the worker died while running the job (WorkerCrashedError)"
    assert ray_failure_reason(rex.NodeDiedError("node gone")) == "the worker died while running the job (NodeDiedError)"
    assert ray_failure_reason(rex.OutOfMemoryError("x\ny")) == ("the worker was killed for using too much memory "
                                                                 "(OutOfMemoryError)")
    task_error = rex.RayTaskError("run_job", "Traceback ...\nOSError: disk full", OSError(28, "No space left"))
    assert ray_failure_reason(task_error) == "OSError: [Errno 28] No space left"


def test_task_options_fit_the_cluster(tiny_seqs, tmp_path):
    job = expand_jobs(inline_spec(tiny_seqs[:1], "dense"), tmp_path)[0]
    executor = RayExecutor(retries=3, env_vars={"NUMBA_CACHE_DIR": "/cache"})
    big = executor.task_options(job, {"CPU": 64.0, "memory": 256e9})
    assert big == {"num_cpus": CPUS_PER_JOB, "memory": memory_estimate(job), "max_retries": 3,
                   "retry_exceptions": True, "runtime_env": {"env_vars": {"NUMBA_CACHE_DIR": "/cache"}}}
    small = executor.task_options(job, {"CPU": 1.0, "memory": 1e9})  # a 1-CPU, 1 GB node: still schedulable
    assert small["num_cpus"] == 1 and small["memory"] == int(0.9e9) < memory_estimate(job)


def test_no_cluster_at_the_address_is_a_one_line_error(monkeypatch):
    import ray

    from surfelslam.batch.executors import local_or
    from surfelslam.errors import ConfigError

    def refuse(**kwargs):
        raise ConnectionError(f"Could not find any running Ray instance.\n(address {kwargs['address']})")

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", refuse)
    with pytest.raises(ConfigError, match=r"^cannot start or join Ray at auto: Could not find any running Ray "
                                          r"instance\. \(address auto\)$"):
        RayExecutor(address="auto")._init()
    # without --address: a new local Ray, unless RAY_ADDRESS names the cluster (a `ray job submit` entry point)
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    assert local_or(None) == "local" and local_or("ray://head:10001") == "ray://head:10001"
    monkeypatch.setenv("RAY_ADDRESS", "head:6379")
    assert local_or(None) is None
