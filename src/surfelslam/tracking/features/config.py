"""Settings of the sparse feature odometry (:class:`FeatureConfig`): extraction, matching, PnP and refinement."""

from __future__ import annotations

from dataclasses import dataclass, replace

MATCHING_MODES = ("crosscheck", "ratio")
DETECTORS = ("orb", "sift")


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


def with_max_motion_norm(cfg: FeatureConfig, max_motion_norm: float) -> FeatureConfig:
    """Copy of ``cfg`` with another motion-norm bound (loops and relocalisation use larger ones)."""
    return replace(cfg, max_motion_norm=max_motion_norm)
