"""Settings of the sparse feature odometry (:class:`FeatureConfig`): extraction, matching, PnP and refinement."""

from __future__ import annotations

from dataclasses import dataclass, replace

from surfelslam.config import Config, ordered, setting

MATCHING_MODES = ("crosscheck", "ratio")
DETECTORS = ("orb", "sift")


@dataclass(frozen=True)
class FeatureConfig(Config):
    """ORB (or SIFT) extraction, matching, keypoint depth, PnP-RANSAC and pose refinement of the sparse odometry."""

    n_features: int = setting(1000, unit="keypoints", ge=1, le=100_000,
                              doc="keypoints kept per image (after grid bucketing)", user=True)
    detector: str = setting("orb", choices=DETECTORS,
                            doc="orb (binary descriptors: what the trackers and place recognition use) or sift "
                                "(more correct matches between views far apart, about 5x the time)")
    detect_oversample: float = setting(2.0, gt=0, le=100,
                                       doc="ORB first detects n_features times this many candidates; the strongest "
                                           "per grid cell are kept")
    grid_cols: int = setting(8, ge=1, le=1000, doc="columns of the bucketing grid")
    grid_rows: int = setting(6, ge=1, le=1000, doc="rows of the bucketing grid")
    scale_factor: float = setting(1.2, gt=1, le=4, doc="ORB pyramid scale ratio between levels")
    n_levels: int = setting(8, ge=1, le=32, doc="ORB pyramid levels")
    fast_threshold: int = setting(12, unit="grey levels", ge=0, le=255, doc="FAST corner threshold")
    edge_threshold_px: int = setting(19, unit="px", ge=2, le=255,
                                     doc="border where no keypoint is detected (also the ORB patch size)")
    matching: str = setting("crosscheck", choices=MATCHING_MODES,
                            doc="crosscheck (mutual nearest neighbours) or ratio (Lowe test)")
    ratio: float = setting(0.8, gt=0, le=1, doc="nearest / second-nearest distance bound of the ratio test")
    good_match_k: float = setting(4.0, gt=0, le=1000, allow_inf=True,
                                  doc="good matches have distance < k * max(min_distance, floor); inf keeps every "
                                      "match")
    good_match_floor_bits: float = setting(10.0, unit="bits", ge=0, le=256, doc="the floor of that rule")
    guided_radius_px: float = setting(
        0.0, unit="px", ge=0, le=10_000,
        doc="with a pose prediction, match each reference keypoint only to current keypoints within this radius of "
            "its predicted pixel (mutual nearest neighbours within the discs); 0 = always brute force")
    guided_min_matches: int = setting(50, unit="matches", ge=0, le=1_000_000,
                                      doc="fewer good guided matches: match by brute force instead")
    depth_median_3x3: bool = setting(True, doc="lift keypoints with the median of the valid depths in their 3x3 "
                                     "neighbourhood instead of the nearest pixel's")
    depth_plane_radius_px: int = setting(
        2, unit="px", ge=0, le=20,
        doc="then refine that depth by a plane fit (linear in inverse depth) over the (2r+1)^2 patch; 0 = off")
    depth_plane_gate: float = setting(0.03, unit="fraction", gt=0, le=10,
                                      doc="only pixels within this fraction of the median depth enter the fit")
    depth_plane_min_pixels: int = setting(12, unit="pixels", ge=3, le=10_000,
                                          doc="with fewer gated pixels the median is kept")
    depth_edge_rel: float = setting(
        0.1, unit="fraction", ge=0, le=100,
        doc="a keypoint whose patch holds a depth differing from its own by more than this fraction sits on an "
            "occluding contour and gets no 3D point; 0 = off")
    depth_edge_radius_px: int = setting(3, unit="px", ge=1, le=100, doc="patch radius of that test")
    min_depth_m: float = setting(0.1, unit="m", ge=0, le=100, doc="nearer keypoints get no 3D point")
    max_depth_m: float = setting(6.0, unit="m", gt=0, le=100, doc="farther keypoints get no 3D point", user=True)
    ransac_iterations: int = setting(300, unit="iterations", ge=1, le=1_000_000, doc="PnP-RANSAC iterations")
    reprojection_error_px: float = setting(2.0, unit="px", gt=0, le=1000, doc="RANSAC inlier threshold")
    ransac_confidence: float = setting(0.99, gt=0, le=1, doc="RANSAC success probability (early stop)")
    ransac_method: str = setting(
        "ransac", choices=("ransac", "usac"),
        doc="OpenCV PnP estimator of calls without a pose guess (loop checks, relocalisation): ransac = classic, "
            "EPnP hypotheses; usac = USAC (MSAC, fixed seed), which stops early on noisy low-inlier matches; "
            "guessed calls stay classic")
    refine: bool = setting(True, doc="refine the RANSAC pose on its inliers (Levenberg-Marquardt)")
    min_good_matches: int = setting(10, unit="matches", ge=0, le=1_000_000,
                                    doc="fewer good matches with reference depth: too_few_matches")
    min_inliers: int = setting(5, unit="inliers", ge=4, le=1_000_000,
                               doc="fewer PnP inliers: too_few_inliers (PnP needs 4 points)")
    max_motion_norm: float = setting(0.3, unit="m + rad", gt=0, le=100,
                                     doc="a motion norm above this: motion_too_large")
    lk_refine: bool = setting(True, doc="before PnP, move each match's current point to where Lucas-Kanade tracks "
                              "the reference keypoint's patch (sub-pixel)")
    lk_window_px: int = setting(11, unit="px", ge=3, le=101, doc="Lucas-Kanade window (square)")
    lk_levels: int = setting(1, ge=0, le=10, doc="Lucas-Kanade pyramid levels above the image")
    lk_max_shift_px: float = setting(2.0, unit="px", gt=0, le=100,
                                     doc="a tracked point farther than this from its ORB keypoint is not used")
    projection_search: bool = setting(
        True, doc="after PnP, project every reference keypoint with a 3D point and track it there by Lucas-Kanade; "
                  "the tracked points join the final refinement")
    projection_search_tol_px: float = setting(1.0, unit="px", gt=0, le=100,
                                              doc="largest distance between a tracked point and its projection")
    projection_search_backtrack_px: float = setting(0.5, unit="px", gt=0, le=100,
                                                    doc="largest forward-backward Lucas-Kanade error")
    projection_search_warp: bool = setting(
        True, doc="track each projected point with its reference window warped by the PnP pose's homography (else "
                  "square windows)")
    rgbd_refine_iterations: int = setting(
        5, unit="iterations", ge=0, le=1000,
        doc="Gauss-Newton iterations of a joint refinement on the inliers: reprojection plus inverse-depth residuals "
            "against the current depth; 0 = off")
    rgbd_pixel_sigma_px: float = setting(0.5, unit="px", gt=0, le=100,
                                         doc="reprojection noise of that refinement with fewer than 10 points")
    rgbd_inverse_depth_sigma: float = setting(0.003, unit="1/m", gt=0, le=10,
                                              doc="inverse-depth noise of that refinement (about constant for "
                                                  "structured light)")
    rgbd_huber: float = setting(2.0, unit="sigmas", gt=0, le=100, doc="Huber threshold on its normalised residuals")
    rgbd_min_pixel_sigma_px: float = setting(
        0.05, unit="px", gt=0, le=100,
        doc="with 10 or more points the reprojection noise is the points' own robust spread, at least this")
    consensus_fallback: bool = setting(
        True, doc="when PnP-RANSAC fails or keeps few matches, also try the rigid 3D consensus of the matches; keep "
                  "the hypothesis with more inliers")
    consensus_below_fraction: float = setting(0.5, unit="fraction", ge=0, le=1,
                                              doc="PnP inlier fraction under which the consensus is also tried")
    consensus_abs_tol_m: float = setting(0.03, unit="m", ge=0, le=10,
                                         doc="two matches are consistent when their distances in the two frames "
                                             "differ by at most abs + rel * distance")
    consensus_rel_tol: float = setting(0.05, unit="fraction", ge=0, le=1, doc="the rel of that rule")
    consensus_seeds: int = setting(10, ge=1, le=10_000, doc="consistent sets grown; the largest is kept")

    _depth_range = ordered("min_depth_m", "max_depth_m")


def with_max_motion_norm(cfg: FeatureConfig, max_motion_norm: float) -> FeatureConfig:
    """Copy of ``cfg`` with another motion-norm bound (loops and relocalisation use larger ones)."""
    return replace(cfg, max_motion_norm=max_motion_norm)
