"""One driver (issue 67.1): `surfelslam run` and `surfelslam.Slam` are the same session and write the run folder with
the same writer; a prior map in which nothing localises ends as a normal run (issue 71)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

import surfelslam as ss
from surfelslam.api import run_sequence
from surfelslam.cli import app
from surfelslam.io.kitti import read_kitti
from surfelslam.io.run_folder import STAGING_PREFIX
from surfelslam.io.trajectory import read_tum
from surfelslam.slam.map_file import read_map_file
from surfelslam.synth.writer import generate_sequence

pytestmark = pytest.mark.slow  # short sequences through a tracker and the CLI

runner = CliRunner()
#: metrics.json fields that are wall-clock measurements (they differ between any two runs)
WALL_CLOCK = {"fps", "wall_s", "warmup_s", "ms_per_frame", "stage_ms", "started", "finished", "startup_s",
              "shutdown_s"}


@pytest.fixture(scope="module")
def seqs(tmp_path_factory):
    base = tmp_path_factory.mktemp("driver")
    room = generate_sequence(base / "room", "room", "slow", 8, "kinect", 3, 160, 120)
    office = generate_sequence(base / "office", "office", "slow", 6, "kinect", 5, 160, 120)
    return room, office


def _files(folder) -> set[str]:
    return {p.name for p in folder.iterdir()}


@pytest.mark.parametrize("tracker", ["dense", "hybrid"])
def test_a_run_saved_from_python_is_the_run_of_the_cli(seqs, tmp_path, tracker):
    seq = ss.open_sequence(seqs[0])
    cli = tmp_path / "cli"
    run_sequence(seq, cli, ss.SlamConfig(), tracker, progress=False, figures=False)
    slam = ss.Slam.from_sequence(seq, tracker=tracker)
    for frame in seq:
        slam.track(frame)
    api = slam.finish().save(tmp_path / "api")
    assert _files(api) == _files(cli) == {"trajectory.txt", "keyframes.txt", "map.ply", "map.npz", "config.toml",
                                          "metrics.json"}
    for name in ("trajectory.txt", "keyframes.txt", "config.toml", "map.ply"):
        assert (api / name).read_bytes() == (cli / name).read_bytes(), name
    m_api, m_cli = (json.loads((d / "metrics.json").read_text()) for d in (api, cli))
    assert list(m_api) == list(m_cli)
    assert m_api["sequence"] == m_cli["sequence"] == str(seqs[0]) and m_api["complete"] is True
    assert m_api["eval"] == m_cli["eval"] and m_api["frames_processed"] == len(seq) == 8
    # start-up (from run_sequence's call: it includes the warm-up) and shut-down: measured for a run, not for a
    # session fed frame by frame
    assert m_cli["startup_s"] > m_cli["warmup_s"] > 0 and m_cli["shutdown_s"] > 0
    assert m_api["startup_s"] is None and m_api["shutdown_s"] is None
    differ = {k for k in m_api if m_api[k] != m_cli[k]}
    assert differ <= WALL_CLOCK | {"prepare_in_reader"}, differ  # the CLI prepares frames in its reader thread
    # the commands that read a run folder work on the one saved from Python: its sequence is recorded
    res = runner.invoke(app, ["mesh", str(api), "--no-progress"])
    assert res.exit_code == 0, res.output
    assert (api / "mesh.ply").stat().st_size > 1000
    res = runner.invoke(app, ["eval", str(api), str(seqs[0]), "--no-figures"])
    assert res.exit_code == 0, res.output
    assert json.loads((api / "eval.json").read_text())["ate_rmse_m"] == pytest.approx(m_api["eval"]["ate_rmse_m"])


def test_rerun_works_on_a_run_saved_from_python(seqs, tmp_path):
    pytest.importorskip("rerun", reason="rerun-sdk (the `viz` extra) is not installed")
    slam = ss.Slam.from_sequence(ss.open_sequence(seqs[0]), tracker="dense")
    for frame in slam.sequence:
        slam.track(frame)
    api = slam.finish().save(tmp_path / "api")
    res = runner.invoke(app, ["rerun", str(api), "--images-every", "4"])
    assert res.exit_code == 0, res.output
    assert "8 poses" in res.output and "2 image pairs" in res.output and "note:" not in res.output


@pytest.mark.parametrize("localize_only", [False, True])
def test_a_map_in_which_nothing_localises_ends_as_a_normal_run(seqs, tmp_path, localize_only):
    room, office = seqs
    first = tmp_path / "first"
    res = runner.invoke(app, ["run", str(room), "--tracker", "dense", "-o", str(first), "--no-figures",
                              "--no-progress"])
    assert res.exit_code == 0, res.output
    out = tmp_path / "second"
    args = ["run", str(office), "--tracker", "dense", "--map", str(first), "-o", str(out), "--no-progress"]
    res = runner.invoke(app, args + (["--localize-only"] if localize_only else []))
    assert res.exit_code == 0, res.output
    assert "not localised in the loaded map in 6 frames" in " ".join(res.output.split())
    assert "trajectory.txt is empty" in " ".join(res.output.split())
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["complete"] is True and metrics["poses_written"] == 0 and metrics["frames_processed"] == 6
    assert metrics["prior_map"]["localised"] is False and "eval" not in metrics
    assert (out / "trajectory.txt").read_text() == "# timestamp tx ty tz qx qy qz qw\n"
    assert not [p for p in out.iterdir() if p.name.startswith(STAGING_PREFIX)]
    # every frame without a pose is reported with its reason: in metrics.json, and one summary line each (the first 5)
    assert [u["frame"] for u in metrics["unposed"]] == list(range(6))
    assert {u["reason"] for u in metrics["unposed"]} == {"not_localised_in_map"}
    assert sum(line.startswith("unposed frame ") for line in res.output.splitlines()) == 5
    assert "1 more unposed frames" in " ".join(res.output.split())


def test_keyframes_and_kitti_poses_beside_the_trajectory(seqs, tmp_path):
    out = tmp_path / "run"
    res = runner.invoke(app, ["run", str(seqs[0]), "--tracker", "hybrid", "-o", str(out), "--no-figures",
                              "--no-progress", "--format", "kitti"])
    assert res.exit_code == 0, res.output
    lines = (out / "trajectory.txt").read_text().splitlines()
    keyframes = (out / "keyframes.txt").read_text().splitlines()
    saved = read_map_file(out / "map.npz").keyframes
    assert len(keyframes) - 1 == len(saved.timestamp) >= 1  # the header, then one line per keyframe
    assert set(keyframes) <= set(lines)  # a keyframe's line is its line of trajectory.txt
    traj = read_tum(out / "trajectory.txt")
    kitti = read_kitti(out / "trajectory_kitti.txt")
    assert kitti.shape == traj.T_world_cam.shape == (8, 4, 4)
    np.testing.assert_allclose(kitti, traj.T_world_cam, atol=2e-8)  # the TUM file's 1e-9 quaternions, rounded
    res = runner.invoke(app, ["run", str(seqs[0]), "-o", str(out), "--overwrite", "--format", "g2o"])
    assert res.exit_code == 2 and "--format: unknown g2o; known: tum, kitti" in res.output
    assert (out / "trajectory_kitti.txt").is_file()  # refused before anything was touched
