"""Settings of the sparse SLAM (:class:`SparseSlamConfig`) and of its depth odometry (:class:`DepthOdometryConfig`)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from surfelslam.backend.keyframes import MapConfig
from surfelslam.backend.loops import LoopConfig
from surfelslam.backend.pose_graph import PoseGraphConfig
from surfelslam.tracking.features import FeatureConfig

REJECTED_POSE_MODES = ("constant_velocity", "last")


@dataclass(frozen=True)
class DepthOdometryConfig:
    """Depth in the frame-to-keyframe odometry of the sparse tracker (:mod:`surfelslam.backend.sparse_slam`).

    A feature tracker has little to go on where the view is one poster on a plain wall or a few cabinet corners:
    its PnP poses are ambiguous (a small turn and a sideways step reproject alike on one distant plane: 3-7 cm off
    with 80-100 inliers in a synthetic plain-walled office) or wrong (8-20 inliers on a wrong RANSAC consensus, up
    to 17 cm off), and the keyframe chain carries the error on. Point-to-plane ICP of the frame's depth against the
    reference keyframe's settles the pose there: relative to their keyframe, the same frames end 0.1-7 mm from the
    ground truth. Synthetic plain-walled sequences, 320x240, ATE (mm), PnP odometry / with depth odometry and
    dense-refined keyframe edges (``orb.loop_icp``): office hand-held 151.3 / 0.72 (dense 2.82), walking loop 50.8
    (25 frames lost) / 0.32 (dense 3.52), office 7-Scenes motion replay 9.48 / 0.97 (dense 1.47).

    Attributes:
        enabled: register every tracked frame's depth to the reference keyframe's.
        trust_min_inliers: a PnP pose with at least this many inliers starts ICP, and its inliers enter it as
            reprojection terms (``loop_icp.feature_*`` weights); with fewer, or when PnP is rejected, ICP starts
            from the constant-velocity prediction with depth alone (30: ORB-SLAM's bar for a tracked frame, as
            ``hybrid.pnp_trust_min_inliers``). When that ICP fails (too few inliers, degenerate, implausible) a
            weak PnP pose is kept as it is and a rejected frame stays rejected.
        max_shift_m, max_shift_deg: ICP started from a PnP pose may move it at most this far (m, deg); farther,
            the PnP pose is kept. In the plain-walled office replay (a first version without refined edges and
            with feature weight 0.1) 3 cm / 3 deg, the keyframe-edge check's bound, kept PnP poses 3-7 cm
            off with 80-100 inliers (ATE 7.62 mm); 10 cm / 5 deg let ICP correct them (6.24 mm).
    """

    enabled: bool = True
    trust_min_inliers: int = 30
    max_shift_m: float = 0.1
    max_shift_deg: float = 5.0

    def __post_init__(self) -> None:
        if self.trust_min_inliers < 0:
            raise ValueError(f"trust_min_inliers must be >= 0, got {self.trust_min_inliers}")
        if not (self.max_shift_m > 0 and self.max_shift_deg > 0):
            raise ValueError(f"max_shift_m and max_shift_deg must be positive, got {self.max_shift_m} and "
                             f"{self.max_shift_deg}")


@dataclass(frozen=True)
class SparseSlamConfig:
    """Sparse SLAM settings.

    Attributes:
        features: ORB / matching / PnP settings (frame-to-keyframe odometry).
        keyframe_threshold: motion norm (m + rad) from the reference keyframe that makes a new keyframe
            (seeds: 0.1).
        rejected_pose: pose of a rejected frame: ``"constant_velocity"`` or ``"last"``.
        velocity_reset_after_failures: after this many rejected frames in a row the constant-velocity prediction
            stops (rejected frames keep the last pose) until a frame is tracked again. Without it a long loss (a
            plain wall filling the view) extrapolated the last motion for every lost frame, 2 m in 40 frames,
            and the repeated composition lost orthonormality until the poses overflowed.
        relocalise_after_failures: consecutive rejected frames before relocalisation is tried. A relocalised frame
            at least ``keyframe_threshold`` from the keyframe it was found against becomes a keyframe (the next
            frames are tracked against it; from the old keyframe they would exceed ``features.max_motion_norm``).
        relocalise_max_norm: motion-norm bound (m + rad) of a relocalisation PnP.
        reinit_after_failures: consecutive rejected frames without a relocalisation after which a frame with at
            least ``reinit_min_keypoints`` keypoints with depth starts a new segment (the package docstring,
            :mod:`surfelslam.backend.sparse_slam`); 0 = never. Without it a view that shares no feature with any
            keyframe (7-Scenes after 60 dropped frames) was lost for the rest of the run.
        reinit_min_keypoints: keypoints with depth a frame needs to start a segment (a plain wall does not).
        reinit_sigma_m, reinit_sigma_rad: standard deviations of the edge that joins a new segment to the old one
            (m, rad): the motion across the loss is unknown, so the edge must not hold the segment where the loop
            closures put it.
        loop: loop-candidate selection and verification.
        graph: pose-graph weights and solver.
        map: keyframe clouds and the final voxel-filtered map.
        features_reference_width_px: ``features.reprojection_error_px`` (the PnP-RANSAC inlier bound) and
            ``features.depth_edge_radius_px`` are given for images this wide and scaled by
            ``width / features_reference_width_px`` for wider ones (never below the value given; 0 = as given): the
            same angle, since keypoint jitter and colour / depth misregistration grow
            with the resolution. 7-Scenes at 640x480 (2 px -> 4 px): frames 250-499 at 3x speed 50.60 -> 38.63 mm
            (dense 23.02: 2.20x -> 1.68x; fewer keyframe pairs verified at 2 px, 42 against 63 at 320x240), 0-249
            31.49 -> 28.31 (1x) and 27.73 -> 27.10 (3x), 250-499 38.11 -> 38.99, 0-499 36.27 -> 36.13, 0-499 at 2x
            36.13 -> 40.73 (dense 25.67): the worst case 2.20x -> 1.68x dense, not every segment better; fourteen
            640x480 synthetic sequences -8 % to +4 % (0.28-0.86 mm). 320x240 input is unchanged. The hybrid sets
            it to 0 (its PnP poses only guess or check ICP's; scaled, 7-Scenes 640x480 went 25.06 -> 25.32 mm).
        background_loop_checks: verify a new keyframe's loop candidates in a background thread while the next
            frames are tracked. The results are applied (edges added, graph optimised) when the next keyframe is
            inserted, before a relocalisation, and in :meth:`SparseSlam.finish`, so they land at the same point
            of the stream every run: results are deterministic either way, and a loop corrects the poses one
            keyframe later than with ``False``.
    """

    features: FeatureConfig = field(default_factory=FeatureConfig)
    keyframe_threshold: float = 0.1
    rejected_pose: str = "constant_velocity"
    velocity_reset_after_failures: int = 3
    relocalise_after_failures: int = 3
    relocalise_max_norm: float = 10.0
    reinit_after_failures: int = 5
    reinit_min_keypoints: int = 100
    reinit_sigma_m: float = 1.0
    reinit_sigma_rad: float = 1.0
    loop: LoopConfig = field(default_factory=LoopConfig)
    graph: PoseGraphConfig = field(default_factory=PoseGraphConfig)
    map: MapConfig = field(default_factory=MapConfig)
    features_reference_width_px: int = 320
    background_loop_checks: bool = True

    def __post_init__(self) -> None:
        if self.rejected_pose not in REJECTED_POSE_MODES:
            raise ValueError(f"rejected_pose must be one of {REJECTED_POSE_MODES}, got {self.rejected_pose!r}")
        if self.keyframe_threshold <= 0:
            raise ValueError(f"keyframe_threshold must be positive, got {self.keyframe_threshold}")
        if self.velocity_reset_after_failures < 1:
            raise ValueError(f"velocity_reset_after_failures must be >= 1, got {self.velocity_reset_after_failures}")
        if self.reinit_after_failures < 0 or self.reinit_min_keypoints < 0:
            raise ValueError(f"reinit_after_failures and reinit_min_keypoints must be >= 0, got "
                             f"{self.reinit_after_failures} and {self.reinit_min_keypoints}")
        if self.reinit_sigma_m <= 0 or self.reinit_sigma_rad <= 0:
            raise ValueError(f"reinit_sigma_m and reinit_sigma_rad must be positive, got {self.reinit_sigma_m} and "
                             f"{self.reinit_sigma_rad}")
        if self.features_reference_width_px < 0:
            raise ValueError(f"features_reference_width_px must be >= 0, got {self.features_reference_width_px}")
        if self.features.detector != "orb":  # place recognition votes with binary (Hamming) descriptors
            raise ValueError(f"the sparse trackers need features.detector = 'orb', got {self.features.detector!r}")


def features_for_width(cfg: SparseSlamConfig, width_px: int) -> SparseSlamConfig:
    """``cfg`` with ``features.reprojection_error_px`` and ``features.depth_edge_radius_px`` scaled for images
    ``width_px`` wide (see ``SparseSlamConfig.features_reference_width_px``)."""
    ref = cfg.features_reference_width_px
    if ref <= 0 or width_px <= ref:
        return cfg
    f = cfg.features
    scale = width_px / ref
    return replace(cfg, features=replace(f, reprojection_error_px=f.reprojection_error_px * scale,
                                         depth_edge_radius_px=int(round(f.depth_edge_radius_px * scale))))
