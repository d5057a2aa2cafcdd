"""``surfelslam batch``: spec expansion, the same ATEs as separate runs, resume, failures, --report, the Ray extra.

Tiny 8-frame 160x120 synthetic sequences and the LocalExecutor; the Ray executor's tests are in test_batch_ray.py.
"""

from __future__ import annotations

import json
import sys
import textwrap
from pathlib import Path

import pytest
from typer.testing import CliRunner

from surfelslam.api import run_sequence
from surfelslam.batch import expand_jobs, inline_spec, load_spec, run_batch
from surfelslam.batch.executors import LocalExecutor, make_executor
from surfelslam.batch.jobs import config_sha256, is_complete
from surfelslam.batch.report import rebuild_rows
from surfelslam.datasets import open_sequence
from surfelslam.errors import ConfigError


@pytest.fixture
def seqs(tiny_seqs) -> list[Path]:
    return tiny_seqs[:2]  # roomA, roomB (conftest.py)


def _spec(tmp_path: Path, seqs: list[Path], configs: str = "") -> Path:
    path = tmp_path / "spec.toml"
    path.write_text(textwrap.dedent(f"""\
        sequences = [{", ".join(json.dumps(str(s)) for s in seqs)}]
        trackers = ["dense", "hybrid"]
        """) + textwrap.dedent(configs))
    return path


def _cli(*args):
    from surfelslam.cli import app

    return CliRunner().invoke(app, ["batch", *(str(a) for a in args)])


def _ates(rows) -> dict[str, float]:
    return {r["job"]: r["ate_rmse_m"] for r in rows}


def test_spec_jobs_match_separate_runs(tmp_path, seqs):
    jobs = expand_jobs(load_spec(_spec(tmp_path, seqs)), tmp_path / "out")
    assert [(Path(j.sequence).name, j.tracker) for j in jobs] == [
        ("roomA", "dense"), ("roomA", "hybrid"), ("roomB", "dense"), ("roomB", "hybrid")]
    result = run_batch(jobs, tmp_path / "out", LocalExecutor(), warmup=False)
    assert [r["status"] for r in result.rows] == ["done"] * 4
    for job, row in zip(jobs, result.rows, strict=True):
        assert job.folder.name == f"{Path(job.sequence).name}-{job.tracker}-{job.short_hash}"
        # the run's config.toml is the job's config: its sha256 is the job's hash
        assert config_sha256((job.folder / "config.toml").read_text()) == job.config_hash
        seq = open_sequence(job.sequence, job.config.dataset)
        ref = run_sequence(seq, tmp_path / "ref" / job.name, job.config, job.tracker, progress=False, figures=False)
        assert row["ate_rmse_m"] == ref["eval"]["ate_rmse_m"]
        assert row["map_points"] == ref["map_points"]
    csv = (tmp_path / "out" / "results.csv").read_text().splitlines()
    assert len(csv) == 5 and csv[0].startswith("sequence,tracker,config,config_hash,sets,status,ate_rmse_m")
    assert (tmp_path / "out" / "ate-roomA.png").is_file() and (tmp_path / "out" / "ate-roomB.png").is_file()
    assert "| roomA | hybrid | default |" in (tmp_path / "out" / "results.md").read_text()


def test_resume_skips_finished_jobs_and_reruns_changed_ones(tmp_path, seqs):
    out = tmp_path / "out"
    first = _spec(tmp_path, seqs[:1], """
        [[configs]]
        name = "strict"
        set = ["icp.min_inliers=300"]
        """)
    jobs = expand_jobs(load_spec(first), out)
    assert [r["status"] for r in run_batch(jobs, out, warmup=False).rows] == ["done", "done"]
    again = run_batch(expand_jobs(load_spec(first), out), out, warmup=False)
    assert [r["status"] for r in again.rows] == ["skipped", "skipped"]
    assert _ates(again.rows) == _ates(run_batch(jobs, out, warmup=False).rows)

    # a config changed (nested form, other value): a new hash, so its jobs run; a damaged run is run again
    changed = _spec(tmp_path, seqs[:1], """
        [[configs]]
        name = "strict"
        set = ["icp.min_inliers=300"]

        [[configs]]
        name = "stricter"
        icp = { min_inliers = 400 }
        """)
    jobs2 = expand_jobs(load_spec(changed), out)
    (jobs2[1].folder / "config.toml").write_text("tracker = \"dense\"\n")  # roomA-hybrid, strict: not the same
    assert not is_complete(jobs2[1])
    rows = run_batch(jobs2, out, warmup=False).rows
    assert [(r["config"], r["tracker"], r["status"]) for r in rows] == [
        ("strict", "dense", "skipped"), ("strict", "hybrid", "done"),
        ("stricter", "dense", "done"), ("stricter", "hybrid", "done")]
    assert jobs2[2].config.icp.min_inliers == 400 and jobs2[2].short_hash != jobs2[0].short_hash


def test_missing_sequence_fails_with_its_reason_and_the_batch_goes_on(tmp_path, seqs):
    spec = inline_spec([seqs[0], tmp_path / "nowhere"], "dense")
    rows = run_batch(expand_jobs(spec, tmp_path / "out"), tmp_path / "out", warmup=False).rows
    assert [r["status"] for r in rows] == ["done", "failed"]
    assert "nowhere" in rows[1]["error"] and "not found" in rows[1]["error"]
    assert rows[1]["ate_rmse_m"] is None
    assert "| failed |" in (tmp_path / "out" / "results.md").read_text()


def test_crashing_job_is_retried_then_recorded(tmp_path, seqs, monkeypatch):
    from surfelslam.batch import executors

    calls = []

    def crash(job):
        calls.append(job.name)
        raise RuntimeError("worker died")

    monkeypatch.setattr(executors, "run_job", crash)
    jobs = expand_jobs(inline_spec([seqs[0]], "dense"), tmp_path / "out")
    rows = run_batch(jobs, tmp_path / "out", LocalExecutor(retries=2), warmup=False).rows
    assert len(calls) == 3
    assert rows[0]["status"] == "failed" and rows[0]["error"] == "RuntimeError: worker died (after 3 attempts)"


def test_cli_inline_sweep_resume_and_report(tmp_path, seqs):
    out = tmp_path / "out"
    res = _cli(seqs[0], "--tracker", "dense", "--set", "icp.min_inliers=300,500", "--end", "6", "--out", out,
               "--executor", "local", "--no-warmup")
    assert res.exit_code == 0, res.output
    assert "2 done" in res.stdout
    rows = json.loads((out / "batch.json").read_text())["jobs"]
    assert [r["sets"] for r in rows] == [["icp.min_inliers=300"], ["icp.min_inliers=500"]]
    assert all(r["frames"] == 6 for r in rows)  # the dataset options reach every job
    table = (out / "results.csv").read_text()

    res = _cli(seqs[0], "--tracker", "dense", "--set", "icp.min_inliers=300,500", "--end", "6", "--out", out,
               "--executor", "local", "--no-warmup")
    assert res.exit_code == 0 and "2 skipped" in res.stdout, res.output

    (out / "results.csv").unlink()
    (out / "results.md").unlink()
    res = _cli("--report", out)
    assert res.exit_code == 0, res.output
    rebuilt = (out / "results.csv").read_text()
    assert rebuilt.replace("skipped", "done") == table.replace("skipped", "done")
    assert len(rebuilt.splitlines()) == 3
    # without batch.json: rebuilt from the run folders' job.json
    (out / "batch.json").unlink()
    assert [r["status"] for r in rebuild_rows(out)] == ["done", "done"]


def test_inline_set_values_are_a_sweep_axis(tmp_path, seqs):
    jobs = expand_jobs(inline_spec(seqs[:1], "dense", ["icp.min_inliers=1,2"]), tmp_path)
    assert len(jobs) == 2
    assert [j.config.icp.min_inliers for j in jobs] == [1, 2]
    grid = expand_jobs(inline_spec(seqs, "dense,hybrid", ["icp.min_inliers=1,2", "icp.max_translation_m=0.1,0.2,0.3"]),
                       tmp_path)
    assert len(grid) == 2 * 2 * 2 * 3 and len({j.name for j in grid}) == len(grid)
    with pytest.raises(ConfigError, match="unknown setting icp.min_inlier"):
        inline_spec(seqs, None, ["icp.min_inlier=1,2"])
    with pytest.raises(ConfigError, match="tracker must be one of"):
        inline_spec(seqs, "dense,nope")


def test_spec_errors_are_one_line(tmp_path, seqs):
    bad = tmp_path / "bad.toml"
    bad.write_text('sequences = ["a"]\ntrackerz = ["dense"]\n')
    res = _cli(bad, "--out", tmp_path / "out")
    assert res.exit_code == 2 and "unknown key(s) trackerz" in res.stderr


def test_missing_ray_names_the_extra(tmp_path, seqs, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    res = _cli(seqs[0], "--out", tmp_path / "out", "--executor", "ray")
    assert res.exit_code == 2
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "pip install 'surfelslam[batch]'" in lines[0], res.stderr
    runner, note = make_executor(None)
    assert runner.name == "local" and "surfelslam[batch]" in note


def test_interrupt_keeps_finished_runs_and_marks_the_rest(tmp_path, seqs, monkeypatch):
    from surfelslam.batch import executors
    from surfelslam.batch.jobs import run_job

    def run_then_stop(job):
        if "roomB" in job.name:
            raise KeyboardInterrupt
        return run_job(job)

    monkeypatch.setattr(executors, "run_job", run_then_stop)
    out = tmp_path / "out"
    jobs = expand_jobs(inline_spec(seqs, "dense"), out)
    with pytest.raises(KeyboardInterrupt):
        run_batch(jobs, out, warmup=False)
    rows = json.loads((out / "batch.json").read_text())["jobs"]
    assert [r["status"] for r in rows] == ["done", "interrupted"]
    assert is_complete(jobs[0]) and not is_complete(jobs[1])


def test_a_failing_executor_leaves_the_table_with_its_reason(tmp_path, seqs):
    class NoCluster:
        name = "ray"

        def run(self, jobs, on_result):
            raise ConfigError("cannot start or join Ray at auto: no cluster")

    out = tmp_path / "out"
    jobs = expand_jobs(inline_spec(seqs, "dense"), out)
    run_batch(jobs[:1], out, warmup=False)
    with pytest.raises(ConfigError):
        run_batch(jobs, out, NoCluster(), warmup=False)
    rows = json.loads((out / "batch.json").read_text())["jobs"]
    assert [r["status"] for r in rows] == ["skipped", "interrupted"]
    assert rows[1]["error"] == ("the batch stopped before this job finished: cannot start or join Ray at auto: "
                                "no cluster")


def test_workers_get_the_numba_cache_folder_this_process_uses(monkeypatch, tmp_path):
    from surfelslam.batch.executors import numba_cache_env

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert numba_cache_env() == {"NUMBA_CACHE_DIR": str(tmp_path)}
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    monkeypatch.setattr("surfelslam.numba_cache.numba_cache_fallback", lambda: str(tmp_path / "fallback"))
    assert numba_cache_env() == {"NUMBA_CACHE_DIR": str(tmp_path / "fallback")}
    monkeypatch.setattr("surfelslam.numba_cache.numba_cache_fallback", lambda: None)  # the in-tree cache works
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    assert numba_cache_env() == {}


@pytest.mark.parametrize(("trackers", "parts"), [(("dense",), ("dense", "shape")), (("orb",), ("sparse",)),
                                                 (("orb", "hybrid"), ("dense", "shape", "sparse"))])
def test_the_driver_warms_the_parts_its_trackers_use(trackers, parts):
    """Both dense trackers relocalise by shape, so the ``shape`` part goes with ``dense``; every part named is one
    that :mod:`surfelslam.warmup` has."""
    from types import SimpleNamespace

    from surfelslam.batch.driver import warm_parts
    from surfelslam.warmup import PARTS

    assert warm_parts([SimpleNamespace(tracker=t) for t in trackers]) == parts
    assert set(parts) <= set(PARTS)
