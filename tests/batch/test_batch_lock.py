"""One batch at a time per --out folder (issue 71.3): a second batch, or a --report rebuild, refuses in one line while
a live batch holds OUT/.batch.lock; a lock left by a killed batch is taken over; the lock is gone after the batch."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from surfelslam.batch import run_batch
from surfelslam.batch.lock import BATCH_LOCK_NAME, BatchLock
from surfelslam.errors import OutputError


def _dead_pid() -> int:
    """The PID of a process that has ended."""
    proc = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                          check=True, env={"PATH": os.environ.get("PATH", "")})
    return int(proc.stdout)


def _held_by_a_live_process(out: Path) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    lock = out / BATCH_LOCK_NAME
    lock.write_text(f"{os.getppid()}\n")  # the parent process: alive, and not this one
    return lock


def test_a_second_batch_refuses_while_one_holds_the_folder(tmp_path):
    out = tmp_path / "out"
    _held_by_a_live_process(out)
    with pytest.raises(OutputError, match=f"another batch \\(process {os.getppid()}\\) is writing into") as exc:
        run_batch([], out, warmup=False, plots=False)
    assert "\n" not in str(exc.value) and "--out" in str(exc.value)
    assert not (out / "results.csv").exists()  # nothing written by the refused batch


def test_a_killed_batchs_lock_is_taken_over_and_released(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / BATCH_LOCK_NAME).write_text(f"{_dead_pid()}\n")
    result = run_batch([], out, warmup=False, plots=False)
    assert result.rows == [] and (out / "results.csv").read_text().startswith("sequence,tracker")
    assert not (out / BATCH_LOCK_NAME).exists()


def test_the_lock_is_exclusive_within_a_process_too(tmp_path):
    with BatchLock(tmp_path):
        assert (tmp_path / BATCH_LOCK_NAME).read_text().strip() == str(os.getpid())
        with pytest.raises(OutputError, match="another batch"):
            BatchLock(tmp_path).__enter__()
    assert not (tmp_path / BATCH_LOCK_NAME).exists()


def test_cli_batch_and_report_refuse_in_one_line(tmp_path, tiny_seqs):
    from surfelslam.cli import app

    out = tmp_path / "out"
    lock = _held_by_a_live_process(out)
    for args in (["batch", str(tiny_seqs[0]), "--out", str(out), "--no-warmup"], ["batch", "--report", str(out)]):
        res = CliRunner().invoke(app, args)
        # without Ray a batch first says where its jobs run ("note: ..."): the refusal is the one error line
        lines = [ln for ln in res.stderr.splitlines() if ln.strip() and not ln.startswith("note:")]
        assert res.exit_code != 0 and "Traceback" not in res.output, res.output
        assert len(lines) == 1 and str(lock) in lines[0] and "another batch" in lines[0], res.stderr
    assert not (out / "results.csv").exists()
