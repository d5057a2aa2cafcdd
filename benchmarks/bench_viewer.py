"""Cost of the live viewer: FPS of a dense ``surfelslam run`` without a viewer and with ``--viewer save=FILE``.

Issue 36 asks that FPS with the viewer be no more than 10 % below FPS without. A generated sequence (room, slow
hand-held orbit, Kinect noise) is run the way ``surfelslam run`` runs it (:func:`surfelslam.slam.runner.run_sequence`
with the live viewer of :func:`surfelslam.viz.live.viewer_for_run` as its per-frame hook, then
:func:`surfelslam.viz.live.finish_viewer`), in this process, the two variants interleaved (without, with, with,
without, ...) so that both see the same load on a shared machine. Per variant: the median and the best of the
runs' FPS (``metrics.json``: frames over the loop's wall time, JIT warm-up excluded) and the process CPU time of
the whole run (every thread: tracking, reader, logging, Rerun's own). The last recording is checked with
``rerun rrd verify`` (the CLI of rerun-sdk, beside the Python executable).

Usage: ``.venv/bin/python -m benchmarks.bench_viewer [--frames N] [--repeats K] [--width W] [--work DIR]``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from surfelslam.api import run_sequence
from surfelslam.datasets import open_sequence
from surfelslam.slam import SlamConfig
from surfelslam.synth.writer import generate_sequence
from surfelslam.viz.live import LiveViewerConfig, finish_viewer, viewer_for_run

#: issue 36's target: FPS with ``--viewer save=FILE`` at most this much below FPS without (%).
TARGET_COST_PCT = 10.0
#: ``rerun rrd verify`` gets this long before the check counts as failed (s).
VERIFY_TIMEOUT_S = 120.0
WARMUP_FRAMES = 10  # the untimed first run of each variant (JIT, rerun-sdk import)
DEFAULTS = LiveViewerConfig()  # `surfelslam run --viewer`'s defaults (images and map every N frames)


def missing() -> str | None:
    """Why the section cannot run here (rerun-sdk, the `viz` extra, is not installed), or ``None``."""
    return None if importlib.util.find_spec("rerun") else "rerun-sdk is not installed (the `viz` extra)"


def rerun_cli() -> Path | None:
    """The ``rerun`` executable the rerun-sdk wheel installs beside this Python, or ``None``."""
    cli = Path(sys.executable).parent / "rerun"
    return cli if cli.is_file() else None


def verify_rrd(path: Path) -> dict:
    """``rerun rrd verify PATH``: ``{"ok": bool | None, "message": first line of its output}`` (``None``: no CLI)."""
    cli = rerun_cli()
    if cli is None:
        return {"ok": None, "message": "rerun CLI not found beside the Python executable"}
    try:
        p = subprocess.run([str(cli), "rrd", "verify", str(path)], capture_output=True, text=True,
                           timeout=VERIFY_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        return {"ok": False, "message": f"timed out after {VERIFY_TIMEOUT_S:.0f} s"}
    lines = (p.stdout + p.stderr).strip().splitlines()
    return {"ok": p.returncode == 0, "message": lines[-1] if lines else f"exit code {p.returncode}"}


def one_run(seq_dir: Path, out: Path, rrd: Path | None, end: int | None = None) -> dict:
    """One ``surfelslam run`` of ``seq_dir`` into ``out``, with ``--viewer save=rrd`` unless ``rrd`` is None."""
    from surfelslam.datasets import DatasetOptions

    seq = open_sequence(seq_dir, DatasetOptions(end=end))
    shutil.rmtree(out, ignore_errors=True)
    c0, t0 = time.process_time(), time.perf_counter()
    live = viewer_for_run(f"save={rrd}" if rrd is not None else None, seq, DEFAULTS.images_every,
                          DEFAULTS.map_every, warn=lambda _: None)
    if rrd is not None and live is None:
        raise RuntimeError("the live viewer did not start (rerun-sdk missing?)")
    m = run_sequence(seq, out, SlamConfig(), progress=False, figures=False, on_frame=live)
    stats = finish_viewer(live, out, warn=lambda _: None)
    row = {"fps": m["fps"], "frames": m["frames_processed"], "cpu_s": time.process_time() - c0,
           "wall_s": time.perf_counter() - t0, "loop_wall_s": m["wall_s"]}
    if stats is not None:
        row |= {"images_logged": stats.images_logged, "images_dropped": stats.images_dropped,
                "maps_logged": stats.maps_logged, "maps_dropped": stats.maps_dropped,
                "on_frame_ms": 1e3 * stats.on_frame_s / max(stats.frames, 1),
                "logging_cpu_ms": 1e3 * stats.logging_cpu_s / max(stats.frames, 1), "error": stats.error,
                "rrd_mb": rrd.stat().st_size / 2**20}
    return row


def bench(frames: int = 300, repeats: int = 5, width: int = 320, work: Path | None = None) -> dict:
    """Interleaved runs without / with the viewer on one generated sequence; the summary row (module docstring)."""
    work = Path(tempfile.mkdtemp(prefix="bench_viewer_")) if work is None else Path(work)
    height = width * 3 // 4
    seq_dir = work / f"room_slow_{frames}_{width}"
    if not (seq_dir / "INFO.txt").is_file():
        generate_sequence(seq_dir, scene="room", style="slow", n_frames=frames, noise="kinect", seed=0, width=width,
                          height=height)
    rrd = work / "live.rrd"
    for r in (None, rrd):  # untimed: compile / load the kernels, import rerun-sdk
        one_run(seq_dir, work / "warmup", r, end=min(WARMUP_FRAMES, frames))
    runs: dict[str, list[dict]] = {"none": [], "viewer": []}
    for i in range(repeats):
        order = ("none", "viewer") if i % 2 == 0 else ("viewer", "none")  # A B B A ...: same load for both
        for v in order:
            runs[v].append(one_run(seq_dir, work / f"run_{v}", rrd if v == "viewer" else None))
    verify = verify_rrd(rrd)
    return summary(runs, verify, frames, f"{width}x{height}")


def summary(runs: dict[str, list[dict]], verify: dict, frames: int, resolution: str) -> dict:
    """FPS (median and best), CPU and the viewer's cost in % per variant, from the runs of :func:`bench`."""
    def med(v: str, k: str) -> float:
        return float(statistics.median(r[k] for r in runs[v]))

    fps_none, fps_view = med("none", "fps"), med("viewer", "fps")
    best_none, best_view = (max(r["fps"] for r in runs[v]) for v in ("none", "viewer"))
    cpu_none, cpu_view = med("none", "cpu_s"), med("viewer", "cpu_s")
    last = runs["viewer"][-1]
    cost = 100.0 * (1.0 - fps_view / fps_none)
    return {
        "sequence": "synthetic room, slow hand-held orbit, Kinect noise", "frames": frames, "resolution": resolution,
        "repeats": len(runs["none"]), "viewer": "--viewer save=FILE", "images_every": DEFAULTS.images_every,
        "map_every": DEFAULTS.map_every, "map_max_points": DEFAULTS.map_max_points,
        "fps_none": fps_none, "fps_viewer": fps_view, "cost_pct": cost,
        "fps_none_best": best_none, "fps_viewer_best": best_view,
        "cost_best_pct": 100.0 * (1.0 - best_view / best_none),
        "cpu_s_none": cpu_none, "cpu_s_viewer": cpu_view,
        "cpu_ms_per_frame_added": 1e3 * (cpu_view - cpu_none) / max(frames, 1),
        "target_cost_pct": TARGET_COST_PCT, "target_ok": cost <= TARGET_COST_PCT,
        "on_frame_ms": last.get("on_frame_ms"), "logging_cpu_ms": last.get("logging_cpu_ms"),
        "images_logged": last.get("images_logged"), "maps_logged": last.get("maps_logged"),
        "dropped": (last.get("images_dropped") or 0) + (last.get("maps_dropped") or 0),
        "viewer_error": last.get("error"), "rrd_mb": last.get("rrd_mb"),
        "rrd_verify_ok": verify["ok"], "rrd_verify_message": verify["message"],
        "runs": runs,
    }


def section_markdown(s: dict) -> list[str]:
    """The ``make bench`` section: one table row per variant, then how it was measured."""
    from benchmarks.common import fmt, table

    md = [f"### Live viewer cost: {s['frames']} synthetic frames at {s['resolution']} (dense `surfelslam run`)", ""]
    md.append(table(["viewer", "FPS (median)", "FPS (best)", "CPU s (median)", "cost vs none (median / best)",
                     f"target (<= {s['target_cost_pct']:g} %)", "`rerun rrd verify`"],
                    [["none", s["fps_none"], s["fps_none_best"], s["cpu_s_none"], "–", "–", "–"],
                     [f"`{s['viewer']}`", s["fps_viewer"], s["fps_viewer_best"], s["cpu_s_viewer"],
                      f"{fmt(s['cost_pct'])} % / {fmt(s['cost_best_pct'])} %", fmt(s["target_ok"]),
                      "passes" if s["rrd_verify_ok"] else f"**{s['rrd_verify_message']}**"]]))
    fps = {v: ", ".join(f"{r['fps']:.1f}" for r in s["runs"][v]) for v in ("none", "viewer")}
    noise = (" A negative cost means the difference is within the run-to-run spread (other jobs on the machine)."
             if s["cost_pct"] < 0 or s["cost_best_pct"] < 0 else "")
    md += [f"{s['sequence'][0].upper()}{s['sequence'][1:]}; {s['repeats']} runs of each, interleaved (without, "
           "with, with, without, ...) so both see the same load; FPS from each run's `metrics.json` (frames over the "
           "loop's wall time, JIT warm-up excluded), CPU: the process's CPU time for the whole run (all threads). "
           f"FPS of the runs: without {fps['none']}; with {fps['viewer']}.{noise} The viewer logged "
           f"{s['images_logged']} image pairs (every {s['images_every']} frames) and {s['maps_logged']} map "
           f"snapshots (every {s['map_every']} frames, at most {s['map_max_points']:,} points), "
           f"{s['dropped']} dropped; {fmt(s['on_frame_ms'], 2)} ms per frame on the tracking thread, "
           f"{fmt(s['logging_cpu_ms'], 2)} ms CPU per frame in the logging thread, "
           f"{fmt(s['cpu_ms_per_frame_added'], 2)} ms CPU per frame more than without (medians); recording "
           f"{fmt(s['rrd_mb'])} MiB.", ""]
    return md


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--work", type=Path, default=None, help="folder for the sequence, runs and recording (kept)")
    a = ap.parse_args()
    s = bench(a.frames, a.repeats, a.width, a.work)
    print(json.dumps({k: v for k, v in s.items() if k != "runs"}, indent=1))
    print("\n".join(section_markdown(s)))


if __name__ == "__main__":
    main()
