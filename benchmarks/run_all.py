"""`make bench`: stage timings, sustained throughput, accuracy, JIT time, and Open3D side by side.

Writes ``benchmarks/results/latest.json``, ``latest.md`` (markdown tables with the date and machine, for the
README) and ``pipeline_cost_<W>x<H>.png`` (per-frame cost against frame index). Sections:

* ``jit``: numba compile (or cache load) and warm-up time, excluded from every FPS.
* ``stages``: ms per frame at 320x240 and 640x480 on the first real sequence with ground truth (7-Scenes):
  read (:mod:`benchmarks.bench_stages`, the dataset reader), preprocess / render / ICP / fuse and the whole loop
  (from the ``metrics.json`` of a dense ``surfelslam run``), ORB extract and match + PnP
  (:mod:`benchmarks.bench_stages`).
* ``icp``: one pairwise registration (:mod:`benchmarks.bench_icp`): preprocessing and pyramid ICP (3 levels, and
  the 4-level default) at 320x240 and 640x480 on 1 and 2 threads, median ms after the JIT warm-up.
* ``sustained``: the dense loop over 2,000 generated frames at 320x240 (:mod:`benchmarks.bench_pipeline`): FPS,
  per-frame cost of the first and last 100 frames and their ratio (flat cost: <= 1.3), plot.
* ``accuracy``: ATE / RPE / FPS of ``surfelslam run`` (:mod:`benchmarks.bench_accuracy`) on every real sequence
  long enough to track (the others are listed in ``not_tracked``) and on synthetic slow / walking loop / fast
  sequences; dense tracker, then orb and hybrid while the time budget allows (``skipped`` says what was left out).
* ``open3d``: when open3d imports, Open3D's ``t.pipelines.slam`` (CPU, its example's defaults) and ours on the same
  first frames of those sequences at 320x240, with the ratios ours / theirs.

``--quick`` (about 1-2 minutes) runs the same sections on fewer frames. Usage:
``.venv/bin/python -m benchmarks.run_all [--quick] [--out DIR] [--budget-s S] [--no-open3d] [--shared DIR]``.
Other tools here (not run by ``make bench``): ``bench_fusion.py``
(render/fuse on a growing corridor map), ``bench_orb.py``, ``icp_pairs.py``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
import traceback
from dataclasses import asdict, dataclass
from pathlib import Path

import surfelslam
from benchmarks import bench_accuracy, bench_icp, bench_pipeline, bench_stages, open3d_slam
from benchmarks.common import SHARED_DATA
from surfelslam.datasets import DatasetOptions, open_sequence
from surfelslam.io.jsonio import json_default
from surfelslam.kernels import threads
from surfelslam.slam import SlamConfig, warm_up
from surfelslam.slam.config import apply_compute

HERE = Path(__file__).resolve().parent
SHARED = SHARED_DATA
RESULTS = HERE / "results"
STAGES = ("read", "preprocess", "render", "icp", "fuse")
# a-priori cost of a frame of the optional trackers relative to the dense one, until one run measured it
TRACKER_COST_VS_DENSE = {"orb": 2.5, "hybrid": 6.0}
OPEN3D_S_PER_FRAME_GUESS = 0.5  # at 320x240 on 2 cores, until the first Open3D run measured it
RESERVE_S = 20.0  # kept free at the end of the budget (writing results)


@dataclass(frozen=True)
class Plan:
    """How much of everything to run (frame counts; ``None`` = the whole sequence)."""

    name: str
    read_frames: int = 40  # frames decoded per resolution for the read timing
    orb_pairs: int = 8  # frame pairs for the ORB timing
    icp_pairs: int = 4  # frame pairs for the one-registration timing
    icp_reps: int = 10  # timed repetitions per pair (median)
    stage_runs: tuple[tuple[int, int | None], ...] = ((2, None), (1, 150))  # (downsample, frames) dense runs
    sustained_frames: int = 2000
    sustained_width: int = 320
    sustained_window: int = 100
    synth_width: int = 320
    synth_slow_frames: int = 300  # "fast" gets a third of these: the same path at 3x speed
    synth_loop_frames: int = 300  # one lap (the lap's length sets the walking speed)
    synth_loop_run_frames: int | None = None  # run only the first frames of the lap (same speed, less time)
    open3d_frames_real: int = 200  # 0: no side by side on real sequences
    open3d_frames_synth: int = 300  # 0: none on synthetic ones (whole sequences: slow 300, loop 300, fast 100)
    # (tracker, sequence: "real" | "slow" | "loop" | "fast", max frames), in order of priority; each one runs
    # only when its estimated time still fits in the budget
    extra_runs: tuple[tuple[str, str, int | None], ...] = (
        ("orb", "real", 200), ("hybrid", "real", 200), ("hybrid", "loop", None), ("orb", "loop", None),
        ("hybrid", "slow", 200), ("orb", "slow", 200), ("hybrid", "fast", None), ("orb", "fast", None))
    min_frames: int = 30  # shorter real sequences are listed as too short to track
    fallback_frames: int = 150  # synthetic 640x480 stage sequence when there is no real sequence
    budget_s: float = 600.0  # optional runs are skipped when they would not fit (0: no limit)


FULL = Plan("full")
QUICK = Plan("quick", read_frames=10, orb_pairs=2, icp_pairs=2, icp_reps=3, stage_runs=((2, 100), (1, 30)),
             sustained_frames=300, sustained_window=50, synth_slow_frames=90, synth_loop_run_frames=90,
             open3d_frames_real=20, open3d_frames_synth=0, extra_runs=(), fallback_frames=30, budget_s=150.0)


class Budget:
    """Wall-clock budget of the whole bench; optional runs ask whether their estimate still fits."""

    def __init__(self, seconds: float):
        self.seconds = seconds
        self.t0 = time.perf_counter()
        self.skipped: list[dict] = []

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def fits(self, what: str, estimate_s: float) -> bool:
        if self.seconds <= 0 or self.elapsed() + estimate_s <= self.seconds - RESERVE_S:
            return True
        self.skipped.append({"what": what, "reason": f"time budget: needs ~{estimate_s:.0f} s, "
                             f"{max(self.seconds - self.elapsed(), 0):.0f} s of {self.seconds:.0f} s left"})
        print(f"  skipped {what}: {self.skipped[-1]['reason']}", file=sys.stderr, flush=True)
        return False


def machine() -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cpu": cpu, "cores": cores, "arch": platform.machine(), "os": f"{platform.system()} {platform.release()}",
            "load_average_at_start": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None}


def git_state() -> dict:
    repo = HERE.parent
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=repo, capture_output=True, text=True,
                                check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "src"], cwd=repo, capture_output=True,
                               text=True, check=True).stdout.strip() != ""
    except (OSError, subprocess.CalledProcessError):
        return {"commit": None, "src_modified": None}
    return {"commit": commit, "src_modified": dirty}


def _cache_files() -> dict[str, float]:
    pkg = Path(surfelslam.__file__).parent
    return {str(p): p.stat().st_mtime for p in pkg.rglob("__pycache__/*.nbi")}


def jit() -> dict:
    """Compile (or load from numba's cache) every dense kernel, then the synthetic renderer's; timed apart."""
    before = _cache_files()
    c0, t0 = time.process_time(), time.perf_counter()
    warm_up(SlamConfig())
    dense_s, dense_cpu = time.perf_counter() - t0, time.process_time() - c0
    from surfelslam.synth.scenes import make_scene
    from surfelslam.synth.trajectories import make_trajectory
    from surfelslam.synth.writer import default_intrinsics, iter_frames, noise_config

    t1 = time.perf_counter()
    scene = make_scene("room")
    list(iter_frames(scene, make_trajectory("slow", 2, scene), default_intrinsics(64, 48), noise_config("kinect")))
    synth_s = time.perf_counter() - t1
    after = _cache_files()
    written = sum(1 for k, v in after.items() if before.get(k) != v)
    return {"warmup_s": round(dense_s, 2), "warmup_cpu_s": round(dense_cpu, 2),
            "synthetic_renderer_s": round(synth_s, 2), "numba_cache_files_written": written,
            "cache": "compiled (cache written)" if written else "loaded from numba's cache"}


def stage_source(plan: Plan, real: list[tuple[str, Path]], tmp: Path) -> tuple[str, Path, bool]:
    """The sequence the stage timings run on: the longest real one, else a generated 640x480 one."""
    if real:
        name, path = max(real, key=lambda r: len(open_sequence(r[1], DatasetOptions())))
        return name, path, True
    from surfelslam.synth.writer import generate_sequence

    path = generate_sequence(tmp / "stages", scene="room", style="slow", n_frames=plan.fallback_frames,
                             noise="kinect", width=640, height=480)
    return "synthetic slow 640x480", path, False


def stages(plan: Plan, name: str, path: Path, tmp: Path) -> tuple[list[dict], list[dict]]:
    """Stage rows per resolution, and the accuracy rows of the dense runs they came from."""
    rows, acc = [], []
    for ds, n in plan.stage_runs:
        read = bench_stages.read_ms(path, ds, plan.read_frames)
        orb = bench_stages.orb_ms(path, ds, plan.orb_pairs)
        run = bench_accuracy.run_tracker(name, path, "dense", ds, tmp / f"stages_{ds}", end=n)
        acc.append(run)
        sm = run["stage_ms"]
        rows.append({
            "resolution": run["resolution"], "sequence": name, "frames": run["frames"],
            "read_ms": read["read_ms"], **{f"{k}_ms": sm.get(k) for k in STAGES[1:]},
            "loop_ms": run["ms_per_frame"], "fps": run["fps"],
            "orb_extract_ms": orb["orb_extract_ms"], "orb_match_pnp_ms": orb["orb_match_pnp_ms"],
            "read_in_run_ms": sm.get("read"), "read_frames": read["read_frames"], "orb_pairs": orb["orb_pairs"],
            "orb_features": orb["orb_features"], "metrics_json_stages": sorted(sm),
        })
    return rows, acc


def _section(results: dict, key: str, fn, *args):
    """Run one section, timed (wall and CPU seconds into ``meta.section_seconds``); an exception is recorded
    (and the bench goes on) instead of losing everything."""
    print(f"[{datetime.datetime.now():%H:%M:%S}] {key}", file=sys.stderr, flush=True)  # progress
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        return fn(*args)
    except Exception as exc:  # noqa: BLE001 - a benchmark reports every failure and carries on
        results["errors"].append({"section": key, "error": f"{type(exc).__name__}: {exc}",
                                  "traceback": traceback.format_exc(limit=4)})
        print(f"  failed: {type(exc).__name__}: {exc}", file=sys.stderr, flush=True)
        return None
    finally:
        results["meta"]["section_seconds"][key] = {"wall": round(time.perf_counter() - t0, 1),
                                                   "cpu": round(time.process_time() - c0, 1)}


def run(plan: Plan, out_dir: Path, shared: Path = SHARED, open3d: bool = True) -> dict:
    """Run every section of ``plan``; write ``latest.json``, ``latest.md`` and the plot into ``out_dir``."""
    budget = Budget(plan.budget_s)
    apply_compute(SlamConfig().compute)  # the kernels every `surfelslam run` uses by default
    c_start = time.process_time()
    o3d_version = open3d_slam.version() if open3d and (plan.open3d_frames_real or plan.open3d_frames_synth) else None
    res: dict = {
        "meta": {"date": datetime.date.today().isoformat(),
                 "time": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
                 "mode": plan.name, "machine": machine(), "python": platform.python_version(),
                 "numba": _version("numba"), "open3d": o3d_version, "git": git_state(),
                 "parallel_kernels": threads.parallel_enabled(), "plan": asdict(plan), "section_seconds": {}},
        "jit": None, "stages": [], "icp": [], "sustained": None, "accuracy": [], "not_tracked": [], "open3d": None,
        "skipped": budget.skipped, "errors": [],
    }
    res["jit"] = _section(res, "jit", jit)
    res["icp"] = _section(res, "icp", bench_icp.run, False, plan.icp_pairs, plan.icp_reps) or []
    real, res["not_tracked"] = bench_accuracy.shared_sequences(shared, plan.min_frames)
    dense_s_per_frame: list[float] = []

    def timed_run(name, path, tracker, ds, out, end=None):
        t0 = time.perf_counter()
        row = bench_accuracy.run_tracker(name, path, tracker, ds, out, end=end)
        row["wall_s"] = round(time.perf_counter() - t0, 1)
        if tracker == "dense":
            dense_s_per_frame.append(row["wall_s"] / max(row["frames"], 1))
        return row

    with tempfile.TemporaryDirectory(prefix="surfelslam_bench_") as tmp_name:
        tmp = Path(tmp_name)
        dense_runs: dict[tuple[str, int], tuple[Path, int]] = {}  # (sequence, downsample) -> (run folder, frames)
        # stage timings at both resolutions (the runs are also the stage sequence's accuracy rows)
        src_name, src_path, src_real = stage_source(plan, real, tmp)  # 7-Scenes here
        out = _section(res, "stages", stages, plan, src_name, src_path, tmp)
        if out is not None:
            res["stages"], acc = out
            res["accuracy"] += acc
            dense_s_per_frame += [r["ms_per_frame"] / 1e3 for r in acc]
            for (ds, _), r in zip(plan.stage_runs, acc, strict=True):
                dense_runs[(src_name, ds)] = (tmp / f"stages_{ds}", r["frames"])
        # accuracy, dense tracker: the other real sequences at 320x240, then the synthetic ones
        seqs = [("real", name, path, _downsample_to_320(path), None) for name, path in real]
        synth = _section(res, "synthetic sequences", bench_accuracy.synthetic_sequences, tmp / "synth",
                         plan.synth_width, plan.synth_slow_frames, plan.synth_loop_frames) or []
        seqs += [(path.name, name, path, 1, plan.synth_loop_run_frames if path.name == "loop" else None)
                 for name, path in synth]  # keys "slow", "loop", "fast"
        for _, name, path, ds, end in seqs:
            if (name, ds) in dense_runs:
                continue
            run_dir = tmp / f"dense_{path.name}_{ds}"
            row = _section(res, f"accuracy {name}", timed_run, name, path, "dense", ds, run_dir, end)
            if row:
                res["accuracy"].append(row)
                dense_runs[(name, ds)] = (run_dir, row["frames"])
        # sustained throughput
        sus = _section(res, "sustained", bench_pipeline.bench, plan.sustained_width, plan.sustained_frames,
                       plan.sustained_window, "handheld", 400, 0, out_dir)
        if sus is not None:
            sus = bench_pipeline.summary(sus)
            sus["plot"] = Path(sus["plot"]).name
            res["sustained"] = sus
        # Open3D side by side at 320x240, on the same first frames
        res["open3d"] = _open3d(res, plan, budget, open3d, o3d_version,
                                [(name, path, ds) for key, name, path, ds, _ in seqs if key == "real"], synth, tmp)
        # optional trackers in the plan's order of priority, while the budget allows
        measured: dict[tuple[str, str], float] = {}  # (tracker, real|synthetic) -> s per frame
        for tracker, key, max_frames in plan.extra_runs:
            for k, name, path, ds, end in seqs:
                if k != key:
                    continue
                caps = [e for e in (max_frames, end) if e is not None]
                end = min(caps) if caps else None
                n = len(open_sequence(path, DatasetOptions(downsample=ds, end=end)))
                kind = "real" if k == "real" else "synthetic"
                per = _per_frame_estimate(measured, tracker, kind, _mean(dense_s_per_frame, 0.05))
                if not budget.fits(f"{tracker} on {name} ({n} frames)", 1.25 * n * per + 3.0):
                    continue
                row = _section(res, f"accuracy {tracker} {name}", timed_run, name, path, tracker, ds,
                               tmp / f"{tracker}_{path.name}_{ds}", end)
                if not row:
                    continue
                res["accuracy"].append(row)
                measured[(tracker, kind)] = row["wall_s"] / max(row["frames"], 1)
                dense = dense_runs.get((name, ds))
                have = {(r["sequence"], r["resolution"], r["frames"])
                        for r in res["accuracy"] if r["tracker"] == "dense"}
                if dense and dense[1] > row["frames"] and (name, row["resolution"], row["frames"]) not in have:
                    res["accuracy"].append(_section(res, f"prefix {name}", bench_accuracy.prefix_row, name, path,
                                                    ds, dense[0], row["frames"]))
        res["accuracy"] = [r for r in res["accuracy"] if r]
    res["meta"]["seconds"] = round(budget.elapsed(), 1)
    res["meta"]["cpu_seconds"] = round(time.process_time() - c_start, 1)
    write(res, out_dir)
    return res


def _open3d(res: dict, plan: Plan, budget: Budget, enabled: bool, version: str | None, real, synth, tmp) -> dict:
    if not enabled:
        return {"available": False, "reason": "disabled (--no-open3d)", "rows": []}
    if not (plan.open3d_frames_real or plan.open3d_frames_synth):
        return {"available": False, "reason": f"not in the {plan.name} plan", "rows": []}
    if version is None:
        return {"available": False, "rows": [],
                "reason": "open3d not importable: install the bench extra (pip install -e '.[bench]'; "
                          "needs libusb-1.0-0)"}
    jobs = [(n, p, ds, plan.open3d_frames_real) for n, p, ds in real] if plan.open3d_frames_real else []
    jobs += [(n, p, 1, plan.open3d_frames_synth) for n, p in synth] if plan.open3d_frames_synth else []
    rows, per = [], OPEN3D_S_PER_FRAME_GUESS
    for name, path, ds, n_frames in jobs:
        n = len(open_sequence(path, DatasetOptions(downsample=ds, end=n_frames)))
        if not budget.fits(f"Open3D on {name} ({n} frames)", n * per + 5.0):
            continue
        row = _section(res, f"open3d {name}", bench_accuracy.open3d_side_by_side, name, path, ds, n,
                       tmp / f"o3d_ours_{path.name}")
        if row:
            rows.append(row)
            per = 1.2 / max(row["open3d_fps"], 1e-9)  # measured, plus our run on the same frames
    return {"available": True, "version": version, "device": "CPU:0",
            "settings": "examples/python/t_reconstruction_system defaults (benchmarks/open3d_slam.py)",
            "rows": rows}


def _downsample_to_320(path: Path) -> int:
    """The ``--downsample`` factor that brings a sequence to about 320 pixels wide (2 for 640x480 files)."""
    return max(1, open_sequence(path, DatasetOptions()).intrinsics.width // 320)


def _per_frame_estimate(measured: dict, tracker: str, kind: str, dense_s: float) -> float:
    """Seconds per frame of ``tracker`` on a ``kind`` sequence: measured, else measured on the other kind x 3
    (orb ran 3.4x slower per frame on the synthetic walking loop than on 7-Scenes), else a multiple of the
    dense tracker's."""
    if (tracker, kind) in measured:
        return measured[(tracker, kind)]
    other = [v for (t, _), v in measured.items() if t == tracker]
    return 3.0 * max(other) if other else TRACKER_COST_VS_DENSE.get(tracker, 5.0) * dense_s


def _mean(v: list[float], default: float) -> float:
    return sum(v) / len(v) if v else default


def _version(module: str) -> str | None:
    try:
        return str(__import__(module).__version__)
    except Exception:  # noqa: BLE001
        return None


# ---------------------------------------------------------------- output


def _fmt(v, nd: int = 1) -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "**NO**"
    if isinstance(v, float):
        return f"{v:.{nd}f}"
    return str(v)


def table(header: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(_fmt(c) if not isinstance(c, str) else c for c in r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def to_markdown(res: dict) -> str:
    meta, mc = res["meta"], res["meta"]["machine"]
    git = meta["git"]
    g = f"git {git['commit']}" if git["commit"] else "(no git)"
    g += " + local changes in src/" if git.get("src_modified") else ""
    load = mc.get("load_average_at_start")
    md = [f"## Benchmarks: `make bench`{' --quick' if meta['mode'] == 'quick' else ''}, {meta['date']}", "",
          f"Machine: {mc['cpu']}, {mc['cores']} cores ({mc['arch']}, {mc['os']}); Python {meta['python']}, "
          f"numba {meta['numba']}, Open3D {meta['open3d'] or 'not installed'}; surfelslam {g}; "
          f"numba kernels {'parallel' if meta['parallel_kernels'] else 'serial'}; load average at start "
          f"{_fmt(load, 2)}{' (machine busy: timings are indicative)' if load and load > 1.0 else ''}. "
          f"Whole bench: {_fmt(meta.get('seconds'), 0)} s wall, {_fmt(meta.get('cpu_seconds'), 0)} s CPU.", ""]
    j = res.get("jit")
    if j:
        md += [f"**JIT** (numba, `cache=True`): compile and warm-up {j['warmup_s']:.1f} s ({j['cache']}), synthetic "
               f"renderer {j['synthetic_renderer_s']:.1f} s; excluded from every FPS below.", ""]
    if res["stages"]:
        s0 = res["stages"][0]
        md += [f"### Stage timings, ms per frame (dense tracker, {s0['sequence']})", ""]
        md.append(table(["resolution", "frames", "read", "preprocess", "render", "ICP", "fuse", "dense loop", "FPS",
                         "ORB extract", "ORB match+PnP"],
                        [[r["resolution"], r["frames"], r["read_ms"], r["preprocess_ms"], r["render_ms"], r["icp_ms"],
                          r["fuse_ms"], r["loop_ms"], r["fps"], r["orb_extract_ms"], r["orb_match_pnp_ms"]]
                         for r in res["stages"]]))
        bg = ", ".join(f"{_fmt(r['read_in_run_ms'])} ms at {r['resolution']}" for r in res["stages"])
        md += ["read: the dataset reader decoding the colour and depth files (mean of "
               f"{s0['read_frames']} frames, synchronous); `surfelslam run` reads in a background thread ({bg}). "
               "At 320x240 (`--downsample 2`) the reader decodes the full 640x480 files, then keeps every second "
               "pixel. preprocess / render / ICP / fuse: means over the frames of a `surfelslam run` (its "
               "`metrics.json`, `stage_ms`); preprocess runs in the reader thread, ahead of the frame "
               "(`io.prepare_in_reader`), so the dense loop (the main thread's time per frame) is render + ICP + fuse; "
               "FPS (wall clock of the whole run) excludes the JIT warm-up. ORB: extraction per frame, matching + "
               f"PnP-RANSAC per frame pair, with the orb/hybrid trackers' settings ({s0['orb_features']} features).",
               ""]
    if res.get("icp"):
        md += ["### One registration (`surfelslam register`'s ICP), median ms after the JIT warm-up", ""]
        md.append(table(["stage", "resolution", "threads", "ms", "iterations (mean)"],
                        [[r["stage"], r["size"], r["threads"], r["ms"],
                          r["iterations"] if r["stage"].startswith("icp") else "–"]
                         for r in res["icp"]]))
        md += [f"Frames: {res['icp'][0]['frames']} pairs {bench_icp.FRAME_GAP} frames apart. `icp 3-level`: the "
               "first three levels of the default `ICPConfig`; `icp default`: all four levels (finest-level source "
               "stride 2); preprocess: depth to the 4-level vertex/normal pyramid (default settings); "
               "shape guess (FPFH): the depth-only guess of `register --init features` and of relocalisation, on pairs "
               f"{bench_icp.SHAPE_GAP} frames apart (7-Scenes), at the pyramid level at most 320 px wide.", ""]
    s = res.get("sustained")
    if s:
        md += [f"### Sustained throughput: {s['frames']} synthetic frames at {s['resolution']}", ""]
        md.append(table(["frames", "FPS", "CPU ms/frame", f"first {s['window']}", f"last {s['window']}",
                         "last/first", f"flat (<= {s['flat_cost_max_ratio']})", "map surfels at end", "ATE cm",
                         "failures"],
                        [[s["frames"], s["fps"], s["cpu_ms_per_frame"], s["cpu_first_ms"], s["cpu_last_ms"],
                          _fmt(s["last_over_first"], 2),
                          _fmt(s["flat_cost_ok"]) + ("" if s.get("flat_cost_verdict", "").startswith("issue") else
                                                     " (indicative)"), s["map_surfels_end"], s["ate_cm"],
                          s["failures"]]]))
        laps = "; ".join(f"{p['lap']}: {p['cpu_ms']:.1f} ms, {p['map_surfels_end']:,} surfels" for p in s["per_lap"])
        same = [f"{label} {s[k]:.2f}" for k, label in (
            ("revisit_over_first", f"start of orbit 2 / first {s['window']}"),
            ("last_over_same_views_first_orbit", f"last {s['window']} / the same views in orbit 1")) if k in s]
        md += [f"{s['trajectory']}; every frame rendered fresh (new pose and noise), generation not timed. "
               f"Frames are fed as `surfelslam run` feeds them (reader thread running `DenseSlam.prepare`, main thread "
               f"`DenseSlam.process`). Per-frame cost is the frame's CPU time in both threads (robust to other "
               f"jobs); FPS is wall clock. "
               f"Per orbit (mean CPU ms, map size at its end): {laps}. The cost varies with the view, so ratios "
               f"of equal views isolate the growth with the map: {', '.join(same) or 'run too short'}. "
               f"Plot: `{s.get('plot')}`.", ""]
    if res["accuracy"]:
        md += ["### Accuracy: ATE RMSE and RPE per frame against ground truth (`surfelslam run`)", ""]
        md.append(table(["sequence", "resolution", "frames", "tracker", "ATE RMSE cm", "ATE max cm", "RPE mm/frame",
                         "RPE deg/frame", "failures", "FPS"],
                        [[r["sequence"], r["resolution"], r["frames"], r["tracker"], _fmt(r["ate_rmse_cm"], 2),
                          _fmt(r["ate_max_cm"], 2), _fmt(r["rpe_trans_mm_per_frame"], 2),
                          _fmt(r["rpe_rot_deg_per_frame"], 3), r["failures"], r["fps"]]
                         for r in _grouped(res["accuracy"])]))
        if any(r.get("from") for r in res["accuracy"]):
            md += ["Dense rows without FPS: the first poses of the longer dense run on that sequence (the dense "
                   "tracker is causal and deterministic, so a run on those frames alone gives the same poses), for "
                   "comparison with the orb / hybrid rows over the same frames.", ""]
        lost = [f"{r['sequence']} {r['resolution']} {r['tracker']}: {r['eval_error']}" for r in res["accuracy"]
                if r.get("eval_error")]
        if lost:
            md += ["No ATE (–): " + "; ".join(lost) + ".", ""]
    if res["not_tracked"]:
        md += ["Not tracked: " + "; ".join(f"`{n['sequence']}` ({n['frames']} frames): {n['reason']}"
                                           for n in res["not_tracked"]) + ".", ""]
    o = res.get("open3d")
    if o is not None:
        if o["available"] and o["rows"]:
            md += [f"### Side by side with Open3D {o['version']} `t.pipelines.slam` (CPU, example defaults)", ""]
            md.append(table(["sequence", "resolution", "frames", "our FPS", "Open3D FPS", "FPS ratio (ours/theirs)",
                             "our ATE cm", "Open3D ATE cm", "ATE ratio (ours/theirs)"],
                            [[r["sequence"], r["resolution"], r["frames"], r["ours_fps"], r["open3d_fps"],
                              _fmt(r["fps_ratio"], 2), _fmt(r["ours_ate_cm"], 2), _fmt(r["open3d_ate_cm"], 2),
                              _fmt(r["ate_ratio"], 2)] for r in o["rows"]]))
            md += ["Both read the same frames through our dataset reader; frames are decoded before Open3D's timer "
                   "starts, and our FPS excludes the JIT warm-up. At 320x240 only (Open3D runs at a few FPS).", ""]
        else:
            md += [f"Open3D side by side: {o.get('reason', 'no rows')}.", ""]
    if res["skipped"]:
        md += ["Skipped: " + "; ".join(f"{s['what']} ({s['reason']})" for s in res["skipped"]) + ".", ""]
    if res["errors"]:
        md += ["**Errors**: " + "; ".join(f"{e['section']}: {e['error']}" for e in res["errors"]) + ".", ""]
    groups: dict[str, list[float]] = {}
    for key, t in meta.get("section_seconds", {}).items():
        g = groups.setdefault(key.split()[0], [0.0, 0.0])
        g[0] += t["wall"]
        g[1] += t["cpu"]
    if groups:
        md += ["Bench time by section (wall / CPU s): " + ", ".join(f"{k} {w:.0f} / {c:.0f}"
                                                                    for k, (w, c) in groups.items()) + ".", ""]
    return "\n".join(md)


def _grouped(rows: list[dict]) -> list[dict]:
    """Accuracy rows grouped by sequence (first appearance), resolution, frames (most first), tracker."""
    seq_order = {k: i for i, k in enumerate(dict.fromkeys(r["sequence"] for r in rows))}
    res_order = {k: i for i, k in enumerate(dict.fromkeys(r["resolution"] for r in rows))}
    trk = {"dense": 0, "orb": 1, "hybrid": 2}
    return sorted(rows, key=lambda r: (seq_order[r["sequence"]], res_order[r["resolution"]], -r["frames"],
                                       trk.get(r["tracker"], 9)))


def write(res: dict, out_dir: Path) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "latest.json").write_text(json.dumps(res, indent=1, default=json_default) + "\n")
    (out_dir / "latest.md").write_text(to_markdown(res))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames everywhere (about 1-2 minutes)")
    ap.add_argument("--out", type=Path, default=RESULTS, help="output folder (default benchmarks/results)")
    ap.add_argument("--budget-s", type=float, default=None,
                    help="wall-clock budget; optional runs that would not fit are skipped (0: no limit)")
    ap.add_argument("--no-open3d", action="store_true", help="no side by side even when open3d is installed")
    ap.add_argument("--shared", type=Path, default=SHARED, help="folder of real sequences (../shared/data)")
    a = ap.parse_args(argv)
    plan = QUICK if a.quick else FULL
    if a.budget_s is not None:
        plan = Plan(**{**asdict(plan), "budget_s": a.budget_s})
    res = run(plan, a.out, a.shared, open3d=not a.no_open3d)
    print(to_markdown(res))
    print(f"written: {a.out / 'latest.json'}, {a.out / 'latest.md'}")
    return 1 if res["errors"] else 0


if __name__ == "__main__":
    sys.exit(main())
