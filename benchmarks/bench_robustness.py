"""Robustness of the trackers on long near-degenerate sequences (issue 33, item 5), beside Open3D's dense SLAM.

Sequences (320x240 unless said, Kinect-like noise, written in TUM layout by
:func:`surfelslam.synth.writer.generate_sequence` and read back like real data; generated once and cached, keyed
by their settings and the generator's source):

* an office tour: the ``office`` scene, ``tour`` style (the slow orbit round the room with a ``upward`` stretch in
  the middle third: a degenerate stretch inside normal motion, as in the office benchmarks), plain;
* ceiling + one wall: the ``office`` scene, ``upward`` style (the camera looks up at the ceiling and one wall and
  moves sideways along it: two planes leave translation along their edge to the texture), plain and textured;
* a single close wall: the ``plane`` scene (one wall about 1.5 m ahead), plain and textured;
* a corridor: the ``corridor`` scene walked back and forth (two long walls), plain and textured, and the plain one
  drawn with a second seed (5): a near-degenerate scene's result varies with the draw;
* the office looking across the room (``tour-across``: most depth beyond 3 m) with ICL-NUIM's synthetic sensor
  noise (``icl``: jittered, quantised disparity, far depth kept), plain, rendered at twice the width (640x480) and
  read as it is, as the default run reads the ICL-NUIM office;
* real hand-held motion in a generated scene: the ``office`` scene, textured, along TUM fr3/teddy's motion-capture
  poses (``surfelslam synth --motion``; 220 frames, 640x480 read as it is), when ``../shared/data`` holds them;
* real: TUM fr3/teddy (first 200 frames) and the two halves of the 7-Scenes kitchen sequence (frames 0-249 and
  250-499), at 320x240, when ``../shared/data`` holds them (otherwise listed in ``not_run`` with the reason).

For each tracker and sequence a row gives ATE RMSE / max, tracking failures, the weak and lost segments from the
run's ``metrics.json`` (:mod:`surfelslam.slam.segments`), the worst 1-second drift and FPS. The worst 1-second
drift is the largest translation of the relative pose error ``(G_i^-1 G_j)^-1 (E_i^-1 E_j)`` over every pair of
estimated poses ``(E_i, E_j)`` and ground-truth poses ``(G_i, G_j)`` whose stamps lie 1 s apart (pairs found by
:func:`surfelslam.eval.metrics.time_delta_pairs`; the errors by :func:`surfelslam.eval.metrics.rpe` with
``delta_unit="seconds"``): how far the trajectory slides, unaligned, within the worst second of the run.

The dense tracker (the frame-to-model engine of both surfel trackers) runs on every sequence; the default hybrid,
``hybrid-full``, orb, the odometry-only variants of hybrid and orb (``hybrid-odometry``, ``orb-odometry``:
:data:`benchmarks.common.VARIANT_TRACKERS`; the page gives each tracker's ATE with loop closure over that without)
and the Open3D side by side (its depth range raised to :data:`OPEN3D_DEPTH_MAX_M` so that it
sees the whole room) run while the time budget allows, and ``skipped`` says what was left out.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from benchmarks.common import (
    ODOMETRY_VARIANTS,
    fmt,
    table,
    tracker_cost_vs_dense,
    tracker_rank,
    tracker_setup,
    variant_set_options,
)
from surfelslam.api import run_sequence
from surfelslam.datasets import DatasetOptions, open_sequence
from surfelslam.eval.metrics import ate, rpe
from surfelslam.io.trajectory import read_tum
from surfelslam.synth.writer import generate_sequence
from surfelslam.types import Trajectory

NOISE = "kinect"  # the generated sequences' noise model unless their spec names another
SEED = 0
DRIFT_WINDOW_S = 1.0  # the worst drift is measured over pose pairs this far apart (s)
OPEN3D_DEPTH_MAX_M = 6.0  # Open3D's example clips depth at 3 m: most of the office is farther
DOWNSAMPLE_REAL = 2  # the real sequences are 640x480: read at 320x240
REAL_FIRST_S_PER_FRAME = 0.05  # a-priori dense cost (s/frame) until a run measured it
# a-priori cost per frame relative to dense, until one run measured it
RUN_OVERHEAD_S = 5.0  # per run: opening, map and metrics writing
SEGMENT_LINES = 3  # segments described per row in the JSON (the counts cover them all)
CACHE_ENV = "SURFELSLAM_BENCH_CACHE"  # where generated sequences are kept between runs (default: the temp folder)


@dataclass(frozen=True)
class Synthetic:
    """One generated sequence: a key, a label, the scene, trajectory style, texture style, noise model and seed."""

    key: str
    label: str
    scene: str
    style: str
    texture: str
    noise: str = NOISE
    render_scale: int = 1  # rendered at this multiple of the section's width and read as it is: the default run
    # then tracks at its ``tracking.max_width_px`` from block means of the larger frames, as on a 640x480 benchmark
    seed: int = SEED  # of the textures, the motion's jitter and the noise


SYNTHETIC = (
    Synthetic("tour_plain", "office tour, looking up mid-way, plain (office, tour)", "office", "tour", "plain"),
    Synthetic("ceiling_plain", "ceiling + wall, plain (office, upward)", "office", "upward", "plain"),
    Synthetic("ceiling_textured", "ceiling + wall, textured (office, upward)", "office", "upward", "rich"),
    Synthetic("wall_plain", "close wall, plain (plane)", "plane", "slow", "plain"),
    Synthetic("wall_textured", "close wall, textured (plane)", "plane", "slow", "rich"),
    Synthetic("corridor_plain", "corridor, plain", "corridor", "slow", "plain"),
    Synthetic("corridor_textured", "corridor, textured", "corridor", "slow", "rich"),
    # the same plain corridor drawn with another seed: the result of a near-degenerate scene varies with the draw
    Synthetic("corridor_plain_seed5", "corridor, plain, seed 5", "corridor", "slow", "plain", seed=5),
    Synthetic("across_icl_plain", "office looking across, ICL-NUIM noise, plain, 640x480 input (office, "
              "tour-across)", "office", "tour-across", "plain", "icl", render_scale=2),
)
SYNTHETIC_KEYS = tuple(s.key for s in SYNTHETIC)


@dataclass(frozen=True)
class Replayed:
    """A generated sequence along a recorded hand-held motion from the shared data (``motion``: its ground-truth
    file, relative to the shared folder; ``n_frames`` at 30 fps, at most what the recording lasts)."""

    label: str
    scene: str
    texture: str
    motion: str
    n_frames: int
    render_scale: int = 2  # 640x480, read as it is, as a hand-held recording is


#: real hand-held motion in a generated scene with exact ground truth: the jerks and rotations of a person's
#: camera, which the scripted styles lack (a desk-sized walk round a teddy bear, TUM fr3/teddy's motion-capture poses)
REPLAYED = (
    Replayed("office, real hand-held motion (TUM fr3/teddy ground truth), textured, 640x480 input", "office",
             "rich", "rgbd_dataset_freiburg3_teddy_first200/groundtruth.txt", 220),
)
#: (label, folder under the shared data, first frame, end frame or None)
REAL = (
    ("TUM fr3/teddy (first 200)", "rgbd_dataset_freiburg3_teddy_first200", 0, None),
    ("7-Scenes kitchen 0-249", "7scenes_redkitchen_0000_0499", 0, 250),
    ("7-Scenes kitchen 250-499", "7scenes_redkitchen_0000_0499", 250, 500),
)


def cache_root() -> Path:
    return Path(os.environ.get(CACHE_ENV) or Path(tempfile.gettempdir()) / "surfelslam_bench_cache")


def _generator_hash() -> str:
    """Hash of the generator's source: a cached sequence is reused only while the generator is unchanged."""
    import surfelslam.synth as synth

    h = hashlib.sha256()
    for p in sorted(Path(synth.__file__).parent.glob("*.py")):
        h.update(p.read_bytes())
    return h.hexdigest()[:12]


def _cached_sequence(cache: Path, key: str, **generate) -> Path:
    """``cache/robustness/key``: the sequence :func:`generate_sequence` writes with ``generate``, from the cache when
    it is there, else written to a partial folder and renamed (a killed run leaves no half sequence behind)."""
    path = cache / "robustness" / key
    if not (path / "groundtruth.txt").is_file():
        part = path.with_name(f".{key}.partial-{os.getpid()}")
        shutil.rmtree(part, ignore_errors=True)
        generate_sequence(part, **generate)
        shutil.rmtree(path, ignore_errors=True)
        part.rename(path)
    return path


def synthetic_sequence(spec: Synthetic, n_frames: int, width: int, cache: Path) -> Path:
    """The generated sequence of ``spec``, cached (keyed by its settings and the generator's source)."""
    width *= spec.render_scale
    height = width * 3 // 4
    key = (f"{spec.scene}_{spec.style}_{spec.texture}_{n_frames}f_{width}x{height}_{spec.noise}_s{spec.seed}_"
           f"{_generator_hash()}")
    return _cached_sequence(cache, key, scene=spec.scene, style=spec.style, n_frames=n_frames, noise=spec.noise,
                            width=width, height=height, texture=spec.texture, seed=spec.seed)


def replayed_sequence(spec: Replayed, motion_file: Path, width: int, cache: Path) -> Path:
    """The generated sequence of ``spec`` along the motion in ``motion_file``, cached (keyed by the motion file's
    content too)."""
    width *= spec.render_scale
    height = width * 3 // 4
    motion_hash = hashlib.sha256(motion_file.read_bytes()).hexdigest()[:8]
    key = (f"{spec.scene}_replay-{motion_hash}_{spec.texture}_{spec.n_frames}f_{width}x{height}_{NOISE}_s{SEED}_"
           f"{_generator_hash()}")
    return _cached_sequence(cache, key, scene=spec.scene, n_frames=spec.n_frames, noise=NOISE, width=width,
                            height=height, texture=spec.texture, motion=read_tum(motion_file),
                            motion_label=spec.motion, seed=SEED)


def worst_drift(est: Trajectory, gt: Trajectory, window_s: float = DRIFT_WINDOW_S) -> tuple[float, float]:
    """``(metres, end of the window in s from the first estimated pose)`` of the worst ``window_s`` drift."""
    r = rpe(est, gt, delta=window_s, delta_unit="seconds")
    k = int(r.trans_errors_m.argmax())
    return float(r.trans_errors_m[k]), float(r.timestamps[k] - est.timestamps[0])


def _cm(v: float | None, nd: int = 2) -> float | None:
    return None if v is None else round(100.0 * v, nd)


def _drift_fields(est: Trajectory, gt: Trajectory, seconds_per_stamp: float = 1.0) -> dict:
    """The worst 1 s drift, with stamps in seconds (ICL-NUIM's frame ids are 1/30 s apart)."""
    est, gt = (Trajectory(t.timestamps * seconds_per_stamp, t.T_world_cam) for t in (est, gt))
    try:
        d, at = worst_drift(est, gt)
    except ValueError as exc:  # EvaluationError: too short for a 1 s pair
        return {"worst_1s_drift_cm": None, "worst_1s_drift_end_s": None, "drift_error": str(exc)}
    return {"worst_1s_drift_cm": _cm(d), "worst_1s_drift_end_s": round(at, 2)}


def run_tracker(label: str, seq, tracker: str, out_dir: Path) -> dict:
    """``surfelslam run`` (defaults but the tracker) on ``seq``; the row from its ``metrics.json`` and trajectory."""
    run_as, cfg = tracker_setup(tracker)
    t0 = time.perf_counter()
    run_sequence(seq, out_dir, cfg, run_as, progress=False, figures=False)
    wall = time.perf_counter() - t0
    m = json.loads((out_dir / "metrics.json").read_text())
    e = m.get("eval") or {}
    segs = m.get("tracking_segments", [])
    est = read_tum(out_dir / "trajectory.txt")
    row = {
        "sequence": label, "tracker": tracker, "frames": m["frames_processed"],
        "resolution": "x".join(str(v) for v in m["resolution"]),
        "ate_rmse_cm": _cm(e.get("ate_rmse_m"), 4), "ate_max_cm": _cm(e.get("ate_max_m")),
        "failures": m.get("tracking_failures", 0),
        "lost_segments": m.get("lost_segments", 0), "weak_segments": m.get("weak_segments", 0),
        "lost_frames": sum(s["frames"] for s in segs if s["kind"] == "lost"),
        "weak_frames": sum(s["frames"] for s in segs if s["kind"] == "weak"),
        "lost_at_end": bool(m.get("lost_at_end", False)),
        "segments": [_describe(s) for s in segs[:SEGMENT_LINES]],
        **_drift_fields(est, seq.ground_truth, seq.seconds_per_stamp),
        "fps": round(m["fps"], 2), "wall_s": round(wall, 1),
    }
    if "eval_error" in m:
        row["eval_error"] = m["eval_error"]
    return row


def _describe(s: dict) -> str:
    text = f"{s['kind']} {s['first_frame']}-{s['last_frame']} ({s['frames']} frames, {s['reason']})"
    return text + (f", {s['bridged_frames']} bridged" if s["bridged_frames"] else "") + f"; {s['recovery']}"


def run_open3d(label: str, seq) -> dict:
    """Open3D's ``t.pipelines.slam`` (its example's settings, depth range up to :data:`OPEN3D_DEPTH_MAX_M`)."""
    from benchmarks.open3d_slam import Open3DSlamConfig, run_open3d_slam

    o3 = run_open3d_slam(seq, Open3DSlamConfig(depth_max_m=OPEN3D_DEPTH_MAX_M))
    a = ate(o3["trajectory"], seq.ground_truth)
    return {"sequence": label, "tracker": f"Open3D (depth <= {OPEN3D_DEPTH_MAX_M:g} m)", "frames": o3["frames"],
            "resolution": f"{seq.intrinsics.width}x{seq.intrinsics.height}",
            "ate_rmse_cm": _cm(a.rmse_m), "ate_max_cm": _cm(a.max_m), "failures": o3["failed"],
            "lost_segments": None, "weak_segments": None, "lost_frames": None, "weak_frames": None,
            "lost_at_end": None, "segments": [],
            **_drift_fields(o3["trajectory"], seq.ground_truth, seq.seconds_per_stamp),
            "fps": round(o3["fps"], 2), "wall_s": round(o3["wall_s"], 1)}


def sequences(n_frames: int, width: int, synthetic: tuple[str, ...], shared: Path | None, cache: Path,
              real_end: int | None = None) -> tuple[list[tuple[str, Path, DatasetOptions]], list[dict]]:
    """``([(label, folder, reader options)], [not run: label and reason])``: the generated ones, those along a
    recorded motion (when the shared data holds it), then the real ones."""
    out, not_run = [], []
    for spec in (s for s in SYNTHETIC if s.key in synthetic):
        path = synthetic_sequence(spec, n_frames, width, cache)
        out.append((spec.label, path, DatasetOptions()))
    for spec in REPLAYED:
        motion = None if shared is None else shared / spec.motion
        if motion is None or not motion.is_file():
            not_run.append({"sequence": spec.label, "reason": f"{spec.motion} not in {shared}"})
            continue
        out.append((spec.label, replayed_sequence(spec, motion, width, cache), DatasetOptions()))
    for label, folder, start, end in REAL:
        path = None if shared is None else shared / folder
        if path is None or not path.is_dir():
            not_run.append({"sequence": label, "reason": f"{folder} not in {shared}"})
            continue
        stop = end if real_end is None else min(start + real_end, end or start + real_end)
        out.append((label, path, DatasetOptions(downsample=DOWNSAMPLE_REAL, start=start, end=stop)))
    return out, not_run


def section(n_frames: int, width: int, work: Path, budget, *, synthetic: tuple[str, ...] = SYNTHETIC_KEYS,
            shared: Path | None = None, extra_trackers: tuple[str, ...] = ("hybrid", "orb"),
            open3d_frames: int = 0, cache: Path | None = None, real_end: int | None = None) -> dict:
    """Run the section: dense on every sequence, then Open3D on the first long generated one (``open3d_frames``
    of it; 0: none), then ``extra_trackers`` on every sequence, each while ``budget.fits`` its estimate."""
    t0 = time.perf_counter()
    seqs, not_run = sequences(n_frames, width, synthetic, shared, cache or cache_root(), real_end)
    gen_s = time.perf_counter() - t0
    rows: list[dict] = []
    per_frame: dict[str, float] = {}  # tracker -> measured wall s per frame

    def estimate(tracker: str, n: int) -> float:
        dense = per_frame.get("dense", REAL_FIRST_S_PER_FRAME)
        return n * per_frame.get(tracker, tracker_cost_vs_dense(tracker) * dense) + RUN_OVERHEAD_S

    def one(tracker: str, label: str, seq, idx: int) -> None:
        if tracker != "dense" and not budget.fits(f"robustness {tracker} on {label} ({len(seq)} frames)",
                                                  estimate(tracker, len(seq))):
            return
        print(f"  robustness: {tracker} on {label} ({len(seq)} frames)", file=sys.stderr, flush=True)
        t = time.perf_counter()
        row = (run_open3d(label, seq) if tracker == "open3d" else
               run_tracker(label, seq, tracker, work / f"{idx}_{tracker}"))
        rows.append(row)
        per_frame[tracker] = (time.perf_counter() - t) / max(len(seq), 1)
        shutil.rmtree(work / f"{idx}_{tracker}", ignore_errors=True)

    for i, (label, path, opts) in enumerate(seqs):
        one("dense", label, open_sequence(path, opts), i)
    if open3d_frames and seqs:
        from benchmarks.open3d_slam import available

        if available():
            label, path, _ = seqs[0]
            one("open3d", label, open_sequence(path, DatasetOptions(end=open3d_frames)), 0)
        else:
            not_run.append({"sequence": "Open3D side by side", "reason": "open3d not importable"})
    for tracker in extra_trackers:
        for i, (label, path, opts) in enumerate(seqs):
            one(tracker, label, open_sequence(path, opts), i)
    return {"frames": n_frames, "resolution": [width, width * 3 // 4], "noise": NOISE,
            "drift_window_s": DRIFT_WINDOW_S, "open3d_depth_max_m": OPEN3D_DEPTH_MAX_M, "rows": rows,
            "not_run": not_run, "generate_or_cache_s": round(gen_s, 1)}


def section_markdown(res: dict) -> list[str]:
    """The ``make bench`` section: one table of every (sequence, tracker) row and how to read it."""
    seq_order = {k: i for i, k in enumerate(dict.fromkeys(r["sequence"] for r in res["rows"]))}
    rows = sorted(res["rows"], key=lambda r: (seq_order[r["sequence"]], tracker_rank(r["tracker"])))
    w, h = res["resolution"]
    md = [f"### Robustness: long near-degenerate sequences ({res['frames']} generated frames at {w}x{h} "
          f"and {res['noise']} noise unless the row says) and real ones", ""]
    md.append(table(["sequence", "frames", "tracker", "ATE RMSE cm", "ATE max cm", "failures", "lost segments "
                     "(frames)", "weak segments (frames)", "worst 1 s drift cm", "FPS"],
                    [[r["sequence"], r["frames"], r["tracker"], fmt(r["ate_rmse_cm"], 2), fmt(r["ate_max_cm"], 2),
                      r["failures"], _seg(r, "lost") + (" **lost at end**" if r.get("lost_at_end") else ""),
                      _seg(r, "weak"), fmt(r["worst_1s_drift_cm"], 2), r["fps"]] for r in rows]))
    md += ["Generated sequences: `surfelslam synth` scenes with Kinect-like noise unless the row says ICL-NUIM noise "
           "(`--noise icl`) and seed 0 unless the row names another (`--seed`), cached between runs. Ceiling + "
           "wall: `office`, style `upward`; close wall: `plane` (one wall about 1.5 m ahead); corridor: `corridor` "
           "walked back and forth; plain = flat paint on walls, ceiling and floor covering, textured = the "
           "default textures; office tour: `office`, style `tour` (the slow orbit with an upward stretch in its middle "
           "third); looking across: style `tour-across`, the same with the orbit looking across the room (most depth "
           "beyond 3 m); 640x480 input: rendered at 640x480 and run as is (the default tracks at 320x240 from 2x2 "
           "block means); real hand-held motion: `surfelslam synth --motion` with TUM fr3/teddy's motion-capture poses "
           "(exact ground truth, a person's jerks and turns). Segments: the weak and lost stretches of the run's "
           "`metrics.json`. Worst 1 s drift: "
           f"the largest translation error of the relative pose over every pair of poses {res['drift_window_s']:g} "
           "s apart (`eval.metrics.rpe`, `delta_unit=\"seconds\"`), unaligned. FPS: wall clock, JIT warm-up "
           "excluded." + (f" Open3D: `t.pipelines.slam` with its example's settings but depth up to "
                          f"{res['open3d_depth_max_m']:g} m, on the same decoded frames."
                          if any(r["tracker"].startswith("Open3D") for r in rows) else ""), ""]
    md += _loops_against_odometry(rows)
    lost = [f"{r['sequence']} / {r['tracker']}: {'; '.join(r['segments'])}" for r in rows
            if r["tracker"] == "dense" and r.get("segments")]
    if lost:
        md += ["Dense tracker's first segments: " + " | ".join(lost) + ".", ""]
    if res.get("skipped"):
        md += ["Skipped (time budget of the section): " + "; ".join(s["what"] for s in res["skipped"]) + ".", ""]
    if res["not_run"]:
        md += ["Not run: " + "; ".join(f"{n['sequence']} ({n['reason']})" for n in res["not_run"]) + ".", ""]
    return md


def _seg(r: dict, kind: str) -> str:
    n = r.get(f"{kind}_segments")
    return "–" if n is None else f"{n} ({r[f'{kind}_frames']})"


def _loops_against_odometry(rows: list[dict]) -> list[str]:
    """One line per tracker with an odometry-only variant (:data:`ODOMETRY_VARIANTS`): per sequence, its ATE with loop
    closure over that without; over 1.1 would be loop closure making the trajectory worse by more than 10 %."""
    ate = {(r["sequence"], r["tracker"]): r["ate_rmse_cm"] for r in rows}
    lines = []
    for tracker, variant in ODOMETRY_VARIANTS.items():
        pairs = [(seq, ate[(seq, tracker)], off) for (seq, trk), off in ate.items()
                 if trk == variant and off and ate.get((seq, tracker)) is not None]
        if not pairs:
            continue
        parts = [f"{seq} {on / off:.2f}" for seq, on, off in pairs]
        worst = max(on / off for _, on, off in pairs)
        lines += [f"Loop closure against the odometry alone ({tracker}; ATE with loop closure / without, "
                  f"`{variant}`: `{variant_set_options(variant)}`): {'; '.join(parts)}. Worst: {worst:.2f}.", ""]
    return lines
