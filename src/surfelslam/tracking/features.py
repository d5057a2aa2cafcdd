"""Sparse feature odometry: ORB keypoints with depth, Hamming matching, PnP-RANSAC.

The pipeline follows the feature-based RGB-D tutorial in the seeds:

1. :func:`extract` detects ORB keypoints spread over the image (retain-best per grid cell), computes
   their descriptors and lifts each keypoint to 3D with the depth image (camera frame).
2. :func:`match` pairs descriptors of a reference and a current frame (cross-check or ratio test)
   and keeps the "good" matches, whose Hamming distance is below ``k * max(min_distance, floor)``.
3. :func:`estimate_motion` solves PnP-RANSAC with 3D points from the *reference* frame and 2D
   keypoints of the *current* frame, refines on the inliers, and applies the rejection rules
   (too few good matches, too few inliers, motion norm too large). The solution maps reference
   camera points into the current camera: ``T_cur_ref``.

``fy`` may be negative (ICL-NUIM). OpenCV's PnP is only exercised with a positive focal length:
for ``fy < 0`` the image rows are mirrored about ``cy`` (``v' = 2 cy - v``) and ``fy' = -fy``,
which describes exactly the same projection of the same 3D points, so the pose is unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from surfelslam.geometry.camera import project
from surfelslam.geometry.se3 import exp as se3_exp
from surfelslam.geometry.se3 import invert, make_T, motion_norm, so3_exp, so3_log
from surfelslam.kernels import hamming
from surfelslam.kernels import lk as klk
from surfelslam.tracking.consensus import has_consistent_set, rigid_consensus
from surfelslam.types import Intrinsics, RGBDFrame

MATCHING_MODES = ("crosscheck", "ratio")
DETECTORS = ("orb", "sift")
REJECT_REASONS = (
    "too_few_matches", "too_few_consistent", "too_few_inliers", "motion_too_large", "pnp_failed",
)
_DESCRIPTOR_BYTES = 32
_SIFT_DIMS = 128
_LK_MAX_ITERATIONS = 30  # Lucas-Kanade stops after this many iterations per level ...
_LK_EPSILON_PX = 0.01  # ... or when its update is below this (pixels)
_MAD_TO_SIGMA = 1.4826  # median absolute deviation -> standard deviation of a Gaussian
_MIN_POINTS_FOR_SPREAD = 6  # fewest depth residuals to estimate their spread from the data
_RGBD_CONVERGED_UPDATE = 1e-9  # twist norm (rad + m) below which the RGB-D refinement stops
_MIN_WARP_DET = 1e-6  # |det| of a warp's R + t n^T / d below this: the current camera is (nearly) on the plane


@dataclass(frozen=True)
class FeatureConfig:
    """ORB extraction, matching and PnP parameters (units in the names; counts are plain ints).

    Attributes:
        n_features: keypoints kept per image (after grid bucketing).
        detector: ``"orb"`` (binary descriptors, Hamming matching with ``matching`` and the good-match filter:
            the seeds' choice and what the trackers and place recognition use) or ``"sift"`` (128-float
            descriptors, Lowe's ratio test at ``ratio``, no good-match filter: far more correct matches between
            views far apart, about 5x the extraction time; ``register --descriptor sift``). The ``scale_factor``,
            ``n_levels``, ``fast_threshold`` and ``edge_threshold_px`` settings are ORB's.
        detect_oversample: ORB first detects ``n_features * detect_oversample`` candidates; the
            strongest per grid cell are then retained.
        grid_cols, grid_rows: bucketing grid; each cell keeps at most ``ceil(n_features / cells)``.
        scale_factor: ORB pyramid scale ratio between levels.
        n_levels: ORB pyramid levels.
        fast_threshold: FAST corner threshold (grey levels, 0..255).
        edge_threshold_px: border (pixels) where no keypoint is detected (also the ORB patch size).
        matching: ``"crosscheck"`` (mutual nearest neighbours) or ``"ratio"`` (Lowe test).
        ratio: nearest / second-nearest Hamming distance bound of the ratio test.
        good_match_k: good matches have distance ``< good_match_k * max(min_distance, floor)``
            (seeds: 4 at first, 10 later).
        good_match_floor_bits: the floor of ``min_distance`` in that rule (seeds: 10 bits).
        depth_median_3x3: lift keypoints with the median of the valid depths in their 3x3 pixel
            neighbourhood (robust at edges and for slightly misregistered colour/depth) instead of the
            nearest pixel's depth.
        depth_plane_radius_px: then refine that depth by a least-squares plane fit over the
            ``(2r+1)^2`` patch around the keypoint (0 = off). The fit is linear in inverse depth, which is
            exactly linear in ``(u, v)`` over a plane and is the quantity a structured-light sensor measures
            (disparity), so quantisation steps and noise average out over the patch. Only pixels within
            ``depth_plane_gate`` of the median depth enter the fit (the patch never mixes a foreground edge
            with the background); with fewer than ``depth_plane_min_pixels`` of them the median is kept.
            Measured on the orb tracker (200 frames; ATE with radius 0 / 2 / 3): 7-Scenes 2.66 / 2.45 /
            2.74 cm (its colour and depth are not registered, so wide patches blur), synthetic slow 320x240
            0.93 / 0.70 / 0.78 cm, 640x480 0.48 / 0.41 / 0.43 cm.
        depth_plane_gate: relative depth gate ``|z - z_median| <= gate * z_median`` of the plane fit.
        depth_edge_rel: a keypoint whose ``(2 r + 1)^2`` patch (``r = depth_edge_radius_px``) holds a valid depth
            differing from its own by more than this fraction gets no 3D point (0 = off). Such a keypoint sits on
            an occluding contour: the corner FAST finds there is where a foreground edge crosses the background,
            which slides over the background as the camera moves, so it is no fixed 3D point, and its depth is
            the foreground's or the background's by a pixel. Where texture is sparse (plain walls, as in real
            rooms) these corners are a large share of the keypoints outside the few textured objects, and they
            biased the PnP pose by centimetres (synthetic plain office, 7-Scenes motion: pairs 15-28 frames apart
            22-33 mm -> 1-7 mm).
        depth_edge_radius_px: patch radius (px) of that test.
        depth_plane_min_pixels: fewest gated pixels for a plane fit.
        min_depth_m, max_depth_m: keypoints with depth outside this range get no 3D point.
        ransac_iterations: PnP-RANSAC iterations. The seeds use 100; at 10 % inlier ratio (wide
            baselines on real data) 100 EPnP samples often miss, so the default is 300.
        reprojection_error_px: RANSAC inlier threshold. The seeds use 1.0 px; on real Kinect data
            (7-Scenes: colour and depth are not registered) 2.0 px keeps more correct inliers and gives
            a better pose, so that is the default.
        ransac_confidence: RANSAC success probability (early stop).
        refine: refine the RANSAC pose on its inliers with Levenberg-Marquardt.
        min_good_matches: fewer good matches with valid reference depth -> ``too_few_matches``.
        min_inliers: fewer PnP inliers -> ``too_few_inliers`` (seeds: 5).
        max_motion_norm: motion norm ``||t|| + min(||r||, 2 pi - ||r||)`` (m + rad) above this ->
            ``motion_too_large`` (seeds: 0.3).
        lk_refine: before PnP, move each good match's current-image point to where pyramidal Lucas-Kanade
            tracks the *reference* keypoint's patch (starting from the matched ORB keypoint). ORB detects
            each keypoint anew in every image, at FAST/pyramid-grid positions, so the two keypoints of a
            match are not the same surface point to within about a pixel; the 3D point comes from the
            reference pixel, so that jitter becomes PnP noise. The tracked point is the reference pixel
            itself, to sub-pixel accuracy. Needs both images' grey levels (``Features.grey``); skipped
            where one is missing.
        lk_window_px: Lucas-Kanade window (square, pixels).
        lk_levels: Lucas-Kanade pyramid levels above the image (0 = the image only).
        lk_max_shift_px: a tracked point farther than this from its ORB keypoint is not used (the ORB
            keypoint is kept): LK slid to another corner, or the match itself is wrong.
        projection_search: after PnP, project *every* reference keypoint with a 3D point into the current image
            with the PnP pose and track its patch there with Lucas-Kanade, starting from the projection (search by
            projection, as ORB-SLAM's tracking does with descriptors; here photometric, to sub-pixel). Points that
            track back to their reference pixel (``projection_search_backtrack_px``) and land within
            ``projection_search_tol_px`` of the projection join the final refinement in place of the PnP
            inliers when there are more of them. Descriptor matching between two independent ORB detections keeps
            about a third of the keypoints (measured at 640x480, frames 5 apart: 1000 keypoints, 476 mutual
            matches, 331 PnP inliers); tracking by projection keeps about 960, and the pose noise falls with them
            (median translation error 0.48 -> 0.26 mm on a noisy synthetic replay). The PnP inliers still decide
            the rejection rules.
        projection_search_tol_px: largest distance (px) between a tracked point and its projection.
        projection_search_backtrack_px: largest forward-backward Lucas-Kanade error (px): tracking the found point
            back into the reference image must return to the keypoint within this.
        projection_search_warp: track each projected point with its reference window warped into the current view
            (:mod:`surfelslam.kernels.lk`): the homography that the PnP pose induces on the fronto-parallel plane
            through the point (rotation, perspective and scale change of the patch; the surface's own slant is not
            modelled), and the forward-backward check through its inverse. Plain Lucas-Kanade compares square
            windows, and under a few degrees of rotation the patch deforms; the translation that best fits the
            deformed patch is not its centre's displacement. Measured on a noisy 640x480 synthetic replay at 3x
            speed, pairs 2-3 frames apart in a fast pan, refined from ground truth on the tracked pixels: point
            error 0.15 -> 0.09 px, pose error 0.70 / 0.62 / 0.61 / 0.35 -> 0.45 / 0.28 / 0.46 / 0.11 mm (in a numpy
            prototype a surface-slant plane fitted to the depth came within 0.03 mm of this). Windows of
            ``lk_window_px``, one pyramid level (the search starts at the projection). False: OpenCV's pyramidal
            Lucas-Kanade (``lk_window_px``, ``lk_levels``) on square windows.
        rgbd_refine_iterations: after PnP, Gauss-Newton iterations of a joint RGB-D refinement on the
            inliers (0 = off): reprojection residuals plus inverse-depth residuals against the *current*
            frame's depth at the tracked points. Reprojection alone leaves a lateral translation nearly
            interchangeable with a small rotation (measured on exact synthetic data, 6 frames apart: 2.2 mm
            and 0.04 deg errors with residuals of 0.15 px); the current depth separates them.
        rgbd_pixel_sigma_px: reprojection noise (px) of the joint refinement when it has fewer than 10 points;
            otherwise see ``rgbd_min_pixel_sigma_px``.
        rgbd_inverse_depth_sigma: inverse-depth noise (1/m) of the joint refinement. A structured-light
            sensor's depth noise grows with ``z^2``, so its inverse-depth noise is about constant:
            ``sigma_z(z) = rgbd_inverse_depth_sigma * z^2`` (0.003: 3 mm at 1 m, 12 mm at 2 m, before the
            plane fit averages it).
        rgbd_huber: Huber threshold on the normalised residuals of the joint refinement.
        rgbd_min_pixel_sigma_px: with 10 or more points the refinement weighs the reprojection residuals by the
            points' own spread (robust sigma, px, at least this), as it does the inverse-depth residuals, instead of
            the fixed ``rgbd_pixel_sigma_px``: pixels and depth are weighed by their actual noise, and the
            information matrix (the pose-graph weight of a keyframe edge) is the pose's actual inverse covariance,
            so edges between keyframes far apart, which track less precisely, weigh less. Measured on a noisy
            640x480 synthetic replay with ``projection_search``, at the fixed 0.5 px the edges' errors against
            ground truth were 1.2 (odometry), 2.2 (loops 1-3 keyframes apart) and 3.4 (farther loops) whitened
            units (median): far loops weighed too much. orb ATE on seven 640x480 synthetic sequences, fixed ->
            own spread: 0.74-1.05 -> 0.60-1.13 mm (room replay from 8 s 0.75 -> 0.62, office replay 0.77 -> 0.60,
            office fast 0.97 -> 0.86); RPE per frame 10-45 % lower on all seven.
        consensus_fallback: when PnP-RANSAC fails, or keeps fewer than ``consensus_below_fraction`` of the good
            matches, also try the rigid 3D consensus of :mod:`surfelslam.tracking.consensus` (matches whose two
            ends both have depth and keep their pairwise distances) and keep whichever hypothesis has more
            reprojection inliers. RANSAC's 5-point samples rarely come out clean below about 25 % inliers (frames
            far apart, loops, relocalisation); the consensus does not sample.
        consensus_below_fraction: PnP inlier fraction under which the consensus is also tried.
        consensus_abs_tol_m, consensus_rel_tol: two matches are consistent when their distances in the two
            frames differ by at most ``abs + rel * distance`` (Kinect depth noise is about 1 cm at 2 m, plus the
            keypoint's position on the surface).
        consensus_seeds: consistent sets grown (from the best-connected matches); the largest is kept.
    """

    n_features: int = 1000
    detector: str = "orb"
    detect_oversample: float = 2.0
    grid_cols: int = 8
    grid_rows: int = 6
    scale_factor: float = 1.2
    n_levels: int = 8
    fast_threshold: int = 12
    edge_threshold_px: int = 19
    matching: str = "crosscheck"
    ratio: float = 0.8
    good_match_k: float = 4.0
    good_match_floor_bits: float = 10.0
    depth_median_3x3: bool = True
    depth_plane_radius_px: int = 2
    depth_plane_gate: float = 0.03
    depth_plane_min_pixels: int = 12
    depth_edge_rel: float = 0.1
    depth_edge_radius_px: int = 3
    min_depth_m: float = 0.1
    max_depth_m: float = 6.0
    ransac_iterations: int = 300
    reprojection_error_px: float = 2.0
    ransac_confidence: float = 0.99
    refine: bool = True
    min_good_matches: int = 10
    min_inliers: int = 5
    max_motion_norm: float = 0.3
    lk_refine: bool = True
    lk_window_px: int = 11
    lk_levels: int = 1
    lk_max_shift_px: float = 2.0
    projection_search: bool = True
    projection_search_tol_px: float = 1.0
    projection_search_backtrack_px: float = 0.5
    projection_search_warp: bool = True
    rgbd_refine_iterations: int = 5
    rgbd_pixel_sigma_px: float = 0.5
    rgbd_inverse_depth_sigma: float = 0.003
    rgbd_huber: float = 2.0
    rgbd_min_pixel_sigma_px: float = 0.05
    consensus_fallback: bool = True
    consensus_below_fraction: float = 0.5
    consensus_abs_tol_m: float = 0.03
    consensus_rel_tol: float = 0.05
    consensus_seeds: int = 10

    def __post_init__(self) -> None:
        if self.detector not in DETECTORS:
            raise ValueError(f"detector must be one of {DETECTORS}, got {self.detector!r}")
        if self.matching not in MATCHING_MODES:
            raise ValueError(f"matching must be one of {MATCHING_MODES}, got {self.matching!r}")
        if self.n_features < 1 or self.grid_cols < 1 or self.grid_rows < 1:
            raise ValueError("n_features, grid_cols and grid_rows must be >= 1")
        if not 0.0 < self.ratio <= 1.0:
            raise ValueError(f"ratio must be in (0, 1], got {self.ratio}")
        if self.min_depth_m < 0 or self.max_depth_m <= self.min_depth_m:
            raise ValueError(f"need 0 <= min_depth_m < max_depth_m, got {self.min_depth_m}, {self.max_depth_m}")
        if self.depth_plane_radius_px < 0 or self.depth_plane_min_pixels < 3 or not self.depth_plane_gate > 0:
            raise ValueError("need depth_plane_radius_px >= 0, depth_plane_min_pixels >= 3, depth_plane_gate > 0")
        if self.depth_edge_rel < 0 or self.depth_edge_radius_px < 1:
            raise ValueError("need depth_edge_rel >= 0 and depth_edge_radius_px >= 1")
        if self.min_inliers < 4:
            raise ValueError(f"min_inliers must be >= 4 (PnP needs 4 points), got {self.min_inliers}")
        if self.lk_window_px < 3 or self.lk_levels < 0 or not self.lk_max_shift_px > 0:
            raise ValueError("need lk_window_px >= 3, lk_levels >= 0, lk_max_shift_px > 0")
        if not (self.projection_search_tol_px > 0 and self.projection_search_backtrack_px > 0):
            raise ValueError("need projection_search_tol_px > 0 and projection_search_backtrack_px > 0")
        if not self.rgbd_min_pixel_sigma_px > 0:
            raise ValueError("rgbd_min_pixel_sigma_px must be positive")
        if not (0.0 <= self.consensus_below_fraction <= 1.0 and self.consensus_abs_tol_m >= 0
                and self.consensus_rel_tol >= 0 and self.consensus_seeds >= 1):
            raise ValueError("need 0 <= consensus_below_fraction <= 1, consensus tolerances >= 0, consensus_seeds >= 1")


@dataclass
class Features:
    """Keypoints of one image.

    Attributes:
        keypoints_uv: ``(N, 2)`` float32 pixel coordinates ``(u, v)`` at full resolution.
        descriptors: ``(N, 32)`` uint8 ORB descriptors, or ``(N, 128)`` float32 SIFT ones.
        points_cam: ``(N, 3)`` float32 camera-frame points (metres); NaN where depth is invalid.
        valid: ``(N,)`` bool, True where ``points_cam`` is finite.
        response: ``(N,)`` float32 detector response (for diagnostics).
        grey: ``(H, W)`` uint8 image the keypoints come from (for sub-pixel tracking), or ``None``.
        depth_m: ``(H, W)`` float32 depth of that image (a reference, not a copy), or ``None``.
    """

    keypoints_uv: np.ndarray
    descriptors: np.ndarray
    points_cam: np.ndarray
    valid: np.ndarray
    response: np.ndarray
    grey: np.ndarray | None = None
    depth_m: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.keypoints_uv)


@dataclass
class MatchResult:
    """Good matches between a reference and a current :class:`Features`.

    Attributes:
        pairs: ``(M, 2)`` int64 ``(ref_index, cur_index)`` of the good matches, ordered by ref index.
        distances: ``(M,)`` float32 Hamming distances (bits).
        n_raw: matches before the distance filter.
        n_good: ``M``.
        min_dist, max_dist: smallest / largest raw match distance (bits; 0 when there is none).
    """

    pairs: np.ndarray
    distances: np.ndarray
    n_raw: int
    n_good: int
    min_dist: float
    max_dist: float


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


def _detector(cfg: FeatureConfig):
    """The OpenCV detector + descriptor extractor of ``cfg.detector``."""
    n_detect = int(np.ceil(cfg.n_features * cfg.detect_oversample))
    if cfg.detector == "sift":
        return cv2.SIFT_create(nfeatures=n_detect)
    return cv2.ORB_create(
        nfeatures=n_detect,
        scaleFactor=cfg.scale_factor,
        nlevels=cfg.n_levels,
        edgeThreshold=cfg.edge_threshold_px,
        patchSize=cfg.edge_threshold_px,
        fastThreshold=cfg.fast_threshold,
    )


def _to_grey(rgb: np.ndarray) -> np.ndarray:
    if rgb.ndim == 2:
        return np.ascontiguousarray(rgb, dtype=np.uint8)
    return cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)


def bucket_keypoints(
    uv: np.ndarray, response: np.ndarray, shape: tuple[int, int], cfg: FeatureConfig
) -> np.ndarray:
    """Indices of the keypoints kept by grid bucketing (strongest first within each cell).

    Args:
        uv: ``(N, 2)`` pixel coordinates.
        response: ``(N,)`` detector responses.
        shape: image ``(H, W)``.

    Returns:
        ``(K,)`` int64 indices into ``uv``, ascending, ``K <= n_features``. Cells with fewer
        keypoints than their quota leave room that is refilled with the best remaining keypoints.
    """
    n = len(uv)
    if n <= cfg.n_features:
        return np.arange(n, dtype=np.int64)
    h, w = shape
    cu = np.clip((uv[:, 0] * cfg.grid_cols / w).astype(np.int64), 0, cfg.grid_cols - 1)
    cv_ = np.clip((uv[:, 1] * cfg.grid_rows / h).astype(np.int64), 0, cfg.grid_rows - 1)
    cell = cv_ * cfg.grid_cols + cu
    # stable sort by (cell, -response, index): deterministic ranks within each cell
    order = np.lexsort((np.arange(n), -response, cell))
    cell_sorted = cell[order]
    first = np.searchsorted(cell_sorted, cell_sorted, side="left")
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n) - first
    quota = int(np.ceil(cfg.n_features / (cfg.grid_cols * cfg.grid_rows)))
    # global order: by rank within the cell first, then by response -> fill evenly, then the strongest
    global_order = np.lexsort((np.arange(n), -response, np.minimum(rank, quota)))
    keep = global_order[: cfg.n_features]
    return np.sort(keep)


def _keypoint_depth(depth_m: np.ndarray, uv: np.ndarray, cfg: FeatureConfig) -> np.ndarray:
    """Depth (m) at each keypoint ``(N,)``; NaN where invalid or out of [min_depth_m, max_depth_m]."""
    h, w = depth_m.shape
    ui = np.clip(np.floor(uv[:, 0] + 0.5).astype(np.int64), 0, w - 1)
    vi = np.clip(np.floor(uv[:, 1] + 0.5).astype(np.int64), 0, h - 1)
    if cfg.depth_median_3x3:
        offs = np.array([-1, 0, 1])
        uu = np.clip(ui[:, None, None] + offs[None, None, :], 0, w - 1)
        vv = np.clip(vi[:, None, None] + offs[None, :, None], 0, h - 1)
        patch = depth_m[vv, uu].reshape(len(uv), 9).astype(np.float64)
        ok = (patch >= cfg.min_depth_m) & (patch <= cfg.max_depth_m)
        patch[~ok] = np.nan
        centre_ok = ok[:, 4]
        # rows without any valid depth stay NaN (no all-NaN median: its warning, and warnings.catch_warnings is
        # not thread-safe while the reader thread extracts features)
        z = np.full(len(uv), np.nan)
        some = ok.any(axis=1)
        z[some] = np.nanmedian(patch[some], axis=1)
        # the centre pixel must itself be valid: a keypoint on a hole has no reliable depth
        z[~centre_ok] = np.nan
        if cfg.depth_plane_radius_px > 0:
            z = _plane_fit_depth(depth_m, uv, ui, vi, z, cfg)
    else:
        z = depth_m[vi, ui].astype(np.float64)
        z[(z < cfg.min_depth_m) | (z > cfg.max_depth_m)] = np.nan
    if cfg.depth_edge_rel > 0:
        z[_on_depth_edge(depth_m, ui, vi, z, cfg)] = np.nan
    return z


def _on_depth_edge(depth_m: np.ndarray, ui: np.ndarray, vi: np.ndarray, z: np.ndarray,
                   cfg: FeatureConfig) -> np.ndarray:
    """``(N,)`` bool: the keypoint's patch holds a valid depth more than ``depth_edge_rel`` away from its depth
    ``z`` (an occluding contour; see :class:`FeatureConfig`)."""
    h, w = depth_m.shape
    offs = np.arange(-cfg.depth_edge_radius_px, cfg.depth_edge_radius_px + 1)
    uu = np.clip(ui[:, None, None] + offs[None, None, :], 0, w - 1)
    vv = np.clip(vi[:, None, None] + offs[None, :, None], 0, h - 1)
    patch = depth_m[vv, uu].reshape(len(ui), -1)
    zc = np.where(np.isfinite(z), z, 0.0)[:, None]
    return ((patch > 0) & (np.abs(patch - zc) > cfg.depth_edge_rel * zc)).any(axis=1) & np.isfinite(z)


def on_occluding_contour(depth_m: np.ndarray, uv: np.ndarray, cfg: FeatureConfig) -> np.ndarray:
    """``(N,)`` bool: pixels ``uv (N, 2)`` whose ``(2 r + 1)^2`` patch of ``depth_m`` (``r = depth_edge_radius_px``)
    holds a valid depth more than ``depth_edge_rel`` away from the nearest pixel's (an occluding contour, see
    :class:`FeatureConfig`); False where that pixel has no depth or ``depth_edge_rel`` is 0."""
    n = len(uv)
    if cfg.depth_edge_rel <= 0 or n == 0:
        return np.zeros(n, bool)
    h, w = depth_m.shape
    ui = np.clip(np.floor(uv[:, 0] + 0.5).astype(np.int64), 0, w - 1)
    vi = np.clip(np.floor(uv[:, 1] + 0.5).astype(np.int64), 0, h - 1)
    z = depth_m[vi, ui].astype(np.float64)
    z[~(z > 0)] = np.nan
    return _on_depth_edge(depth_m, ui, vi, z, cfg)


def _plane_fit_depth(depth_m: np.ndarray, uv: np.ndarray, ui: np.ndarray, vi: np.ndarray, z0: np.ndarray,
                     cfg: FeatureConfig) -> np.ndarray:
    """Depth at each keypoint ``(N,)`` from a plane fit in inverse depth over its patch (see
    :class:`FeatureConfig`); ``z0 (N,)`` is the median depth (NaN = no depth, kept NaN)."""
    h, w = depth_m.shape
    r = cfg.depth_plane_radius_px
    offs = np.arange(-r, r + 1)
    n = len(uv)
    uu, vv = np.broadcast_arrays(ui[:, None, None] + offs[None, None, :], vi[:, None, None] + offs[None, :, None])
    uu, vv = uu.reshape(n, -1), vv.reshape(n, -1)
    inside = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
    patch = depth_m[np.clip(vv, 0, h - 1), np.clip(uu, 0, w - 1)].astype(np.float64)
    du = uu - uv[:, 0:1].astype(np.float64)  # offsets from the sub-pixel keypoint
    dv = vv - uv[:, 1:2].astype(np.float64)
    ok = inside & (patch > 0) & (np.abs(patch - z0[:, None]) <= cfg.depth_plane_gate * z0[:, None])
    wgt = ok.astype(np.float64)
    inv = np.where(ok, 1.0 / np.where(patch > 0, patch, 1.0), 0.0)
    # weighted least squares  1/z = a + b du + c dv  per keypoint: 3x3 normal equations, batched
    M = np.empty((n, 3, 3))
    M[:, 0, 0] = wgt.sum(1)
    M[:, 0, 1] = M[:, 1, 0] = (wgt * du).sum(1)
    M[:, 0, 2] = M[:, 2, 0] = (wgt * dv).sum(1)
    M[:, 1, 1] = (wgt * du * du).sum(1)
    M[:, 1, 2] = M[:, 2, 1] = (wgt * du * dv).sum(1)
    M[:, 2, 2] = (wgt * dv * dv).sum(1)
    rhs = np.stack([inv.sum(1), (inv * du).sum(1), (inv * dv).sum(1)], axis=1)
    fit = (M[:, 0, 0] >= cfg.depth_plane_min_pixels) & np.isfinite(z0)
    z = z0.copy()
    if fit.any():
        Mf = M[fit]
        det = np.linalg.det(Mf)
        good = np.abs(det) > 1e-9 * np.maximum(Mf[:, 0, 0], 1.0) ** 3
        idx = np.flatnonzero(fit)[good]
        a = np.linalg.solve(Mf[good], rhs[fit][good][:, :, None])[:, 0, 0]
        zf = np.where(a > 0, 1.0 / np.where(a > 0, a, 1.0), np.nan)
        keep = np.isfinite(zf) & (np.abs(zf - z0[idx]) <= cfg.depth_plane_gate * z0[idx])
        z[idx[keep]] = zf[keep]
    return z


def extract(rgb: np.ndarray, depth_m: np.ndarray, intr: Intrinsics, cfg: FeatureConfig) -> Features:
    """Detect ORB keypoints, compute descriptors and lift them to 3D.

    Args:
        rgb: ``(H, W, 3)`` uint8 RGB (or ``(H, W)`` grey).
        depth_m: ``(H, W)`` float32 metres, 0 = invalid.
        intr: intrinsics of these images.

    Returns:
        :class:`Features`; ``points_cam`` rows are NaN where the depth is invalid.
    """
    grey = _to_grey(rgb)
    if grey.shape != depth_m.shape:
        raise ValueError(f"rgb {grey.shape} and depth {depth_m.shape} sizes differ")
    kps, desc = _detector(cfg).detectAndCompute(grey, None)
    if desc is None or len(kps) == 0:
        empty2 = np.zeros((0, 2), np.float32)
        no_desc = np.zeros((0, _SIFT_DIMS), np.float32) if cfg.detector == "sift" else \
            np.zeros((0, _DESCRIPTOR_BYTES), np.uint8)
        return Features(
            empty2, no_desc, np.zeros((0, 3), np.float32),
            np.zeros(0, bool), np.zeros(0, np.float32), grey, depth_m,
        )
    uv = np.array([kp.pt for kp in kps], dtype=np.float32).reshape(-1, 2)
    response = np.array([kp.response for kp in kps], dtype=np.float32)
    keep = bucket_keypoints(uv, response, grey.shape, cfg)
    uv, response, desc = uv[keep], response[keep], np.ascontiguousarray(desc[keep])
    z = _keypoint_depth(depth_m, uv, cfg)
    x = (uv[:, 0] - intr.cx) / intr.fx * z
    y = (uv[:, 1] - intr.cy) / intr.fy * z
    pts = np.column_stack([x, y, z]).astype(np.float32)
    return Features(uv, desc, pts, np.isfinite(z), response, grey, depth_m)


def match(ref: Features, cur: Features, cfg: FeatureConfig) -> MatchResult:
    """Match ``ref`` descriptors to ``cur`` descriptors and keep the good matches.

    Good matches: Hamming distance ``< good_match_k * max(min_dist, good_match_floor_bits)`` where
    ``min_dist`` is the smallest distance of all raw matches (the seeds' rule).
    """
    empty = MatchResult(np.zeros((0, 2), np.int64), np.zeros(0, np.float32), 0, 0, 0.0, 0.0)
    if len(ref) == 0 or len(cur) == 0:
        return empty
    if ref.descriptors.dtype != np.uint8 or cur.descriptors.dtype != np.uint8:
        return _match_float(ref, cur, cfg)
    ref_w, cur_w = hamming.as_words(ref.descriptors), hamming.as_words(cur.descriptors)
    if cfg.matching == "crosscheck":  # brute force, numba (see kernels.hamming); both directions in one pass
        d12, d12_second, j12, i21 = hamming.nearest_two_mutual_words(ref_w, cur_w)
        keep = i21[j12] == np.arange(len(ref))  # mutual nearest neighbours
    else:
        d12, d12_second, j12 = hamming.nearest_two_words(ref_w, cur_w)
        keep = (d12_second != hamming.NO_MATCH) & (d12 < cfg.ratio * d12_second)
    if not keep.any():
        return empty
    q = np.nonzero(keep)[0]  # ordered by ref index
    d = d12[q].astype(np.float64)
    min_d, max_d = float(d.min()), float(d.max())
    thresh = cfg.good_match_k * max(min_d, cfg.good_match_floor_bits)
    good = d < thresh
    pairs = np.column_stack([q[good], j12[q[good]]]).astype(np.int64)
    return MatchResult(pairs, d[good].astype(np.float32), len(q), int(good.sum()), min_d, max_d)


def _match_float(ref: Features, cur: Features, cfg: FeatureConfig) -> MatchResult:
    """SIFT descriptors: L2 nearest neighbours (OpenCV brute force) kept by Lowe's ratio test at ``cfg.ratio``;
    with ``crosscheck`` matching they must also be mutual. No good-match distance filter."""
    if ref.descriptors.dtype != cur.descriptors.dtype or ref.descriptors.shape[1] != cur.descriptors.shape[1]:
        raise ValueError("reference and current descriptors are of different kinds (ORB and SIFT?)")
    empty = MatchResult(np.zeros((0, 2), np.int64), np.zeros(0, np.float32), 0, 0, 0.0, 0.0)
    bf = cv2.BFMatcher(cv2.NORM_L2)
    knn = bf.knnMatch(ref.descriptors, cur.descriptors, k=2)
    rows = [(m[0].queryIdx, m[0].trainIdx, m[0].distance) for m in knn
            if len(m) == 2 and m[0].distance < cfg.ratio * m[1].distance]
    if not rows:
        return empty
    q = np.array([r[0] for r in rows], np.int64)
    j = np.array([r[1] for r in rows], np.int64)
    d = np.array([r[2] for r in rows], np.float32)
    if cfg.matching == "crosscheck":
        back = np.array([m[0].trainIdx for m in bf.knnMatch(cur.descriptors, ref.descriptors, k=1)], np.int64)
        keep = back[j] == q
        q, j, d = q[keep], j[keep], d[keep]
    if len(q) == 0:
        return empty
    return MatchResult(np.column_stack([q, j]), d, len(knn), len(q), float(d.min()), float(d.max()))


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


def track_subpixel(ref: Features, cur: Features, pairs: np.ndarray, cfg: FeatureConfig) -> np.ndarray:
    """Current-image points of the matches ``pairs (M, 2)``: LK-tracked reference keypoints (see
    ``FeatureConfig.lk_refine``) where tracking succeeds within ``lk_max_shift_px`` of the ORB keypoint,
    the ORB keypoints elsewhere; ``(M, 2)`` float32."""
    uv = cur.keypoints_uv[pairs[:, 1]].astype(np.float32)
    if not cfg.lk_refine or ref.grey is None or cur.grey is None or len(pairs) == 0 \
            or ref.grey.shape != cur.grey.shape:
        return uv
    p1, ok = _lk(ref.grey, cur.grey, ref.keypoints_uv[pairs[:, 0]], uv, cfg)
    ok &= np.linalg.norm(p1 - uv, axis=1) <= cfg.lk_max_shift_px
    uv[ok] = p1[ok]
    return uv


def _lk(grey_from: np.ndarray, grey_to: np.ndarray, p_from: np.ndarray, p_to: np.ndarray,
        cfg: FeatureConfig) -> tuple[np.ndarray, np.ndarray]:
    """Pyramidal Lucas-Kanade of the points ``p_from (M, 2)`` starting at ``p_to (M, 2)``:
    ``(tracked (M, 2) float32, ok (M,) bool)``."""
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, _LK_MAX_ITERATIONS, _LK_EPSILON_PX)
    p0 = np.ascontiguousarray(p_from, np.float32).reshape(-1, 1, 2)
    p1 = np.ascontiguousarray(p_to, np.float32).reshape(-1, 1, 2).copy()
    p1, status, _ = cv2.calcOpticalFlowPyrLK(
        grey_from, grey_to, p0, p1, winSize=(cfg.lk_window_px, cfg.lk_window_px), maxLevel=cfg.lk_levels,
        criteria=crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    p1 = p1.reshape(-1, 2)
    return p1, status.reshape(-1).astype(bool) & np.all(np.isfinite(p1), axis=1)


def _lk_warped(grey_ref: np.ndarray, grey_cur: np.ndarray, uv_ref: np.ndarray, pred: np.ndarray, z_ref: np.ndarray,
               T_cur_ref: np.ndarray, intr: Intrinsics, half: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Warped-window Lucas-Kanade of the reference pixels ``uv_ref (M, 2)`` (depth ``z_ref (M,)``) into the current
    image, starting at their projections ``pred (M, 2)`` under ``T_cur_ref``, and back (``projection_search_warp``):
    ``(found (M, 2), back (M, 2), ok (M,))``."""
    K = intr.K  # signed fy: the warp lives in the images' own pixel grid
    T = np.asarray(T_cur_ref, np.float64)
    # homography of the fronto-parallel plane z = z_ref through each point: K (R + t (0, 0, 1/z)) K^-1, ref -> cur
    G = np.broadcast_to(T[:3, :3], (len(z_ref), 3, 3)).copy()
    G[:, :, 2] += T[None, :3, 3] / np.asarray(z_ref, np.float64)[:, None]
    # singular when the current camera lies on that plane (a point at zero depth there): not tracked
    singular = ~(np.abs(np.linalg.det(G)) > _MIN_WARP_DET)
    G[singular] = np.eye(3)
    H = K @ G @ np.linalg.inv(K)
    m = len(pred)
    found = np.empty((m, 2))
    ok = np.empty(m, np.bool_)
    klk.track_warped(grey_ref, grey_cur, np.linalg.inv(H), np.ascontiguousarray(pred, np.float64), np.zeros((m, 2)),
                     half, _LK_MAX_ITERATIONS, _LK_EPSILON_PX, found, ok)
    back = np.empty((m, 2))
    ok_back = np.empty(m, np.bool_)
    start = np.ascontiguousarray(uv_ref, np.float64)
    klk.track_warped(grey_cur, grey_ref, np.ascontiguousarray(H), start, found - pred, half, _LK_MAX_ITERATIONS,
                     _LK_EPSILON_PX, back, ok_back)
    return found, back, ok & ok_back & ~singular


def search_by_projection(ref: Features, cur: Features, T_cur_ref: np.ndarray, intr: Intrinsics,
                         cfg: FeatureConfig) -> tuple[np.ndarray, np.ndarray]:
    """Reference keypoints found in the current image by projection (see ``FeatureConfig.projection_search``).

    Args:
        ref, cur: features with their grey images (same size).
        T_cur_ref: ``(4, 4)`` pose that projects the reference points into the current image.

    Returns:
        ``(points_ref (K, 3) float64, uv_cur (K, 2) float64)``: reference-camera points and their tracked
        current pixels (``K = 0`` when the grey images are missing or differ in size).
    """
    none = np.zeros((0, 3)), np.zeros((0, 2))
    if ref.grey is None or cur.grey is None or ref.grey.shape != cur.grey.shape or not ref.valid.any():
        return none
    P = ref.points_cam[ref.valid].astype(np.float64)
    uv_ref = ref.keypoints_uv[ref.valid]
    T = np.asarray(T_cur_ref, np.float64)
    u, v, z = project(P @ T[:3, :3].T + T[:3, 3], intr)
    h, w = cur.grey.shape
    half = cfg.lk_window_px // 2
    inside = (z > 0) & (u >= half) & (u <= w - 1 - half) & (v >= half) & (v <= h - 1 - half)
    if not inside.any():
        return none
    pred = np.column_stack([u[inside], v[inside]])
    if cfg.projection_search_warp:
        found, back, ok = _lk_warped(ref.grey, cur.grey, uv_ref[inside], pred, P[inside, 2], T, intr, half)
    else:
        found, ok = _lk(ref.grey, cur.grey, uv_ref[inside], pred, cfg)
        back, ok_back = _lk(cur.grey, ref.grey, found, uv_ref[inside], cfg)
        ok &= ok_back
    ok &= np.linalg.norm(back - uv_ref[inside], axis=1) <= cfg.projection_search_backtrack_px
    ok &= np.linalg.norm(found - pred, axis=1) <= cfg.projection_search_tol_px
    return P[inside][ok], found[ok].astype(np.float64)


def robust_sigma(values: np.ndarray) -> float:
    """Standard deviation of ``values (N,)`` estimated from their median absolute deviation (outlier-proof)."""
    v = np.asarray(values, np.float64)
    return _MAD_TO_SIGMA * float(np.median(np.abs(v - np.median(v))))


#: Fewest points in front of the camera for :func:`reprojection_spread_px` to estimate a spread.
MIN_POINTS_FOR_SPREAD = 10


def reprojection_spread_px(points_cam: np.ndarray, uv: np.ndarray, intr: Intrinsics) -> float:
    """Robust spread (px) of the reprojection residuals of ``points_cam (N, 3)`` (camera frame, m) against their
    observed pixels ``uv (N, 2)``: :func:`robust_sigma` over both coordinates of the points in front of the camera;
    0 when fewer than :data:`MIN_POINTS_FOR_SPREAD` are."""
    X = np.asarray(points_cam, np.float64)
    uv = np.asarray(uv, np.float64)
    ok = X[:, 2] > 0
    if ok.sum() < MIN_POINTS_FOR_SPREAD:
        return 0.0
    z = X[ok, 2]
    return robust_sigma(np.concatenate([intr.fx * X[ok, 0] / z + intr.cx - uv[ok, 0],
                                        intr.fy * X[ok, 1] / z + intr.cy - uv[ok, 1]]))


def _rgbd_system(T: np.ndarray, P: np.ndarray, uv: np.ndarray, q: np.ndarray, w_inv: np.ndarray, sp: float,
                 si: float, intr: Intrinsics, cfg: FeatureConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """Huber-weighted normal equations ``(H (6, 6), g (6,))`` of the joint refinement at ``T`` (left update
    ``exp(xi) T``, ``xi = (omega, v)``; residuals normalised by their sigmas: ``sp`` px, ``si`` 1/m);
    ``None`` if a point is behind."""
    X = P @ T[:3, :3].T + T[:3, 3]
    z = X[:, 2]
    if np.any(z <= 0):
        return None
    n = len(P)
    fx, fy = intr.fx, intr.fy
    k = cfg.rgbd_huber
    iz = 1.0 / z
    # d(point)/d(xi) for a left update exp(xi) T: dX = -[X]x omega + v
    J_X = np.zeros((n, 3, 6))
    J_X[:, 0, 1], J_X[:, 0, 2] = X[:, 2], -X[:, 1]
    J_X[:, 1, 0], J_X[:, 1, 2] = -X[:, 2], X[:, 0]
    J_X[:, 2, 0], J_X[:, 2, 1] = X[:, 1], -X[:, 0]
    J_X[:, 0, 3] = J_X[:, 1, 4] = J_X[:, 2, 5] = 1.0
    # projection u = fx x/z + cx, v = fy y/z + cy; inverse depth 1/z
    J_u = np.zeros((n, 3, 3))
    J_u[:, 0, 0] = fx * iz
    J_u[:, 0, 2] = -fx * X[:, 0] * iz * iz
    J_u[:, 1, 1] = fy * iz
    J_u[:, 1, 2] = -fy * X[:, 1] * iz * iz
    J_u[:, 2, 2] = -iz * iz
    J = J_u @ J_X  # (n, 3, 6)
    r = np.empty((n, 3))
    r[:, 0] = (fx * X[:, 0] * iz + intr.cx - uv[:, 0]) / sp
    r[:, 1] = (fy * X[:, 1] * iz + intr.cy - uv[:, 1]) / sp
    r[:, 2] = np.where(w_inv, (iz - q) / si, 0.0)
    J[:, :2] /= sp
    J[:, 2] = np.where(w_inv[:, None], J[:, 2] / si, 0.0)
    a = np.abs(r)
    w = np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))
    Jf = J.reshape(-1, 6)  # one row per residual: two BLAS products instead of a three-operand einsum
    Jw = Jf * w.reshape(-1, 1)
    H = Jw.T @ Jf
    g = Jw.T @ r.reshape(-1)
    return H, g


def refine_rgbd(T_cur_ref: np.ndarray, pts_ref: np.ndarray, uv_cur: np.ndarray, inv_depth_cur: np.ndarray,
                intr: Intrinsics, cfg: FeatureConfig, with_information: bool = False):
    """Joint reprojection + inverse-depth refinement of ``T_cur_ref`` (see ``FeatureConfig.rgbd_refine_iterations``).

    Args:
        T_cur_ref: ``(4, 4)`` initial pose (PnP).
        pts_ref: ``(N, 3)`` reference-camera points; uv_cur: ``(N, 2)`` their pixels in the current image.
        inv_depth_cur: ``(N,)`` measured inverse depth (1/m) at ``uv_cur``; NaN = none (reprojection only).
        with_information: also return the information matrix of the result.

    Returns:
        ``(4, 4)`` refined ``T_cur_ref`` (Gauss-Newton with Huber weights, left-multiplied SE(3) updates); with
        ``with_information``, ``(T, information)`` where ``information (6, 6)`` is the Gauss-Newton Hessian at
        ``T`` in normalised residual units, for a left perturbation ``exp(xi) T``, ``xi = (omega, v)``
        (``None`` when it cannot be formed): the inverse covariance of the pose under the residual sigmas (the
        points' own spreads: pixels at least ``rgbd_min_pixel_sigma_px``, inverse depth at least
        ``rgbd_inverse_depth_sigma``; see :class:`FeatureConfig`).
    """
    T = np.asarray(T_cur_ref, np.float64).copy()
    P = np.asarray(pts_ref, np.float64)
    uv = np.asarray(uv_cur, np.float64)
    w_inv = np.isfinite(inv_depth_cur)
    q = np.where(w_inv, inv_depth_cur, 0.0)
    si_model = cfg.rgbd_inverse_depth_sigma

    def pixel_sigma(T: np.ndarray) -> float:
        """The data's own reprojection spread (px), at least ``rgbd_min_pixel_sigma_px``."""
        if len(P) < MIN_POINTS_FOR_SPREAD:
            return cfg.rgbd_pixel_sigma_px
        return max(cfg.rgbd_min_pixel_sigma_px, reprojection_spread_px(P @ T[:3, :3].T + T[:3, 3], uv, intr))

    def spread(T: np.ndarray) -> float:
        """The data's own inverse-depth spread, when it exceeds the model (``si_model``)."""
        if w_inv.sum() < _MIN_POINTS_FOR_SPREAD:
            return si_model
        z = P[w_inv] @ T[2, :3] + T[2, 3]
        return max(si_model, robust_sigma(1.0 / z - q[w_inv]))

    for _ in range(cfg.rgbd_refine_iterations):
        if np.any(P @ T[2, :3] + T[2, 3] <= 0):
            break
        system = _rgbd_system(T, P, uv, q, w_inv, pixel_sigma(T), spread(T), intr, cfg)
        if system is None:
            break
        H, g = system
        try:
            xi = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        T = se3_exp(xi) @ T
        if np.linalg.norm(xi) < _RGBD_CONVERGED_UPDATE:
            break
    if not with_information:
        return T
    finite = bool(np.all(np.isfinite(T)))
    system = _rgbd_system(T, P, uv, q, w_inv, pixel_sigma(T), spread(T), intr, cfg) if finite else None
    info = None if system is None or not np.all(np.isfinite(system[0])) else system[0]
    return T, info


def _failed(n_raw: int, n_good: int, reason: str, pairs: np.ndarray) -> MotionResult:
    return MotionResult(
        np.eye(4), False, reason, n_raw, n_good, 0, np.zeros(3), np.zeros(3),
        np.zeros(len(pairs), bool), pairs,
    )


def _pnp_ransac(obj: np.ndarray, img: np.ndarray, K: np.ndarray, rvec0: np.ndarray, tvec0: np.ndarray,
                use_guess: bool, cfg: FeatureConfig):
    """OpenCV PnP-RANSAC: ``(inlier mask (N,), rvec (3, 1), tvec (3, 1), None)`` or ``(None, _, _, reason)``."""
    try:
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


def reprojection_inliers(points_cam: np.ndarray, uv: np.ndarray, intr: Intrinsics, bound_px: float) -> np.ndarray:
    """``(N,)`` bool: camera-frame points ``(N, 3)`` in front of the camera that project within ``bound_px`` of their
    pixels ``uv (N, 2)``."""
    u, v, z = project(points_cam, intr)
    return (z > 0) & (np.hypot(u - uv[:, 0], v - uv[:, 1]) < bound_px)


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


def estimate_motion(
    ref: Features,
    cur: Features,
    intr: Intrinsics,
    cfg: FeatureConfig,
    T_init_cur_ref: np.ndarray | None = None,
    min_consistent: int = 0,
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

    Returns:
        :class:`MotionResult`; ``ok`` is False with a ``reason`` when a rejection rule fired.
    """
    m = match(ref, cur, cfg)
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
    use_guess = T_init_cur_ref is not None
    if use_guess:
        rvec0 = so3_log(T_init_cur_ref[:3, :3]).reshape(3, 1).copy()
        tvec0 = np.asarray(T_init_cur_ref[:3, 3], np.float64).reshape(3, 1).copy()
    else:
        rvec0 = np.zeros((3, 1))
        tvec0 = np.zeros((3, 1))
    mask, rvec, tvec, reason = _pnp_ransac(obj, img, K, rvec0, tvec0, use_guess, cfg)
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
        z_cur = _keypoint_depth(cur.depth_m, uv_final, cfg)
        T, information = refine_rgbd(T, pts_final, uv_final, 1.0 / z_cur, intr, cfg, with_information=True)
        rvec, tvec = so3_log(T[:3, :3]).reshape(3), T[:3, 3].copy()
    res = MotionResult(T, True, None, m.n_raw, n_good, int(mask.sum()), rvec, tvec, mask, pairs, uv_cur, information,
                       len(pts_final))
    if not np.all(np.isfinite(T)):
        res.ok, res.reason, res.T_cur_ref = False, "pnp_failed", np.eye(4)
    elif motion_norm(T) > cfg.max_motion_norm:
        res.ok, res.reason = False, "motion_too_large"
    return res


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


def with_max_motion_norm(cfg: FeatureConfig, max_motion_norm: float) -> FeatureConfig:
    """Copy of ``cfg`` with another motion-norm bound (loops and relocalisation use larger ones)."""
    return replace(cfg, max_motion_norm=max_motion_norm)
