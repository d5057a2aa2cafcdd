"""The frame-pair sections: ICP on pairs (1), the linear solvers (2) and feature odometry (5)."""

from __future__ import annotations

import timeit
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import scipy.linalg

from surfelslam.experiments.common import (
    SECTION_TITLES,
    SOLVER_PAIR_GATE_M,
    SOLVER_TIMEIT_NUMBER,
    SOLVER_TIMEIT_REPEAT,
    ExperimentOptions,
    fmt_value,
    gt_relative,
)

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
        T_gt = gt_relative(T_wc, valid, s, t)
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
        lines.append(f"| {name} | ({xs}) | {fmt_value(r['max_diff_vs_cholesky'][name], '.3e')} | "
                     f"{1e6 * r['median_s'][name]:.1f} |")
    lines += ["", f"Largest difference between any two solutions: {fmt_value(r['max_pairwise_diff'], '.3e')}.", ""]
    return lines, r


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
    T_gt = gt_relative(T_wc, valid, s, t)
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
