"""Register two frames of a sequence and report it: ``surfelslam register`` without its printing.

:func:`register_frames` runs :func:`~surfelslam.tracking.registration.register_pair` on two frames of an opened
sequence (colour re-timed to the depth stamps from the neighbour frames when asked), and reports the pose, the ICP
statistics per level, the initial guesses, the depth agreement of the estimate and, where the sequence has ground
truth, the errors against it: :class:`PairReport` (its ``result`` is ``registration.json``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from surfelslam.errors import ConfigError, FrameError
from surfelslam.geometry import se3
from surfelslam.tracking.depth_agreement import depth_agreement
from surfelslam.tracking.icp import ICPConfig
from surfelslam.tracking.preprocess import PreprocessConfig, Preprocessor
from surfelslam.tracking.registration import (
    FEATURE_MAX_NORM,
    PAIR_FEATURES,
    PairRegistration,
    colour_timing,
    pair_feature_config,
    register_pair,
)
from surfelslam.tracking.retime import RetimeConfig


@dataclass
class PairReport:
    """A registered pair: ``result`` (``registration.json``: pose, ICP, guesses, timing, depth agreement, ground-truth
    errors), the registration itself, and both frames' pyramids (``(levels,)`` of vertex/normal maps, for figures).
    """

    result: dict
    registration: PairRegistration
    pyramids: tuple
    agreement: dict


def register_frames(sq, source: int, target: int, icp_cfg: ICPConfig, init: str = "auto",
                    photometric: bool = False, retime_cfg: RetimeConfig | None = None,
                    feature_max_norm: float = FEATURE_MAX_NORM, n_features: int = PAIR_FEATURES,
                    descriptor: str = "sift") -> PairReport:
    """Register frame ``source`` onto frame ``target`` (positions in ``sq``'s selection) and report it."""
    for name, idx in (("--source", source), ("--target", target)):
        if not 0 <= idx < len(sq):
            raise ConfigError(f"{name} {idx} is out of range: the selection has {len(sq)} frames")
    retime_cfg = RetimeConfig() if retime_cfg is None else retime_cfg
    pre = Preprocessor(sq.intrinsics, PreprocessConfig(pyramid_levels=icp_cfg.levels))
    f_src, f_tgt = sq[source], sq[target]
    p_src, p_tgt = pre.process(f_src.depth_m), pre.process(f_tgt.depth_m)
    timing, retime_note = (None, None), None
    if photometric:
        timing, retime_note = _pair_timing(sq, (f_src, f_tgt), (p_src, p_tgt), pre, icp_cfg, retime_cfg)
    reg = register_pair(f_src, f_tgt, p_src, p_tgt, sq.intrinsics, icp_cfg, init, feature_max_norm, photometric,
                        pair_feature_config(descriptor, n_features), preprocess_cfg=pre.cfg, colour_timing=timing)
    feat_info, geo_info = _guess_records(reg, descriptor, n_features)
    result = {**_pair_record(sq, source, target, f_src, f_tgt, reg), "init": init, "init_used": reg.init_used,
              "photometric": photometric,
              "colour_timing": {**{name: _timing_info(f, ct) for name, f, ct in
                                   (("source", f_src, timing[0]), ("target", f_tgt, timing[1]))},
                                "note": retime_note, "config": asdict(retime_cfg)},
              "features": feat_info, "geometric": geo_info,
              "levels": [{k: (v if not isinstance(v, float) or np.isfinite(v) else None)
                          for k, v in vars(li).items()} for li in reg.icp.levels]}
    T_init = reg.guess if reg.init_used != "identity" else None
    agree = _add_depth_agreement_and_gt(result, sq, source, target, f_src, f_tgt, reg.icp.T_target_source, T_init)
    return PairReport(result, reg, (p_src, p_tgt), agree)


def _pair_record(sq, source: int, target: int, f_src, f_tgt, reg: PairRegistration) -> dict:
    """``registration.json``'s frames, pose and ICP statistics."""
    res = reg.icp
    return {
        "source": source, "target": target,
        "source_timestamp": f_src.timestamp, "target_timestamp": f_tgt.timestamp,
        "source_depth_timestamp": float(sq.depth_timestamps[source]),
        "target_depth_timestamp": float(sq.depth_timestamps[target]),
        "T_target_source": res.T_target_source.tolist(),
        "inliers": res.inliers, "inlier_fraction": res.inlier_fraction, "rmse_m": res.rmse_m,
        "iterations": res.iterations, "converged": res.converged, "degenerate": res.degenerate,
        "condition_number": res.condition_number if np.isfinite(res.condition_number) else None,
        "reason": res.reason,
    }


def _colour_timing(sq, frame, pyramid, pre, icp_cfg, retime_cfg):
    """The colour timing (:func:`surfelslam.tracking.registration.colour_timing`) of ``frame`` (loaded, with its
    ``pyramid``) from its neighbours in the selection; a neighbour that cannot be read is left out."""
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
