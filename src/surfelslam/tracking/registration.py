"""Pairwise registration of two RGB-D frames with a choice of ICP start (what ``surfelslam register`` runs).

Starts (``INIT_MODES``):

* ``identity``: ICP from the identity;
* ``features``: ICP from the ORB + PnP-RANSAC guess between the two frames (identity when a rejection rule fires);
* ``auto``: ICP from both, keeping the pose the two depth images agree with better
  (:func:`surfelslam.eval.depth_agreement.depth_agreement`: lower median ``|dz|``; no ground truth involved).

With ``photometric=True`` every ICP run also minimises the intensity differences
(:mod:`surfelslam.tracking.photometric`); for colour registered to depth only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surfelslam.errors import ConfigError
from surfelslam.eval.depth_agreement import depth_agreement
from surfelslam.tracking.features import FeatureConfig, MotionResult, feature_guess, with_max_motion_norm
from surfelslam.tracking.icp import ICPConfig, ICPResult, icp, photometric_term
from surfelslam.tracking.photometric import intensity_from_rgb, intensity_pyramid
from surfelslam.tracking.preprocess import FramePyramid
from surfelslam.types import Intrinsics, RGBDFrame

INIT_MODES = ("identity", "features", "auto")
FEATURE_MAX_NORM = 2.0  # m + rad: the PnP guess accepts motions up to this (pairs far apart; odometry uses 0.3)
#: Keypoints per image for a pair's guess. Pairs far apart share a small part of the view, so twice the
#: odometry's 1000 (ORB on 7-Scenes pairs 90 frames apart at 640x480: the guess is accepted on 4 of 8, not 1).
PAIR_FEATURES = 2000
#: Keypoints of a pair's guess: SIFT (ratio test) finds more correct matches than ORB between views far apart. Of
#: the 12 7-Scenes pairs 90 frames apart in the README tables, ICP from the identity misses the ICP-from-GT result
#: on 10 at 320x240; from the SIFT guess it reaches it on 8 of them (ORB: 5).
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
        init_used: ``"identity"`` or ``"features"``: the start of the kept result.
        guess: ``(4, 4)`` feature guess ``T_target_source`` when one was computed and accepted, else ``None``.
        motion: the PnP outcome when features were tried, else ``None``.
    """

    icp: ICPResult
    init_used: str
    guess: np.ndarray | None
    motion: MotionResult | None


def register_pair(src: RGBDFrame, tgt: RGBDFrame, p_src: FramePyramid, p_tgt: FramePyramid, intr: Intrinsics,
                  icp_cfg: ICPConfig, init: str = "auto", feature_max_norm: float = FEATURE_MAX_NORM,
                  photometric: bool = False, feature_cfg: FeatureConfig | None = None) -> PairRegistration:
    """Register ``src`` onto ``tgt`` (their pyramids ``p_src`` / ``p_tgt``, level 0 at the frames' resolution)
    from the start ``init``; ``photometric``: joint geometric + photometric ICP; ``feature_cfg``: the feature / PnP
    settings of the guess (default :func:`pair_feature_config`), whose motion bound becomes
    ``feature_max_norm``."""
    if init not in INIT_MODES:
        raise ConfigError(f"--init must be one of {', '.join(INIT_MODES)}, got {init!r}")
    i_src = i_tgt = None
    if photometric and icp_cfg.photometric_weight > 0:
        i_src = intensity_pyramid(intensity_from_rgb(src.rgb), icp_cfg.levels, gradients=False)
        i_tgt = intensity_pyramid(intensity_from_rgb(tgt.rgb), icp_cfg.levels, gradients=True)

    def run(T_init: np.ndarray | None) -> ICPResult:
        term = None if i_src is None else photometric_term(i_src, i_tgt, icp_cfg)
        return icp(p_src, p_tgt, T_init, icp_cfg, photometric=term)

    guess = motion = None
    if init != "identity":
        fcfg = pair_feature_config() if feature_cfg is None else feature_cfg
        fcfg = with_max_motion_norm(fcfg, feature_max_norm)
        guess, motion = feature_guess(src, tgt, intr, fcfg)
    if init == "features" and guess is not None:
        return PairRegistration(run(guess), "features", guess, motion)
    res = run(None)
    if init == "auto" and guess is not None:
        res_f = run(guess)
        dz_id, dz_f = (depth_agreement(src.depth_m, tgt.depth_m, intr, r.T_target_source).median_abs_dz_m
                       for r in (res, res_f))
        if np.isfinite(dz_f) and not dz_id <= dz_f:
            return PairRegistration(res_f, "features", guess, motion)
    return PairRegistration(res, "identity", guess, motion)
