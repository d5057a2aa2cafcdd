"""Trajectory evaluation: agreement with evo's CLI, alignment invariance, known errors, `surfelslam eval`."""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import typer
from evo.core import metrics as evo_metrics
from typer.testing import CliRunner

from surfelslam.errors import GroundTruthError
from surfelslam.eval import metrics
from surfelslam.geometry.se3 import make_T, so3_exp
from surfelslam.io.trajectory import read_tum, write_tum
from surfelslam.tools import eval as eval_tool
from surfelslam.types import Trajectory

from helpers import shared_sequence

EVO_BIN = Path(sys.executable).parent
RATE_HZ = 30.0


def smooth_gt(duration_s: float = 10.0, t0: float = 1000.0) -> Trajectory:
    """30 Hz smooth helical trajectory with smoothly varying orientation."""
    t = np.arange(0.0, duration_s, 1.0 / RATE_HZ)
    pos = np.column_stack([np.sin(t), 0.3 * np.cos(0.5 * t), 0.2 * t])
    R = np.array([so3_exp(np.array([0.1 * np.sin(x), 0.2 * x, 0.05])) for x in t])
    return Trajectory(t + t0, make_T(R, pos))


def rigid(rotvec, t) -> np.ndarray:
    return make_T(so3_exp(np.asarray(rotvec, dtype=np.float64)), np.asarray(t, dtype=np.float64))


def perturbed_estimate(gt: Trajectory, seed: int = 0) -> Trajectory:
    """Fewer poses, jittered timestamps (< 10 ms), per-pose noise, and a global rigid transform."""
    rng = np.random.default_rng(seed)
    idx = np.sort(rng.choice(len(gt), int(0.7 * len(gt)), replace=False))
    stamps = gt.timestamps[idx] + rng.uniform(-0.009, 0.009, len(idx))
    noise = np.array([rigid(rng.normal(0, 0.01, 3), rng.normal(0, 0.01, 3)) for _ in idx])
    G = rigid([0.3, -0.2, 1.0], [1.0, 2.0, 3.0])
    return Trajectory(stamps, G @ gt.T_world_cam[idx] @ noise)


@pytest.fixture(scope="module")
def traj_files(tmp_path_factory) -> tuple[Path, Path, Trajectory, Trajectory]:
    """GT and estimate written as TUM files and read back (both evo and we see the same numbers)."""
    d = tmp_path_factory.mktemp("traj")
    gt_path, est_path = d / "gt.txt", d / "est.txt"
    write_tum(smooth_gt(), gt_path)
    write_tum(perturbed_estimate(smooth_gt()), est_path)
    return gt_path, est_path, read_tum(gt_path), read_tum(est_path)


def evo_cli_stats(tmp_path: Path, tool: str, gt_path: Path, est_path: Path, *args: str) -> dict:
    out = tmp_path / f"{tool}_{len(list(tmp_path.iterdir()))}.zip"
    exe = EVO_BIN / tool
    if not exe.exists():
        pytest.skip(f"{exe} not installed")
    subprocess.run(
        [str(exe), "tum", str(gt_path), str(est_path), *args, "--save_results", str(out), "--no_warnings",
         "--silent"],
        check=True, capture_output=True, timeout=120,
    )
    with zipfile.ZipFile(out) as zf:
        return json.loads(zf.read("stats.json"))


# ------------------------------------------------------------------------------- agreement with evo CLI
def test_ate_matches_evo_ape_cli(traj_files, tmp_path):
    gt_path, est_path, gt, est = traj_files
    ref = evo_cli_stats(tmp_path, "evo_ape", gt_path, est_path, "-a", "--t_max_diff", "0.02")
    res = metrics.ate(est, gt, max_diff_s=0.02)
    assert res.n_pairs > 0.6 * len(gt)  # most of the estimate was associated
    assert abs(res.rmse_m - ref["rmse"]) < 1e-6
    assert abs(res.mean_m - ref["mean"]) < 1e-6
    assert abs(res.median_m - ref["median"]) < 1e-6
    assert abs(res.max_m - ref["max"]) < 1e-6
    assert abs(res.std_m - ref["std"]) < 1e-6
    assert 0.005 < res.rmse_m < 0.05  # the rigid offset of metres was removed by the alignment


def test_rpe_per_frame_matches_evo_rpe_cli(traj_files, tmp_path):
    gt_path, est_path, gt, est = traj_files
    common = ("--t_max_diff", "0.02", "--delta", "1", "--delta_unit", "f")
    ref_t = evo_cli_stats(tmp_path, "evo_rpe", gt_path, est_path, *common)
    ref_r = evo_cli_stats(tmp_path, "evo_rpe", gt_path, est_path, *common, "-r", "angle_deg")
    res = metrics.rpe(est, gt, delta=1, delta_unit="frames", max_diff_s=0.02)
    assert abs(res.trans_rmse_m - ref_t["rmse"]) < 1e-6
    assert abs(res.trans_mean_m - ref_t["mean"]) < 1e-6
    assert abs(res.rot_rmse_deg - ref_r["rmse"]) < 1e-6
    assert abs(res.rot_mean_deg - ref_r["mean"]) < 1e-6
    assert res.rot_rmse_deg > 0.1  # the injected 0.01 rad rotation noise shows up


# ------------------------------------------------------------------------------------- ATE properties
def test_ate_zero_for_identical_and_invariant_to_rigid_transform():
    gt = smooth_gt()
    assert metrics.ate(gt, gt).rmse_m < 1e-9
    est = perturbed_estimate(gt, seed=1)
    base = metrics.ate(est, gt)
    G = rigid([-1.0, 0.5, 2.0], [-4.0, 7.0, 0.5])
    moved = metrics.ate(Trajectory(est.timestamps, G @ est.T_world_cam), gt)
    assert moved.n_pairs == base.n_pairs
    assert abs(moved.rmse_m - base.rmse_m) < 1e-9
    # exactly-rigidly moved GT is aligned back to zero error, and T_align undoes the motion
    shifted = metrics.ate(Trajectory(gt.timestamps, G @ gt.T_world_cam), gt)
    assert shifted.rmse_m < 1e-9
    np.testing.assert_allclose(shifted.T_align @ G, np.eye(4), atol=1e-9)
    # without alignment the offset stays
    assert metrics.ate(est, gt, align=False).rmse_m > 1.0


def test_ate_known_constant_offset_and_scale():
    gt = smooth_gt()
    d = np.array([0.03, -0.04, 0.0])  # |d| = 0.05 m
    off = gt.T_world_cam.copy()
    off[:, :3, 3] += d
    res = metrics.ate(Trajectory(gt.timestamps, off), gt, align=False)
    np.testing.assert_allclose(res.errors_m, 0.05, atol=1e-12)
    assert abs(res.rmse_m - 0.05) < 1e-12
    assert metrics.ate(Trajectory(gt.timestamps, off), gt).rmse_m < 1e-9  # alignment removes it
    scaled = gt.T_world_cam.copy()
    scaled[:, :3, 3] *= 2.5
    assert metrics.ate(Trajectory(gt.timestamps, scaled), gt, correct_scale=True).rmse_m < 1e-9
    assert metrics.ate(Trajectory(gt.timestamps, scaled), gt).rmse_m > 0.1


def test_ate_isotropic_noise_of_known_rms():
    gt = smooth_gt(duration_s=100.0)  # 3000 poses
    rng = np.random.default_rng(7)
    sigma_m = 0.01
    noisy = gt.T_world_cam.copy()
    noisy[:, :3, 3] += rng.normal(0.0, sigma_m, (len(gt), 3))
    res = metrics.ate(Trajectory(gt.timestamps, noisy), gt)
    expected = sigma_m * np.sqrt(3.0)  # E|e|^2 = 3 sigma^2; the 6-dof fit absorbs only ~6/(3N) of it
    assert abs(res.rmse_m - expected) / expected < 0.03


# ------------------------------------------------------------------------------- association / RPE
def test_association_pairs_within_max_diff():
    gt = smooth_gt()
    est = perturbed_estimate(gt)
    est_s, gt_s = metrics.associate(est, gt, 0.02)
    assert len(est_s) == len(gt_s) == len(est)
    assert np.max(np.abs(est_s.timestamps - gt_s.timestamps)) <= 0.02


def test_too_few_associations_raise_clear_error():
    gt = smooth_gt()
    est = Trajectory(gt.timestamps + 500.0, gt.T_world_cam)
    with pytest.raises(GroundTruthError) as err:
        metrics.ate(est, gt)
    msg = str(err.value)
    assert "0 estimate/ground-truth pose pairs" in msg and "0.02" in msg
    assert f"{len(est)} poses" in msg and "1500.000" in msg and "1000.000" in msg
    with pytest.raises(GroundTruthError, match="only 2"):
        metrics.evaluate(gt.subset(slice(0, 2)), gt)


def test_rpe_per_second_equals_frame_delta_on_uniform_rate():
    gt = smooth_gt()
    rng = np.random.default_rng(3)
    noise = np.array([rigid(rng.normal(0, 0.005, 3), rng.normal(0, 0.005, 3)) for _ in range(len(gt))])
    est = Trajectory(gt.timestamps, gt.T_world_cam @ noise)
    # with a 1 % tolerance only pairs exactly 30 frames apart qualify (the last ones, clamped at the end of
    # the run, are >= 1 frame short); evo with all (overlapping) pairs 30 frames apart is the same set
    per_s = metrics.rpe(est, gt, delta=1.0, delta_unit="seconds", rel_delta_tol=0.01)
    for relation, ours in ((evo_metrics.PoseRelation.translation_part, per_s.trans_rmse_m),
                           (evo_metrics.PoseRelation.rotation_angle_deg, per_s.rot_rmse_deg)):
        ref = evo_metrics.RPE(relation, delta=int(RATE_HZ), delta_unit=evo_metrics.Unit.frames,
                              all_pairs=True)
        est_e, gt_e = metrics.to_evo(est), metrics.to_evo(gt)
        ref.process_data((gt_e, est_e))
        assert per_s.n_pairs == len(ref.error) == len(gt) - int(RATE_HZ)
        assert abs(ours - ref.get_statistic(evo_metrics.StatisticsType.rmse)) < 1e-12


def test_rpe_per_second_pairs_span_one_second_with_dropped_frames():
    gt = smooth_gt()
    keep = np.ones(len(gt), bool)
    keep[100:160] = False  # a 2 s tracking gap
    est = gt.subset(keep)
    res = metrics.rpe(est, gt, delta=1.0, delta_unit="seconds")
    t = est.timestamps
    dt = t[res.pairs[:, 1]] - t[res.pairs[:, 0]]
    assert np.all(np.abs(dt - 1.0) <= 0.1 + 1e-9)
    assert res.trans_rmse_m < 1e-9 and res.rot_rmse_deg < 1e-6
    # a frame-count delta would pair across the gap instead
    assert np.max(np.diff(t)) > 1.0
    with pytest.raises(ValueError, match="no pose pairs"):
        metrics.rpe(gt.subset(slice(0, 20)), gt, delta=1.0, delta_unit="seconds")


def evo_pair_errors(est_sync, gt_sync, pairs) -> tuple[np.ndarray, np.ndarray]:
    """evo's own per-pair RPE (the reference :func:`metrics.relative_pose_errors` stands in for)."""
    from evo.core import lie_algebra as lie

    E = [evo_metrics.RPE.rpe_base(gt_sync.poses_se3[i], gt_sync.poses_se3[j], est_sync.poses_se3[i],
                                  est_sync.poses_se3[j]) for i, j in pairs]
    return (np.array([np.linalg.norm(e[:3, 3]) for e in E]),
            np.array([abs(lie.so3_log_angle(e[:3, :3], True)) for e in E]))


@pytest.mark.parametrize("delta, unit", [(1, "frames"), (3, "frames"), (1.0, "seconds")])
def test_rpe_batched_equals_evo_per_pair(delta, unit):
    """The RPE's pairs computed together equal evo's loop over them: pairs, every error and the statistics, to
    1e-9 (a trajectory with 2 cm / 0.6 deg noise per pose, a 2 s gap, an offset and jittered timestamps)."""
    gt = smooth_gt()
    keep = np.ones(len(gt), bool)
    keep[100:160] = False
    est = perturbed_estimate(gt.subset(keep), seed=4)
    res = metrics.rpe(est, gt, delta=delta, delta_unit=unit)
    est_e, gt_e = evo_sync_pair(est, gt)
    if unit == "frames":
        ref = {}
        for relation in (evo_metrics.PoseRelation.translation_part, evo_metrics.PoseRelation.rotation_angle_deg):
            ref[relation] = evo_metrics.RPE(relation, delta=delta, delta_unit=evo_metrics.Unit.frames)
            ref[relation].process_data((gt_e, est_e))
        ref_t = ref[evo_metrics.PoseRelation.translation_part].error
        ref_r = ref[evo_metrics.PoseRelation.rotation_angle_deg].error
        np.testing.assert_array_equal(res.pairs[:, 1], ref[evo_metrics.PoseRelation.translation_part].delta_ids)
    else:
        ref_t, ref_r = evo_pair_errors(est_e, gt_e, res.pairs)
    assert len(res.pairs) > 50
    np.testing.assert_allclose(res.trans_errors_m, ref_t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.rot_errors_deg, ref_r, rtol=0, atol=1e-9)
    assert abs(res.trans_rmse_m - np.sqrt(np.mean(ref_t ** 2))) < 1e-9
    assert abs(res.rot_rmse_deg - np.sqrt(np.mean(ref_r ** 2))) < 1e-9
    assert res.rot_rmse_deg > 0.1  # the noise is there to be measured


def evo_sync_pair(est: Trajectory, gt: Trajectory):
    """The associated (estimate, ground truth) as evo trajectories, as the evaluation pairs them."""
    from evo.core import sync

    gt_e, est_e = sync.associate_trajectories(metrics.to_evo(gt), metrics.to_evo(est), max_diff=0.02)
    return est_e, gt_e


def test_rpe_refuses_error_rotations_that_are_not_rotations():
    """A pose whose rotation block is scaled (not orthonormal) fails evo's SO(3) check: an EvaluationError."""
    from surfelslam.errors import EvaluationError

    gt = smooth_gt(duration_s=2.0)
    bad = gt.T_world_cam.copy()
    bad[10, :3, :3] *= 1.01
    with pytest.raises(EvaluationError, match="not a rotation"):
        metrics.rpe(Trajectory(gt.timestamps, bad), gt)


def test_evaluate_dict_is_json_serialisable(traj_files):
    _, _, gt, est = traj_files
    res = metrics.evaluate(est, gt)
    text = json.dumps(res)
    back = json.loads(text)
    for key in ("ate_rmse_m", "ate_mean_m", "ate_median_m", "ate_max_m", "rpe_trans_rmse_m_per_frame",
                "rpe_rot_rmse_deg_per_frame", "rpe_trans_rmse_m_per_s", "rpe_rot_rmse_deg_per_s"):
        assert isinstance(back[key], float) and back[key] > 0
    assert back["n_est"] == len(est) and back["n_gt"] == len(gt) and back["n_pairs"] == len(est)


# ------------------------------------------------------------------------------------------------ CLI
@pytest.fixture
def cli() -> typer.Typer:
    app = typer.Typer()
    eval_tool.register(app)

    @app.command("noop")  # a second command keeps typer in multi-command mode, as in surfelslam.cli
    def noop() -> None:
        pass

    return app


def test_cli_writes_plots_and_json(cli, traj_files, tmp_path):
    gt_path, est_path, gt, est = traj_files
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["eval", str(est_path), str(gt_path), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "ATE RMSE" in r.output
    for name in ("eval_trajectory.png", "eval_ate_errors.png"):  # names `run` never writes
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    saved = json.loads((out / "eval.json").read_text())
    assert abs(saved["ate_rmse_m"] - metrics.ate(est, gt).rmse_m) < 1e-12
    assert not list(out.glob(".*.tmp"))  # no temp files left behind
    r = CliRunner().invoke(cli, ["eval", str(est_path), str(gt_path), "--out", str(tmp_path / "np"),
                                 "--no-plots"])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (tmp_path / "np").iterdir()) == ["eval.json"]


def test_cli_bad_input_exit_2_one_line(cli, traj_files, tmp_path):
    gt_path, est_path, gt, _ = traj_files
    bad = tmp_path / "bad.txt"
    bad.write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 oops 0 0 0 1\n")
    far = tmp_path / "far.txt"
    write_tum(Trajectory(gt.timestamps + 500.0, gt.T_world_cam), far)
    cases = [
        ([str(tmp_path / "missing.txt"), str(gt_path)], "missing.txt"),
        ([str(bad), str(gt_path)], "bad.txt: line 2"),
        ([str(far), str(gt_path)], "far.txt"),
        ([str(est_path), str(tmp_path / "nogt")], "nogt"),
    ]
    for args, needle in cases:
        r = CliRunner().invoke(cli, ["eval", *args, "--no-plots", "--out", str(tmp_path / "o")])
        assert r.exit_code == 2, (args, r.output)
        lines = [ln for ln in r.output.splitlines() if ln.strip()]
        assert len(lines) == 1 and needle in lines[0], r.output
    empty = tmp_path / "emptyseq"
    empty.mkdir()
    r = CliRunner().invoke(cli, ["eval", str(est_path), str(empty), "--no-plots"])
    assert r.exit_code == 2 and "emptyseq" in r.output


def test_cli_gt_from_sequence_folder(cli, tmp_path):
    seq = shared_sequence("7scenes_redkitchen_0000_0499")
    gt = read_tum(seq / "groundtruth.txt")
    est_path = tmp_path / "est.txt"
    write_tum(Trajectory(gt.timestamps, rigid([0.1, 0.2, 0.3], [1, 2, 3]) @ gt.T_world_cam), est_path)
    r = CliRunner().invoke(cli, ["eval", str(est_path), str(seq), "--no-plots"])
    assert r.exit_code == 0, r.output
    saved = json.loads((tmp_path / "eval.json").read_text())
    assert saved["n_pairs"] == len(gt) and saved["ate_rmse_m"] < 1e-5
