"""Whole dense loop (preprocess, render, ICP, fuse) FPS and per-frame cost over a long sequence.

Frames are generated in memory first (synthetic room, Kinect noise; by default the ``handheld`` orbit
across the room, which keeps revisiting what it saw; or ``loop`` laps of ``lap`` frames, repeated), then fed to
:class:`~surfelslam.pipeline.DenseSlam` with the timer running, so reading/decoding costs nothing here
(``surfelslam run`` reads in a background thread). Reported per resolution: FPS of the loop, mean ms per
stage, the mean per-frame cost of the first and of the last ``window`` frames and their ratio (flat cost:
<= 1.3), the map size at the end, the mean number of surfel candidates in view at the start and the end,
and the pose error vs the generator's trajectory. A PNG of the per-frame cost against the frame index
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
from surfelslam.kernels import threads
from surfelslam.pipeline import DenseSlam, SlamConfig, warm_up
from surfelslam.synth.scenes import make_scene
from surfelslam.synth.trajectories import make_trajectory
from surfelslam.synth.writer import default_intrinsics, iter_frames, noise_config
from surfelslam.types import RGBDFrame, Trajectory

RESULTS = Path(__file__).resolve().parent / "results"


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


def bench(width: int, n_frames: int, window: int, style: str = "handheld", lap: int = 250, plot: bool = True) -> dict:
    frames, gt = _frames(width, n_frames, style, lap)
    intr = default_intrinsics(width, width * 3 // 4)
    cfg = SlamConfig()
    warm_up(cfg)
    slam = DenseSlam(intr, cfg)
    per_frame = np.zeros(len(frames))
    stages: dict[str, list[float]] = {}
    cands = np.zeros(len(frames))
    poses = []
    for k, f in enumerate(frames):
        t0 = time.perf_counter()
        res = slam.process(f)
        per_frame[k] = (time.perf_counter() - t0) * 1e3
        poses.append(res.T_world_cam)
        for name, ms in res.timings_ms.items():
            stages.setdefault(name, []).append(ms)
        cands[k] = len(slam.map.visible_candidates(res.T_world_cam, intr, cfg.fusion.min_depth_m,
                                                   cfg.fusion.max_depth_m))
    total_s = float(per_frame.sum()) / 1e3  # the loop only (not the candidate counting below)
    est = Trajectory(gt.timestamps, np.array(poses))
    w = min(window, len(frames) // 2)
    first, last = float(per_frame[1 : w + 1].mean()), float(per_frame[-w:].mean())
    row = {
        "resolution": f"{intr.width}x{intr.height}", "frames": len(frames),
        "style": style if style != "loop" else f"loop/{lap}",
        "fps": round(len(frames) / total_s, 2),
        **{f"{k}_ms": round(float(np.mean(v)), 2) for k, v in stages.items()},
        "first_ms": round(first, 2), "last_ms": round(last, 2), "last_over_first": round(last / first, 3),
        "map_surfels": int(slam.map.n_alive), "cand_first": int(cands[1 : w + 1].mean()),
        "cand_last": int(cands[-w:].mean()), "ate_cm": round(ate(est, gt).rmse_m * 100, 2),
        "failures": int(slam.failures), "parallel": threads.parallel_enabled(), "window": w,
    }
    if plot:
        _plot(per_frame, cands, row)
    return row


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
    ax.set_ylabel("ms per frame (preprocess+render+ICP+fuse)")
    ax.set_ylim(0, max(1.0, float(np.percentile(per_frame, 99)) * 1.3))
    ax2 = ax.twinx()
    ax2.plot(k, cands / 1e3, lw=1.0, color="C3", label="surfels in view (k)")
    ax2.set_ylabel("surfel candidates in view (thousands)")
    ax.set_title(f"dense loop {row['resolution']}, {row['frames']} frames ({row['style']}): "
                 f"last/first {row['last_over_first']:.2f}, {row['fps']:.1f} FPS")
    ax.legend(loc="upper left")
    ax2.legend(loc="upper right")
    RESULTS.mkdir(exist_ok=True)
    save_figure(fig, RESULTS / f"pipeline_cost_{row['resolution']}.png")


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
    a = ap.parse_args()
    threads.set_parallel(a.parallel)
    rows = [bench(a.width, a.frames, a.window, a.style, a.lap)] if a.frames else run(a.quick)
    cols = list(rows[0])
    print(" | ".join(cols))
    for r in rows:
        print(" | ".join(str(r.get(c)) for c in cols))


if __name__ == "__main__":
    main()
