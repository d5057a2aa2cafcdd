"""`surfelslam run`: outputs, mapping with given poses, kill safety, bad frames, determinism."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from surfelslam.api import run_sequence
from surfelslam.cli import app
from surfelslam.config import load_toml
from surfelslam.datasets import DatasetOptions, open_sequence
from surfelslam.io.ply import read_ply
from surfelslam.io.run_folder import staging_path
from surfelslam.io.trajectory import read_tum, write_tum
from surfelslam.slam import SlamConfig
from surfelslam.synth.scenes import make_scene
from surfelslam.synth.writer import generate_sequence

pytestmark = pytest.mark.slow  # whole sequences through trackers or commands

runner = CliRunner()


@pytest.fixture(scope="module")
def synth_seq(tmp_path_factory):
    """24 noisy frames of the 'room' scene at 320x240, hand-held motion."""
    out = tmp_path_factory.mktemp("seq") / "room"
    generate_sequence(out, scene="room", style="handheld", n_frames=24, noise="kinect", seed=3, width=320,
                      height=240)
    return out


def _traj_rows(path):
    return [ln for ln in path.read_text().splitlines() if ln and not ln.startswith("#")]


def test_run_with_gt_poses_writes_every_output_and_map_lies_on_the_true_surfaces(synth_seq, tmp_path):
    out = tmp_path / "run"
    res = runner.invoke(app, ["run", str(synth_seq), "--out", str(out), "--poses", "gt", "--no-progress"])
    assert res.exit_code == 0, res.output
    for name in ("trajectory.txt", "map.ply", "config.toml", "metrics.json", "trajectory.png", "map_top.png",
                 "map_camera.png"):
        assert (out / name).is_file(), name
    assert len(_traj_rows(out / "trajectory.txt")) == 24
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames_processed"] == 24
    assert metrics["eval"]["ate_rmse_m"] < 1e-6  # the trajectory written is the one used
    assert metrics["map_points"] > 0
    assert metrics["compression_ratio"] == pytest.approx(metrics["map_points"] / (24 * 320 * 240))
    assert isinstance(load_toml(SlamConfig, out / "config.toml"), SlamConfig)

    ply = read_ply(out / "map.ply")
    xyz = np.stack([ply["x"], ply["y"], ply["z"]], axis=1).astype(np.float64)
    assert len(xyz) == metrics["map_points"]
    dist = make_scene("room", seed=3).distance_to_surface(xyz)
    stable = ply["confidence"] >= SlamConfig().fusion.stable_min_confidence
    assert stable.mean() > 0.3
    assert np.percentile(dist[stable], 99) < 0.01  # stable surfels within 1 cm of the true surfaces
    assert np.median(dist) < 0.003


def test_figure_kinds_chosen_one_by_one(synth_seq, tmp_path):
    out = tmp_path / "run"
    res = runner.invoke(app, ["run", str(synth_seq), "--out", str(out), "--poses", "gt", "--no-progress", "--end",
                              "6", "--figure", "trajectory", "--figure", "map_top"])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in out.glob("*.png")) == ["map_top.png", "trajectory.png"]
    res = runner.invoke(app, ["run", str(synth_seq), "--out", str(tmp_path / "bad"), "--figure", "map_side"])
    assert res.exit_code == 2 and "--figure: unknown map_side" in res.output
    assert not (tmp_path / "bad").exists()  # refused before anything was written


def test_given_trajectory_file_skips_frames_without_a_pose(synth_seq, tmp_path):
    gt = open_sequence(synth_seq).ground_truth
    keep = np.arange(len(gt)) % 2 == 0
    poses = tmp_path / "half.txt"
    write_tum(gt.subset(keep), poses)
    out = tmp_path / "run"
    res = runner.invoke(app, ["run", str(synth_seq), "--out", str(out), "--poses", str(poses), "--no-progress",
                              "--no-figures"])
    assert res.exit_code == 0, res.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames_processed"] == keep.sum()
    assert metrics["frames_skipped"] == (~keep).sum()
    written = read_tum(out / "trajectory.txt")
    assert np.allclose(written.T_world_cam, gt.T_world_cam[keep], atol=1e-6)


def test_killed_run_keeps_every_finished_frame_in_its_staging_folder(synth_seq, tmp_path, monkeypatch):
    import surfelslam.slam.given as pipeline

    calls = {"n": 0}
    real = pipeline.GivenPoseMapper.process

    def dying(self, frame, prepared=None, T_world_cam=None):
        if calls["n"] == 7:
            raise KeyboardInterrupt
        calls["n"] += 1
        return real(self, frame, prepared=prepared, T_world_cam=T_world_cam)

    monkeypatch.setattr(pipeline.GivenPoseMapper, "process", dying)
    seq = open_sequence(synth_seq)
    with pytest.raises(KeyboardInterrupt):
        run_sequence(seq, tmp_path / "run", SlamConfig(), "dense", poses="gt", progress=False, figures=False)
    assert not (tmp_path / "run" / "trajectory.txt").exists()  # nothing handed over
    traj = read_tum(staging_path(tmp_path / "run") / "trajectory.txt")
    assert len(traj) == 7
    assert np.allclose(traj.T_world_cam, seq.ground_truth.T_world_cam[:7], atol=1e-6)


def test_corrupt_frame_is_skipped_and_reported(synth_seq, tmp_path):
    seq_dir = tmp_path / "seq"
    shutil.copytree(synth_seq, seq_dir)
    bad = sorted((seq_dir / "depth").iterdir())[5]
    bad.write_bytes(b"not a png at all")
    out = tmp_path / "run"
    res = runner.invoke(app, ["run", str(seq_dir), "--out", str(out), "--poses", "gt", "--no-progress",
                              "--no-figures", "--end", "10"])
    assert res.exit_code == 0, res.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames_skipped"] == 1 and metrics["frames_processed"] == 9
    assert bad.name in metrics["skipped"][0]["reason"]
    assert bad.name in res.output


def test_run_bad_input_is_one_line(tmp_path):
    res = runner.invoke(app, ["run", str(tmp_path / "missing"), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2
    assert "missing" in res.output and "Traceback" not in res.output
    res = runner.invoke(app, ["run", str(tmp_path), "--tracker", "magic"])
    assert res.exit_code == 2 and "--tracker" in res.output
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[icp]\nbogus = 1\n")
    res = runner.invoke(app, ["run", str(tmp_path), "--config", str(cfg)])
    assert res.exit_code == 2 and "bogus" in res.output
    # the message keeps its [section] name (rich markup used to swallow it) and names the file
    cfg.write_text("[sparse.loop]\nmin_consistent_matches = -1\n")
    res = runner.invoke(app, ["run", str(tmp_path), "--config", str(cfg)])
    assert res.exit_code == 2
    assert f"{cfg}: config: [sparse.loop] min_consistent_matches must be " in res.output
    assert "got -1" in res.output


def test_config_file_overrides_defaults(synth_seq, tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[fusion]\ndist_diff_m = 0.01\nweight_mode = \"constant\"\n")
    out = tmp_path / "run"
    res = runner.invoke(app, ["run", str(synth_seq), "--out", str(out), "--poses", "gt", "--no-progress",
                              "--no-figures", "--config", str(cfg), "--end", "4"])
    assert res.exit_code == 0, res.output
    saved = load_toml(SlamConfig, out / "config.toml")
    assert saved.fusion.dist_diff_m == 0.01 and saved.fusion.weight_mode == "constant"


def test_downsample_option_changes_resolution(synth_seq, tmp_path):
    seq = open_sequence(synth_seq, DatasetOptions(downsample=2, end=3))
    m = run_sequence(seq, tmp_path / "r", SlamConfig(), "dense", poses="gt", progress=False, figures=False)
    assert m["resolution"] == [160, 120]
