"""``surfelslam register SEQ --source I --target J --out DIR [--init identity|features]``: pairwise ICP.

Projective point-to-plane ICP from the identity, or from a feature-based guess (ORB + PnP-RANSAC,
:func:`surfelslam.tracking.features.feature_guess`) for pairs too far apart for ICP alone.
"""

from __future__ import annotations

import json
from dataclasses import asdict, replace
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from surfelslam.errors import ConfigError
from surfelslam.tools.common import DatasetOptionsArgs, SeqArg, console, handle_errors, with_dataset_options


def per_level(text: str | None, default: tuple, levels: int, name: str, cast=float,
              coarser_factor: float = 2.0) -> tuple:
    """Parse ``"a"`` (finest level; coarser levels multiplied by ``coarser_factor`` per level) or
    ``"a,b,c"`` (one value per level, finest first) into a tuple of ``levels`` values."""
    if text is None:
        vals = tuple(default)
        if len(vals) < levels:  # more levels than the defaults: extend the last one
            vals = vals + tuple(cast(vals[-1] * coarser_factor ** (k + 1)) for k in range(levels - len(vals)))
        return vals[:levels]
    try:
        vals = tuple(cast(x) for x in text.replace(" ", "").split(","))
    except ValueError:
        raise ConfigError(f"{name} must be a number or a comma list of numbers, got {text!r}") from None
    if len(vals) == 1:
        return tuple(cast(vals[0] * coarser_factor**k) for k in range(levels))
    if len(vals) != levels:
        raise ConfigError(f"{name} has {len(vals)} values but --levels is {levels}")
    return vals


def _colour_timing(sq, frame, pyramid, pre, icp_cfg, retime_cfg):
    """The colour timing (:func:`surfelslam.tracking.registration.colour_timing`) of ``frame`` (loaded, with its
    ``pyramid``) from its neighbours in the selection; a neighbour that cannot be read is left out."""
    from surfelslam.errors import FrameError
    from surfelslam.tracking.registration import colour_timing

    offset = frame.colour_minus_depth_s
    if not retime_cfg.applies(offset):
        return None
    i = frame.index
    frames = {i: (frame, pyramid)}
    for j in (i - 1, i + 1):
        if 0 <= j < len(sq):
            try:
                f = sq[j]
            except FrameError:
                continue
            frames[j] = (f, pre.process(f.depth_m))
    pairs = [(frames[a][0], frames[b][0], frames[a][1], frames[b][1], frames[a][0].depth_stamp_s,
              frames[b][0].depth_stamp_s) for a, b in ((i - 1, i), (i, i + 1)) if a in frames and b in frames]
    return colour_timing(offset, frame.depth_stamp_s, pairs, sq.intrinsics, icp_cfg, retime_cfg)


def _timing_info(frame, ct) -> dict:
    """``registration.json``'s record of one frame's colour timing."""
    return {"colour_minus_depth_s": frame.colour_minus_depth_s, "retimed": ct is not None,
            "twist_per_s": None if ct is None else [float(x) for x in ct.twist_per_s]}


def _icp_config(levels: int | None, dist_thresh: str | None, angle_thresh: str | None, iterations: str | None,
                solver: str):
    """``register``'s ICP settings (:func:`~surfelslam.tracking.icp.pairwise_config`) with the per-level options."""
    from surfelslam.tracking.icp import pairwise_config

    d = pairwise_config()
    n_levels = d.levels if levels is None else levels
    if n_levels < 1:
        raise ConfigError(f"--levels must be >= 1, got {n_levels}")
    return replace(
        d,
        levels=n_levels,
        dist_thresh_m=per_level(dist_thresh, d.dist_thresh_m, n_levels, "--dist-thresh"),
        angle_thresh_deg=per_level(angle_thresh, d.angle_thresh_deg, n_levels, "--angle-thresh",
                                   coarser_factor=1.0),
        iterations=per_level(iterations, d.iterations, n_levels, "--iterations", cast=int, coarser_factor=1.0),
        solver=solver,
    )


def _pair_timing(sq, frames, pyramids, pre, cfg, retime_cfg):
    """``((source timing, target timing), note)``: both frames' colour timings, or neither (with a note) when one
    that needs re-timing has none."""
    timing = tuple(_colour_timing(sq, f, p, pre, cfg, retime_cfg) for f, p in zip(frames, pyramids, strict=True))
    if any(retime_cfg.applies(f.colour_minus_depth_s) and ct is None for f, ct in zip(frames, timing, strict=True)):
        # one frame alone re-timed is worse than neither: the offsets' common part no longer cancels
        return (None, None), "a frame's velocity could not be measured near its colour stamp: neither re-timed"
    return timing, None


def _guess_records(reg, descriptor: str, n_features: int) -> tuple[dict | None, dict | None]:
    """``registration.json``'s records of the feature guess and the shape (FPFH) guess (None: not tried)."""
    from surfelslam.geometry import se3

    feat_info = None
    if reg.motion is not None:
        mres = reg.motion
        feat_info = {"ok": bool(mres.ok), "reason": mres.reason, "descriptor": descriptor,
                     "n_features": n_features,
                     "good_matches": mres.n_good,
                     "inliers": mres.n_inliers,
                     "T_target_source": se3.invert(mres.T_cur_ref).tolist() if mres.ok else None}
    geo_info = None
    if reg.geometric is not None:
        g = reg.geometric
        geo_info = {"ok": g.T_target_source is not None, "reason": g.reason, "points": list(g.n_points),
                    "matches": g.n_matches, "inliers": g.n_inliers,
                    "T_target_source": None if g.T_target_source is None else g.T_target_source.tolist()}
    return feat_info, geo_info


def _add_depth_agreement_and_gt(result: dict, sq, source: int, target: int, f_src, f_tgt, T: np.ndarray,
                                T_init: np.ndarray | None) -> dict:
    """Add the depth agreement of the estimate (and of the ground truth) and the errors against the ground truth
    to ``result``; returns the agreements by pose name."""
    from surfelslam.geometry import se3
    from surfelslam.tracking.depth_agreement import depth_agreement

    def agreement(T_pose: np.ndarray) -> dict:
        a = vars(depth_agreement(f_src.depth_m, f_tgt.depth_m, sq.intrinsics, T_pose)).copy()
        a["median_abs_dz_m"] = a["median_abs_dz_m"] if np.isfinite(a["median_abs_dz_m"]) else None
        return a

    agree = {"estimate": agreement(T)}
    result["depth_agreement"] = agree
    # the depth camera's ground-truth pose at its own capture time: ICP registers the depth images
    T_wc, valid = sq.gt_poses(at_depth_time=True)
    if valid[source] and valid[target]:
        T_gt = se3.invert(T_wc[target]) @ T_wc[source]
        agree["ground_truth"] = agreement(T_gt)
        t_err, r_err = se3.pose_error(T, T_gt)
        t0, r0 = se3.pose_error(np.eye(4), T_gt)
        result["gt_error"] = {"trans_m": t_err, "rot_deg": r_err}
        result["gt_motion"] = {"trans_m": t0, "rot_deg": r0}
        if T_init is not None:
            ti, ri = se3.pose_error(T_init, T_gt)
            result["init_gt_error"] = {"trans_m": ti, "rot_deg": ri}
    return agree


def _write_outputs(out: Path, result: dict, p_src, p_tgt, res, source: int, target: int, figures: bool) -> None:
    """``registration.json``, and ``before.png`` and ``after.png`` when ``figures``."""
    from surfelslam.geometry import se3
    from surfelslam.io.atomic import write_text_atomic
    from surfelslam.viz.registration import plot_registration

    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "registration.json", json.dumps(result, indent=2) + "\n")
    if not figures:
        return
    src_pts = p_src[0].vertex[p_src[0].vertex[..., 2] > 0]
    tgt_pts = p_tgt[0].vertex[p_tgt[0].vertex[..., 2] > 0]
    plot_registration(src_pts, tgt_pts, out / "before.png", f"before: source {source} (red), target "
                      f"{target} (green), identity")
    plot_registration(se3.transform_points(res.T_target_source, src_pts.astype(np.float64)), tgt_pts,
                      out / "after.png", f"after ICP: {res.inliers} inliers, RMSE {1000 * res.rmse_m:.1f} mm")


def _print_guesses(result: dict, init: str) -> None:
    for label, info, n_key, n_name in (("feature guess", result["features"], "good_matches", "good matches"),
                                       ("shape (FPFH) guess", result["geometric"], "matches", "mutual matches")):
        if info is not None:
            console.print(f"{label}: {info['inliers']} inliers of {info[n_key]} {n_name}" if info["ok"] else
                          f"{label} rejected ({info['reason']}: {info[n_key]} {n_name}, {info['inliers']} "
                          "inliers)", highlight=False)
    if init != "identity":
        console.print(f"ICP started from: {result['init_used']}", highlight=False)
    ctm = result["colour_timing"]
    if ctm["source"]["retimed"] or ctm["target"]["retimed"] or ctm["note"]:
        console.print("colour re-timed to the depth stamps (colour - depth: "
                      f"{1000 * ctm['source']['colour_minus_depth_s']:.1f} / "
                      f"{1000 * ctm['target']['colour_minus_depth_s']:.1f} ms)" if ctm["note"] is None else
                      f"colour not re-timed: {ctm['note']}", highlight=False)


def _print_result(result: dict, res, T: np.ndarray, agree: dict, out: Path) -> None:
    source, target = result["source"], result["target"]
    console.print(f"registered frame {source} -> {target}: inliers {res.inliers} "
                  f"({100 * res.inlier_fraction:.1f}%), RMSE {1000 * res.rmse_m:.2f} mm, "
                  f"iterations {res.iterations}, converged {res.converged}"
                  + ("" if res.reason is None else f" ({res.reason})"), highlight=False)
    console.print(f"condition number {res.condition_number:.3g}, degenerate {res.degenerate}",
                  highlight=False)
    console.print("T_target_source =\n" + np.array2string(T, precision=6, suppress_small=True),
                  highlight=False)
    if "gt_error" in result:
        g = result["gt_error"]
        m = result["gt_motion"]
        if "init_gt_error" in result:
            gi = result["init_gt_error"]
            console.print(f"initial guess GT error: {1000 * gi['trans_m']:.1f} mm, {gi['rot_deg']:.3f} deg",
                          highlight=False)
        console.print(f"GT error: {1000 * g['trans_m']:.1f} mm, {g['rot_deg']:.3f} deg "
                      f"(GT motion {1000 * m['trans_m']:.1f} mm, {m['rot_deg']:.2f} deg)", highlight=False)
    else:
        console.print("no ground truth for these frames", highlight=False)
    text = ", ".join(f"{name.replace('_', ' ')} pose "
                     + ("no overlap" if a["median_abs_dz_m"] is None else
                        f"{1000 * a['median_abs_dz_m']:.1f} mm over {100 * a['overlap_fraction']:.0f}% "
                        "of the source")
                     for name, a in agree.items())
    console.print(f"depth agreement (median |dz| where the moved source meets target depth): {text}",
                  highlight=False)
    console.print(f"wrote {out / 'registration.json'}, {out / 'before.png'}, {out / 'after.png'}",
                  highlight=False, markup=False)


def register(app: typer.Typer) -> None:
    @app.command("register")
    @handle_errors
    @with_dataset_options
    def register_cmd(
        seq: SeqArg,
        source: Annotated[int, typer.Option("--source", help="Source frame position (after selection).")],
        target: Annotated[int, typer.Option("--target", help="Target frame position (after selection).")],
        out: Annotated[Path, typer.Option("--out", help="Output folder (registration.json, before/after.png).")],
        dataset: DatasetOptionsArgs,
        levels: Annotated[int | None, typer.Option("--levels", help="Pyramid levels (default 4).")] = None,
        dist_thresh: Annotated[str | None, typer.Option(
            "--dist-thresh", help="Association distance in metres: finest level (doubled per coarser level) "
                                  "or a comma list per level, finest first.")] = None,
        angle_thresh: Annotated[str | None, typer.Option(
            "--angle-thresh", help="Normal angle gate in degrees: one value for all levels or a comma list, "
                                   "finest first.")] = None,
        iterations: Annotated[str | None, typer.Option(
            "--iterations", help="Max iterations: one value for all levels or a comma list, finest first.")] = None,
        solver: Annotated[str, typer.Option("--solver", help="cholesky | lu | qr | pinv")] = "cholesky",
        init: Annotated[str, typer.Option(
            "--init", help="ICP initial guess: identity; features (SIFT/ORB + PnP-RANSAC between the two frames; "
                           "when a rejection rule fires, FPFH shape features of the depth + rigid consensus; "
                           "identity when both are rejected); geometry (the FPFH guess only); auto (ICP from "
                           "the identity and the features guess, keeping the pose whose depth agreement is "
                           "better; the default).")] = "auto",
        photometric: Annotated[str, typer.Option(
            "--photometric", help="Joint geometric + photometric ICP: auto (on when colour and depth are "
                                  "registered, e.g. TUM, ICL-NUIM; off for 7-Scenes), on, off.")] = "auto",
        feature_max_norm: Annotated[float | None, typer.Option(
            "--feature-max-norm", help="--init features / auto: largest accepted PnP motion norm (m + rad; "
                                       "default 2.0); the odometry default 0.3 is too small for pairs far "
                                       "apart.")] = None,
        features: Annotated[int | None, typer.Option(
            "--features", help="--init features / auto: keypoints per image (default 2000, twice the "
                               "odometry's: pairs far apart share little of the view).")] = None,
        descriptor: Annotated[str, typer.Option(
            "--descriptor", help="--init features / auto: sift (Lowe's ratio test; more correct matches between "
                                 "views far apart, the default) or orb (the odometry's matching).")] = "sift",
        retime_colour: Annotated[str, typer.Option(
            "--retime-colour", help="With the photometric term: auto (a frame whose colour and depth stamps differ "
                                    "by 1-50 ms, e.g. TUM, has its colour re-timed to its depth stamp with the "
                                    "camera velocity from its neighbour frames), off.")] = "auto",
        figures: Annotated[bool, typer.Option("--figures/--no-figures",
                                              help="Write before.png and after.png.")] = True,
    ) -> None:
        """Register frame SOURCE onto frame TARGET; print and save the pose, inliers, RMSE and GT error."""
        from surfelslam.datasets import open_sequence
        from surfelslam.tracking.features import DETECTORS
        from surfelslam.tracking.photometric import PHOTOMETRIC_MODES, colour_switch
        from surfelslam.tracking.preprocess import PreprocessConfig, Preprocessor
        from surfelslam.tracking.registration import (
            FEATURE_MAX_NORM,
            INIT_MODES,
            PAIR_FEATURES,
            pair_feature_config,
            register_pair,
        )
        from surfelslam.tracking.retime import RETIME_MODES, RetimeConfig

        if init not in INIT_MODES:
            raise ConfigError(f"--init must be one of {', '.join(INIT_MODES)}, got {init!r}")
        if retime_colour not in RETIME_MODES:
            raise ConfigError(f"--retime-colour (colour re-timing) must be one of {', '.join(RETIME_MODES)}, "
                              f"got {retime_colour!r}")
        if photometric not in PHOTOMETRIC_MODES:
            raise ConfigError(f"--photometric must be one of {', '.join(PHOTOMETRIC_MODES)}, got {photometric!r}")
        sq = open_sequence(seq, dataset.resolve())
        for name, idx in (("--source", source), ("--target", target)):
            if not 0 <= idx < len(sq):
                raise ConfigError(f"{name} {idx} is out of range: the selection has {len(sq)} frames")
        cfg = _icp_config(levels, dist_thresh, angle_thresh, iterations, solver)
        pre = Preprocessor(sq.intrinsics, PreprocessConfig(pyramid_levels=cfg.levels))
        f_src, f_tgt = sq[source], sq[target]
        p_src = pre.process(f_src.depth_m)
        p_tgt = pre.process(f_tgt.depth_m)
        use_photometric = colour_switch(photometric, sq.colour_registered)
        retime_cfg = RetimeConfig(mode=retime_colour)
        timing, retime_note = (None, None), None
        if use_photometric:
            timing, retime_note = _pair_timing(sq, (f_src, f_tgt), (p_src, p_tgt), pre, cfg, retime_cfg)
        n_features = PAIR_FEATURES if features is None else features
        if n_features < 1:
            raise ConfigError(f"--features must be >= 1, got {n_features}")
        if descriptor not in DETECTORS:
            raise ConfigError(f"--descriptor must be one of {', '.join(DETECTORS)}, got {descriptor!r}")
        reg = register_pair(f_src, f_tgt, p_src, p_tgt, sq.intrinsics, cfg, init,
                            FEATURE_MAX_NORM if feature_max_norm is None else feature_max_norm, use_photometric,
                            pair_feature_config(descriptor, n_features), preprocess_cfg=pre.cfg,
                            colour_timing=timing)
        res, init_used = reg.icp, reg.init_used
        feat_info, geo_info = _guess_records(reg, descriptor, n_features)
        T_init = reg.guess if init_used != "identity" else None
        T = res.T_target_source

        result = {
            "source": source,
            "target": target,
            "source_timestamp": f_src.timestamp,
            "target_timestamp": f_tgt.timestamp,
            "source_depth_timestamp": float(sq.depth_timestamps[source]),
            "target_depth_timestamp": float(sq.depth_timestamps[target]),
            "T_target_source": T.tolist(),
            "inliers": res.inliers,
            "inlier_fraction": res.inlier_fraction,
            "rmse_m": res.rmse_m,
            "iterations": res.iterations,
            "converged": res.converged,
            "degenerate": res.degenerate,
            "condition_number": res.condition_number if np.isfinite(res.condition_number) else None,
            "reason": res.reason,
            "init": init,
            "init_used": init_used,
            "photometric": use_photometric,
            "colour_timing": {**{name: _timing_info(f, ct) for name, f, ct in
                                 (("source", f_src, timing[0]), ("target", f_tgt, timing[1]))},
                              "note": retime_note, "config": asdict(retime_cfg)},
            "features": feat_info,
            "geometric": geo_info,
            "levels": [{k: (v if not isinstance(v, float) or np.isfinite(v) else None)
                        for k, v in vars(li).items()} for li in res.levels],
        }
        agree = _add_depth_agreement_and_gt(result, sq, source, target, f_src, f_tgt, T, T_init)
        _write_outputs(out, result, p_src, p_tgt, res, source, target, figures)
        _print_guesses(result, init)
        _print_result(result, res, T, agree, out)
