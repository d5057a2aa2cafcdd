"""`surfelslam rerun`: a run as a Rerun recording (world frame, contents read back with Rerun's own CLI)."""

from __future__ import annotations

import builtins
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from surfelslam.cli import app
from surfelslam.geometry import se3
from surfelslam.synth.writer import generate_sequence
from surfelslam.types import Trajectory
from surfelslam.viz.rerun_export import build_scene

# whole sequences through trackers or commands; the tests share a module fixture, so they run on one worker
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("rerun_export")]

runner = CliRunner()


def _random_poses(n: int, rng: np.random.Generator) -> np.ndarray:
    return np.stack([se3.exp(np.r_[rng.normal(0, 0.3, 3), rng.normal(0, 0.2, 3)]) for _ in range(n)])


def test_scene_is_put_in_the_ground_truth_frame():
    """An estimate that is the ground truth seen from another world frame: after the ATE alignment the poses,
    the map points and the loop-edge end points land on the ground truth's, and the per-pose ATE is zero."""
    rng = np.random.default_rng(0)
    stamps = np.arange(12) / 30.0
    T_gt = _random_poses(12, rng)
    T_est_gt = se3.exp(np.array([0.4, -0.2, 1.0, 0.3, -0.5, 0.2]))  # world_est <- world_gt
    est = Trajectory(stamps, T_est_gt @ T_gt)
    pts_gt = rng.normal(0, 1, (50, 3))
    pts_est = pts_gt @ T_est_gt[:3, :3].T + T_est_gt[:3, 3]
    verts = {"x": pts_est[:, 0], "y": pts_est[:, 1], "z": pts_est[:, 2],
             "red": np.full(50, 10, np.uint8), "green": np.full(50, 20, np.uint8), "blue": np.full(50, 30, np.uint8),
             "radius": np.full(50, 0.01, np.float32)}
    scene = build_scene(est, verts, [(stamps[2], stamps[9])], Trajectory(stamps, T_gt))
    np.testing.assert_allclose(scene.T_world_run, se3.invert(T_est_gt), atol=1e-9)
    np.testing.assert_allclose(scene.trajectory.T_world_cam, T_gt, atol=1e-9)
    np.testing.assert_allclose(scene.points_xyz, pts_gt, atol=1e-5)
    assert scene.points_rgb.tolist()[0] == [10, 20, 30] and scene.points_radius_m[0] == pytest.approx(0.01)
    np.testing.assert_allclose(scene.ate_errors_m, 0.0, atol=1e-9)
    np.testing.assert_allclose(scene.loop_edges, [[T_gt[2][:3, 3], T_gt[9][:3, 3]]], atol=1e-9)


def test_scene_of_a_run_that_never_moved_is_aligned_at_the_first_pose():
    """Every estimated pose at one place (tracking lost throughout, as on frames 300 apart): Umeyama is degenerate,
    so the first poses are made to coincide instead of failing."""
    rng = np.random.default_rng(2)
    stamps = np.arange(6) / 30.0
    T_gt = _random_poses(6, rng)
    T0 = se3.exp(np.array([1.0, 2.0, 3.0, 0.1, 0.2, 0.3]))
    scene = build_scene(Trajectory(stamps, np.repeat(T0[None], 6, axis=0)), None, [], Trajectory(stamps, T_gt))
    assert scene.alignment == "origin"
    np.testing.assert_allclose(scene.trajectory.T_world_cam, np.repeat(T_gt[:1], 6, axis=0), atol=1e-9)
    assert scene.ate_errors_m[0] == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(scene.ate_errors_m[1:], np.linalg.norm(T_gt[1:, :3, 3] - T_gt[0, :3, 3], axis=1),
                               atol=1e-9)
    two = build_scene(Trajectory(stamps[:2], T_gt[:2]), None, [], Trajectory(stamps, T_gt))
    assert two.alignment == "none" and two.ground_truth is None and two.ate_errors_m is None


def test_scene_without_ground_truth_keeps_the_run_frame():
    rng = np.random.default_rng(1)
    est = Trajectory(np.arange(5) / 30.0, _random_poses(5, rng))
    scene = build_scene(est, None, [])
    np.testing.assert_array_equal(scene.trajectory.T_world_cam, est.T_world_cam)
    assert scene.ground_truth is None and scene.ate_errors_m is None
    assert scene.points_xyz.shape == (0, 3) and scene.loop_edges.shape == (0, 2, 3)


def test_missing_rerun_is_one_line(tmp_path, monkeypatch):
    real_import = builtins.__import__

    def no_rerun(name, *args, **kwargs):
        if name == "rerun" or name.startswith("rerun."):
            raise ImportError("no rerun here")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_rerun)
    res = runner.invoke(app, ["rerun", str(tmp_path)])
    assert res.exit_code == 2
    assert "rerun-sdk is not installed" in res.output and "surfelslam[viz]" in res.output
    assert "Traceback" not in res.output


# --- with rerun-sdk (installed by `make test`; the `viz` extra) ---------------------------------------------------

def _rerun_cli() -> Path:
    pytest.importorskip("rerun", reason="rerun-sdk (the `viz` extra) is not installed")
    cli = Path(sys.executable).parent / "rerun"
    if not cli.is_file():
        pytest.skip(f"rerun CLI not found beside {sys.executable}")
    return cli


def _rows_per_entity(cli: Path, rrd: Path) -> dict[str, int]:
    out = subprocess.run([str(cli), "rrd", "print", str(rrd)], capture_output=True, text=True, check=True).stdout
    rows: dict[str, int] = {}
    for m in re.finditer(r"with (\d+) rows .*? - (/\S+) - data columns", out):
        rows[m.group(2)] = rows.get(m.group(2), 0) + int(m.group(1))
    return rows


@pytest.fixture(scope="module")
def loop_run(tmp_path_factory):
    """A run of the default tracker on 40 frames of the synthetic walking loop at 320x240 (one loop edge in
    metrics.json)."""
    base = tmp_path_factory.mktemp("rr")
    seq = base / "loop"
    generate_sequence(seq, scene="office", style="loop", n_frames=40, noise="kinect", seed=1, width=320, height=240)
    out = base / "run"
    res = runner.invoke(app, ["run", str(seq), "--out", str(out), "--no-progress",
                              "--no-figures"])  # the export reads the trajectory, map and metrics, not the figures
    assert res.exit_code == 0, res.output
    return seq, out


def test_recording_holds_map_trajectories_camera_and_images(loop_run):
    cli = _rerun_cli()
    seq, out = loop_run
    res = runner.invoke(app, ["rerun", str(out), "--images-every", "8"])
    assert res.exit_code == 0, res.output
    rrd = out / "run.rrd"
    text = " ".join(res.output.split())
    assert "wrote" in text and "40 poses" in text and "5 image pairs" in text
    subprocess.run([str(cli), "rrd", "verify", str(rrd)], capture_output=True, check=True)
    rows = _rows_per_entity(cli, rrd)
    assert rows["/world/camera"] == 40  # one pose per frame
    assert rows["/plots/ate_m"] == 40  # every pose has ground truth
    assert rows["/world/camera/image/rgb"] == 5 and rows["/world/camera/image/depth"] == 5  # frames 0, 8, ..., 32
    for entity in ("/world/map", "/world/estimate", "/world/ground_truth", "/world/camera/image"):
        assert rows[entity] == 1, entity
    metrics = json.loads((out / "metrics.json").read_text())
    assert len(metrics["loop_edges"]) == metrics["loops_accepted"] >= 1
    assert rows["/world/loops"] == 1 and f"{metrics['loops_accepted']} loop edges" in text
    assert not list(out.glob(".run.rrd.*"))  # no temp file left behind


def test_recording_without_the_sequence_still_has_map_and_trajectory(loop_run, tmp_path):
    cli = _rerun_cli()
    _, out = loop_run
    run2 = tmp_path / "moved"
    run2.mkdir()
    for name in ("trajectory.txt", "map.ply"):
        (run2 / name).write_bytes((out / name).read_bytes())
    metrics = json.loads((out / "metrics.json").read_text())
    metrics["sequence"] = str(tmp_path / "gone")
    (run2 / "metrics.json").write_text(json.dumps(metrics))
    res = runner.invoke(app, ["rerun", str(run2), "--out", str(tmp_path / "x.rrd")])
    assert res.exit_code == 0, res.output
    assert "is not here: pass --seq PATH" in " ".join(res.output.split())
    rows = _rows_per_entity(cli, tmp_path / "x.rrd")
    assert rows["/world/camera"] == 40 and rows["/world/map"] == 1
    assert "/world/ground_truth" not in rows and "/world/camera/image/rgb" not in rows


@pytest.mark.parametrize("case", ["no_folder", "no_trajectory", "bad_metrics", "bad_every", "wrong_downsample"])
def test_bad_input_is_one_line(loop_run, tmp_path, case):
    pytest.importorskip("rerun", reason="rerun-sdk (the `viz` extra) is not installed")
    seq, out = loop_run
    args = {"no_folder": [str(tmp_path / "nope")],
            "no_trajectory": [str(tmp_path)],
            "bad_every": [str(out), "--images-every", "0"],
            "wrong_downsample": [str(out), "--downsample", "2"]}.get(case)
    expect = {"no_folder": "not a folder", "no_trajectory": "trajectory.txt: missing",
              "bad_every": "--images-every must be >= 1", "wrong_downsample": "pass the run's --downsample",
              "bad_metrics": "metrics.json: cannot read the run's metrics"}[case]
    if case == "bad_metrics":
        run2 = tmp_path / "r"
        run2.mkdir()
        (run2 / "trajectory.txt").write_bytes((out / "trajectory.txt").read_bytes())
        (run2 / "metrics.json").write_text("{not json")
        args = [str(run2)]
    res = runner.invoke(app, ["rerun", *args])
    assert res.exit_code == 2, res.output
    assert expect in res.output and "Traceback" not in res.output
    assert len(res.output.strip().splitlines()) == 1


def test_run_with_rerun_flag_writes_the_recording(loop_run, tmp_path):
    """`run --rerun` on a selection (frames 8-31, half resolution) exports it: one camera pose per processed frame,
    images every 10th, and the dataset options kept in metrics.json for a later `surfelslam rerun`."""
    cli = _rerun_cli()
    seq, _ = loop_run
    out = tmp_path / "selection"
    res = runner.invoke(app, ["run", str(seq), "--out", str(out), "--start", "8", "--end", "32", "--downsample", "2",
                              "--no-figures", "--no-progress", "--rerun"])
    assert res.exit_code == 0, res.output
    assert "24 poses" in " ".join(res.output.split()) and "3 image pairs" in " ".join(res.output.split())
    opts = json.loads((out / "metrics.json").read_text())["dataset_options"]
    assert (opts["start"], opts["end"], opts["downsample"]) == (8, 32, 2)
    rows = _rows_per_entity(cli, out / "run.rrd")
    assert rows["/world/camera"] == 24 and rows["/world/camera/image/rgb"] == 3
    # the standalone command re-opens the sequence with the run's options and finds the same frames
    again = runner.invoke(app, ["rerun", str(out), "--out", str(tmp_path / "again.rrd")])
    assert again.exit_code == 0, again.output
    assert "3 image pairs" in " ".join(again.output.split())


def test_unreadable_frame_is_skipped_and_reported(loop_run, tmp_path):
    """A frame that became unreadable since the run is left out of the images and named; the rest is written."""
    import shutil

    cli = _rerun_cli()
    seq, out = loop_run
    seq2 = tmp_path / "seq"
    shutil.copytree(seq, seq2)
    bad = sorted((seq2 / "depth").iterdir())[8]
    bad.write_bytes(b"not a png")
    res = runner.invoke(app, ["rerun", str(out), "--seq", str(seq2), "--images-every", "8", "--out",
                              str(tmp_path / "r.rrd")])
    assert res.exit_code == 0, res.output
    text = " ".join(res.output.split())
    assert f"skippedframe:{bad}:cannotdecode" in "".join(res.output.split())  # rich wraps long paths
    assert "4 image pairs" in text  # 0, 16, 24, 32; frame 8 skipped
    rows = _rows_per_entity(cli, tmp_path / "r.rrd")
    assert rows["/world/camera"] == 40 and rows["/world/camera/image/rgb"] == 4
