"""Scale: one run over a generated multi-room floor (issue 68), the default beside dense (and Open3D on a part).

The sequence: ``surfelslam synth`` scene ``floor`` (rooms off a corridor), trajectory ``walk`` (about 1.2 m/s at
30 Hz, hand-held jitter, revisits after long loops), Kinect noise, at ``width`` x 3/4 ``width``.

Each tracker runs twice:

* as a user runs it, ``python -m surfelslam run SEQ --no-figures --no-progress`` in a child process
  (:func:`child_run`): the whole-process wall time timed from outside, the child's own CPU time and peak memory
  (``os.wait4``'s rusage of that child alone: ``ru_utime + ru_stime``, ``ru_maxrss``); ATE, FPS, loops, surfel count,
  start-up and shut-down times from its ``metrics.json``; the worst drift over 1 m of path from its
  ``trajectory.txt`` (:func:`worst_drift_over_path`); the map's accuracy from its ``map.ply`` (:func:`map_accuracy`);
* in this process (:func:`cpu_series`), for the CPU time of every frame (the process's CPU time between two
  frames' ends: main thread, reader thread and back end), plotted against the frame index.

The default runs a third time as a child, with ``--set hybrid.loop_correction=false``: its own odometry, no
pose-graph correction applied (the same measures), for issue 68's ratio of the two ATEs.

Then, on the default's run: ``surfelslam mesh`` and ``surfelslam rerun`` in child processes (time, peak memory,
file size), and the sizes of ``map.ply`` / ``map.npz`` (written inside the run's ``shutdown_s``). Open3D's
``t.pipelines.slam`` on the first frames, when it imports.

Usage: ``.venv/bin/python -m benchmarks.bench_scale [--frames 5000] [--width 320] [--open3d-frames 300]
[--work DIR]``; prints the Markdown; ``section(...)`` returns the results.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import MB, child_run, fmt, table
from surfelslam.datasets import DatasetOptions, open_sequence
from surfelslam.slam import SlamConfig

SCENE, TRAJECTORY, NOISE = "floor", "walk", "kinect"
TRACKERS = ("hybrid", "dense")  # the default first: mesh and Rerun run on its map
# the default's own odometry: the same run with no pose-graph correction applied (issue 68: ATE <= 0.5x of it)
ODOMETRY_ONLY_LABEL, ODOMETRY_ONLY_SET = "hybrid, odometry only", "hybrid.loop_correction=false"
DRIFT_PATH_M = 1.0  # issue 68: the worst drift over this much travelled (ground-truth) path
MAP_SAMPLES = 50_000  # map.ply points whose distance to the true surfaces is measured (deterministic subset)
DISTANCE_CHUNK = 20_000  # points per call of the scene's distance (points x primitives float64 in memory)
NEAR_SURFACE_M = 0.01  # a map point this close to the true surface counts as on it
FLAT_WINDOW = 500  # issue 68: the last 500 frames against the first 500 (CPU per frame)
FLAT_MAX_RATIO = 1.3  # ... at most this ratio
SMOOTH_FRAMES = 50  # the plot's running mean (frames)
# issue 68's "done when" on a floor of at least TARGET_FRAMES frames (the default at 320x240)
TARGET_FRAMES = 5000
TARGET_FPS, TARGET_OVER_DENSE = 30.0, 0.75  # FPS, and FPS over dense's in the same run
TARGET_PEAK_MB = 4096.0  # peak resident memory below 4 GB
TARGET_ATE_CM = 2.0
TARGET_OVER_ODOMETRY = 0.5  # the default's ATE over its own odometry-only ATE


def worst_drift_over_path(T_est: np.ndarray, T_gt: np.ndarray, path_m: float = DRIFT_PATH_M
                          ) -> tuple[float, int, int] | None:
    """The worst drift over ``path_m`` of travelled path: ``(metres, start index, end index)``, ``None`` when the
    whole ground-truth path is shorter.

    ``T_est``, ``T_gt``: ``(N, 4, 4)`` ``T_world_cam`` of the same frames. For every start ``i``, ``j`` is the first
    frame at least ``path_m`` further along the ground-truth path; the drift is the translation of the relative
    pose error ``(G_i^-1 G_j)^-1 (E_i^-1 E_j)`` (independent of each trajectory's world frame)."""
    T_est, T_gt = np.asarray(T_est, np.float64), np.asarray(T_gt, np.float64)
    walked = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(T_gt[:, :3, 3], axis=0), axis=1))])
    j = np.searchsorted(walked, walked + path_m, side="left")
    i = np.flatnonzero(j < len(walked))
    if len(i) == 0:
        return None
    j = j[i]
    rel_gt = np.linalg.inv(T_gt[i]) @ T_gt[j]
    rel_est = np.linalg.inv(T_est[i]) @ T_est[j]
    err = np.linalg.norm((np.linalg.inv(rel_gt) @ rel_est)[:, :3, 3], axis=1)
    k = int(np.argmax(err))
    return float(err[k]), int(i[k]), int(j[k])


def map_accuracy(points_run: np.ndarray, T_align: np.ndarray, scene, samples: int = MAP_SAMPLES) -> dict:
    """Distance of map points (``(N, 3)`` in the run's frame, moved into the scene's by ``T_align``) to the scene's
    exact surfaces, over an evenly spaced subset of ``samples`` of them: mean, median, p90 (m), share within
    :data:`NEAR_SURFACE_M`."""
    pts = np.asarray(points_run, np.float64)
    pts = pts[np.linspace(0, len(pts) - 1, min(samples, len(pts))).astype(np.int64)] if len(pts) else pts
    pts = pts @ T_align[:3, :3].T + T_align[:3, 3]
    d = np.concatenate([scene.distance_to_surface(pts[s : s + DISTANCE_CHUNK])
                        for s in range(0, len(pts), DISTANCE_CHUNK)] or [np.zeros(0)])
    if len(d) == 0:
        return {"map_points_measured": 0}
    return {"map_points_measured": int(len(d)), "map_accuracy_mean_mm": round(1e3 * float(d.mean()), 2),
            "map_accuracy_median_mm": round(1e3 * float(np.median(d)), 2),
            "map_accuracy_p90_mm": round(1e3 * float(np.percentile(d, 90)), 2),
            "map_within_1cm_pct": round(100.0 * float(np.mean(d <= NEAR_SURFACE_M)), 1)}


def ate_aligned_map_accuracy(points_run: np.ndarray, est, gt, scene) -> dict:
    """:func:`map_accuracy` with the map moved by the ATE's best-fit alignment of the trajectory (``est``, ``gt``:
    :class:`~surfelslam.types.Trajectory`), keys prefixed ``ate_aligned_``: how good the map's shape is, apart
    from where the first pose put it (the first-pose figure mostly measures the trajectory's drift)."""
    from surfelslam.errors import SurfelSlamError
    from surfelslam.eval.metrics import ate

    try:
        T_align = ate(est, gt).T_align
    except SurfelSlamError:
        return {}
    acc = map_accuracy(points_run, T_align, scene)
    return {f"ate_aligned_{k}": v for k, v in acc.items() if k != "map_points_measured"}


def cpu_series(seq_dir: Path, tracker: str, out_dir: Path) -> np.ndarray:
    """``(N,)`` CPU ms of each frame of an in-process run (NaN for the first: no previous frame end)."""
    from surfelslam.api import run_sequence

    seq = open_sequence(seq_dir, DatasetOptions())
    cpu = np.full(len(seq), np.nan)
    last = [None]

    def on_frame(frame, result, _tracker) -> None:
        now = time.process_time()
        if last[0] is not None and result.index < len(cpu):
            cpu[result.index] = (now - last[0]) * 1e3
        last[0] = now

    run_sequence(seq, out_dir, SlamConfig(), tracker, progress=False, figures=False, on_frame=on_frame)
    return cpu


def flat_ratio(cpu_ms: np.ndarray, window: int = FLAT_WINDOW) -> dict:
    """Mean CPU ms of the first and the last ``window`` frames (at most a third of the run each) and their ratio."""
    c = np.asarray(cpu_ms, np.float64)
    w = max(1, min(window, len(c) // 3))
    first, last = float(np.nanmean(c[:w])), float(np.nanmean(c[-w:]))
    return {"window": w, "cpu_first_ms": round(first, 2), "cpu_last_ms": round(last, 2),
            "last_over_first": round(last / first, 3) if first > 0 else None}


def run_row(tracker: str, seq_dir: Path, run_dir: Path, scene, gt, extra: tuple[str, ...] = (),
            label: str | None = None) -> dict:
    """One tracker through ``surfelslam run`` in a child process (``extra``: more arguments; ``label``: the row's
    name, the tracker's by default): the row (module docstring)."""
    from surfelslam.eval.mesh_quality import first_pose_alignment
    from surfelslam.io.ply import read_ply
    from surfelslam.io.trajectory import read_tum

    child = child_run(["run", str(seq_dir), "--out", str(run_dir), "--tracker", tracker, "--no-figures",
                       "--no-progress", *extra])
    if child["returncode"] != 0:
        raise RuntimeError(f"surfelslam run --tracker {tracker} exited {child['returncode']}: {child['stderr']}")
    m = json.loads((run_dir / "metrics.json").read_text())
    e, n = m.get("eval") or {}, m["frames_processed"]
    est, ok = read_tum(run_dir / "trajectory.txt").lookup(gt.timestamps, 1e-4)
    drift = worst_drift_over_path(est[ok], gt.T_world_cam[ok]) if ok.sum() > 1 else None
    first = int(np.flatnonzero(ok)[0]) if ok.any() else 0
    ply = read_ply(run_dir / "map.ply")
    pts = np.stack([ply["x"], ply["y"], ply["z"]], 1)
    acc = map_accuracy(pts, first_pose_alignment(est[first], gt.T_world_cam[first]), scene)
    acc |= ate_aligned_map_accuracy(pts, read_tum(run_dir / "trajectory.txt"), gt, scene)
    return {"tracker": label or tracker, "frames": n, "ate_cm": None if e.get("ate_rmse_m") is None else
            round(100 * e["ate_rmse_m"], 2), "worst_1m_drift_cm": None if drift is None else round(100 * drift[0], 2),
            "worst_1m_drift_frames": None if drift is None else [drift[1], drift[2]],
            "loops_found": m.get("loops_found"), "loops_accepted": m.get("loops_accepted"),
            "fps": round(m["fps"], 2), "wall_s": child["wall_s"],
            "cpu_ms_per_frame": round(1e3 * child["cpu_s"] / n, 2),
            "peak_mb": child["peak_mb"], "surfels": m.get("map_points"), "startup_s": round(m["startup_s"], 2),
            "shutdown_s": round(m["shutdown_s"], 2), "failures": m.get("tracking_failures"),
            "lost_segments": m.get("lost_segments"),
            "map_ply_mb": round((run_dir / "map.ply").stat().st_size / MB, 2),
            "map_npz_mb": round((run_dir / "map.npz").stat().st_size / MB, 2) if (run_dir / "map.npz").is_file()
            else None, **acc}


def outputs(run_dir: Path, work: Path) -> list[dict]:
    """``surfelslam mesh`` and ``surfelslam rerun`` on a run, each in a child process: time, peak memory, size."""
    from benchmarks.bench_viewer import missing

    rows = []
    mesh = work / "mesh.ply"
    c = child_run(["mesh", str(run_dir), "--out", str(mesh), "--no-progress"])
    rows.append({"what": "surfelslam mesh (TSDF, defaults)", **c,
                 "size_mb": round(mesh.stat().st_size / MB, 2) if mesh.is_file() else None})
    why = missing()
    if why:
        rows.append({"what": "surfelslam rerun", "skipped": why})
    else:
        rrd = work / "run.rrd"
        c = child_run(["rerun", str(run_dir), "--out", str(rrd)])
        rows.append({"what": "surfelslam rerun (images every 10 frames)", **c,
                     "size_mb": round(rrd.stat().st_size / MB, 2) if rrd.is_file() else None})
    for r in rows:
        if r.get("returncode") == 0:
            del r["stderr"]  # kept only to say why a command failed
    return rows


def open3d_part(seq_dir: Path, n_frames: int) -> dict | None:
    """Open3D's ``t.pipelines.slam`` on the first ``n_frames`` frames (``None`` when it does not import; its error,
    e.g. a full voxel-block hash map, in ``error``: it runs last and must not lose the section's other rows)."""
    from benchmarks import open3d_slam
    from surfelslam.eval.metrics import evaluate

    if not n_frames or not open3d_slam.available():
        return None
    seq = open_sequence(seq_dir, DatasetOptions(end=n_frames))
    try:
        o3 = open3d_slam.run_open3d_slam(seq)
        e = evaluate(o3["trajectory"], seq.ground_truth)
    except Exception as exc:  # noqa: BLE001 - reported on the page, the section goes on
        return {"tracker": "open3d", "frames": len(seq), "version": open3d_slam.version(),
                "error": f"{type(exc).__name__}: {exc}"}
    return {"tracker": "open3d", "frames": len(seq), "ate_cm": round(100 * e["ate_rmse_m"], 2),
            "fps": round(o3["fps"], 2), "failures": o3["failed"], "version": open3d_slam.version()}


def section(n_frames: int, width: int, work: Path, open3d_frames: int = 0, plot_dir: Path | None = None) -> dict:
    """``make bench``'s ``scale`` section (module docstring); the CPU-per-frame plot goes to ``plot_dir``."""
    from surfelslam.synth.scenes import make_scene
    from surfelslam.synth.writer import generate_sequence

    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    seq_dir = generate_sequence(work / "floor", scene=SCENE, style=TRAJECTORY, n_frames=n_frames, noise=NOISE,
                                seed=0, width=width, height=width * 3 // 4)
    gen_s = time.perf_counter() - t0
    gt = open_sequence(seq_dir, DatasetOptions()).ground_truth
    scene = make_scene(SCENE)
    rows, series = [], {}
    for tracker in TRACKERS:
        rows.append(run_row(tracker, seq_dir, work / f"run_{tracker}", scene, gt))
        series[tracker] = cpu_series(seq_dir, tracker, work / f"series_{tracker}")
        rows[-1].update(flat_ratio(series[tracker]))
    rows.append(run_row(TRACKERS[0], seq_dir, work / "run_odometry_only", scene, gt, ("--set", ODOMETRY_ONLY_SET),
                        ODOMETRY_ONLY_LABEL))
    path_m = float(np.linalg.norm(np.diff(gt.T_world_cam[:, :3, 3], axis=0), axis=1).sum())
    res = {"frames": n_frames, "resolution": f"{width}x{width * 3 // 4}", "path_m": round(path_m, 1),
           "generate_s": round(gen_s, 1), "rows": rows, "outputs": outputs(work / f"run_{TRACKERS[0]}", work),
           "open3d": open3d_part(seq_dir, open3d_frames), "flat_max_ratio": FLAT_MAX_RATIO,
           "cpu_ms_per_block": {k: _blocks(v) for k, v in series.items()}}
    if plot_dir is not None:
        res["plot"] = _plot(series, res, plot_dir).name
    return res


def _blocks(cpu_ms: np.ndarray, n_blocks: int = 50) -> dict:
    """The per-frame series (from frame 1) in about ``n_blocks`` block means (compact JSON)."""
    c = np.asarray(cpu_ms[1:])  # frame 0 has no time (NaN)
    block = max(1, len(c) // n_blocks)
    n = len(c) // block
    means = c[: n * block].reshape(n, block).mean(axis=1)
    return {"block_frames": block, "mean": [round(float(x), 2) for x in means]}


def _plot(series: dict[str, np.ndarray], res: dict, out_dir: Path) -> Path:
    from surfelslam.viz.save import new_figure, save_figure

    fig = new_figure((9.0, 4.0))
    ax = fig.add_subplot(1, 1, 1)
    top = 1.0
    for i, (tracker, cpu) in enumerate(series.items()):
        k = np.arange(len(cpu))
        c = np.nan_to_num(cpu, nan=float(np.nanmean(cpu)))
        ax.plot(k, c, lw=0.4, color=f"C{i}", alpha=0.3)
        win = max(1, min(SMOOTH_FRAMES, len(c) // 5))  # short runs (--quick): a shorter running mean
        ax.plot(k[win - 1 :], np.convolve(c, np.ones(win) / win, mode="valid"), lw=1.5, color=f"C{i}",
                label=f"{tracker} (mean of {win})")
        top = max(top, float(np.nanpercentile(cpu, 99)) * 1.2)
    ax.set_ylim(0, top)
    ax.set_xlabel("frame index")
    ax.set_ylabel("process CPU ms per frame")
    ax.set_title(f"floor walk, {res['frames']} frames at {res['resolution']} ({res['path_m']:.0f} m of path)")
    ax.legend(loc="upper left", fontsize=8)
    out_dir.mkdir(parents=True, exist_ok=True)
    return save_figure(fig, out_dir / f"scale_cpu_{res['resolution']}.png")


def section_markdown(res: dict) -> list[str]:
    """The page's ``scale`` section: the run table, the outputs table and the notes."""
    md = [f"### Scale: a multi-room floor, {res['frames']} synthetic frames at {res['resolution']} "
          f"({res['path_m']:g} m walked)", ""]
    rows = list(res["rows"]) + ([res["open3d"]] if res.get("open3d") else [])
    md.append(table(
        ["tracker", "frames", "ATE cm", "worst 1 m drift cm", "loops found / accepted", "FPS", "wall s",
         "CPU ms/frame", f"last/first {res['rows'][0].get('window', FLAT_WINDOW)} CPU", "peak MB", "surfels",
         "map acc. mean / p90 mm", "map within 1 cm", "map acc. ATE-aligned mean / p90 mm / within 1 cm",
         "start s", "end s", "map.ply / map.npz MB"],
        [[r["tracker"], r["frames"], fmt(r.get("ate_cm"), 2), fmt(r.get("worst_1m_drift_cm"), 2),
          f"{fmt(r.get('loops_found'))} / {fmt(r.get('loops_accepted'))}" if "loops_found" in r else "–",
          fmt(r.get("fps")), fmt(r.get("wall_s")), fmt(r.get("cpu_ms_per_frame")), fmt(r.get("last_over_first"), 2),
          fmt(r.get("peak_mb"), 0), f"{r['surfels']:,}" if r.get("surfels") is not None else "–",
          f"{fmt(r.get('map_accuracy_mean_mm'), 1)} / {fmt(r.get('map_accuracy_p90_mm'), 1)}",
          f"{fmt(r.get('map_within_1cm_pct'))} %" if r.get("map_within_1cm_pct") is not None else "–",
          f"{fmt(r.get('ate_aligned_map_accuracy_mean_mm'), 1)} / {fmt(r.get('ate_aligned_map_accuracy_p90_mm'), 1)}"
          f" / {fmt(r.get('ate_aligned_map_within_1cm_pct'))} %" if "ate_aligned_map_accuracy_mean_mm" in r else "–",
          fmt(r.get("startup_s"), 2), fmt(r.get("shutdown_s"), 2),
          f"{fmt(r.get('map_ply_mb'), 2)} / {fmt(r.get('map_npz_mb'), 2)}" if "map_ply_mb" in r else "–"]
         for r in rows]))
    md += _verdict(res)
    o = res.get("open3d")
    md += ["`surfelslam synth --scene floor --trajectory walk` (Kinect noise, seed 0). Each of our rows is one "
           "`python -m surfelslam run SEQ --tracker T --no-figures --no-progress` in a child process: wall s is "
           "the whole process timed from outside (start-up, JIT cache load, warm-up, frames, writing the outputs); "
           "CPU ms/frame is the child's own CPU time (`os.wait4` rusage, user + system, every thread) divided by "
           "the frames; peak MB its `ru_maxrss`; ATE, FPS, loops, surfels, start s (`startup_s`) and end s "
           "(`shutdown_s`: last frame to the outputs written, map.ply and map.npz included) from its "
           f"`metrics.json`. Worst 1 m drift: the largest translation error of the relative pose from each frame "
           f"to the first frame {DRIFT_PATH_M:g} m further along the true path. Map accuracy: distance of "
           f"{MAP_SAMPLES:,} of map.ply's surfels (evenly spaced) to the scene's exact surfaces, the map put on the "
           "first true pose; ATE-aligned: the same with the map moved by the ATE's best-fit alignment "
           "(the map's own shape, apart from the drift that the first-pose figure adds). last/first 500 CPU: "
           "the process CPU time per frame of a second, in-process run of "
           f"the same tracker (between two frames' ends), last over first {res['rows'][0].get('window', '–')} "
           f"frames (issue 68: <= {res['flat_max_ratio']}); plot: `{res.get('plot', '–')}`. "
           f"{ODOMETRY_ONLY_LABEL}: the default with `--set {ODOMETRY_ONLY_SET}` (its pose graph's corrections not "
           "applied to the trajectory or the map)."
           + (f" Open3D {o['version']} `t.pipelines.slam` (CPU, example defaults) on the first {o['frames']} "
              "frames only, in the bench's process (frames decoded first)" if o else "")
           + (f"; it failed: {o['error']}." if o and o.get("error") else "." if o else ""), ""]
    out = res.get("outputs") or []
    if out:
        md.append(table(["on the default's run", "wall s", "CPU s", "peak MB", "file MB", "exit"],
                        [[r["what"], fmt(r.get("wall_s")), fmt(r.get("cpu_s")), fmt(r.get("peak_mb"), 0),
                          fmt(r.get("size_mb"), 2), r.get("skipped") or fmt(r.get("returncode"))] for r in out]))
        md += ["Each command in a child process on the whole floor's run (times and peak memory as above); writing "
               "map.ply and map.npz is part of the run's end s above.", ""]
    return md


def _verdict(res: dict) -> list[str]:
    """One line: the default's row against issue 68's targets (indicative on fewer than :data:`TARGET_FRAMES`)."""
    rows = {r["tracker"]: r for r in res["rows"]}
    d, dense = rows.get(TRACKERS[0]), rows.get("dense")
    if d is None or d.get("fps") is None:
        return []
    checks = [(f"FPS >= {TARGET_FPS:g}", d["fps"] >= TARGET_FPS)]
    if dense and dense.get("fps"):
        checks.append((f">= {TARGET_OVER_DENSE}x dense's FPS ({d['fps'] / dense['fps']:.2f})",
                       d["fps"] >= TARGET_OVER_DENSE * dense["fps"]))
    if d.get("last_over_first") is not None:
        checks.append((f"last/first CPU <= {res['flat_max_ratio']}", d["last_over_first"] <= res["flat_max_ratio"]))
    if d.get("peak_mb") is not None:
        checks.append(("peak memory < 4 GB", d["peak_mb"] < TARGET_PEAK_MB))
    if d.get("ate_cm") is not None:
        checks.append((f"ATE <= {TARGET_ATE_CM:g} cm", d["ate_cm"] <= TARGET_ATE_CM))
        odo = rows.get(ODOMETRY_ONLY_LABEL)
        if odo and odo.get("ate_cm"):
            checks.append((f"ATE <= {TARGET_OVER_ODOMETRY:g}x its odometry-only ATE "
                           f"({d['ate_cm'] / odo['ate_cm']:.2f})", d["ate_cm"] <= TARGET_OVER_ODOMETRY * odo["ate_cm"]))
    if d.get("lost_segments") is not None:
        checks.append(("no lost segment", d["lost_segments"] == 0))
    scope = ("issue 68's targets" if res["frames"] >= TARGET_FRAMES else
             f"issue 68's targets (indicative: they are for >= {TARGET_FRAMES} frames)")
    return [f"The default (`{d['tracker']}`) against {scope}: "
            + "; ".join(f"{name} {fmt(ok)}" for name, ok in checks) + ".", ""]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=5000)
    ap.add_argument("--width", type=int, default=320, help="image width (height = 3/4 of it)")
    ap.add_argument("--open3d-frames", type=int, default=0, help="Open3D on the first N frames (0: none)")
    ap.add_argument("--work", type=Path, default=None, help="working folder (default: a temporary one)")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench_scale_") as tmp:
        work = a.work or Path(tmp)
        res = section(a.frames, a.width, work, a.open3d_frames, plot_dir=work)
        print("\n".join(section_markdown(res)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
