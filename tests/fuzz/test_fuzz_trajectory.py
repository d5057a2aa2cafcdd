"""Fuzzing the trajectory files ``surfelslam eval`` reads (TUM ``timestamp tx ty tz qx qy qz qw``): mutated and random
files through the reader, and pairs of them through the evaluation (``run_eval``, figures off). A valid result is a
trajectory of finite rigid poses in time order, and finite metrics; ``eval`` writes only into its output folder."""

from __future__ import annotations

import json
import math

import numpy as np
from fuzzkit import check_trajectory, example_dir, is_error, outcome, text_or_bytes, tree, unchanged
from hypothesis import example, given
from hypothesis import strategies as st

from surfelslam.eval.metrics import evaluate_all
from surfelslam.io.trajectory import read_tum
from surfelslam.tools.eval import EVAL_FILES, run_eval

#: poses of the seed trajectories, their first stamp and period [s]
N_POSES, T0_S, DT_S = 24, 1305031102.0, 0.1


def seed_text(noise_m: float = 0.0, seed: int = 0) -> str:
    """A TUM trajectory on a curve with turning orientation (not degenerate for the alignment)."""
    rng = np.random.default_rng(seed)
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for k in range(N_POSES):
        a = 0.2 * k
        p = np.array([np.cos(a), np.sin(a), 0.05 * k]) + rng.normal(0, noise_m, 3) * (noise_m > 0)
        q = np.array([0.0, 0.0, np.sin(a / 4), np.cos(a / 4)])
        lines.append(f"{T0_S + DT_S * k:.6f} " + " ".join(f"{x:.6f}" for x in (*p, *q)))
    return "\n".join(lines) + "\n"


GT_TEXT, EST_TEXT = seed_text(), seed_text(0.01, seed=1)


def check_summary(res: dict) -> None:
    for key in ("ate_rmse_m", "ate_mean_m", "ate_max_m", "rpe_trans_rmse_m_per_frame", "rpe_rot_rmse_deg_per_frame"):
        assert math.isfinite(res[key]) and res[key] >= 0, f"{key} = {res[key]}"
    assert res["n_pairs"] >= 3
    json.dumps(res, allow_nan=False)


def test_seeds_evaluate(tmp_path):
    (tmp_path / "est.txt").write_text(EST_TEXT)
    (tmp_path / "gt.txt").write_text(GT_TEXT)
    res = run_eval(tmp_path / "est.txt", tmp_path / "gt.txt", tmp_path / "out", 0.02, plots=False)
    check_summary(res)
    assert res["n_pairs"] == N_POSES and 0.001 < res["ate_rmse_m"] < 0.05


@given(content=text_or_bytes(EST_TEXT))
@example(content=b"1 0 0 0 0 0 0 1\n1e308 0 0 0 0 0 0 1\n-1e308 0 0 0 0 0 0 1\n")
@example(content=b"0 0 0 0 1e200 1e200 0 0\n1 0 0 0 1e-200 0 0 0\n")
def test_mutated_trajectory_file(tmp_path, content):
    path = example_dir(tmp_path) / "traj.txt"
    path.write_bytes(content)
    with unchanged(path.parent):
        traj = outcome(lambda: read_tum(path))
    if not is_error(traj):
        check_trajectory(traj)


@given(content=st.one_of(st.binary(max_size=300), st.text(max_size=300).map(str.encode)))
def test_random_trajectory_file(tmp_path, content):
    path = example_dir(tmp_path) / "traj.txt"
    path.write_bytes(content)
    traj = outcome(lambda: read_tum(path))
    if not is_error(traj):
        check_trajectory(traj)


@given(est=text_or_bytes(EST_TEXT), gt=text_or_bytes(GT_TEXT), which=st.sampled_from(("est", "gt", "both")),
       max_diff_s=st.one_of(st.just(0.02), st.floats()))
def test_eval_of_mutated_files(tmp_path, est, gt, which, max_diff_s):
    """``surfelslam eval EST GT --out OUT --no-figures`` as a library call: metrics or one line, files only in OUT."""
    folder = example_dir(tmp_path)
    (folder / "est.txt").write_bytes(est if which != "gt" else EST_TEXT.encode())
    (folder / "gt.txt").write_bytes(gt if which != "est" else GT_TEXT.encode())
    before = tree(folder)
    res = outcome(lambda: run_eval(folder / "est.txt", folder / "gt.txt", folder / "out", max_diff_s, plots=False))
    written = {k for k in tree(folder) if k not in before}
    if is_error(res):
        assert written <= {"out"}, written
        return
    check_summary(res)
    assert written == {"out", f"out/{EVAL_FILES['json']}"}, written


@given(est=text_or_bytes(EST_TEXT))
@example(est=EST_TEXT.replace(" 1.003456 ", " 1e155 ", 1).encode())  # found: overflow warnings
def test_metrics_of_parsed_trajectories(tmp_path, est):
    """Whatever the reader accepts, the metrics are finite or one line (evo's own errors included)."""
    path = example_dir(tmp_path) / "est.txt"
    path.write_bytes(est)
    traj = outcome(lambda: read_tum(path))
    if is_error(traj):
        return
    gt = read_tum_text(tmp_path, GT_TEXT)
    res = outcome(lambda: evaluate_all(traj, gt, 0.02))
    if not is_error(res):
        a, rf, _ = res
        assert np.isfinite(a.rmse_m) and np.isfinite(rf.trans_rmse_m) and np.isfinite(rf.rot_rmse_deg)


def read_tum_text(base, text: str):
    path = example_dir(base) / "t.txt"
    path.write_text(text)
    return read_tum(path)
