"""Hybrid vs dense under fast motion, and feature-initialised registration of pairs 90 frames apart.

Trackers: ``geometric`` is the dense tracker with ``tracking.photometric = "off"`` (point-to-plane ICP only),
``dense`` and ``hybrid`` the defaults (with the photometric term: these sequences have registered colour).

* Fast motion: synthetic sequences at 320x240 with Kinect-like noise for several scenes and seeds, "the same
  motion at 3x speed" two ways: ``fast`` (the ``slow`` orbit at 3x the step, 100 frames) and ``handheld`` (the
  orbit with hand jitter) read with ``stride`` 3. Every run goes through ``surfelslam run``
  (:func:`surfelslam.slam.runner.run_sequence`); ATE RMSE from its ``metrics.json``.
* Colour taken before depth: the same synthetic scenes with each frame's colour rendered one trajectory step before
  its depth (a 60 Hz trajectory, colour from the even poses and depth from the odd ones), as with a sensor whose
  colour and depth are not simultaneous (TUM: up to 20 ms apart). The features then measure a slightly different
  pose than the depth; ATE against the depth poses (first poses identical, no alignment).
* Wide baseline: pairs ``(i, i + 90)`` of a synthetic handheld sequence (about 1 m and 50 deg apart), registered by
  the ``register`` settings from the identity and from the ORB + PnP guess (``--init features``); errors against the
  exact ground truth.

Usage: ``.venv/bin/python -m benchmarks.bench_hybrid [--quick] [--out DIR]``; writes ``hybrid.json`` and
``hybrid.md`` to ``--out`` (default ``benchmarks/results``) and prints the tables.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from surfelslam.api import run_sequence
from surfelslam.datasets import DatasetOptions, open_sequence
from surfelslam.geometry import se3
from surfelslam.io.atomic import write_text_atomic
from surfelslam.slam import SlamConfig, build_slam
from surfelslam.slam.config import TrackingConfig
from surfelslam.synth.render import render
from surfelslam.synth.scenes import make_scene
from surfelslam.synth.trajectories import make_trajectory
from surfelslam.synth.writer import default_intrinsics, generate_sequence, make_frame, noise_config
from surfelslam.tracking.icp import pairwise_config
from surfelslam.tracking.preprocess import PreprocessConfig, Preprocessor
from surfelslam.tracking.registration import register_pair
from surfelslam.types import RGBDFrame

WIDTH, HEIGHT = 320, 240
SPEED = 3  # "fast" = 3x the speed of the same motion
FULL_CASES = [(scene, seed, style) for scene in ("room", "office") for seed in (0, 1, 2) for style in ("fast",)]
FULL_CASES += [("room", seed, "handheld") for seed in (1, 2)]
QUICK_CASES = [("room", 1, "fast")]
FAST_FRAMES = 100  # frames of a "fast" run (handheld: SPEED x this many generated, every SPEED-th read)
OFFSET_CASES = [(0, "slow", 150), (0, "fast", 100), (1, "handheld", 150), (2, "fast", 100)]  # (seed, style, frames)
PAIR_GAP = 90
PAIR_STARTS = (100, 200, 300, 400)


def _ate_cm(m: dict) -> float | None:
    e = m.get("eval")
    return None if e is None else round(100 * e["ate_rmse_m"], 2)


TRACKER_RUNS = (("geometric", "dense"), ("dense", "dense"), ("hybrid", "hybrid"))  # (column, tracker)


def _config(column: str) -> SlamConfig:
    return SlamConfig(tracking=TrackingConfig(photometric="off")) if column == "geometric" else SlamConfig()


def fast_motion(tmp: Path, cases) -> list[dict]:
    rows = []
    for scene, seed, style in cases:
        n = FAST_FRAMES * (SPEED if style == "handheld" else 1)
        path = generate_sequence(tmp / f"{scene}_{seed}_{style}", scene, style, n, "kinect", seed, WIDTH, HEIGHT)
        stride = SPEED if style == "handheld" else 1
        row = {"scene": scene, "seed": seed, "motion": f"{style} x{SPEED}" if style == "handheld" else "fast",
               "frames": FAST_FRAMES}
        for col, tracker in TRACKER_RUNS:
            seq = open_sequence(path, DatasetOptions(stride=stride))
            t0 = time.perf_counter()
            m = run_sequence(seq, tmp / f"run_{scene}_{seed}_{style}_{col}", _config(col), tracker,
                             progress=False, figures=False)
            row[f"{col}_ate_cm"] = _ate_cm(m)
            row[f"{col}_fps"] = round(m["fps"], 1)
            row[f"{col}_wall_s"] = round(time.perf_counter() - t0, 1)
            row[f"{col}_failures"] = m.get("tracking_failures", 0)
        rows.append(row)
    return rows


def colour_before_depth(cases) -> list[dict]:
    """Frames whose colour is rendered one trajectory step before their depth; dense vs hybrid ATE (cm)."""
    intr = default_intrinsics(WIDTH, HEIGHT)
    rows = []
    for seed, style, n in cases:
        scene = make_scene("room", seed)
        traj = make_trajectory(style, 2 * n, scene, fps=60.0, seed=seed)
        frames, gt = [], []
        for i in range(n):
            rgb = render(scene, traj.T_world_cam[2 * i], intr).rgb.copy()
            depth = make_frame(i, i / 30.0, render(scene, traj.T_world_cam[2 * i + 1], intr), intr,
                               noise_config("kinect"), seed).depth_m
            frames.append(RGBDFrame(i, i / 30.0, rgb, depth))
            gt.append(traj.T_world_cam[2 * i + 1])
        gt = se3.invert(gt[0]) @ np.stack(gt)
        row = {"scene": "room", "seed": seed, "motion": style, "frames": n}
        for col, tracker in TRACKER_RUNS:
            slam = build_slam(intr, _config(col), tracker)
            live = np.stack([slam.process(f).T_world_cam for f in frames])
            res = slam.finish()
            est = live if res.trajectory_override is None else res.trajectory_override.T_world_cam
            row[f"{col}_ate_cm"] = round(100 * float(np.sqrt(np.mean(np.sum((est[:, :3, 3] - gt[:, :3, 3]) ** 2,
                                                                                   axis=1)))), 2)
        rows.append(row)
    return rows


def wide_pairs(tmp: Path, starts) -> list[dict]:
    n = max(starts) + PAIR_GAP + 1
    path = generate_sequence(tmp / "pairs", "room", "handheld", n, "kinect", 0, WIDTH, HEIGHT)
    seq = open_sequence(path, DatasetOptions())
    gt = seq.ground_truth
    cfg = pairwise_config()
    pre = Preprocessor(seq.intrinsics, PreprocessConfig(pyramid_levels=cfg.levels))
    rows = []
    for s in starts:
        t = s + PAIR_GAP
        src, tgt = seq[s], seq[t]
        T_gt = se3.invert(gt.T_world_cam[t]) @ gt.T_world_cam[s]  # T_target_source
        p_src, p_tgt = pre.process(src.depth_m), pre.process(tgt.depth_m)
        row = {"pair": f"{s}->{t}", "motion_m": round(float(np.linalg.norm(T_gt[:3, 3])), 2),
               "motion_deg": round(se3.rotation_angle_deg(T_gt[:3, :3]), 1)}
        for init in ("identity", "features"):  # as `register --init identity / features`
            reg = register_pair(src, tgt, p_src, p_tgt, seq.intrinsics, cfg, init)
            if init == "features" and reg.guess is None:
                row[init] = "no guess"
                continue
            dt, dr = se3.pose_error(reg.icp.T_target_source, T_gt)
            shape = " (shape guess)" if reg.init_used == "geometry" else ""  # PnP rejected, FPFH used
            row[init] = f"{100 * dt:.2f} cm / {dr:.2f} deg{shape}"
        rows.append(row)
    return rows


def markdown(fast: list[dict], offset: list[dict], pairs: list[dict]) -> str:
    md = [f"### Hybrid vs dense under fast motion ({WIDTH}x{HEIGHT}, Kinect-like noise, ATE RMSE)", "",
          "| scene | seed | motion | frames | geometric ICP only | dense | hybrid | dense / hybrid |",
          "|---|---|---|---|---|---|---|---|"]
    for r in fast:
        g, d, h = r["geometric_ate_cm"], r["dense_ate_cm"], r["hybrid_ate_cm"]
        ratio = f"{d / h:.1f}" if d is not None and h else "-"
        md.append(f"| {r['scene']} | {r['seed']} | {r['motion']} | {r['frames']} | {g} cm | {d} cm | {h} cm "
                  f"| {ratio} |")
    md += ["", "### Colour rendered one trajectory step before depth (ATE against the depth poses, no alignment)", "",
           "| scene | seed | motion | frames | geometric ICP only | dense | hybrid |", "|---|---|---|---|---|---|---|"]
    for r in offset:
        md.append(f"| {r['scene']} | {r['seed']} | {r['motion']} | {r['frames']} | {r['geometric_ate_cm']} cm | "
                  f"{r['dense_ate_cm']} cm | {r['hybrid_ate_cm']} cm |")
    md += ["", f"### Pairs {PAIR_GAP} frames apart (synthetic handheld, room, seed 0): error after ICP", "",
           "| pair | motion | ICP from identity | with `--init features` |", "|---|---|---|---|"]
    for r in pairs:
        md.append(f"| {r['pair']} | {r['motion_m']} m, {r['motion_deg']} deg | {r['identity']} | {r['features']} |")
    return "\n".join(md) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="one fast case and one pair")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        fast = fast_motion(tmp, QUICK_CASES if a.quick else FULL_CASES)
        offset = colour_before_depth([(2, "fast", 30)] if a.quick else OFFSET_CASES)
        pairs = wide_pairs(tmp, PAIR_STARTS[:1] if a.quick else PAIR_STARTS)
    md = markdown(fast, offset, pairs)
    print(md)
    if not a.quick:
        a.out.mkdir(parents=True, exist_ok=True)
        write_text_atomic(a.out / "hybrid.json", json.dumps({"fast": fast, "colour_before_depth": offset,
                                                             "pairs": pairs}, indent=2) + "\n")
        write_text_atomic(a.out / "hybrid.md", md)


if __name__ == "__main__":
    main()
