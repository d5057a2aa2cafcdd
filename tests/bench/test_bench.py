"""`make bench` (``python -m benchmarks.run_all``) end to end on tiny inputs: the JSON sections and the markdown tables.

A tiny plan (80x60 and 160x120 images, a few frames each) over a temporary "shared data" folder holding a
12-frame generated sequence (stands in for 7-Scenes), a 4-frame one (too short to track) and a folder that is
not a sequence. Open3D is left out (its import alone takes seconds; the side-by-side code is exercised by
``make bench``). The viewer and mesh sections run on their own (``--sections``), spliced into a stand-in result.
"""

from __future__ import annotations

import datetime
import json
import math
from pathlib import Path

import pytest

from benchmarks import run_all  # the repository root is on sys.path (pytest's `pythonpath`)
from surfelslam.synth.writer import generate_sequence

TINY = run_all.Plan(
    "tiny", read_frames=2, orb_pairs=1, icp_pairs=1, icp_reps=1,
    stage_runs=((2, None), (1, 8)), sustained_frames=30, sustained_width=80,
    sustained_window=5, synth_width=80, synth_slow_frames=24, synth_loop_frames=12, open3d_frames_real=0,
    open3d_frames_synth=0, extra_runs=(("orb", "real", 6), ("orb", "slow", 6)), min_frames=8, budget_s=0.0,
    viewer_frames=0, mesh_frames=0,  # run apart below (test_viewer_and_mesh_sections_spliced_into_the_last_results)
    robust_frames=0,  # run apart below (test_robustness_section_spliced_into_the_last_results)
    hires_frames=6, open3d_frames_hires=0,  # the synthetic sequences again at 160x120, 6 frames each
    scale_frames=0,  # tests/bench/test_scale.py
)

# whole sequences through trackers or commands; the tests share a module fixture, so they run on one worker
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("bench")]
# make test-all: the tiny plan's whole bench (about 30 s of one worker, a tenth of the suite's CPU); `make test` keeps
# the tests of the bench's parts below, which need no run of the plan
HEAVY_PLAN = pytest.mark.heavy


@pytest.fixture(scope="module")
def bench(tmp_path_factory) -> tuple[dict, Path]:
    tmp = tmp_path_factory.mktemp("bench")
    shared = tmp / "shared"
    generate_sequence(shared / "tiny_real", style="slow", n_frames=12, width=160, height=120, seed=1)
    generate_sequence(shared / "short", style="slow", n_frames=4, width=160, height=120, seed=2)
    (shared / "junk").mkdir()
    (shared / "junk" / "notes.txt").write_text("not a sequence\n")
    out = tmp / "out"
    res = run_all.run(TINY, out, shared=shared, open3d=False)
    return res, out


@HEAVY_PLAN
def test_json_sections(bench) -> None:
    res, out = bench
    on_disk = json.loads((out / "latest.json").read_text())
    assert set(on_disk) == {"meta", "jit", "stages", "icp", "sustained", "accuracy", "not_tracked", "open3d", "viewer",
                            "mesh", "robustness", "scale", "skipped", "errors"}
    assert on_disk["viewer"] is None and on_disk["mesh"] is None and on_disk["robustness"] is None  # not planned
    assert on_disk["scale"] is None
    assert on_disk["errors"] == [], on_disk["errors"]
    assert on_disk["meta"]["mode"] == "tiny" and on_disk["meta"]["machine"]["cores"] >= 1
    assert on_disk["jit"]["warmup_s"] >= 0.0 and "cache" in on_disk["jit"]
    # stage timings at both resolutions, every stage a positive number; the dense run's metrics.json has them
    assert [r["resolution"] for r in on_disk["stages"]] == ["80x60", "160x120"]
    # one registration: preprocess and ICP timed at both sizes
    icp_rows = {(r["stage"], r["size"]) for r in on_disk["icp"] if r["ms"] > 0.0}
    assert {("preprocess", "320x240"), ("icp 3-level", "320x240"), ("icp default", "640x480")} <= icp_rows
    assert [r["frames"] for r in on_disk["stages"]] == [12, 8]
    for r in on_disk["stages"]:
        for k in ("read_ms", "preprocess_ms", "render_ms", "icp_ms", "fuse_ms", "loop_ms", "fps", "orb_extract_ms",
                  "orb_match_pnp_ms", "read_in_run_ms"):
            assert isinstance(r[k], float) and r[k] > 0.0, (k, r[k])
        assert {"read", "preprocess", "render", "icp", "fuse"} <= set(r["metrics_json_stages"])
        # the ICP stage is timed inside each frame's main-thread time (part <= whole); preprocessing runs in the
        # reader thread, ahead of the frame, so it is not part of the loop (comparing sums of timings was flaky)
        assert r["loop_ms"] >= r["icp_ms"]


@HEAVY_PLAN
def test_sustained(bench) -> None:
    res, out = bench
    s = res["sustained"]
    assert s["frames"] == 30 and s["resolution"] == "80x60" and s["window"] == 5
    assert s["last_over_first"] == pytest.approx(s["cpu_last_ms"] / s["cpu_first_ms"], rel=0.01)
    assert s["flat_cost_ok"] == (s["last_over_first"] <= 1.3)
    assert s["flat_cost_verdict"].startswith("indicative")  # 30 frames: not the 2000-frame criterion
    blocks = s["cpu_ms_per_block"]
    assert blocks["block_frames"] == 2 and len(blocks["mean"]) == 14  # 29 tracked frames in blocks of 2
    assert "series" not in s  # per-frame series stay out of the JSON
    assert (out / s["plot"]).is_file() and (out / s["plot"]).stat().st_size > 10_000


@HEAVY_PLAN
def test_accuracy_and_notes(bench) -> None:
    res, _ = bench
    rows = {(r["sequence"], r["resolution"], r["tracker"]): r for r in res["accuracy"] if not r.get("from")}
    expected = {("tiny_real", "80x60", "dense"): 12, ("tiny_real", "160x120", "dense"): 8,
                ("synthetic slow", "80x60", "dense"): 24, ("synthetic walking loop", "80x60", "dense"): 12,
                ("synthetic fast (slow x3)", "80x60", "dense"): 8, ("tiny_real", "160x120", "orb"): 6,
                ("synthetic slow", "80x60", "orb"): 6, ("synthetic slow", "160x120", "dense"): 6,
                ("synthetic walking loop", "160x120", "dense"): 6, ("synthetic fast (slow x3)", "160x120", "dense"): 6}
    for key, frames in expected.items():
        assert key in rows, (key, sorted(rows))
        r = rows[key]
        assert r["frames"] == frames and r["fps"] > 0
        assert r["startup_s"] >= r["warmup_s"] >= 0 and r["shutdown_s"] >= 0  # start-up includes the warm-up
        # a child process timed from outside: its wall time holds the frames, start-up and end
        assert r["wall_s"] >= r["frames"] / r["fps"] + r["startup_s"] + r["shutdown_s"] - 0.05
        assert r["cpu_ms_per_frame"] == pytest.approx(1e3 * r["cpu_s"] / r["frames"], rel=0.05) and r["peak_mb"] > 50
        if r["ate_rmse_cm"] is None:  # a run lost from its first frames cannot be aligned: the reason is kept
            assert key[0] == "synthetic walking loop" and "alignment" in r["eval_error"]
            continue
        assert math.isfinite(r["ate_rmse_cm"]) and r["ate_rmse_cm"] >= 0.0
        assert r["rpe_trans_mm_per_frame"] is not None and r["rpe_rot_deg_per_frame"] is not None
    assert rows[("tiny_real", "80x60", "dense")]["ate_rmse_cm"] < 2.0  # 12 slow frames: tracked
    # trackers run on fewer frames than the dense row get a dense row over the same frames (its first poses)
    prefix = [r for r in res["accuracy"] if r.get("from")]
    assert {(r["sequence"], r["resolution"], r["frames"]) for r in prefix} == {("tiny_real", "160x120", 6),
                                                                           ("synthetic slow", "80x60", 6)}
    assert all(r["tracker"] == "dense" and r["fps"] is None and r["ate_rmse_cm"] is not None for r in prefix)
    assert len(res["accuracy"]) == len(expected) + 2
    notes = {n["sequence"]: n for n in res["not_tracked"]}
    assert notes["short"]["frames"] == 4 and "too short" in notes["short"]["reason"]
    assert "not a sequence" in notes["junk"]["reason"]
    assert res["open3d"] == {"available": False, "reason": "disabled (--no-open3d)", "rows": []}


@HEAVY_PLAN
def test_markdown(bench) -> None:
    res, out = bench
    md = (out / "latest.md").read_text()
    assert md == run_all.to_markdown(res)
    assert res["meta"]["date"] in md and res["meta"]["machine"]["cpu"] in md
    assert "**JIT**" in md and "excluded from every FPS" in md
    assert "| resolution | frames | read | preprocess | render | ICP | fuse | dense loop | FPS | ORB extract |" in md
    assert "\n| 80x60 | 12 |" in md and "\n| 160x120 | 8 |" in md
    assert "### Sustained throughput: 30 synthetic frames at 80x60" in md
    assert "### One registration" in md and "\n| icp 3-level | 320x240 | 1 |" in md
    assert "| synthetic fast (slow x3) | 80x60 | 8 | dense |" in md
    assert "### Speed at 80x60: the default (`hybrid`) beside dense and Open3D" in md
    assert "### Speed at 160x120" in md and "| synthetic slow | dense | 6 |" in md
    assert "`short` (4 frames): too short to track" in md
    assert "Open3D side by side: disabled" in md
    # every table row has as many cells as its header
    for block in md.split("\n\n"):
        lines = [ln for ln in block.splitlines() if ln.startswith("|")]
        if lines:
            assert len({ln.count("|") for ln in lines}) == 1, block


@HEAVY_PLAN
def test_docs_page_is_the_markdown_under_its_header(bench, tmp_path) -> None:
    res, _ = bench
    page = tmp_path / "benchmarks.md"
    run_all.write_docs_page(res, page)
    assert page.read_text() == run_all.DOCS_HEADER + run_all.to_markdown(res)
    assert not list(tmp_path.glob(".*.tmp"))


def test_markdown_flags_failures() -> None:
    """A flat-cost ratio above 1.3, a budget skip and a section error all show in the markdown."""
    res = {"meta": {"date": "2000-01-01", "mode": "full", "python": "3", "numba": "0", "open3d": None,
                    "git": {"commit": "abc", "src_modified": True}, "parallel_kernels": False, "seconds": 1.0,
                    "cpu_seconds": 1.0, "machine": {"cpu": "cpu X", "cores": 2, "arch": "x", "os": "y",
                                                    "load_average_at_start": 0.1}},
           "jit": None, "stages": [], "accuracy": [], "not_tracked": [], "open3d": None,
           "sustained": {"frames": 10, "resolution": "8x6", "window": 2, "flat_cost_max_ratio": 1.3, "fps": 1.0,
                         "cpu_ms_per_frame": 1.0, "cpu_first_ms": 1.0, "cpu_last_ms": 1.5, "last_over_first": 1.5,
                         "flat_cost_ok": False, "map_surfels_end": 5, "ate_cm": 1.0, "failures": 0, "per_lap": [],
                         "trajectory": "t", "flat_cost_verdict": "issue 6 criterion"},
           "skipped": [{"what": "hybrid on x", "reason": "time budget"}],
           "errors": [{"section": "stages", "error": "ValueError: boom"}]}
    md = run_all.to_markdown(res)
    assert "| 1.50 | **NO** |" in md
    assert "Skipped: hybrid on x (time budget)" in md
    assert "**Errors**: stages: ValueError: boom" in md
    assert "git abc + local changes in src/" in md


def test_default_speed_line_names_the_rows_below_the_target() -> None:
    """The default tracker's 320x240 rows against 30 FPS, dense's FPS beside them; other trackers, other
    resolutions and the dense rows cut from a longer run (``from``) do not count."""
    from benchmarks import report

    def row(seq, tracker, fps, resolution="320x240", **kw):
        return {"sequence": seq, "tracker": tracker, "fps": fps, "resolution": resolution, **kw}

    rows = [row("a", "dense", 40.0), row("a", "hybrid", 31.0), row("b", "dense", 35.0), row("b", "hybrid", 29.5),
            row("b", "orb", 10.0), row("c", "hybrid", 12.0, "640x480"),
            row("b", "dense", None, frames=200, **{"from": 1})]
    (line, _) = report._default_speed(rows)
    assert "29.5-31.0 FPS over its 2 rows" in line
    assert "(issue 33): **NO** on b." in line
    assert "Dense on the same rows: 40.0, 35.0 FPS" in line
    (line, _) = report._default_speed(rows[:2])
    assert "(issue 33): yes." in line
    assert report._default_speed([row("a", "dense", 40.0)]) == []


def test_budget() -> None:
    b = run_all.Budget(100.0)
    assert b.fits("a", 10.0)
    assert not b.fits("b", 100.0 - run_all.RESERVE_S + 1.0)
    assert [s["what"] for s in b.skipped] == ["b"]
    assert run_all.Budget(0.0).fits("c", 1e9)  # 0 = no limit


def test_sustained_equal_view_ratios() -> None:
    """Laps of 15 frames (walking loop): the ratios of equal views use the right windows of the series."""
    from benchmarks import bench_pipeline

    row = bench_pipeline.bench(80, 40, 5, style="loop", lap=15, plot_dir=None)
    cpu = row["series"]["cpu_ms"]
    assert row["laps"] == 3 and [p["frames"] for p in row["per_lap"]] == [14, 15, 10]
    assert row["cpu_revisit_ms"] == pytest.approx(cpu[16:21].mean(), abs=0.006)
    a = (40 - 5) % 15  # the last 5 frames (35-39) are views 5-9 of a lap
    assert a == 5 and row["cpu_same_views_first_orbit_ms"] == pytest.approx(cpu[5:10].mean(), abs=0.006)
    assert row["last_over_same_views_first_orbit"] == pytest.approx(cpu[35:].mean() / cpu[5:10].mean(), rel=0.01)
    assert "plot" not in row


# --- the sections `--sections` runs on their own, spliced into the last results ----------------------------------

SPLICE = run_all.Plan("tiny", viewer_frames=12, viewer_width=80, viewer_repeats=1, mesh_frames=6, mesh_width=80,
                      mesh_repeats=1, mesh_voxel_m=0.04)


@pytest.mark.heavy  # make test-all: the viewer and the mesh have their own tests (tests/viz, tests/mapping)
def test_viewer_and_mesh_sections_spliced_into_the_last_results(tmp_path) -> None:
    """``run_all --sections viewer,mesh`` on tiny inputs: both sections' rows, the rest of the page kept as it was,
    the page regenerated by the same ``to_markdown``."""
    pytest.importorskip("rerun", reason="rerun-sdk (the `viz` extra) is not installed")
    base = {"meta": {"date": "2000-01-01", "mode": "tiny", "python": "3", "numba": "0", "open3d": None,
                     "git": {"commit": "abc", "src_modified": False}, "parallel_kernels": False,
                     "section_seconds": {"jit": {"wall": 1.0, "cpu": 1.0}},
                     "machine": {"cpu": "cpu X", "cores": 2, "arch": "x", "os": "y", "load_average_at_start": 0.1}},
            "jit": None, "stages": [], "icp": [], "sustained": None, "accuracy": [], "not_tracked": [],
            "open3d": None, "skipped": [{"what": "hybrid on x", "reason": "time budget"}],
            "errors": [{"section": "mesh", "error": "old"}]}
    out = tmp_path / "out"
    out.mkdir()
    (out / "latest.json").write_text(json.dumps(base))
    res = run_all.run_sections(SPLICE, ["viewer", "mesh"], out, open3d=False)
    assert res["errors"] == [], res["errors"]
    v = res["viewer"]
    assert v["frames"] == 12 and v["resolution"] == "80x60" and v["repeats"] == 1
    assert v["fps_none"] > 0 and v["fps_viewer"] > 0 and v["rrd_verify_ok"] in (True, None)
    assert v["cost_pct"] == pytest.approx(100 * (1 - v["fps_viewer"] / v["fps_none"]))
    assert v["images_logged"] == 3 and v["dropped"] == 0 and v["viewer_error"] is None  # frames 0, 5, 10
    m = res["mesh"]
    assert [(r["method"], r["poses"]) for r in m["rows"]] == [("surfelslam TSDF", "ground truth"),
                                                              ("surfelslam TSDF", "estimated (dense run)")]
    for r in m["rows"]:
        assert 0.0 <= r["accuracy_mean_m"] <= r["accuracy_p90_m"] < m["voxel_m"] and 0.5 < r["completeness"] <= 1.0
        assert r["fuse_s"] > 0 and r["faces"] > 0
    assert m["targets"]["ok"] in (True, False) and m["measured"]["mode"] == "tiny"
    assert m["measured"]["date"] == datetime.date.today().isoformat() != base["meta"]["date"]  # measured now
    md = (out / "latest.md").read_text()
    assert md == run_all.to_markdown(res) == run_all.to_markdown(json.loads((out / "latest.json").read_text()))
    assert "### Live viewer cost: 12 synthetic frames at 80x60" in md and "Skipped: hybrid on x" in md
    assert "### Mesh quality: 6 synthetic frames at 80x60" in md and "Choice of libraries" in md
    assert "Measured apart from the rest of this page (`python -m benchmarks.run_all --sections viewer`)" in md
    for block in md.split("\n\n"):  # every table row has as many cells as its header
        lines = [ln for ln in block.splitlines() if ln.startswith("|")]
        if lines:
            assert len({ln.count("|") for ln in lines}) == 1, block


def test_viewer_section_without_rerun_is_skipped_not_an_error(tmp_path, monkeypatch) -> None:
    """Without rerun-sdk (an optional extra) the viewer section is skipped with the reason, and nothing is an error."""
    from benchmarks import bench_viewer

    monkeypatch.setattr(bench_viewer.importlib.util, "find_spec", lambda name: None)
    res = {"skipped": [], "errors": [], "meta": {"section_seconds": {}}}
    assert run_all.standalone_section(res, "viewer", SPLICE, tmp_path, open3d=False) is None
    assert res["skipped"] == [{"what": "the viewer section", "reason": "rerun-sdk is not installed (the `viz` extra)"}]
    assert res["errors"] == []


def test_sections_option_refuses_other_names(capsys) -> None:
    with pytest.raises(SystemExit):
        run_all.main(["--sections", "stages"])
    assert "--sections" in capsys.readouterr().err


# 33 frames at 30 Hz: just over the 1 s the worst-drift window needs; one generated sequence, no real data
ROBUST = run_all.Plan("tiny", robust_frames=33, robust_width=80, robust_synthetic=("wall_textured",),
                      robust_trackers=("orb",), robust_open3d_frames=0, robust_budget_s=1e-6)


def test_robustness_section_spliced_into_the_last_results(tmp_path, monkeypatch) -> None:
    """``run_all --sections robustness`` on tiny inputs: the dense row with its drift and segments, orb skipped by
    the budget, the real sequences listed as not run (no shared data), the sequence generated once then cached."""
    monkeypatch.setenv(run_all.bench_robustness.CACHE_ENV, str(tmp_path / "cache"))
    base = {"meta": {"date": "2000-01-01", "mode": "tiny", "python": "3", "numba": "0", "open3d": None,
                     "git": {"commit": "abc", "src_modified": False}, "parallel_kernels": False,
                     "machine": {"cpu": "cpu X", "cores": 2, "arch": "x", "os": "y", "load_average_at_start": 0.1}},
            "jit": None, "stages": [], "icp": [], "sustained": None, "accuracy": [], "not_tracked": [],
            "open3d": None, "skipped": [], "errors": []}
    out = tmp_path / "out"
    out.mkdir()
    (out / "latest.json").write_text(json.dumps(base))
    res = run_all.run_sections(ROBUST, ["robustness"], out, open3d=False, shared=tmp_path / "no_shared")
    assert res["errors"] == [], res["errors"]
    r = res["robustness"]
    [row] = r["rows"]
    assert (row["sequence"], row["tracker"], row["frames"], row["resolution"]) == (
        "close wall, textured (plane)", "dense", 33, "80x60")
    assert row["ate_rmse_cm"] >= 0 and row["worst_1s_drift_cm"] >= 0 and row["fps"] > 0
    assert 0 < row["worst_1s_drift_end_s"] <= 33 / 30 and row["lost_segments"] >= 0 and row["failures"] >= 0
    assert [s["what"] for s in r["skipped"]] == ["robustness orb on close wall, textured (plane) (33 frames)"]
    assert len(r["not_run"]) == len(run_all.bench_robustness.REPLAYED) + len(run_all.bench_robustness.REAL)
    assert len(list((tmp_path / "cache" / "robustness").iterdir())) == 1  # generated once, kept
    md = (out / "latest.md").read_text()
    assert md == run_all.to_markdown(json.loads((out / "latest.json").read_text()))
    assert "### Robustness: long near-degenerate sequences (33 generated frames at 80x60" in md
    assert "| close wall, textured (plane) | 33 | dense |" in md and "Skipped (time budget of the section)" in md


def test_odometry_only_variant_and_the_loops_ratio_line() -> None:
    """``hybrid-odometry`` is the default hybrid with its loop corrections off, ``orb-odometry`` orb without loop
    candidates (nothing else changed), and the robustness page gives, per sequence, each tracker's ATE over its
    variant's (item: loops never worse)."""
    from dataclasses import replace

    from benchmarks.bench_robustness import _loops_against_odometry
    from benchmarks.common import tracker_setup
    from surfelslam.slam import SlamConfig

    tracker, cfg = tracker_setup("hybrid-odometry")
    default = SlamConfig()
    assert tracker == default.tracker == "hybrid" and not cfg.hybrid.loop_correction
    assert cfg == replace(default, hybrid=replace(default.hybrid, loop_correction=False))
    rows = [{"sequence": "tour", "tracker": "hybrid", "ate_rmse_cm": 0.5386},
            {"sequence": "tour", "tracker": "hybrid-odometry", "ate_rmse_cm": 0.8702},
            {"sequence": "wall", "tracker": "hybrid", "ate_rmse_cm": 0.0834},
            {"sequence": "wall", "tracker": "hybrid-odometry", "ate_rmse_cm": 0.0811},
            {"sequence": "corridor", "tracker": "hybrid", "ate_rmse_cm": 0.72}]  # no odometry row: left out
    [line, blank] = _loops_against_odometry(rows)
    assert "tour 0.62; wall 1.03. Worst: 1.03." in line and "corridor" not in line and blank == ""
    assert _loops_against_odometry(rows[-1:]) == []
    # orb's variant: no loop candidates among the older keyframes, nothing else changed; a line of its own
    tracker, cfg = tracker_setup("orb-odometry")
    loop = replace(default.sparse.loop, n_random=0, n_retrieved=0)
    assert tracker == "orb" and cfg == replace(default, tracker="orb", sparse=replace(default.sparse, loop=loop))
    orb = [{"sequence": "tour", "tracker": "orb", "ate_rmse_cm": 43.6},
           {"sequence": "tour", "tracker": "orb-odometry", "ate_rmse_cm": 84.3}]
    hybrid_line, _, orb_line, _ = _loops_against_odometry(rows + orb)
    assert hybrid_line == line and orb_line.startswith("Loop closure against the odometry alone (orb;")
    assert "`--set sparse.loop.n_random=0 --set sparse.loop.n_retrieved=0`): tour 0.52. Worst: 0.52." in orb_line
    assert "`--set hybrid.loop_correction=false`): tour 0.62" in line  # the settings as a user types them


def test_a_synthetic_rows_seed_reaches_the_generator_and_the_cache_key(tmp_path, monkeypatch) -> None:
    """Two rows that differ only by their seed are two sequences: each seed is generated and cached on its own."""
    from dataclasses import replace

    from benchmarks import bench_robustness as br

    calls = []

    def fake_generate(out, **kw):
        calls.append(kw["seed"])
        out.mkdir(parents=True)
        (out / "groundtruth.txt").write_text("")

    monkeypatch.setattr(br, "generate_sequence", fake_generate)
    spec = next(s for s in br.SYNTHETIC if s.key == "corridor_plain")
    paths = [br.synthetic_sequence(replace(spec, seed=seed), 10, 80, tmp_path) for seed in (0, 5, 5)]
    assert calls == [0, 5] and paths[1] == paths[2] != paths[0] and "_s5_" in paths[1].name
    assert next(s for s in br.SYNTHETIC if s.key == "corridor_plain_seed5") == replace(
        spec, key="corridor_plain_seed5", label="corridor, plain, seed 5", seed=5)


@pytest.mark.heavy  # make test-all: four runs and two commands on a generated floor
def test_scale_section_spliced_into_the_last_results(tmp_path) -> None:
    """``run_all --sections scale`` on a 45-frame floor walk at 80x60: both trackers' rows from child runs, the
    measures issue 68 asks for, the mesh command's cost, the plot, the page regenerated."""
    plan = run_all.Plan("tiny", scale_frames=45, scale_width=80, scale_open3d_frames=0)
    out = tmp_path / "out"
    res = run_all.run_sections(plan, ["scale"], out, open3d=False, shared=tmp_path / "no_shared")
    assert res["errors"] == [], res["errors"]
    s = res["scale"]
    assert (s["frames"], s["resolution"], s["open3d"]) == (45, "80x60", None) and s["path_m"] > 1.0
    assert [r["tracker"] for r in s["rows"]] == ["hybrid", "dense", "hybrid, odometry only"]
    for r in s["rows"]:
        assert r["frames"] == 45 and r["fps"] > 0 and r["wall_s"] > r["startup_s"] > 0 and r["peak_mb"] > 50
        assert r["worst_1m_drift_cm"] >= 0 and r["surfels"] > 0 and r["map_points_measured"] > 0
        assert 0 <= r["map_accuracy_median_mm"] <= r["map_accuracy_p90_mm"] and r["map_ply_mb"] > 0
        # the best-fit figure exists exactly when the run's ATE does (a run lost from its second frame has neither)
        assert ("ate_aligned_map_accuracy_mean_mm" in r) == (r["ate_cm"] is not None)
    assert all(r["window"] == 15 and r["last_over_first"] > 0 for r in s["rows"][:2])
    assert s["rows"][0]["loops_found"] >= s["rows"][0]["loops_accepted"] >= 0
    mesh = s["outputs"][0]
    assert mesh["what"].startswith("surfelslam mesh") and mesh["returncode"] == 0 and mesh["size_mb"] > 0
    assert (out / s["plot"]).is_file()
    md = (out / "latest.md").read_text()
    assert "### Scale: a multi-room floor, 45 synthetic frames at 80x60" in md and "| hybrid | 45 |" in md


def test_a_kept_section_older_than_its_table_is_one_line_not_a_failed_page() -> None:
    """``--sections scale`` splices new results into an older ``latest.json``: a kept section whose rows lack a
    field its table now reads (here the mesh rows' topology counts) becomes one line saying so; the rest renders."""
    old_mesh = {"rows": [{"method": "surfelslam TSDF", "poses": "ground truth", "accuracy_mean_m": 0.001}]}
    res = {"meta": {"date": "2000-01-01", "mode": "full", "python": "3", "numba": "0", "open3d": None,
                    "git": {"commit": "abc", "src_modified": False}, "parallel_kernels": False,
                    "section_seconds": {},
                    "machine": {"cpu": "cpu X", "cores": 2, "arch": "x", "os": "y", "load_average_at_start": 0.1}},
           "jit": None, "stages": [], "icp": [], "sustained": None, "accuracy": [], "not_tracked": [],
           "open3d": None, "skipped": [], "errors": [], "mesh": old_mesh}
    md = run_all.to_markdown(res)
    note = [ln for ln in md.splitlines() if ln.startswith("(results from an older bench")]
    assert note == ["(results from an older bench, without the field 'resolution' this table now shows; run "
                    "`make bench` to refresh this section)"], md
    assert "### mesh" in md and "Machine: " in md
