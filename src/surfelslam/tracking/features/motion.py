"""Relative pose of two frames' features: PnP-RANSAC (or rigid consensus), refinement and the rejection rules.

``fy`` may be negative (ICL-NUIM). OpenCV's PnP is only exercised with a positive focal length:
for ``fy < 0`` the image rows are mirrored about ``cy`` (``v' = 2 cy - v``) and ``fy' = -fy``,
which describes exactly the same projection of the same 3D points, so the pose is unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from surfelslam.geometry.camera import project
from surfelslam.geometry.se3 import invert, make_T, motion_norm, so3_exp, so3_log, transform_points
from surfelslam.tracking.consensus import has_consistent_set, rigid_consensus
from surfelslam.tracking.features.config import FeatureConfig
from surfelslam.tracking.features.depth import keypoint_depth
from surfelslam.tracking.features.extract import Features, extract
from surfelslam.tracking.features.matching import MatchResult, match
from surfelslam.tracking.features.refine import refine_rgbd
from surfelslam.tracking.features.reprojection import reprojection_inliers
from surfelslam.tracking.features.subpixel import search_by_projection, track_subpixel
from surfelslam.types import Intrinsics, RGBDFrame

REJECT_REASONS = (
    "too_few_matches", "too_few_consistent", "too_few_inliers", "motion_too_large", "pnp_failed",
)


@dataclass
class MotionResult:
    """Outcome of :func:`estimate_motion`.

    Attributes:
        T_cur_ref: ``(4, 4)`` maps reference-camera points into the current camera (identity when
            PnP failed; still filled when a later rule rejects the motion).
        ok: True when every rule passed.
        reason: ``None`` or one of ``REJECT_REASONS``.
        n_matches: raw matches; n_good: good matches with a valid reference 3D point;
        n_inliers: PnP inliers.
        rvec, tvec: ``(3,)`` OpenCV pose (the same transform as ``T_cur_ref``).
        inlier_mask: ``(n_good,)`` bool over ``pairs``.
        pairs: ``(n_good, 2)`` the good matches used for PnP (ref, cur).
        uv_cur: ``(n_good, 2)`` float32 current-image pixels of ``pairs`` (sub-pixel tracked where LK succeeded),
            or ``None`` when matching stopped before PnP.
        information: ``(6, 6)`` information matrix of ``T_cur_ref`` from the joint RGB-D refinement, for a left
            perturbation ``exp(xi) T_cur_ref`` with ``xi = (omega, v)`` (rad, m); ``None`` without that refinement.
        n_refined: points in the final refinement (the PnP inliers, or the keypoints found by projection when
            ``FeatureConfig.projection_search`` found more); 0 when PnP failed.
    """

    T_cur_ref: np.ndarray
    ok: bool
    reason: str | None
    n_matches: int
    n_good: int
    n_inliers: int
    rvec: np.ndarray
    tvec: np.ndarray
    inlier_mask: np.ndarray
    pairs: np.ndarray
    uv_cur: np.ndarray | None = None
    information: np.ndarray | None = None
    n_refined: int = 0

    @property
    def motion_norm(self) -> float:
        return motion_norm(self.T_cur_ref)


def _cv_camera(intr: Intrinsics) -> tuple[np.ndarray, float]:
    """OpenCV camera matrix with positive fy and the row sign to apply to v (+1 or -1 mirror)."""
    K = intr.K.copy()
    if intr.fy < 0:
        K[1, 1] = -intr.fy
        return K, -1.0
    return K, 1.0


def _image_points_cv(uv: np.ndarray, intr: Intrinsics, sign: float) -> np.ndarray:
    pts = uv.astype(np.float64).copy()
    if sign < 0:
        pts[:, 1] = 2.0 * intr.cy - pts[:, 1]
    return pts


def _failed(n_raw: int, n_good: int, reason: str, pairs: np.ndarray) -> MotionResult:
    return MotionResult(
        np.eye(4), False, reason, n_raw, n_good, 0, np.zeros(3), np.zeros(3),
        np.zeros(len(pairs), bool), pairs,
    )


def pnp_ransac(obj: np.ndarray, img: np.ndarray, K: np.ndarray, rvec0: np.ndarray, tvec0: np.ndarray,
               use_guess: bool, cfg: FeatureConfig):
    """OpenCV PnP-RANSAC: ``(inlier mask (N,), rvec (3, 1), tvec (3, 1), None)`` or ``(None, _, _, reason)``.
    Without a guess and with ``cfg.ransac_method == "usac"``: OpenCV's USAC (see :class:`FeatureConfig`)."""
    try:
        if not use_guess and cfg.ransac_method == "usac":
            ok, _, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K.copy(), None, params=_usac_params(cfg))
        else:
            ok, rvec, tvec, inl = cv2.solvePnPRansac(
                obj, img, K, None, rvec0, tvec0, use_guess,
                cfg.ransac_iterations, cfg.reprojection_error_px, cfg.ransac_confidence,
                flags=cv2.SOLVEPNP_ITERATIVE if use_guess else cv2.SOLVEPNP_EPNP,
            )
    except cv2.error:
        return None, None, None, "pnp_failed"
    if not ok or inl is None:
        return None, None, None, "too_few_inliers" if ok else "pnp_failed"
    mask = np.zeros(len(obj), bool)
    mask[inl.reshape(-1)] = True
    return mask, rvec, tvec, None


def _usac_params(cfg: FeatureConfig) -> cv2.UsacParams:
    """USAC settings for PnP: the config's threshold, iterations and confidence; MSAC score, uniform sampling, no
    local optimisation (the pose is refined on the inliers afterwards); OpenCV's fixed seed keeps it deterministic."""
    p = cv2.UsacParams()
    p.threshold = cfg.reprojection_error_px
    p.maxIterations = cfg.ransac_iterations
    p.confidence = cfg.ransac_confidence
    p.sampler = cv2.SAMPLING_UNIFORM
    p.score = cv2.SCORE_METHOD_MSAC
    p.loMethod = cv2.LOCAL_OPTIM_NULL
    return p


def _reprojection_inliers(obj: np.ndarray, uv: np.ndarray, intr: Intrinsics, rvec: np.ndarray, tvec: np.ndarray,
                          cfg: FeatureConfig) -> np.ndarray:
    """``(N,)`` bool: points in front of the camera that reproject within ``reprojection_error_px`` of ``uv``."""
    X = obj @ so3_exp(np.asarray(rvec, np.float64).reshape(3)).T + np.asarray(tvec, np.float64).reshape(3)
    return reprojection_inliers(X, uv, intr, cfg.reprojection_error_px)


def _consensus_hypothesis(obj: np.ndarray, pts_cur: np.ndarray, uv_cur: np.ndarray, img: np.ndarray,
                          K: np.ndarray, intr: Intrinsics, cfg: FeatureConfig):
    """Pose from the rigid 3D consensus (see ``FeatureConfig.consensus_fallback``), refined by Levenberg-Marquardt
    on the consensus members' pixels and then on its reprojection inliers: ``(mask (N,), rvec (3, 1),
    tvec (3, 1))``, or ``None``.

    ``obj``: ``(N, 3)`` reference points; ``pts_cur``: ``(N, 3)`` current-camera points of the same matches (NaN
    without depth); ``uv_cur``: ``(N, 2)`` their current pixels; ``img``, ``K``: the same pixels and camera in
    OpenCV's convention (rows mirrored when ``fy < 0``, which leaves the pose unchanged; see the module notes)."""
    T, members = rigid_consensus(obj, pts_cur, cfg.consensus_abs_tol_m, cfg.consensus_rel_tol, cfg.consensus_seeds,
                                 cfg.min_inliers)
    if T is None or len(members) < cfg.min_inliers:
        return None
    rvec, tvec = so3_log(T[:3, :3]).reshape(3, 1).copy(), T[:3, 3].reshape(3, 1).copy()
    # the 3D fit carries the depth noise of both frames; the members' pixels pin the pose down in the image
    rvec, tvec = cv2.solvePnPRefineLM(obj[members], img[members], K, None, rvec, tvec)
    mask = _reprojection_inliers(obj, uv_cur, intr, rvec, tvec, cfg)
    if mask.sum() >= cfg.min_inliers:
        rvec, tvec = cv2.solvePnPRefineLM(obj[mask], img[mask], K, None, rvec, tvec)
        mask = _reprojection_inliers(obj, uv_cur, intr, rvec, tvec, cfg)
    return mask, rvec, tvec


def _initial_vectors(T_init_cur_ref: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's ``(rvec (3, 1), tvec (3, 1))`` of the initial guess (zeros without one)."""
    if T_init_cur_ref is None:
        return np.zeros((3, 1)), np.zeros((3, 1))
    rvec0 = so3_log(T_init_cur_ref[:3, :3]).reshape(3, 1).copy()
    tvec0 = np.asarray(T_init_cur_ref[:3, 3], np.float64).reshape(3, 1).copy()
    return rvec0, tvec0


def _refined_pose(ref: Features, cur: Features, obj: np.ndarray, img: np.ndarray, uv_cur: np.ndarray,
                  mask: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, K: np.ndarray, sign: float, intr: Intrinsics,
                  cfg: FeatureConfig):
    """The accepted PnP pose refined (``cfg.refine``, ``projection_search``, ``rgbd_refine_iterations``):
    ``(T_cur_ref, rvec (3,), tvec (3,), information or None, points in the final refinement)``."""
    if cfg.refine:
        rvec, tvec = cv2.solvePnPRefineLM(obj[mask], img[mask], K, None, rvec.copy(), tvec.copy())
    rvec = np.asarray(rvec, np.float64).reshape(3)
    tvec = np.asarray(tvec, np.float64).reshape(3)
    T = make_T(so3_exp(rvec), tvec)
    information = None
    pts_final, uv_final = obj[mask], uv_cur[mask].astype(np.float64)
    if cfg.projection_search and np.all(np.isfinite(T)):
        found = search_by_projection(ref, cur, T, intr, cfg)
        if len(found[0]) > len(pts_final):
            pts_final, uv_final = found
            if cfg.rgbd_refine_iterations <= 0 or cur.depth_m is None:
                rvec, tvec = cv2.solvePnPRefineLM(pts_final, _image_points_cv(uv_final, intr, sign), K, None,
                                                  rvec.reshape(3, 1).copy(), tvec.reshape(3, 1).copy())
                rvec, tvec = np.asarray(rvec, np.float64).reshape(3), np.asarray(tvec, np.float64).reshape(3)
                T = make_T(so3_exp(rvec), tvec)
    if cfg.rgbd_refine_iterations > 0 and cur.depth_m is not None and np.all(np.isfinite(T)):
        z_cur = keypoint_depth(cur.depth_m, uv_final, cfg)
        T, information = refine_rgbd(T, pts_final, uv_final, 1.0 / z_cur, intr, cfg, with_information=True)
        rvec, tvec = so3_log(T[:3, :3]).reshape(3), T[:3, 3].copy()
    return T, rvec, tvec, information, len(pts_final)


def _guided_match(ref: Features, cur: Features, intr: Intrinsics, cfg: FeatureConfig,
                  T_init_cur_ref: np.ndarray | None) -> MatchResult | None:
    """Matches of the reference keypoints with depth near where ``T_init_cur_ref`` projects them
    (``cfg.guided_radius_px``), or ``None`` (no prediction, guided matching off, or fewer good matches than
    ``cfg.guided_min_matches``: the caller then matches by brute force)."""
    if T_init_cur_ref is None or cfg.guided_radius_px <= 0 or not np.all(np.isfinite(T_init_cur_ref)):
        return None
    u, v, z = project(transform_points(np.asarray(T_init_cur_ref, np.float64), ref.points_cam.astype(np.float64)),
                      intr)
    pred = np.where(((z > 0) & ref.valid)[:, None], np.column_stack([u, v]), np.nan)  # NaN depth stays NaN
    m = match(ref, cur, cfg, pred_uv=pred, image_size=(intr.width, intr.height))
    return m if m.n_good >= max(cfg.guided_min_matches, 1) else None


def estimate_motion(
    ref: Features,
    cur: Features,
    intr: Intrinsics,
    cfg: FeatureConfig,
    T_init_cur_ref: np.ndarray | None = None,
    min_consistent: int = 0,
    prior_min_inlier_fraction: float = 0.0,
) -> MotionResult:
    """Relative pose ``T_cur_ref`` by PnP-RANSAC: 3D from the reference depth, 2D from the current image.

    Args:
        ref, cur: features of the reference and the current frame (same intrinsics).
        intr: camera intrinsics (``fy`` may be negative).
        T_init_cur_ref: optional ``(4, 4)`` initial guess (used by RANSAC's iterative solver).
        min_consistent: when positive, a cheap test before RANSAC: the good matches whose two ends both have
            depth must hold a rigidly consistent set (:func:`~surfelslam.tracking.consensus.rigid_consensus`,
            the ``consensus_*`` tolerances) of at least this many, else ``too_few_consistent``. Two views that do
            not overlap still give a hundred or more good matches, and RANSAC then runs all its iterations in
            vain; loop and relocalisation checks use it (``LoopConfig.min_consistent_matches``).
        prior_min_inlier_fraction: when positive, a guess trusted to be right (a keyframe pair's odometry): the
            guided matches that reproject within ``reprojection_error_px`` under it are the inliers, and the guess
            refined on them is the pose, without the consistency test and RANSAC, if they are at least
            ``min_inliers`` and this fraction of the good matches (else as without it).

    With ``cfg.guided_radius_px`` and a guess, the matches are searched near where the guess projects the
    reference keypoints; when that gives fewer than ``cfg.guided_min_matches`` good matches or PnP inliers, or
    fails, the result is that of brute-force matching.

    Returns:
        :class:`MotionResult`; ``ok`` is False with a ``reason`` when a rejection rule fired.
    """
    guided = _guided_match(ref, cur, intr, cfg, T_init_cur_ref)
    if guided is not None:
        res = None
        if prior_min_inlier_fraction > 0:
            res = _motion_from_prior(guided, ref, cur, intr, cfg, T_init_cur_ref, prior_min_inlier_fraction)
        if res is None:
            res = _motion_from_matches(guided, ref, cur, intr, cfg, T_init_cur_ref, min_consistent)
        if res.ok and res.n_inliers >= cfg.guided_min_matches:
            return res
    return _motion_from_matches(match(ref, cur, cfg), ref, cur, intr, cfg, T_init_cur_ref, min_consistent)


def _motion_from_prior(m: MatchResult, ref: Features, cur: Features, intr: Intrinsics, cfg: FeatureConfig,
                       T_prior_cur_ref: np.ndarray, min_fraction: float) -> MotionResult | None:
    """:func:`estimate_motion` from the guided matches ``m`` and the trusted guess ``T_prior_cur_ref`` (see its
    ``prior_min_inlier_fraction``), or ``None`` when the guess explains too few of them."""
    pairs = m.pairs[ref.valid[m.pairs[:, 0]]] if m.n_good else m.pairs
    n_good = len(pairs)
    if n_good < max(cfg.min_good_matches, 4):
        return None
    obj = ref.points_cam[pairs[:, 0]].astype(np.float64)
    uv_cur = track_subpixel(ref, cur, pairs, cfg)
    rvec, tvec = _initial_vectors(T_prior_cur_ref)
    mask = _reprojection_inliers(obj, uv_cur, intr, rvec, tvec, cfg)
    n_in = int(mask.sum())
    if n_in < max(cfg.min_inliers, 4) or n_in < min_fraction * n_good:
        return None
    return _accepted(m.n_raw, ref, cur, intr, cfg, pairs, obj, uv_cur, mask, rvec, tvec)


def _accepted(n_raw: int, ref: Features, cur: Features, intr: Intrinsics, cfg: FeatureConfig, pairs: np.ndarray,
              obj: np.ndarray, uv_cur: np.ndarray, mask: np.ndarray, rvec: np.ndarray,
              tvec: np.ndarray) -> MotionResult:
    """The result of a pose ``(rvec, tvec)`` with the inliers ``mask`` among ``pairs``: refined
    (:func:`_refined_pose`), then the finiteness and motion-norm rules."""
    K, sign = _cv_camera(intr)
    img = _image_points_cv(uv_cur, intr, sign)
    T, rvec, tvec, information, n_final = _refined_pose(ref, cur, obj, img, uv_cur, mask, rvec, tvec, K, sign, intr,
                                                        cfg)
    res = MotionResult(T, True, None, n_raw, len(pairs), int(mask.sum()), rvec, tvec, mask, pairs, uv_cur,
                       information, n_final)
    if not np.all(np.isfinite(T)):
        res.ok, res.reason, res.T_cur_ref = False, "pnp_failed", np.eye(4)
    elif motion_norm(T) > cfg.max_motion_norm:
        res.ok, res.reason = False, "motion_too_large"
    return res


def _motion_from_matches(m: MatchResult, ref: Features, cur: Features, intr: Intrinsics, cfg: FeatureConfig,
                         T_init_cur_ref: np.ndarray | None, min_consistent: int) -> MotionResult:
    """:func:`estimate_motion` from the matches ``m``."""
    pairs = m.pairs[ref.valid[m.pairs[:, 0]]] if m.n_good else m.pairs
    n_good = len(pairs)
    if n_good < max(cfg.min_good_matches, 4):
        return _failed(m.n_raw, n_good, "too_few_matches", pairs)
    obj = ref.points_cam[pairs[:, 0]].astype(np.float64)
    if min_consistent > 0:
        if not has_consistent_set(obj, cur.points_cam[pairs[:, 1]], cfg.consensus_abs_tol_m, cfg.consensus_rel_tol,
                                  cfg.consensus_seeds, min_consistent):
            return _failed(m.n_raw, n_good, "too_few_consistent", pairs)
    K, sign = _cv_camera(intr)
    uv_cur = track_subpixel(ref, cur, pairs, cfg)
    img = _image_points_cv(uv_cur, intr, sign)
    rvec0, tvec0 = _initial_vectors(T_init_cur_ref)
    mask, rvec, tvec, reason = pnp_ransac(obj, img, K, rvec0, tvec0, T_init_cur_ref is not None, cfg)
    if cfg.consensus_fallback and (mask is None or mask.sum() < cfg.consensus_below_fraction * n_good):
        alt = _consensus_hypothesis(obj, cur.points_cam[pairs[:, 1]], uv_cur, img, K, intr, cfg)
        if alt is not None and alt[0].sum() > (0 if mask is None else mask.sum()):
            mask, rvec, tvec = alt
    if mask is None:
        return _failed(m.n_raw, n_good, reason, pairs)
    if mask.sum() < cfg.min_inliers:
        res = _failed(m.n_raw, n_good, "too_few_inliers", pairs)
        res.n_inliers = int(mask.sum())
        res.inlier_mask = mask
        return res
    return _accepted(m.n_raw, ref, cur, intr, cfg, pairs, obj, uv_cur, mask, rvec, tvec)


def feature_guess(
    src_frame: RGBDFrame, tgt_frame: RGBDFrame, intr: Intrinsics, cfg: FeatureConfig
) -> tuple[np.ndarray | None, MotionResult]:
    """Relative pose between two frames for an ICP initial guess.

    Returns:
        ``(T_target_source, result)``: ``T_target_source`` ``(4, 4)`` maps points from the source camera
        into the target camera, or ``None`` when a rejection rule fired (see ``result.reason``).
    """
    f_src = extract(src_frame.rgb, src_frame.depth_m, intr, cfg)
    f_tgt = extract(tgt_frame.rgb, tgt_frame.depth_m, intr, cfg)
    # reference = target (its depth gives the 3D points), current = source: T_cur_ref = T_source_target
    res = estimate_motion(f_tgt, f_src, intr, cfg)
    if not res.ok:
        return None, res
    return invert(res.T_cur_ref), res
