"""Pairwise registration of two RGB-D frames with a choice of ICP start (what ``surfelslam register`` runs).

Starts (``INIT_MODES``):

* ``identity``: ICP from the identity;
* ``features``: ICP from the image-feature guess between the two frames (SIFT or ORB, PnP-RANSAC); when a rejection
  rule fires, from the shape-feature guess (FPFH and a rigid consensus on the depth alone,
  :mod:`surfelslam.tracking.geometric`); from the identity when both are rejected;
* ``geometry``: ICP from the shape-feature guess only (identity when it is rejected);
* ``auto``: ICP from the identity and from the ``features`` guess, keeping the pose the two depth images agree with
  better (:func:`surfelslam.tracking.depth_agreement.depth_agreement`: lower median ``|dz|``; no ground truth involved).

With ``photometric=True`` every ICP run also minimises the intensity differences
(:mod:`surfelslam.tracking.photometric`); for colour registered to depth only.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from surfelslam.errors import ConfigError
from surfelslam.tracking.depth_agreement import depth_agreement
from surfelslam.tracking.features import FeatureConfig, MotionResult, feature_guess, with_max_motion_norm
from surfelslam.tracking.geometric import GeometricGuess, GeometricGuessConfig, geometric_guess
from surfelslam.tracking.icp import ICPConfig, ICPResult, icp, photometric_term
from surfelslam.tracking.photometric import intensity_from_rgb, intensity_pyramid
from surfelslam.tracking.preprocess import FramePyramid, PreprocessConfig, Preprocessor, level_for_width
from surfelslam.tracking.retime import ColourTiming, RetimeConfig, retime_intensity, twist_from_pose
from surfelslam.types import Intrinsics, RGBDFrame

INIT_MODES = ("identity", "features", "geometry", "auto")
#: The shape-feature guess is computed at the pyramid level at most this wide (px): its clouds are voxel means, so
#: finer levels only cost time, and their noisier normals blur the descriptors.
GEOMETRIC_MAX_WIDTH_PX = 320
FEATURE_MAX_NORM = 2.0  # m + rad: the PnP guess accepts motions up to this (pairs far apart; odometry uses 0.3)
#: Keypoints per image for a pair's guess. Pairs far apart share a small part of the view, so twice the
#: odometry's 1000.
PAIR_FEATURES = 2000
#: Keypoints of a pair's guess: SIFT (ratio test) finds more correct matches than ORB between views far apart
#: (``benchmarks/icp_pairs.py``).
PAIR_DETECTOR = "sift"


def pair_feature_config(detector: str = PAIR_DETECTOR, n_features: int = PAIR_FEATURES) -> FeatureConfig:
    """Feature settings of a pair's guess: ``detector`` keypoints (SIFT with Lowe's ratio test, ORB with the
    odometry's cross-check and good-match filter), ``n_features`` per image."""
    return FeatureConfig(n_features=n_features, detector=detector, matching="ratio" if detector == "sift" else
                         FeatureConfig().matching)


@dataclass
class PairRegistration:
    """Outcome of :func:`register_pair`.

    Attributes:
        icp: the kept ICP result (``icp.T_target_source`` is the pose).
        init_used: ``"identity"``, ``"features"`` (the image-feature guess) or ``"geometry"`` (the shape-feature
            guess): the start of the kept result.
        guess: ``(4, 4)`` guess ``T_target_source`` (image or shape features) when one was computed and accepted,
            else ``None``.
        motion: the PnP outcome when image features were tried, else ``None``.
        geometric: the shape-feature outcome when it was tried, else ``None``.
    """

    icp: ICPResult
    init_used: str
    guess: np.ndarray | None
    motion: MotionResult | None
    geometric: GeometricGuess | None = None


def guess_level(pyramid: FramePyramid, max_width_px: int = GEOMETRIC_MAX_WIDTH_PX) -> int:
    """The finest level of ``pyramid`` at most ``max_width_px`` wide (its coarsest if none is)."""
    return min(level_for_width(pyramid.intrinsics.width, max_width_px), len(pyramid) - 1)


def guess_maps(frame: RGBDFrame, pyramid: FramePyramid, intr: Intrinsics,
               max_width_px: int = GEOMETRIC_MAX_WIDTH_PX,
               preprocess_cfg: PreprocessConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Vertex and normal maps ``(h, w, 3)`` the shape-feature guess uses: the frame's depth at most ``max_width_px``
    wide, reduced by keeping every ``2**k``-th pixel (intrinsics divided by ``2**k``, as ``--downsample``), not the
    pyramid's 2x2 block means, so that a 640x480 frame gives the guess what ``--downsample 2`` would (the block
    means smooth away some of the shape the descriptors need). At 320x240 input both are the frame itself.
    ``pyramid`` is the frame's (level 0 at ``intr``), built with ``preprocess_cfg`` (default
    :class:`PreprocessConfig`), whose filters the reduced maps use too."""
    level = guess_level(pyramid, max_width_px)
    if level == 0:
        return pyramid[0].vertex, pyramid[0].normal
    f = 2 ** level
    small = Preprocessor(intr.scaled(f), replace(preprocess_cfg or PreprocessConfig(), pyramid_levels=1))
    top = small.process(np.ascontiguousarray(frame.depth_m[::f, ::f]))[0]
    return top.vertex, top.normal


def register_pair(src: RGBDFrame, tgt: RGBDFrame, p_src: FramePyramid, p_tgt: FramePyramid, intr: Intrinsics,
                  icp_cfg: ICPConfig, init: str = "auto", feature_max_norm: float = FEATURE_MAX_NORM,
                  photometric: bool = False, feature_cfg: FeatureConfig | None = None,
                  geometric_cfg: GeometricGuessConfig | None = None,
                  preprocess_cfg: PreprocessConfig | None = None,
                  colour_timing: tuple[ColourTiming | None, ColourTiming | None] = (None, None)) -> PairRegistration:
    """Register ``src`` onto ``tgt`` (their pyramids ``p_src`` / ``p_tgt``, level 0 at the frames' resolution)
    from the start ``init``; ``photometric``: joint geometric + photometric ICP; ``feature_cfg``: the feature / PnP
    settings of the guess (default :func:`pair_feature_config`), whose motion bound becomes
    ``feature_max_norm``; ``geometric_cfg``: the shape-feature guess's settings (default
    :class:`GeometricGuessConfig`); ``preprocess_cfg``: the settings the pyramids were built with (the shape guess
    reduces wide frames with them; default :class:`PreprocessConfig`); ``colour_timing``: the source's and the target's
    colour capture relative to their depth (:mod:`surfelslam.tracking.retime`; ``None``: simultaneous): with the
    photometric term, each colour image is re-timed to its depth stamp first."""
    if init not in INIT_MODES:
        raise ConfigError(f"--init must be one of {', '.join(INIT_MODES)}, got {init!r}")
    i_src = i_tgt = None
    if photometric and icp_cfg.photometric_weight > 0:
        img_src, img_tgt = (intensity_from_rgb(f.rgb) if ct is None else
                            retime_intensity(intensity_from_rgb(f.rgb), f.depth_m, intr, ct.T_colour_depth)
                            for f, ct in zip((src, tgt), colour_timing, strict=True))
        i_src = intensity_pyramid(img_src, icp_cfg.levels, gradients=False)
        i_tgt = intensity_pyramid(img_tgt, icp_cfg.levels, gradients=True)

    def run(T_init: np.ndarray | None) -> ICPResult:
        term = None if i_src is None else photometric_term(i_src, i_tgt, icp_cfg)
        return icp(p_src, p_tgt, T_init, icp_cfg, photometric=term)

    guess = motion = geo = None
    kind = "identity"
    if init in ("features", "auto"):
        fcfg = pair_feature_config() if feature_cfg is None else feature_cfg
        fcfg = with_max_motion_norm(fcfg, feature_max_norm)
        guess, motion = feature_guess(src, tgt, intr, fcfg)
        kind = "features"
    if init == "geometry" or (init != "identity" and guess is None):
        (v_src, n_src), (v_tgt, n_tgt) = (guess_maps(src, p_src, intr, preprocess_cfg=preprocess_cfg),
                                          guess_maps(tgt, p_tgt, intr, preprocess_cfg=preprocess_cfg))
        geo = geometric_guess(v_src, n_src, v_tgt, n_tgt, geometric_cfg)
        guess, kind = geo.T_target_source, "geometry"
    if init in ("features", "geometry") and guess is not None:
        return PairRegistration(run(guess), kind, guess, motion, geo)
    res = run(None)
    if init == "auto" and guess is not None:
        res_f = run(guess)
        dz_id, dz_f = (depth_agreement(src.depth_m, tgt.depth_m, intr, r.T_target_source).median_abs_dz_m
                       for r in (res, res_f))
        if np.isfinite(dz_f) and not dz_id <= dz_f:
            return PairRegistration(res_f, kind, guess, motion, geo)
    return PairRegistration(res, "identity", guess, motion, geo)


def capture_twist(before: RGBDFrame, after: RGBDFrame, p_before: FramePyramid, p_after: FramePyramid,
                  intr: Intrinsics, icp_cfg: ICPConfig, dt_s: float, photometric: bool) -> np.ndarray | None:
    """``(6,)`` body twist per second of the depth camera between two nearby frames (``dt_s`` = depth stamp of
    ``after`` minus that of ``before``), for re-timing a frame between them (:mod:`surfelslam.tracking.retime`);
    ``None`` when their ICP (from the identity; joint with the photometric term when ``photometric``: on plain
    walls depth alone slides, 0.1-0.9 m off on the synthetic office) does not converge. The colour of the two
    frames is used as captured: its offsets bias this velocity only by their difference over ``dt_s``."""
    term = None
    if photometric and icp_cfg.photometric_weight > 0:
        term = photometric_term(intensity_pyramid(intensity_from_rgb(before.rgb), icp_cfg.levels, gradients=False),
                                intensity_pyramid(intensity_from_rgb(after.rgb), icp_cfg.levels, gradients=True),
                                icp_cfg)
    res = icp(p_before, p_after, None, icp_cfg, photometric=term)
    return twist_from_pose(res.T_target_source, dt_s) if res.converged else None


def colour_timing(offset_s: float, depth_stamp_s: float,
                  neighbours: list[tuple[RGBDFrame, RGBDFrame, FramePyramid, FramePyramid, float, float]],
                  intr: Intrinsics, icp_cfg: ICPConfig, retime_cfg: RetimeConfig,
                  photometric: bool = True) -> ColourTiming | None:
    """A frame's :class:`ColourTiming` from its colour - depth stamp offset and its neighbour pairs.

    ``neighbours``: ``(before, after, p_before, p_after, t_before_s, t_after_s)`` per pair of consecutive frames that
    contains it (the previous and the frame, the frame and the next; the ``t`` their depth stamps). Each pair's
    :func:`capture_twist` is the velocity at the middle of its interval; the frame's twist is the one between the
    colour and the depth stamp (at ``depth_stamp_s + offset_s / 2``), linear in time between the two pairs' (held at
    the nearer one outside them), or the one pair's. ``None`` when ``retime_cfg`` does not apply to ``offset_s``, no
    pair converged, or the pairs' velocities were measured farther than ``retime_cfg.max_velocity_lag_s`` from
    there: a velocity from a pair whose interval lies far from the colour-depth interval re-times worse than none."""
    if not retime_cfg.applies(offset_s):
        return None
    found = [((t_b + t_a) / 2 - depth_stamp_s, tw) for b, a, p_b, p_a, t_b, t_a in neighbours if t_a > t_b
             if (tw := capture_twist(b, a, p_b, p_a, intr, icp_cfg, t_a - t_b, photometric)) is not None]
    if not found:
        return None
    found.sort(key=lambda m: m[0])
    (m0, tw0), (m1, tw1) = found[0], found[-1]
    mid = offset_s / 2
    if max(m0 - mid, mid - m1) > retime_cfg.max_velocity_lag_s:
        return None  # no velocity measured near the colour capture
    w = 0.0 if m1 <= m0 else float(np.clip((mid - m0) / (m1 - m0), 0.0, 1.0))
    return ColourTiming(float(offset_s), (1 - w) * tw0 + w * tw1)
