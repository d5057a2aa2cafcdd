"""``surfelslam experiments SEQ --out DIR``: the reference assignment's experiments on one
sequence, as ``DIR/report.md`` + PNGs.

Sections (every number comes from this run; ``DIR/results.json`` holds the same numbers):

1. ICP on frame pairs (single level at 0.07 m, single level at 0.17 m, coarse-to-fine defaults, and
   ``register --init features``);
2. the linear solvers on one Gauss-Newton system (cholesky, lu, qr, pinv);
3. fusion with ground-truth poses vs dense-tracker poses;
4. the dormant-point rule on / off;
5. feature odometry (ORB + PnP-RANSAC) on a pair;
6. every tracker of ``surfelslam.slam.TRACKERS`` against the ground truth.
"""

from __future__ import annotations

import json
import math
import time
import timeit
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated

import numpy as np
import scipy.linalg
import typer

from surfelslam.errors import ConfigError
from surfelslam.io.jsonio import json_default
from surfelslam.tools.common import (
    DatasetOptionsArgs,
    SeqArg,
    console,
    handle_errors,
    with_dataset_options,
)

# The reference assignment's dormant-rule values (surfels older than 20 frames seen in fewer than 15 are removed).
REFERENCE_DORMANT_MAX_AGE_FRAMES = 20
REFERENCE_DORMANT_MIN_HITS = 15
SOLVER_TIMEIT_NUMBER = 10
SOLVER_TIMEIT_REPEAT = 7
SOLVER_PAIR_GATE_M = 0.17

SECTION_TITLES = (
    "## 1. ICP on frame pairs",
    "## 2. Solver comparison",
    "## 3. Fusion with ground-truth poses vs estimated poses",
    "## 4. Dormant-point rule",
    "## 5. Feature odometry on a pair",
    "## 6. Trajectories against ground truth",
)


@dataclass(frozen=True)
class ExperimentOptions:
    """What to run: ``frames`` frames for sections 3, 4 and 6; pairs ``pair_start -> pair_start + gap``."""

    frames: int = 200
    pair_start: int = 10
    pair_gaps: tuple[int, ...] = (40, 90)
    progress: bool = True

    def __post_init__(self) -> None:
        if self.frames < 3:
            raise ConfigError(f"--frames must be >= 3, got {self.frames}")
        if self.pair_start < 0:
            raise ConfigError(f"--pair-start must be >= 0, got {self.pair_start}")
        if not self.pair_gaps or any(g < 1 for g in self.pair_gaps):
            raise ConfigError(f"--pair-gaps must be positive frame gaps, got {self.pair_gaps}")


FEATURES_SETTING = "register --init features"


def after_figures(s: int, t: int) -> list[tuple[str, str]]:
    """``[(setting, figure file)]`` of pair ``s -> t`` after ICP: the :func:`icp_settings`, then
    ``FEATURES_SETTING``."""
    return ([(name, f"icp_{s}_{t}_setting{k}_after.png") for k, (name, _) in enumerate(icp_settings())]
            + [(FEATURES_SETTING, f"icp_{s}_{t}_features_after.png")])


def icp_settings():
    """``[(name, ICPConfig)]``: the reference assignment's single-level setting at 0.07 m and
    0.17 m, and the defaults.

    The reference setting: one level, 10 fixed iterations, every source pixel, no angle gate, no robust kernel.
    """
    from surfelslam.tracking.icp import ICPConfig

    def single(gate_m: float) -> ICPConfig:
        return ICPConfig(levels=1, iterations=(10,), dist_thresh_m=(gate_m,), angle_thresh_deg=(180.0,),
                         robust_kernel="none", min_update_norm=0.0, min_relative_residual_change=0.0,
                         finest_source_stride_px=1)

    return [("1 level, 0.07 m", single(0.07)), ("1 level, 0.17 m", single(0.17)),
            ("coarse-to-fine defaults", ICPConfig())]


def choose_pairs(n_frames: int, start: int, gaps: tuple[int, ...]) -> tuple[list[tuple[int, int]], bool]:
    """Frame pairs ``(source, target)`` ``start -> start + gap``; scaled down to fit a short selection.

    Returns ``(pairs, scaled)``; ``pairs`` is empty when the selection has fewer than 2 frames.
    """
    if n_frames < 2:
        return [], False
    if start + max(gaps) < n_frames:
        return [(start, start + g) for g in gaps], False
    s = min(start, n_frames // 10)
    scale = (n_frames - 1 - s) / max(gaps)
    pairs: list[tuple[int, int]] = []
    for g in gaps:
        p = (s, s + max(1, int(g * scale)))
        if p not in pairs:
            pairs.append(p)
    return pairs, True


def _fmt(x, spec: str = ".2f", none: str = "n/a") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return none
    return format(x, spec)


def _gt_relative(T_wc: np.ndarray, valid: np.ndarray, s: int, t: int) -> np.ndarray | None:
    from surfelslam.geometry import se3

    if not (valid[s] and valid[t]):
        return None
    return se3.invert(T_wc[t]) @ T_wc[s]


# --------------------------------------------------------------------------------------------- section 1


def section_icp_pairs(seq, out_dir: Path, pairs, scaled: bool, opts: ExperimentOptions):
    from surfelslam.geometry import se3
    from surfelslam.tracking.icp import icp, pairwise_config
    from surfelslam.tracking.photometric import colour_switch
    from surfelslam.tracking.preprocess import PreprocessConfig, Preprocessor
    from surfelslam.tracking.registration import register_pair
    from surfelslam.viz.registration import plot_registration

    lines = [SECTION_TITLES[0], ""]
    res_out: list[dict] = []
    if not pairs:
        lines += ["Not available: the selection has fewer than 2 frames.", ""]
        return lines, res_out, {}
    pair_txt = ", ".join(f"{s}->{t}" for s, t in pairs)
    lines.append(f"Pairs (source->target, positions in the selection): {pair_txt}."
                 + (f" The selection has {len(seq)} frames, too few for {opts.pair_start}->"
                    f"{opts.pair_start}+{max(opts.pair_gaps)}: the gaps were scaled down." if scaled else ""))
    lines.append("ICP registers the source frame onto the target frame from the identity. Settings: the reference "
                 "assignment's single level (10 fixed iterations, every pixel, no angle gate, no robust kernel) with "
                 "a 0.07 m and a 0.17 m association gate, and the coarse-to-fine defaults (4 levels, every 2nd "
                 "pixel at the finest level, hence fewer inliers), and `register --init features` (the `register` ICP "
                 "settings started from the image-feature guess, else the shape-feature guess; the start used is "
                 "named in brackets). Residual = "
                 "point-to-plane RMS over the inliers at the end (mean squared residual in brackets).")
    lines.append("")
    T_wc, valid = seq.gt_poses(at_depth_time=True)  # ICP registers depth: GT at the depth capture time
    if not valid.any():
        lines += ["This sequence has no ground truth: the error columns are n/a.", ""]
    pre = Preprocessor(seq.intrinsics, PreprocessConfig())
    lines += ["| pair | GT motion | setting | inliers | residual RMS (mm) [mean sq. (m²)] | iterations | converged "
              "| error vs GT (mm, deg) | figure |",
              "|---|---|---|---|---|---|---|---|---|"]
    pyramids = {}
    figs = []
    for s, t in pairs:
        src, tgt = pre.process(seq[s].depth_m), pre.process(seq[t].depth_m)
        pyramids[(s, t)] = (src, tgt)
        T_gt = _gt_relative(T_wc, valid, s, t)
        motion = "n/a" if T_gt is None else "{:.0f} mm, {:.1f} deg".format(
            *(lambda e: (1000 * e[0], e[1]))(se3.pose_error(np.eye(4), T_gt)))
        src_pts = src[0].vertex[src[0].vertex[..., 2] > 0].astype(np.float64)
        tgt_pts = tgt[0].vertex[tgt[0].vertex[..., 2] > 0]
        before = f"icp_{s}_{t}_before.png"
        plot_registration(src_pts, tgt_pts, out_dir / before,
                          f"before: source {s} (red), target {t} (green), identity")
        figs.append(before)
        reg = register_pair(seq[s], seq[t], src, tgt, seq.intrinsics, pairwise_config(), "features",
                            photometric=colour_switch("auto", seq.colour_registered))
        results = [icp(src, tgt, None, cfg) for _, cfg in icp_settings()] + [reg.icp]
        for (name, after), r in zip(after_figures(s, t), results, strict=True):
            extra, label = ({"start": reg.init_used}, f"{name} ({reg.init_used})") if r is reg.icp else ({}, name)
            err = None if T_gt is None else se3.pose_error(r.T_target_source, T_gt)
            plot_registration(se3.transform_points(r.T_target_source, src_pts), tgt_pts, out_dir / after,
                              f"after {name}: {s}->{t}, {r.inliers} inliers, RMS {1000 * r.rmse_m:.1f} mm")
            figs.append(after)
            res_out.append({"source": s, "target": t, "setting": name, **extra, "inliers": int(r.inliers),
                            "rmse_m": float(r.rmse_m), "iterations": int(r.iterations),
                            "converged": bool(r.converged), "reason": r.reason,
                            "err_trans_m": None if err is None else float(err[0]),
                            "err_rot_deg": None if err is None else float(err[1])})
            err_txt = "n/a" if err is None else f"{1000 * err[0]:.1f}, {err[1]:.2f}"
            conv = "yes" if r.converged else f"no ({r.reason})" if r.reason else "no"
            lines.append(f"| {s}->{t} | {motion} | {label} | {r.inliers} | {1000 * r.rmse_m:.2f} "
                         f"[{r.rmse_m ** 2:.3e}] | {r.iterations} | {conv} | {err_txt} | [after]({after}) |")
    lines.append("")
    for s, t in pairs:
        lines.append(f"Pair {s}->{t}, before ICP (source red, target green): ![before {s}->{t}]"
                     f"(icp_{s}_{t}_before.png)")
        lines.append("")
        for name, after in after_figures(s, t):
            lines.append(f"After ICP, {name}: ![after {s}->{t} {name}]({after})")
            lines.append("")
    return lines, res_out, pyramids


# --------------------------------------------------------------------------------------------- section 2


def solver_comparison(src, tgt, gate_m: float = SOLVER_PAIR_GATE_M) -> dict:
    """The four solvers on the explicit point-to-plane system of ``src`` -> ``tgt`` at the identity.

    Returns ``{"n_rows", "solutions": {name: (6,) list}, "max_diff_vs_cholesky": {name: float},
    "max_pairwise_diff", "median_s": {name: float}}``.
    """
    from surfelslam.kernels.icp import ROBUST_NONE, build_linear_system_ref, normal_equations_ref
    from surfelslam.tracking.icp import solve

    lv_s, lv_t = src[0], tgt[0]
    intr = lv_s.intrinsics
    A, b, _w, _z, _n = build_linear_system_ref(lv_s.vertex, lv_s.normal, lv_t.vertex, lv_t.normal, np.eye(4),
                                               intr.fx, intr.fy, intr.cx, intr.cy, gate_m, -1.0, ROBUST_NONE, 1.0)
    AtA, Atb = normal_equations_ref(A, b)
    calls = {
        "cholesky": lambda: solve(AtA, Atb, "cholesky"),
        "lu": lambda: solve(AtA, Atb, "lu"),
        "qr (explicit A, b)": lambda: solve(AtA, Atb, "qr", A=A, b=b),
        "qr (6x6 normal matrix)": lambda: solve(AtA, Atb, "qr"),
        "pinv": lambda: solve(AtA, Atb, "pinv"),
    }
    sols, times = {}, {}
    for name, fn in calls.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", scipy.linalg.LinAlgWarning)  # singular: reported as failed below
            try:
                x = np.asarray(fn(), np.float64)
            except (np.linalg.LinAlgError, ValueError):  # singular system (too few or degenerate associations)
                x = np.full(6, np.nan)
        sols[name] = x
        if not np.all(np.isfinite(x)):
            times[name] = float("nan")
            continue
        t = timeit.repeat(fn, number=SOLVER_TIMEIT_NUMBER, repeat=SOLVER_TIMEIT_REPEAT)
        times[name] = float(np.median(t)) / SOLVER_TIMEIT_NUMBER
    ref = sols["cholesky"]
    names = [k for k, v in sols.items() if np.all(np.isfinite(v))]
    pairwise = max((float(np.max(np.abs(sols[a] - sols[b]))) for a in names for b in names), default=float("nan"))
    return {"n_rows": int(len(b)), "gate_m": gate_m,
            "solutions": {k: v.tolist() for k, v in sols.items()},
            "max_diff_vs_cholesky": {k: float(np.max(np.abs(v - ref))) for k, v in sols.items()},
            "max_pairwise_diff": pairwise, "median_s": times}


def section_solvers(pyramids, pairs):
    lines = [SECTION_TITLES[1], ""]
    if not pairs:
        lines += ["Not available: no frame pair (the selection has fewer than 2 frames).", ""]
        return lines, None
    s, t = pairs[0]
    src, tgt = pyramids[(s, t)]
    r = solver_comparison(src, tgt)
    if r["n_rows"] < 6:
        lines += [f"Not available: pair {s}->{t} has {r['n_rows']} associations at the identity (6 needed).", ""]
        return lines, r
    lines.append(f"Pair {s}->{t}: the explicit point-to-plane system A (N x 6), b (N) at the identity "
                 f"(finest level, every pixel, {r['gate_m']} m gate, no angle gate, no robust weights; "
                 f"N = {r['n_rows']} rows, via `kernels.icp.build_linear_system_ref`), solved with "
                 f"`tracking.icp.solve`. Time: median of {SOLVER_TIMEIT_REPEAT} repeats of "
                 f"{SOLVER_TIMEIT_NUMBER} calls (the QR on A, b includes factorising A).")
    lines += ["", "| solver | step xi = (omega, v) | max abs difference vs cholesky | median time per solve (µs) |",
              "|---|---|---|---|"]
    for name, x in r["solutions"].items():
        if not np.all(np.isfinite(x)):
            lines.append(f"| {name} | failed (singular system) | n/a | n/a |")
            continue
        xs = ", ".join(f"{v:+.6f}" for v in x)
        lines.append(f"| {name} | ({xs}) | {_fmt(r['max_diff_vs_cholesky'][name], '.3e')} | "
                     f"{1e6 * r['median_s'][name]:.1f} |")
    lines += ["", f"Largest difference between any two solutions: {_fmt(r['max_pairwise_diff'], '.3e')}.", ""]
    return lines, r


# --------------------------------------------------------------------------------------------- runs


def _run(seq_runs, out_dir: Path, cfg, tracker: str, poses: str | None, opts: ExperimentOptions,
         figures: bool) -> dict:
    from surfelslam.slam.runner import run_sequence

    return run_sequence(seq_runs, out_dir, cfg, tracker, poses=poses, progress=opts.progress, figures=figures)


def _ate(metrics: dict | None) -> float | None:
    if metrics is None or "eval" not in metrics:
        return None
    return float(metrics["eval"]["ate_rmse_m"])


def section_fusion(seq_runs, out_dir: Path, cfg, opts: ExperimentOptions, has_gt: bool):
    lines = [SECTION_TITLES[2], ""]
    intr = seq_runs.intrinsics
    lines.append(f"The first {len(seq_runs)} frames of the selection at {intr.width}x{intr.height}, fused once with "
                 "the ground-truth poses (`run --poses gt`) and once with the dense tracker's poses. Compression = "
                 "map points / (frames x pixels per frame).")
    lines.append("")
    runs: dict[str, dict | None] = {}
    if has_gt:
        runs["ground-truth poses"] = _run(seq_runs, out_dir / "runs" / "gt_poses", cfg, "dense", "gt", opts, True)
    runs["dense tracker poses"] = _run(seq_runs, out_dir / "runs" / "dense", cfg, "dense", None, opts, True)
    lines += ["| poses | frames fused | map points | compression | ATE RMSE (cm) | maps |", "|---|---|---|---|---|---|"]
    for name, m in runs.items():
        d = "gt_poses" if name.startswith("ground") else "dense"
        ate = _ate(m) if d == "dense" else None
        lines.append(f"| {name} | {m['frames_processed']} | {m['map_points']} | "
                     f"{100 * m['compression_ratio']:.2f}% | {_fmt(None if ate is None else 100 * ate)} | "
                     f"[top](runs/{d}/map_top.png), [camera](runs/{d}/map_camera.png) |")
    if not has_gt:
        lines.append("| ground-truth poses | not available: this sequence has no ground truth | | | | |")
    lines.append("")
    for name in runs:
        d = "gt_poses" if name.startswith("ground") else "dense"
        lines += [f"Map with {name} (coloured by normal, confidence, first-seen frame and colour), top view and "
                  f"view from the first camera:", "", f"![{name} top](runs/{d}/map_top.png)", "",
                  f"![{name} camera](runs/{d}/map_camera.png)", ""]
    return lines, runs


def section_dormant(seq_runs, out_dir: Path, cfg, opts: ExperimentOptions, dense_metrics: dict, has_gt: bool):
    lines = [SECTION_TITLES[3], ""]
    f = cfg.fusion
    variants = []
    if f.remove_unstable:
        variants.append((f"on: age > {f.unstable_max_age_frames} frames, hits < {f.stable_min_hits} (configured)",
                         "dense", dense_metrics))
    cfg_off = replace(cfg, fusion=replace(f, remove_unstable=False))
    variants.append(("off", "dormant_off", _run(seq_runs, out_dir / "runs" / "dormant_off", cfg_off, "dense", None,
                                                 opts, True)))
    cfg_reference = replace(cfg, fusion=replace(f, remove_unstable=True,
                                                unstable_max_age_frames=REFERENCE_DORMANT_MAX_AGE_FRAMES,
                                                stable_min_hits=REFERENCE_DORMANT_MIN_HITS))
    if not (f.remove_unstable and f.unstable_max_age_frames == REFERENCE_DORMANT_MAX_AGE_FRAMES
            and f.stable_min_hits == REFERENCE_DORMANT_MIN_HITS):
        variants.append((f"on: age > {REFERENCE_DORMANT_MAX_AGE_FRAMES} frames, hits < {REFERENCE_DORMANT_MIN_HITS} "
                         "(the reference assignment's values)", "dormant_reference",
                         _run(seq_runs, out_dir / "runs" / "dormant_reference", cfg_reference, "dense", None, opts,
                              True)))
    lines.append(f"Dense tracking over the same {len(seq_runs)} frames with `FusionConfig.remove_unstable` on and "
                 "off. The rule removes a surfel older than `unstable_max_age_frames` that was observed in fewer "
                 "than `stable_min_hits` frames (see `mapping/fusion.py`)."
                 + ("" if has_gt else " This sequence has no ground truth: ATE is n/a."))
    lines += ["", "| dormant-point rule | map points | ATE RMSE (cm) | tracking failures | render |",
              "|---|---|---|---|---|"]
    out = {}
    for name, d, m in variants:
        ate = _ate(m)
        out[name] = {"map_points": m["map_points"], "ate_rmse_m": ate, "run": d}
        lines.append(f"| {name} | {m['map_points']} | {_fmt(None if ate is None else 100 * ate)} | "
                     f"{m.get('tracking_failures', 0)} | [camera](runs/{d}/map_camera.png) |")
    lines.append("")
    for name, d, _ in variants:
        lines += [f"Dormant rule {name}:", "", f"![dormant {name}](runs/{d}/map_camera.png)", ""]
    return lines, out


# --------------------------------------------------------------------------------------------- section 5


def feature_pair(seq, s: int, t: int, fcfg) -> dict:
    """ORB odometry of frame ``s`` (reference) -> frame ``t`` (current): the numbers of section 5."""
    from surfelslam.tracking.features import estimate_motion, extract, match

    a, b = seq[s], seq[t]
    fa = extract(a.rgb, a.depth_m, seq.intrinsics, fcfg)
    fb = extract(b.rgb, b.depth_m, seq.intrinsics, fcfg)
    raw = match(fa, fb, replace(fcfg, good_match_k=float("inf")))  # every raw match (no distance filter)
    good = match(fa, fb, fcfg)
    motion = estimate_motion(fa, fb, seq.intrinsics, fcfg)
    good_set = {(int(i), int(j)) for i, j in good.pairs}
    kept = np.array([(int(i), int(j)) in good_set for i, j in raw.pairs], bool)
    return {"fa": fa, "fb": fb, "raw": raw, "good": good, "motion": motion, "kept": kept,
            "threshold_bits": fcfg.good_match_k * max(good.min_dist, fcfg.good_match_floor_bits)}


def section_features(seq, out_dir: Path, pairs, cfg):
    from surfelslam.geometry import se3
    from surfelslam.tracking.features import FeatureConfig
    from surfelslam.viz.experiment_figures import plot_matches

    lines = [SECTION_TITLES[4], ""]
    if not pairs:
        lines += ["Not available: no frame pair (the selection has fewer than 2 frames).", ""]
        return lines, None
    fcfg = getattr(cfg, "features", None) or FeatureConfig()
    s, t = pairs[0]
    r = feature_pair(seq, s, t, fcfg)
    fa, fb, raw, good, mo = r["fa"], r["fb"], r["raw"], r["good"], r["motion"]
    T_wc, valid = seq.gt_poses()
    T_gt = _gt_relative(T_wc, valid, s, t)
    err = None if T_gt is None else se3.pose_error(mo.T_cur_ref, T_gt)
    fig = "features_matches.png"
    plot_matches(out_dir / fig, seq[s].rgb, seq[t].rgb, fa.keypoints_uv[raw.pairs[:, 0]],
                 fb.keypoints_uv[raw.pairs[:, 1]], r["kept"],
                 f"ORB matches {s} -> {t}: kept {good.n_good} (green), rejected {raw.n_raw - good.n_good} (red)")
    rv = ", ".join(f"{v:+.4f}" for v in mo.rvec)
    tv = ", ".join(f"{v:+.4f}" for v in mo.tvec)
    lines.append(f"Pair {s} (reference, 3D from its depth) -> {t} (current, 2D): ORB ({fcfg.n_features} features, "
                 f"{fcfg.grid_cols}x{fcfg.grid_rows} grid), {fcfg.matching} Hamming matching, good matches under "
                 f"{fcfg.good_match_k:g} x max(min distance, {fcfg.good_match_floor_bits:g}) bits, PnP-RANSAC "
                 f"({fcfg.ransac_iterations} iterations, {fcfg.reprojection_error_px:g} px)"
                 + (" + LM refinement" if fcfg.refine else "") + ". R, t map reference points into the current "
                 "camera (T_cur_ref).")
    lines += ["", "| quantity | value |", "|---|---|",
              f"| keypoints in frame {s} / {t} | {len(fa)} / {len(fb)} |",
              f"| keypoints with valid depth in frame {s} | {int(fa.valid.sum())} |",
              f"| matches before the distance filter | {raw.n_raw} |",
              f"| min / max descriptor distance (bits) | {raw.min_dist:g} / {raw.max_dist:g} |",
              f"| distance threshold (bits) | {r['threshold_bits']:g} |",
              f"| matches after the distance filter | {good.n_good} |",
              f"| ... with a valid reference depth (PnP input) | {mo.n_good} |",
              f"| PnP inliers | {mo.n_inliers} |",
              f"| accepted | {'yes' if mo.ok else f'no ({mo.reason})'} |",
              f"| R (Rodrigues vector, rad) | ({rv}) |",
              f"| t (m) | ({tv}) |",
              "| error vs GT (mm, deg) | "
              + ("n/a (no ground truth)" if err is None else f"{1000 * err[0]:.1f}, {err[1]:.2f}") + " |",
              "", f"![matches]({fig})", ""]
    out = {"pair": [s, t], "keypoints": [len(fa), len(fb)], "matches_raw": raw.n_raw, "matches_good": good.n_good,
           "min_dist": raw.min_dist, "max_dist": raw.max_dist, "pnp_input": mo.n_good, "pnp_inliers": mo.n_inliers,
           "ok": mo.ok, "reason": mo.reason, "rvec": mo.rvec.tolist(), "tvec": mo.tvec.tolist(),
           "err_trans_m": None if err is None else float(err[0]), "err_rot_deg": None if err is None else float(err[1])}
    return lines, out


# --------------------------------------------------------------------------------------------- section 6


def section_trajectories(seq_runs, out_dir: Path, cfg, opts: ExperimentOptions, dense_metrics: dict,
                         has_gt: bool):
    from surfelslam.eval.metrics import ate
    from surfelslam.slam import TRACKERS
    from surfelslam.types import Trajectory
    from surfelslam.viz.experiment_figures import plot_trajectories

    lines = [SECTION_TITLES[5], ""]
    if not has_gt:
        lines += ["Not available: this sequence has no ground truth. Trackers: " + ", ".join(TRACKERS) + ".", ""]
        return lines, {}
    lines.append(f"Every tracker (`surfelslam.slam.TRACKERS`) over the same {len(seq_runs)} frames, default "
                 "configuration; ATE after SE(3) alignment (no scale).")
    lines += ["", "| tracker | status | frames | tracking failures | ATE RMSE (cm) | FPS |",
              "|---|---|---|---|---|---|"]
    out: dict[str, dict] = {}
    estimates = {}
    gt_plot = None  # the ground truth over the run's frames (the associated poses)
    for name in TRACKERS:
        d = out_dir / "runs" / name
        try:
            m = dense_metrics if name == "dense" else _run(seq_runs, d, cfg, name, None, opts, False)
        except Exception as exc:  # noqa: BLE001 - a failing tracker is reported, never dropped
            out[name] = {"status": f"failed: {exc}"}
            lines.append(f"| {name} | failed: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__} "
                         "| | | | |")
            continue
        a = _ate(m)
        out[name] = {"status": "ran", "ate_rmse_m": a, "frames": m["frames_processed"],
                     "tracking_failures": m.get("tracking_failures", 0), "fps": m["fps"]}
        lines.append(f"| {name} | ran | {m['frames_processed']} | {m.get('tracking_failures', 0)} | "
                     f"{_fmt(None if a is None else 100 * a)} | {m['fps']:.1f} |")
        try:
            ar = ate(Trajectory.read_tum(d / "trajectory.txt"), seq_runs.ground_truth)
            estimates[f"{name} (ATE {_fmt(None if a is None else 100 * a)} cm)"] = ar.est_aligned
            gt_plot = ar.gt if gt_plot is None else gt_plot
        except Exception as exc:  # noqa: BLE001 - a trajectory that cannot be aligned is left out of the plot
            out[name]["plot_error"] = str(exc)
    lines.append("")
    if estimates:
        plot_trajectories(out_dir / "trajectories.png", estimates, gt_plot,
                          f"trajectories vs ground truth ({len(seq_runs)} frames)")
        lines += ["![trajectories](trajectories.png)", ""]
    return lines, out


# --------------------------------------------------------------------------------------------- driver


def run_experiments(seq, seq_runs, out_dir: Path, cfg, opts: ExperimentOptions) -> dict:
    """Run every section; write ``out_dir/report.md``, ``out_dir/results.json`` and the PNGs.

    Args:
        seq: the whole selection (frame pairs are taken from it).
        seq_runs: its first ``opts.frames`` frames (fusion, dormant rule and trajectory sections).

    Returns:
        the results dict (also written as ``results.json``).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    has_gt = seq.ground_truth is not None and bool(seq.gt_poses()[1].any())
    t_all = time.perf_counter()
    times: dict[str, float] = {}
    results: dict = {"sequence": str(seq.root), "frames_in_selection": len(seq), "frames_run": len(seq_runs),
                     "resolution": [seq.intrinsics.width, seq.intrinsics.height],
                     "downsample": seq.options.downsample, "has_ground_truth": has_gt}
    pairs, scaled = choose_pairs(len(seq), opts.pair_start, opts.pair_gaps)
    results["pairs"] = [list(p) for p in pairs]
    body: list[str] = []

    def timed(key, fn, *a):
        t0 = time.perf_counter()
        r = fn(*a)
        times[key] = time.perf_counter() - t0
        return r

    lines, results["icp_pairs"], pyramids = timed("icp_pairs", section_icp_pairs, seq, out_dir, pairs, scaled, opts)
    body += lines
    lines, results["solvers"] = timed("solvers", section_solvers, pyramids, pairs)
    body += lines
    lines, runs = timed("fusion", section_fusion, seq_runs, out_dir, cfg, opts, has_gt)
    body += lines
    results["fusion"] = {k: {"frames": m["frames_processed"], "map_points": m["map_points"],
                             "compression_ratio": m["compression_ratio"], "ate_rmse_m": _ate(m)}
                         for k, m in runs.items()}
    dense_metrics = runs["dense tracker poses"]
    lines, results["dormant"] = timed("dormant", section_dormant, seq_runs, out_dir, cfg, opts, dense_metrics, has_gt)
    body += lines
    lines, results["features"] = timed("features", section_features, seq, out_dir, pairs, cfg)
    body += lines
    lines, results["trackers"] = timed("trackers", section_trajectories, seq_runs, out_dir, cfg, opts,
                                       dense_metrics, has_gt)
    body += lines
    total = time.perf_counter() - t_all
    results["seconds"] = {**times, "total": total}

    intr = seq.intrinsics
    head = ["# surfelslam experiments", "",
            f"Sequence `{seq.root}` ({seq.layout}), {len(seq)} frames selected at {intr.width}x{intr.height} "
            f"(downsample {seq.options.downsample}); sections 3, 4 and 6 use the first {len(seq_runs)} frames. "
            + ("Ground truth: yes." if has_gt else "Ground truth: none (sections needing it say so)."),
            f"Run time {total:.0f} s ("
            + ", ".join(f"{k.replace('_', ' ')} {v:.0f} s" for k, v in times.items()) + ").", ""]
    from surfelslam.io.atomic import write_text_atomic

    write_text_atomic(out_dir / "report.md", "\n".join(head + body).rstrip() + "\n")
    write_text_atomic(out_dir / "results.json", json.dumps(results, indent=2, default=json_default) + "\n")
    return results


def parse_gaps(text: str) -> tuple[int, ...]:
    try:
        gaps = tuple(int(x) for x in text.replace(" ", "").split(",") if x)
    except ValueError:
        raise ConfigError(f"--pair-gaps must be a comma list of frame gaps, got {text!r}") from None
    if not gaps:
        raise ConfigError(f"--pair-gaps must be a comma list of frame gaps, got {text!r}")
    return gaps


def register(app: typer.Typer) -> None:
    @app.command("experiments")
    @handle_errors
    @with_dataset_options
    def experiments_cmd(
        seq_path: SeqArg,
        dataset: DatasetOptionsArgs,
        out: Annotated[Path, typer.Option("--out", "-o", help="Output folder (report.md, PNGs, runs/).")] = Path(
            "out/experiments"),
        config: Annotated[Path | None, typer.Option("--config", help="TOML configuration file.")] = None,
        frames: Annotated[int, typer.Option("--frames", help="Frames used by the fusion and trajectory "
                                                             "sections.")] = 200,
        pair_start: Annotated[int, typer.Option("--pair-start", help="Source frame of the ICP/feature pairs.")] = 10,
        pair_gaps: Annotated[str, typer.Option("--pair-gaps", help="Frame gaps of the pairs, comma list.")] = "40,90",
        progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Show progress bars.")] = True,
    ) -> None:
        """The seeds' experiments (ICP pairs, solvers, fusion, dormant rule, features, trackers) -> report.md."""
        from surfelslam.datasets import open_sequence
        from surfelslam.slam.runner import load_config

        opts = ExperimentOptions(frames=frames, pair_start=pair_start, pair_gaps=parse_gaps(pair_gaps),
                                 progress=progress)
        cfg = load_config(config)
        dopts = dataset.resolve()
        seq = open_sequence(seq_path, dopts)
        if len(seq) == 0:
            raise ConfigError(f"{seq_path}: the selection has no frames (check --start/--end/--stride)")
        run_end = dopts.start + frames * dopts.stride
        seq_runs = open_sequence(seq_path, replace(dopts, end=run_end if dopts.end is None else min(dopts.end,
                                                                                                   run_end)))
        t0 = time.perf_counter()
        res = run_experiments(seq, seq_runs, out, cfg, opts)
        console.print(f"wrote {out / 'report.md'} in {time.perf_counter() - t0:.0f} s "
                      f"({res['frames_run']} frames run, pairs {res['pairs']})", highlight=False, markup=False)
