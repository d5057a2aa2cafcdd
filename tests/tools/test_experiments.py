"""``surfelslam experiments``: every section is written, figures exist, numbers equal the library's."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from typer.testing import CliRunner

from surfelslam.cli import app
from surfelslam.datasets import open_sequence
from surfelslam.datasets.base import DatasetOptions
from surfelslam.experiments import (
    FEATURES_SETTING,
    SECTION_TITLES,
    ExperimentOptions,
    choose_pairs,
    feature_pair,
    icp_settings,
    section_trajectories,
)
from surfelslam.slam import TRACKERS, SlamConfig
from surfelslam.tracking.features import FeatureConfig

# whole sequences through trackers or commands; the tests share a module fixture, so they run on one worker
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("experiments")]

FRAMES = 10
GAPS = (10, 20)
START = 10


@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    from surfelslam.synth.writer import generate_sequence

    root = tmp_path_factory.mktemp("exp")
    seq_dir = generate_sequence(root / "seq", scene="room", style="handheld", n_frames=60, noise="kinect", seed=1,
                                width=160, height=120)
    out = root / "out"
    r = CliRunner().invoke(app, ["experiments", str(seq_dir), "--out", str(out), "--frames", str(FRAMES),
                                 "--pair-gaps", ",".join(map(str, GAPS)), "--pair-start", str(START),
                                 "--downsample", "1", "--no-progress"])
    assert r.exit_code == 0, r.output
    return seq_dir, out, (out / "report.md").read_text()


def _section(report: str, k: int) -> str:
    start = report.index(SECTION_TITLES[k])
    end = report.index(SECTION_TITLES[k + 1]) if k + 1 < len(SECTION_TITLES) else len(report)
    return report[start:end]


def _row(text: str, *cells: str) -> list[str]:
    """Cells of the first table row whose leading cells are ``cells``."""
    for line in text.splitlines():
        parts = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and parts[: len(cells)] == list(cells):
            return parts
    raise AssertionError(f"no row starting with {cells}")


def test_sections_in_order_and_figures_exist(experiment):
    _, out, report = experiment
    pos = [report.index(t) for t in SECTION_TITLES]
    assert pos == sorted(pos)
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report)
    assert len(links) >= 2 * 4 + 2 + 2 + 1 + 1
    for link in links:
        assert (out / link).is_file(), link
    for s, t in [(START, START + g) for g in GAPS]:
        assert (out / f"icp_{s}_{t}_before.png").is_file()
    assert (out / "features_matches.png").is_file() and (out / "trajectories.png").is_file()
    for d in ("gt_poses", "dense"):
        assert (out / "runs" / d / "map_top.png").is_file() and (out / "runs" / d / "map_camera.png").is_file()
    # the runs write the figures the report links, and no other
    written = {p.relative_to(out).as_posix() for p in (out / "runs").rglob("*.png")}
    assert written == {link for link in links if link.startswith("runs/")}, written


def test_a_run_refuses_unknown_figure_names_before_writing(experiment, tmp_path):
    from surfelslam.api import run_sequence
    from surfelslam.errors import ConfigError
    from surfelslam.viz.run_report import RUN_FIGURES

    seq_dir, _, _ = experiment
    with pytest.raises(ConfigError, match="figures: unknown map_side; known: ate_errors, map_camera"):
        run_sequence(open_sequence(seq_dir, DatasetOptions(end=2)), tmp_path / "r", SlamConfig(), "dense",
                     progress=False, figures=("map_camera", "map_side"))
    assert not (tmp_path / "r").exists() and "map_top" in RUN_FIGURES


def test_fusion_numbers_match_run_sequence(experiment, tmp_path):
    from surfelslam.api import run_sequence

    seq_dir, out, report = experiment
    seq_runs = open_sequence(seq_dir, DatasetOptions(end=FRAMES))
    m = run_sequence(seq_runs, tmp_path / "gt", SlamConfig(), "dense", poses="gt", progress=False, figures=False)
    row = _row(_section(report, 2), "ground-truth poses")
    assert int(row[1]) == FRAMES == m["frames_processed"]
    assert int(row[2]) == m["map_points"]
    assert row[3] == f"{100 * m['map_points'] / (FRAMES * 160 * 120):.2f}%"
    res = json.loads((out / "results.json").read_text())
    assert res["fusion"]["ground-truth poses"]["map_points"] == m["map_points"]
    # the dense-pose map is in the same range as the GT map on this easy synthetic sequence
    dense = int(_row(_section(report, 2), "dense tracker poses")[2])
    assert 0.8 * m["map_points"] < dense < 1.2 * m["map_points"]


def test_icp_rows_match_library(experiment):
    from surfelslam.geometry import se3
    from surfelslam.tracking.icp import icp
    from surfelslam.tracking.preprocess import PreprocessConfig, Preprocessor

    seq_dir, _, report = experiment
    seq = open_sequence(seq_dir, DatasetOptions())
    T_wc, _ = seq.gt_poses()
    sec = _section(report, 0)
    s, t = START, START + GAPS[1]
    pre = Preprocessor(seq.intrinsics, PreprocessConfig())
    src, tgt = pre.process(seq[s].depth_m), pre.process(seq[t].depth_m)
    T_gt = se3.invert(T_wc[t]) @ T_wc[s]
    for name, cfg in icp_settings():
        r = icp(src, tgt, None, cfg)
        motion = _row(sec, f"{s}->{t}")[1]
        row = _row(sec, f"{s}->{t}", motion, name)
        assert int(row[3]) == r.inliers
        assert row[4].startswith(f"{1000 * r.rmse_m:.2f} ")
        assert int(row[5]) == r.iterations
        e_t, e_r = se3.pose_error(r.T_target_source, T_gt)
        assert row[7] == f"{1000 * e_t:.1f}, {e_r:.2f}"
    # the defaults recover this 20-frame synthetic pair to a few mm
    res = json.loads((experiment[1] / "results.json").read_text())
    default = [x for x in res["icp_pairs"] if x["setting"] == "coarse-to-fine defaults"]
    assert len(default) == len(GAPS) and all(x["err_trans_m"] < 0.01 for x in default)
    feat = [x for x in res["icp_pairs"] if x["setting"] == FEATURES_SETTING]
    assert len(feat) == len(GAPS) and all(x["start"] == "features" and x["err_trans_m"] < 0.01 for x in feat)
    assert f"| {FEATURES_SETTING} (features) |" in sec and "icp_" in sec


def test_solvers_agree(experiment):
    _, out, report = experiment
    res = json.loads((out / "results.json").read_text())["solvers"]
    assert set(res["solutions"]) == {"cholesky", "lu", "qr (explicit A, b)", "qr (6x6 normal matrix)", "pinv"}
    assert res["max_pairwise_diff"] < 1e-9
    assert res["n_rows"] > 1000
    assert f"N = {res['n_rows']} rows" in _section(report, 1)


def test_feature_numbers_match_library(experiment):
    seq_dir, _, report = experiment
    seq = open_sequence(seq_dir, DatasetOptions())
    r = feature_pair(seq, START, START + GAPS[0], FeatureConfig())
    sec = _section(report, 4)
    assert _row(sec, f"keypoints in frame {START} / {START + GAPS[0]}")[1] == f"{len(r['fa'])} / {len(r['fb'])}"
    assert int(_row(sec, "matches before the distance filter")[1]) == r["raw"].n_raw
    assert int(_row(sec, "matches after the distance filter")[1]) == r["good"].n_good
    assert int(_row(sec, "PnP inliers")[1]) == r["motion"].n_inliers
    assert r["kept"].sum() == r["good"].n_good and len(r["kept"]) == r["raw"].n_raw
    assert r["good"].n_good < r["raw"].n_raw  # the filter rejected some


def test_every_tracker_ran(experiment):
    _, _, report = experiment
    sec = _section(report, 5)
    for name in TRACKERS:
        row = _row(sec, name)
        assert row[1] == "ran"
        assert float(row[4]) < 2.0  # ATE in cm over 10 easy synthetic frames


def test_dormant_rows(experiment):
    _, _, report = experiment
    sec = _section(report, 3)
    assert _row(sec, "off")[1].isdigit()
    assert "the reference assignment's values" in sec


def test_choose_pairs_scales_to_short_selections():
    assert choose_pairs(500, 10, (40, 90)) == ([(10, 50), (10, 100)], False)
    pairs, scaled = choose_pairs(60, 10, (40, 90))
    assert scaled and all(0 <= s < t < 60 for s, t in pairs) and pairs[0][1] < pairs[-1][1]
    assert choose_pairs(1, 10, (40,)) == ([], False)


def test_trajectories_without_ground_truth_say_so(tmp_path):
    lines, out = section_trajectories(None, tmp_path, SlamConfig(), ExperimentOptions(), {}, has_gt=False)
    text = "\n".join(lines)
    assert "no ground truth" in text and out == {}
    for name in TRACKERS:
        assert name in text
    assert not any(tmp_path.iterdir())  # nothing was run


@pytest.mark.heavy  # make test-all (a second experiments run); make test covers the report with ground truth
def test_sequence_without_ground_truth(tmp_path):
    """A short selection without ground truth: pairs are scaled down, GT sections say so, nothing fails."""
    from surfelslam.synth.writer import generate_sequence

    seq_dir = generate_sequence(tmp_path / "seq", scene="room", style="handheld", n_frames=12, noise="kinect",
                                seed=2, width=160, height=120)
    (seq_dir / "groundtruth.txt").unlink()
    out = tmp_path / "out"
    r = CliRunner().invoke(app, ["experiments", str(seq_dir), "--out", str(out), "--frames", "3",
                                 "--downsample", "1", "--no-progress"])
    assert r.exit_code == 0, r.output
    report = (out / "report.md").read_text()
    for title in SECTION_TITLES:
        assert title in report
    res = json.loads((out / "results.json").read_text())
    assert not res["has_ground_truth"]
    assert all(0 <= s < t < 12 for s, t in res["pairs"]) and len(res["pairs"]) == 2
    assert "This sequence has no ground truth: the error columns are n/a" in _section(report, 0)
    assert _row(_section(report, 2), "ground-truth poses")[1].startswith("not available")
    assert "Not available: this sequence has no ground truth" in _section(report, 5)
    assert _row(_section(report, 4), "error vs GT (mm, deg)")[1] == "n/a (no ground truth)"


def test_solver_section_reports_singular_systems():
    """A single plane leaves rotation about its normal and in-plane translation unconstrained: solvers fail."""
    from surfelslam.experiments import section_solvers
    from surfelslam.tracking.preprocess import FramePyramid, PyramidLevel
    from surfelslam.types import Intrinsics

    intr = Intrinsics(100.0, 100.0, 40.0, 30.0, 80, 60)
    u, v = np.meshgrid(np.arange(80), np.arange(60))
    vert = np.stack([(u - 40) / 50.0, (v - 30) / 50.0, np.full(u.shape, 2.0)], axis=-1).astype(np.float32)
    normal = np.zeros_like(vert)
    normal[..., 2] = -1.0
    p = FramePyramid([PyramidLevel(vert, normal, intr)])
    lines, r = section_solvers({(0, 1): (p, p)}, [(0, 1)])
    text = "\n".join(lines)
    assert r["n_rows"] == 80 * 60
    assert _row(text, "cholesky")[1] == "failed (singular system)"
    assert np.allclose(r["solutions"]["pinv"], 0.0)

    empty = FramePyramid([PyramidLevel(np.zeros_like(vert), np.zeros_like(vert), intr)])
    lines, r = section_solvers({(0, 1): (empty, empty)}, [(0, 1)])
    assert r["n_rows"] == 0 and "Not available" in "\n".join(lines)
