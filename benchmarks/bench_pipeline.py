"""Whole dense loop (preprocess, render, ICP, fuse) FPS and per-frame cost over a long sequence.

Frames are generated in memory first (synthetic room, Kinect noise; by default the ``handheld`` orbit
across the room, which keeps revisiting what it saw; or ``loop`` laps of ``lap`` frames, repeated), then fed to
:class:`~surfelslam.pipeline.DenseSlam` with the timer running, so reading/decoding costs nothing here
(``surfelslam run`` reads in a background thread). Reported per resolution: FPS of the loop (wall clock),
mean ms per stage, the mean per-frame CPU time of the main thread (robust to other jobs; the kernels are
serial by default) over the first and the last ``window`` frames and over the same views seen again one
orbit later (``revisit``), with their ratios (flat cost: <= 1.3), the density of the map in view (surfels
projecting into the image per valid depth pixel), the map size at the end, and the pose error vs the
generator's trajectory. A PNG of the per-frame cost against the frame index
is written next to the results (``benchmarks/results/pipeline_cost_<W>x<H>.png``).

Serial kernels unless ``--parallel`` (see :mod:`surfelslam.kernels.threads`).

Usage: ``.venv/bin/python benchmarks/bench_pipeline.py [--quick] [--frames N] [--lap N] [--width W]``;
``run(quick)`` returns the rows.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from surfelslam.eval.metrics import ate
from surfelslam.kernels import fusion as kf
from surfelslam.kernels import threads
from surfelslam.pipeline import DenseSlam, SlamConfig, warm_up
from surfelslam.synth.scenes import make_scene
from surfelslam.synth.trajectories import TrajectoryConfig, make_trajectory
from surfelslam.synth.writer import default_intrinsics, iter_frames, noise_config
from surfelslam.types import RGBDFrame, Trajectory

RESULTS = Path(__file__).resolve().parent / "results"
_STEP_DEG = TrajectoryConfig().slow_step_deg  # "handheld" advances this much per frame: a full orbit per 720


def _frames(width: int, n_frames: int, style: str, lap: int, seed: int = 0) -> tuple[list[RGBDFrame], Trajectory]:
    """``n_frames`` noisy frames and their true poses: ``style`` ``handheld`` (an orbit across the room that
    keeps coming back) or ``loop`` (laps round the room of ``lap`` frames, repeated)."""
    scene = make_scene("room")
    intr = default_intrinsics(width, width * 3 // 4)
    if style == "loop":
        one = make_trajectory("loop", lap, scene, seed=seed)
        reps = -(-n_frames // lap)
        T = np.concatenate([one.T_world_cam] * reps)[:n_frames]
        traj = Trajectory(np.arange(n_frames) / 30.0, T)
    else:
        traj = make_trajectory(style, n_frames, scene, seed=seed)
    frames = list(iter_frames(scene, traj, intr, noise_config("kinect"), seed))
    return frames, traj


def bench(width: int, n_frames: int, window: int, style: str = "handheld", lap: int = 250, plot: bool = True,
          remove_duplicates: bool = True) -> dict:
    frames, gt = _frames(width, n_frames, style, lap)
    intr = default_intrinsics(width, width * 3 // 4)
    cfg = SlamConfig()
    cfg.fusion.remove_duplicates = remove_duplicates
    warm_up(cfg)
    slam = DenseSlam(intr, cfg)
    per_frame = np.zeros(len(frames))
    cpu = np.zeros(len(frames))
    stages: dict[str, list[float]] = {}
    density = np.zeros(len(frames))
    poses = []
    for k, f in enumerate(frames):
        t0, c0 = time.perf_counter(), time.thread_time()
        res = slam.process(f)
        per_frame[k] = (time.perf_counter() - t0) * 1e3
        cpu[k] = (time.thread_time() - c0) * 1e3
        poses.append(res.T_world_cam)
        for name, ms in res.timings_ms.items():
            stages.setdefault(name, []).append(ms)
        density[k] = _surfels_per_pixel(slam, res.T_world_cam, intr, cfg, f)
    total_s = float(per_frame.sum()) / 1e3  # the loop only (not the density measurement)
    est = Trajectory(gt.timestamps, np.array(poses))
    w = min(window, len(frames) // 2)
    first, last = float(cpu[1 : w + 1].mean()), float(cpu[-w:].mean())
    row = {
        "resolution": f"{intr.width}x{intr.height}", "frames": len(frames),
        "style": style if style != "loop" else f"loop/{lap}",
        "fps": round(len(frames) / total_s, 2),
        **{f"{k}_ms": round(float(np.mean(v)), 2) for k, v in stages.items()},
        "cpu_first_ms": round(first, 2), "cpu_last_ms": round(last, 2), "last_over_first": round(last / first, 3),
        "density_first": round(float(density[1 : w + 1].mean()), 3),
        "density_last": round(float(density[-w:].mean()), 3),
        "map_surfels": int(slam.map.n_alive), "ate_cm": round(ate(est, gt).rmse_m * 100, 2),
        "failures": int(slam.failures), "parallel": threads.parallel_enabled(), "window": w,
        "remove_duplicates": remove_duplicates,
    }
    period = lap if style == "loop" else int(round(360.0 / _STEP_DEG))
    if len(frames) >= period + w + 1:  # the same views seen a second time
        again = float(cpu[period + 1 : period + w + 1].mean())
        row["cpu_revisit_ms"] = round(again, 2)
        row["revisit_over_first"] = round(again / first, 3)
        row["density_revisit"] = round(float(density[period + 1 : period + w + 1].mean()), 3)
    if plot:
        _plot(cpu, density, row)
    return row


def _surfels_per_pixel(slam: DenseSlam, T: np.ndarray, intr, cfg: SlamConfig, frame: RGBDFrame) -> float:
    """Map surfels whose centre projects into the image (in range, facing the camera) per valid depth pixel."""
    smap = slam.map
    cand = smap.visible_candidates(T, intr, cfg.fusion.min_depth_m, cfg.fusion.max_depth_m)
    Tc = np.linalg.inv(T)
    H, W = intr.shape
    arr = smap.raw()
    n = kf.bucket_by_pixel(
        cand, len(cand), arr["position"], arr["normal"], np.ascontiguousarray(Tc[:3, :3]),
        np.ascontiguousarray(Tc[:3, 3]), float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy), H, W,
        cfg.fusion.min_depth_m, cfg.fusion.max_depth_m, True, np.empty(len(cand), np.int32),
        np.empty(H * W + 1, np.int32), np.empty(len(cand), np.int32),
    )
    d = frame.depth_m
    valid = int(np.count_nonzero((d >= cfg.fusion.min_depth_m) & (d <= cfg.fusion.max_depth_m)))
    return n / max(valid, 1)


def _plot(per_frame: np.ndarray, cands: np.ndarray, row: dict) -> None:
    from surfelslam.viz.save import new_figure, save_figure

    fig = new_figure((9.0, 4.0))
    ax = fig.add_subplot(1, 1, 1)
    k = np.arange(len(per_frame))
    ax.plot(k, per_frame, lw=0.5, color="0.6", label="per frame")
    win = 25
    if len(per_frame) > win:
        smooth = np.convolve(per_frame, np.ones(win) / win, mode="valid")
        ax.plot(k[win - 1 :], smooth, lw=1.5, color="C0", label=f"mean of {win}")
    ax.set_xlabel("frame index")
    ax.set_ylabel("CPU ms per frame (preprocess+render+ICP+fuse)")
    ax.set_ylim(0, max(1.0, float(np.percentile(per_frame, 99)) * 1.3))
    ax2 = ax.twinx()
    ax2.plot(k, cands, lw=1.0, color="C3", label="surfels per valid pixel")
    ax2.set_ylabel("map surfels in view per valid depth pixel")
    ax2.set_ylim(0, max(2.0, float(cands.max()) * 1.1))
    ax.set_title(f"dense loop {row['resolution']}, {row['frames']} frames ({row['style']}): "
                 f"last/first {row['last_over_first']:.2f}, {row['fps']:.1f} FPS")
    ax.legend(loc="upper left")
    ax2.legend(loc="upper right")
    RESULTS.mkdir(exist_ok=True)
    tag = "" if row["remove_duplicates"] else "_keep_duplicates"
    save_figure(fig, RESULTS / f"pipeline_cost_{row['resolution']}{tag}.png")


def run(quick: bool = False) -> list[dict]:
    """Rows for 320x240 (and 640x480 unless ``quick``)."""
    if quick:
        return [bench(320, 150, 30)]
    return [bench(320, 1000, 100), bench(640, 300, 50)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="150 frames at 320x240 only")
    ap.add_argument("--frames", type=int, default=None, help="one run of this many frames")
    ap.add_argument("--style", default="handheld", help="handheld | slow | loop (laps repeated)")
    ap.add_argument("--lap", type=int, default=250, help="frames per lap round the room (--style loop)")
    ap.add_argument("--width", type=int, default=320, help="image width (height = 3/4 of it)")
    ap.add_argument("--window", type=int, default=100, help="frames in the first/last windows")
    ap.add_argument("--parallel", action="store_true", help="parallel numba kernels")
    ap.add_argument("--keep-duplicates", action="store_true", help="fusion.remove_duplicates = False")
    a = ap.parse_args()
    threads.set_parallel(a.parallel)
    if a.frames:
        rows = [bench(a.width, a.frames, a.window, a.style, a.lap, remove_duplicates=not a.keep_duplicates)]
    else:
        rows = run(a.quick)
    cols = list(rows[0])
    print(" | ".join(cols))
    for r in rows:
        print(" | ".join(str(r.get(c)) for c in cols))


if __name__ == "__main__":
    main()
