"""A keyframe's keypoints followed into a later frame by Lucas-Kanade, without extracting features there.

Between keyframes the hybrid tracker needs, per frame, keyframe points paired with their pixels in the frame (the
joint term's reprojections) and a pose from them (the terms' pixel noise, checks, retries). Extracting and
matching ORB in every frame and running PnP-RANSAC costs about as much as ICP; here the keyframe's points are
projected with the motion prediction and tracked from the keyframe's image into the frame's by pyramidal
Lucas-Kanade (the pyramid absorbs the prediction's error), checked forward and backward, and the pose is refined
from the prediction on the tracked points (no RANSAC: the prediction is the hypothesis; points that then reproject
badly are dropped and the pose refined again).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from surfelslam.geometry.camera import project
from surfelslam.geometry.se3 import make_T, so3_exp, so3_log
from surfelslam.tracking.features.config import FeatureConfig
from surfelslam.tracking.features.extract import Features, bucket_keypoints
from surfelslam.tracking.features.reprojection import reprojection_inliers
from surfelslam.types import Intrinsics

#: most keyframe points tracked per frame, spread over the image by the extractor's grid (the cost is linear in them:
#: about 6 us each at 320x240; a few hundred pin the joint term's six degrees of freedom)
MAX_TRACKED_POINTS = 300
#: pyramid levels above the image: at level 3 an 11 px window spans 88 px of the image, more than a constant-velocity
#: prediction is off at 30 Hz hand-held
TRACK_LEVELS = 3
#: px at 640 wide (scaled with the width): a tracked point farther than this from its predicted pixel is taken for a
#: false lock (the prediction's error on fast hand-held motion stays well inside)
MAX_PREDICTION_ERROR_PX = 60.0
#: px: largest distance between a keyframe pixel and where its tracked point tracks back to (a point that does not
#: track back lies on an occlusion, a repeated pattern or a specularity)
BACKTRACK_PX = 0.5
#: Lucas-Kanade stops after this many iterations per level or below this update (px)
_LK_ITERATIONS = 30
_LK_EPSILON_PX = 0.01
#: seeded pose refinements, each followed by dropping the points that reproject beyond the inlier bound
_REFINE_ROUNDS = 2


@dataclass
class TrackedKeyframe:
    """Keyframe points found in a frame by :func:`track_keyframe`.

    Attributes:
        T_cur_ref: ``(4, 4)`` the frame's pose relative to the keyframe, refined from the tracked points.
        points_ref: ``(M, 3)`` float64 keyframe-camera points (m) that tracked and reproject within the inlier bound.
        uv_cur: ``(M, 2)`` float64 their pixels in the frame.
    """

    T_cur_ref: np.ndarray
    points_ref: np.ndarray
    uv_cur: np.ndarray


def _lk(grey_from: np.ndarray, grey_to: np.ndarray, p_from: np.ndarray, p_init: np.ndarray, window_px: int,
        levels: int) -> tuple[np.ndarray, np.ndarray]:
    """Pyramidal Lucas-Kanade of ``p_from (M, 2)`` starting at ``p_init (M, 2)``: ``(found (M, 2), ok (M,))``."""
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, _LK_ITERATIONS, _LK_EPSILON_PX)
    p0 = np.ascontiguousarray(p_from, np.float32).reshape(-1, 1, 2)
    p1 = np.ascontiguousarray(p_init, np.float32).reshape(-1, 1, 2).copy()
    p1, status, _ = cv2.calcOpticalFlowPyrLK(grey_from, grey_to, p0, p1, winSize=(window_px, window_px),
                                             maxLevel=levels, criteria=crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    p1 = p1.reshape(-1, 2).astype(np.float64)
    return p1, status.reshape(-1).astype(bool) & np.all(np.isfinite(p1), axis=1)


def _refined(P: np.ndarray, uv: np.ndarray, T_init: np.ndarray, intr: Intrinsics,
             bound_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Pose refined by Levenberg-Marquardt from ``T_init`` on ``P (M, 3)`` -> ``uv (M, 2)``, dropping the points
    that reproject beyond ``bound_px`` after each round (at most :data:`_REFINE_ROUNDS`; none after a round that
    dropped none): ``(T (4, 4), kept (M,) bool)``."""
    K = intr.K.copy()
    img = uv.copy()
    if intr.fy < 0:  # OpenCV wants fy > 0: mirror the rows (the pose is unchanged)
        K[1, 1] = -intr.fy
        img[:, 1] = 2.0 * intr.cy - img[:, 1]
    rvec = so3_log(T_init[:3, :3]).reshape(3, 1).copy()
    tvec = np.asarray(T_init[:3, 3], np.float64).reshape(3, 1).copy()
    kept = np.ones(len(P), bool)
    for _ in range(_REFINE_ROUNDS):
        rvec, tvec = cv2.solvePnPRefineLM(P[kept], img[kept], K, None, rvec, tvec)
        T = make_T(so3_exp(rvec.reshape(3)), tvec.reshape(3))
        used, kept = kept, reprojection_inliers(P @ T[:3, :3].T + T[:3, 3], uv, intr, bound_px)
        # fewer than 4 points: no pose; the same points: another round would start from its own optimum
        if kept.sum() < 4 or np.array_equal(kept, used):
            break
    return make_T(so3_exp(np.asarray(rvec, np.float64).reshape(3)), np.asarray(tvec, np.float64).reshape(3)), kept


def _selected(ref: Features, shape: tuple[int, int], cfg: FeatureConfig) -> np.ndarray:
    """Indices of at most :data:`MAX_TRACKED_POINTS` keyframe keypoints with depth, strongest per grid cell."""
    idx = np.flatnonzero(ref.valid)
    if len(idx) <= MAX_TRACKED_POINTS:
        return idx
    return idx[bucket_keypoints(ref.keypoints_uv[idx], ref.response[idx], shape, cfg, n_keep=MAX_TRACKED_POINTS)]


class KeyframePoints:
    """The points of a keyframe that :func:`track_keyframe` follows, selected once per keyframe (not once per frame:
    the reference keyframe stays the same over many frames). Holds the last keyframe's selection; a call for another
    keyframe, image size or config replaces it (so the result never depends on what was asked before)."""

    def __init__(self) -> None:
        self._last: tuple | None = None  # (ref, shape, cfg, points (M, 3) float64, pixels (M, 2) float64)

    def of(self, ref: Features, shape: tuple[int, int], cfg: FeatureConfig) -> tuple[np.ndarray, np.ndarray]:
        """``(points (M, 3), pixels (M, 2))`` float64 of ``ref``'s selected keypoints (:func:`_selected`)."""
        last = self._last  # one read: another thread may replace it meanwhile
        if last is None or last[0] is not ref or last[1] != shape or last[2] is not cfg:
            idx = _selected(ref, shape, cfg)
            last = (ref, shape, cfg, ref.points_cam[idx].astype(np.float64), ref.keypoints_uv[idx].astype(np.float64))
            self._last = last
        return last[3], last[4]


def track_keyframe(ref: Features, grey_cur: np.ndarray, T_cur_ref_pred: np.ndarray, intr: Intrinsics,
                   cfg: FeatureConfig, points: KeyframePoints | None = None) -> TrackedKeyframe | None:
    """The keyframe ``ref``'s keypoints with depth found in the frame ``grey_cur (H, W)`` uint8 (see the module).

    ``T_cur_ref_pred``: ``(4, 4)`` predicted pose of the frame relative to the keyframe. ``points``: where the
    keyframe's selected points are kept between calls (default: selected in this call). Returns ``None`` when fewer
    than ``cfg.min_inliers`` points are found.
    """
    if ref.grey is None or ref.grey.shape != grey_cur.shape or not ref.valid.any():
        return None
    P, uv_ref = (KeyframePoints() if points is None else points).of(ref, grey_cur.shape, cfg)
    T = np.asarray(T_cur_ref_pred, np.float64)
    u, v, z = project(P @ T[:3, :3].T + T[:3, 3], intr)
    h, w = grey_cur.shape
    half = cfg.lk_window_px // 2
    inside = (z > 0) & (u >= half) & (u <= w - 1 - half) & (v >= half) & (v <= h - 1 - half)
    if inside.sum() < cfg.min_inliers:
        return None
    P, uv_ref = P[inside], uv_ref[inside]
    pred = np.column_stack([u[inside], v[inside]])
    found, ok = _lk(ref.grey, grey_cur, uv_ref, pred, cfg.lk_window_px, TRACK_LEVELS)
    back, ok_back = _lk(grey_cur, ref.grey, found, uv_ref, cfg.lk_window_px, 0)
    ok &= ok_back & (np.linalg.norm(back - uv_ref, axis=1) <= BACKTRACK_PX)
    ok &= np.linalg.norm(found - pred, axis=1) <= MAX_PREDICTION_ERROR_PX * w / 640.0
    if ok.sum() < cfg.min_inliers:
        return None
    P, found = P[ok], found[ok]
    T, kept = _refined(P, found, T, intr, cfg.reprojection_error_px)
    if kept.sum() < cfg.min_inliers or not np.all(np.isfinite(T)):
        return None
    return TrackedKeyframe(T, P[kept], found[kept])
