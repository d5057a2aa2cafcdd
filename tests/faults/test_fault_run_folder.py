"""The run folder policy (:mod:`surfelslam.io.run_folder`): a finished `--out` is refused without --overwrite; with it
only the run's own files are replaced and nothing of the older run stays; a failed or killed run leaves the
previous run byte for byte (a killed one also a valid partial trajectory in `.partial-<pid>/`); a lock stops a second
run; a hand-over cut short is finished by the next run. Runs use given poses and no figures (fast)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from faultkit import assert_one_line, cli, index_rows, no_temp_files

from surfelslam.errors import ConfigError
from surfelslam.io import run_folder
from surfelslam.io.run_folder import RunFolder, staging_path
from surfelslam.io.trajectory import read_tum

RUN = ("--poses", "gt", "--no-figures", "--no-progress")
#: what a run with --no-figures hands over
RUN_FILES = ["config.toml", "keyframes.txt", "map.npz", "map.ply", "metrics.json", "trajectory.txt"]
#: files of an older run or an eval beside it that a --no-figures rerun does not write
OLDER_FILES = ["eval.json", "eval_trajectory.png", "eval_ate_errors.png", "trajectory.png", "ate_errors.png",
               "map_top.png", "map_camera.png", "run.rrd"]


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file below ``folder`` (relative path -> content)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def top_files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def leftovers(folder: Path) -> list[str]:
    """Lock, staging and hand-over entries left in a run folder."""
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


@pytest.fixture
def restore_sigint():
    old = signal.getsignal(signal.SIGINT)  # the CLI's Ctrl-C handling makes a second Ctrl-C exit at once
    yield
    signal.signal(signal.SIGINT, old)


@pytest.fixture
def done(synth_seq, tmp_path) -> Path:
    """A finished run of all 10 frames."""
    out = tmp_path / "run"
    res = cli("run", synth_seq, "-o", out, *RUN)
    assert res.exit_code == 0, res.output
    return out


def _die_after(monkeypatch, n: int, exc: BaseException) -> None:
    """The given-poses mapper raises ``exc`` instead of processing its (n+1)-th frame (a kill or Ctrl-C)."""
    import surfelslam.slam.given as given

    real = given.GivenPoseMapper.process
    calls = {"n": 0}

    def dying(self, frame, prepared=None, T_world_cam=None):
        if calls["n"] == n:
            raise exc
        calls["n"] += 1
        return real(self, frame, prepared=prepared, T_world_cam=T_world_cam)

    monkeypatch.setattr(given.GivenPoseMapper, "process", dying)


# ------------------------------------------------------------------------------------------------ the policy
def test_a_finished_folder_is_refused_without_overwrite(synth_seq, done):
    before = snapshot(done)
    res = cli("run", synth_seq, "-o", done, *RUN, "--end", "5")
    assert_one_line(res, 2, f"{done} holds a previous run (config.toml, keyframes.txt, map.npz, ...)",
                    "pass --overwrite")
    assert snapshot(done) == before and leftovers(done) == []


def test_overwrite_replaces_the_run_and_leaves_nothing_of_the_older_one(synth_seq, done):
    for name in OLDER_FILES:
        (done / name).write_text("older\n")
    (done / "notes.txt").write_text("the user's own file\n")
    res = cli("run", synth_seq, "-o", done, *RUN, "--end", "5", "--overwrite")
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in done.iterdir()) == sorted([*RUN_FILES, "notes.txt"])  # no .lock, no .partial-*
    assert (done / "notes.txt").read_text() == "the user's own file\n"
    assert len(read_tum(done / "trajectory.txt")) == 5
    m = json.loads((done / "metrics.json").read_text())
    assert m["complete"] is True and m["frames_processed"] == 5
    assert m["started"] <= m["finished"] and m["finished"][:4].isdigit()
    # the console may fold a long path anywhere: compare without whitespace
    said = "".join(res.stdout.split())
    assert "".join(f"run -> {done} (writing into {staging_path(done)} until complete)".split()) in said


@pytest.mark.parametrize("args, fragment", [
    (("--poses", "missing.txt"), "missing.txt: trajectory file not found"),
    (("--set", "icp.bogus=1"), "--set icp.bogus=1: unknown setting icp.bogus"),
    (("--config", "nope.toml"), "nope.toml: config file not found"),
    (("--tracker", "magic"), "--tracker must be one of dense, orb, hybrid, got 'magic'"),
    (("--end", "0"), "--end (0) must be greater than --start (0)"),
    (("--depth-scale", "1"), "--depth-scale 1"),
])
def test_a_failing_run_leaves_the_previous_folder_byte_identical(synth_seq, done, args, fragment):
    before = snapshot(done)
    res = cli("run", synth_seq, "-o", done, "--overwrite", "--no-figures", "--no-progress", *args)
    assert_one_line(res, 2, fragment)
    assert snapshot(done) == before and leftovers(done) == []


def test_an_output_folder_that_is_a_file_is_refused_before_the_run(synth_seq, tmp_path):
    blocker = tmp_path / "out"
    blocker.write_text("x")
    assert_one_line(cli("run", synth_seq, "-o", blocker, *RUN), 2, f"{blocker}: cannot be the output folder: "
                                                                    "it is a file")
    assert_one_line(cli("run", synth_seq, "-o", blocker / "r", *RUN), 2, f"it is below a file ({blocker})")


# ------------------------------------------------------------------------------------------------ the lock
def test_a_second_run_into_a_locked_folder_is_refused(synth_seq, tmp_path):
    out = tmp_path / "run"
    first = RunFolder(out)
    first.open()  # a run of this very process is writing into out
    try:
        res = cli("run", synth_seq, "-o", out, *RUN)
        assert_one_line(res, 2, f"{out / '.lock'}: another run (process {os.getpid()}) is writing into {out}")
    finally:
        first.close()
    assert not (out / ".lock").exists()


def test_a_lock_of_another_live_process_is_refused(synth_seq, tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / ".lock").write_text(f"{os.getppid()}\n")  # our parent: alive
    assert_one_line(cli("run", synth_seq, "-o", out, *RUN), 2, f"another run (process {os.getppid()})")
    assert sorted(os.listdir(out)) == [".lock"]


def test_a_stale_lock_of_a_dead_process_is_taken_over(synth_seq, tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                          check=True)
    pid = int(dead.stdout)
    assert not run_folder.pid_alive(pid)
    out = tmp_path / "run"
    out.mkdir()
    (out / ".lock").write_text(f"{pid}\n")
    res = cli("run", synth_seq, "-o", out, *RUN)
    assert res.exit_code == 0, res.output
    assert sorted(os.listdir(out)) == RUN_FILES


# ------------------------------------------------------------------------------------------------ kills
def test_ctrl_c_mid_rerun_keeps_the_old_run_and_a_valid_partial_trajectory(synth_seq, done, monkeypatch,
                                                                        restore_sigint):
    before = top_files(done)
    _die_after(monkeypatch, 4, KeyboardInterrupt())
    res = cli("run", synth_seq, "-o", done, *RUN, "--overwrite")
    assert_one_line(res, 130, "interrupted")
    assert top_files(done) == before  # the previous complete run, untouched
    partial = staging_path(done)
    assert leftovers(done) == [partial.name]  # no lock
    traj = read_tum(partial / "trajectory.txt")
    gt = read_tum(synth_seq / "groundtruth.txt")
    assert len(traj) == 4 and np.allclose(traj.T_world_cam, gt.T_world_cam[:4], atol=1e-6)
    assert (partial / "config.toml").is_file() and not (partial / "metrics.json").exists()
    assert no_temp_files(done)

    monkeypatch.undo()
    res = cli("run", synth_seq, "-o", done, *RUN, "--overwrite", "--end", "3")  # cleans the partial folder up
    assert res.exit_code == 0, res.output
    assert leftovers(done) == [] and len(read_tum(done / "trajectory.txt")) == 3


def test_kill_of_a_first_run_leaves_only_its_partial_folder(synth_seq, tmp_path, monkeypatch):
    from surfelslam.api import run_sequence
    from surfelslam.datasets import open_sequence
    from surfelslam.slam import SlamConfig

    _die_after(monkeypatch, 3, SystemExit(137))  # not an Exception: as abrupt as the loop can see
    out = tmp_path / "run"
    with pytest.raises(SystemExit):
        run_sequence(open_sequence(synth_seq), out, SlamConfig(), poses="gt", progress=False, figures=False)
    assert leftovers(out) == [staging_path(out).name] and not [p for p in out.iterdir() if p.is_file()]
    assert len(read_tum(staging_path(out) / "trajectory.txt")) == 3
    # a first run killed leaves no previous run: the next one needs no --overwrite
    monkeypatch.undo()
    assert cli("run", synth_seq, "-o", out, *RUN, "--end", "2").exit_code == 0
    assert sorted(os.listdir(out)) == RUN_FILES


def test_a_hand_over_cut_short_is_finished_by_the_next_run(tmp_path, monkeypatch):
    out = tmp_path / "run"
    out.mkdir()
    for name in ("trajectory.txt", "map.ply", "metrics.json", "eval.json", "map_top.png"):
        (out / name).write_text(f"old {name}\n")
    (out / "notes.txt").write_text("mine\n")
    folder = RunFolder(out, overwrite=True)
    stage = folder.open()
    for name in ("config.toml", "trajectory.txt", "map.ply", "metrics.json"):
        (stage / name).write_text(f"new {name}\n")
    real, moves = os.replace, []

    def killed_after_two(src, dst):
        if len(moves) == 2:
            raise KeyboardInterrupt
        moves.append(Path(dst).name)
        real(src, dst)

    monkeypatch.setattr(run_folder.os, "replace", killed_after_two)
    with pytest.raises(KeyboardInterrupt):
        folder.commit()
    folder.close()
    monkeypatch.undo()
    # cut short: no metrics.json (no complete run is claimed), the rest waits in .commit-<pid>/
    assert moves == ["config.toml", "map.ply"] and not (out / "metrics.json").exists()
    assert leftovers(out) == [f".commit-{os.getpid()}"]
    with pytest.raises(ConfigError, match=r"holds a previous run \(\.commit-"):
        RunFolder(out).check()
    nxt = RunFolder(out, overwrite=True)
    nxt.open()  # finishes the hand-over first
    nxt.close()
    assert top_files(out) == {"config.toml": b"new config.toml\n", "map.ply": b"new map.ply\n",
                              "metrics.json": b"new metrics.json\n", "notes.txt": b"mine\n",
                              "trajectory.txt": b"new trajectory.txt\n"}
    assert leftovers(out) == [staging_path(out).name]  # the next run's own (empty) staging folder


# ------------------------------------------------------------------------------------------------ nothing dropped
def test_unpaired_images_and_warnings_are_in_metrics_and_the_summary(seq, tmp_path):
    rows = index_rows(seq / "depth.txt")
    (seq / "depth.txt").write_text("\n".join(rows[:3] + rows[5:]) + "\n")  # 2 of 10 depth rows gone
    (seq / "INFO.txt").unlink()  # the layout's default camera does not fit the 160x120 images: a warning
    out = tmp_path / "run"
    res = cli("run", seq, "-o", out, *RUN, "--intrinsics", "131.25,131.25,79.5,59.5")
    assert res.exit_code == 0, res.output
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"] == 8 and m["frames_unpaired"] == 2
    assert [Path(u["file"]).name for u in m["unpaired"]] == [Path(r.split()[1]).name
                                                             for r in index_rows(seq / "rgb.txt")[3:5]]
    assert all("no depth image within 0.02 s in depth.txt" in u["reason"] for u in m["unpaired"])
    assert m["unpaired"][0]["timestamp"] == pytest.approx(0.1, abs=1e-6)
    text = " ".join(res.stdout.split())
    assert "8 processed, 0 skipped, 2 unpaired images left out" in text
    assert "unpaired: 2 listed images without a partner, e.g. " in text and "(and 1 more, see metrics.json)" in text
    assert m["warnings"] == []  # --intrinsics given: the layout default is not used

    res = cli("run", seq, "-o", out, *RUN, "--overwrite")
    assert res.exit_code == 0, res.output
    m = json.loads((out / "metrics.json").read_text())
    assert len(m["warnings"]) == 1 and "default intrinsics 525,525,319.5,239.5 do not fit" in m["warnings"][0]
    assert "warning: " + m["warnings"][0] in " ".join(res.stdout.split())
