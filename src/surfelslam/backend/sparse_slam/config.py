"""Settings of the sparse SLAM (:class:`SparseSlamConfig`) and of its depth odometry (:class:`DepthOdometryConfig`)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar

from surfelslam.backend.keyframes import KeyframeMapConfig
from surfelslam.backend.loops import LoopConfig
from surfelslam.backend.pose_graph import PoseGraphConfig
from surfelslam.config import Config, check, setting
from surfelslam.tracking.features import FeatureConfig

REJECTED_POSE_MODES = ("constant_velocity", "last")


@dataclass(frozen=True)
class DepthOdometryConfig(Config):
    """Depth in the sparse tracker's frame-to-keyframe odometry: ICP of the frame's depth against the reference
    keyframe's settles poses that PnP leaves ambiguous (one textured plane) or gets wrong (few inliers)."""

    enabled: bool = setting(True, doc="register every tracked frame's depth to the reference keyframe's", user=True)
    trust_min_inliers: int = setting(
        30, unit="inliers", ge=0, le=1_000_000,
        doc="a PnP pose with at least this many inliers starts ICP and adds its inliers as reprojection terms; with "
            "fewer, ICP starts from the constant-velocity prediction with depth alone")
    max_shift_m: float = setting(0.1, unit="m", gt=0, le=10,
                                 doc="ICP started from a PnP pose may move it at most this far (farther: PnP kept)")
    max_shift_deg: float = setting(5.0, unit="deg", gt=0, le=180, doc="the same bound on the rotation")
    hold_after_depth_only: bool = setting(
        True, doc="a frame registered by depth alone (PnP not trusted) does not set the predicted velocity: the next "
                  "one is predicted where it is. ICP keeps the prediction along directions the depth leaves free "
                  "(a ceiling and a wall), so feeding its step back made the pose run away by metres")


@dataclass(frozen=True)
class SparseSlamConfig(Config):
    """Sparse SLAM (the orb tracker, the hybrid's back end): keyframes, relocalisation, loop closure, pose graph. A key
    left none takes the running tracker's own value; the hybrid replaces the reference width, depth_edge_rel,
    guided_radius_px and the graph's weights and kernel scale by constants of its own (slam/hybrid_profile.py)."""

    features: FeatureConfig = setting(default_factory=FeatureConfig,
                                      doc="ORB, matching and PnP of the frame-to-keyframe odometry")
    keyframe_threshold: float | None = setting(
        None, unit="m + rad", gt=0, le=100, user=True,
        doc="motion norm from the reference keyframe that makes a new keyframe; none: the running tracker's own "
            "(orb 0.1, hybrid 0.12: its back-end profile)")
    keyframe_min_gap_frames: int | None = setting(
        None, unit="frames", ge=1, le=1_000_000,
        doc="a frame becomes a keyframe only this many placed frames after the reference keyframe at the earliest "
            "(caps the keyframe rate under fast motion); none: the running tracker's own (orb 1, hybrid 3, so that "
            "its loop checks keep up)")
    rejected_pose: str = setting("constant_velocity", choices=REJECTED_POSE_MODES, doc="pose of a rejected frame")
    velocity_reset_after_failures: int = setting(
        3, unit="frames", ge=1, le=1_000_000,
        doc="after this many rejected frames in a row the constant-velocity prediction stops until a frame is "
            "tracked again")
    relocalise_max_norm: float = setting(10.0, unit="m + rad", gt=0, le=100,
                                         doc="motion-norm bound of a relocalisation PnP")
    reinit_after_failures: int = setting(
        5, unit="frames", ge=0, le=1_000_000,
        doc="consecutive rejected frames without a relocalisation after which a frame with enough keypoints starts "
            "a new segment; 0 = never")
    reinit_min_keypoints: int = setting(100, unit="keypoints", ge=0, le=1_000_000,
                                        doc="keypoints with depth a frame needs to start a segment")
    reinit_sigma_m: float = setting(1.0, unit="m", gt=0, le=1000,
                                    doc="sigma of the edge joining a new segment to the old one (the motion across "
                                        "the loss is unknown)")
    reinit_sigma_rad: float = setting(1.0, unit="rad", gt=0, le=1000, doc="the same on the rotation")
    loop: LoopConfig = setting(default_factory=LoopConfig, doc="loop-candidate selection and verification")
    graph: PoseGraphConfig = setting(default_factory=PoseGraphConfig, doc="pose-graph weights and solver")
    map: KeyframeMapConfig = setting(default_factory=KeyframeMapConfig,
                                     doc="keyframe clouds and the final voxel-filtered map")
    features_reference_width_px: int = setting(
        320, unit="px", ge=0, le=65536,
        doc="features.reprojection_error_px and depth_edge_radius_px are given for images this wide and scaled up "
            "for wider ones (the same angle); 0 = as given")
    background_loop_checks: bool = setting(
        True, doc="verify a keyframe's loop candidates in a background thread; results are applied at fixed points of "
                  "the stream (deterministic), loop_check_lag_keyframes later", user=True)
    loop_check_lag_keyframes: int = setting(
        2, unit="keyframes", ge=1, le=16,
        doc="with background_loop_checks, a keyframe's checks are applied when this many newer keyframes have been "
            "added (1: at the next one, which then waits for them; 2 lets the tracking run on while the checks of "
            "one keyframe are still running)")

    REMOVED_KEYS: ClassVar[dict[str, str]] = {
        "relocalise_after_failures": "one setting for every tracker: [tracking] relocalise_after_failures"}

    @check
    def _orb_descriptors(self) -> str | None:
        """features.detector is orb (place recognition votes with binary descriptors)."""
        if self.features.detector != "orb":
            return f"the sparse trackers need features.detector = 'orb', got {self.features.detector!r}"
        return None


@dataclass(frozen=True)
class SparseProfile:
    """A tracker's own values of the ``[sparse]`` keys whose right value depends on the tracker (their default is
    none): a key a config sets applies to whichever tracker runs, an unset one takes the running tracker's profile
    (:func:`with_profile`)."""

    keyframe_threshold: float  # m + rad: motion from the reference keyframe that makes a new keyframe
    keyframe_min_gap_frames: int  # frames: at most one keyframe every this many
    loop_nearby: int  # keyframes: [sparse.loop] n_nearby
    loop_random: int  # keyframes: [sparse.loop] n_random
    loop_closed_retrieved: int = 0  # candidates: [sparse.loop] closed_retrieved
    loop_retrieved: int = 3  # keyframes: [sparse.loop] n_retrieved


#: the back end's own profile (the orb tracker's, and a :class:`SparseSlam` built without one): every keyframe that
#: moved 0.1 m + rad, 5 nearby + 3 retrieved + 5 random loop candidates (the loop checks run in the background)
BACK_END_PROFILE = SparseProfile(keyframe_threshold=0.1, keyframe_min_gap_frames=1, loop_nearby=5, loop_random=5,
                                 loop_retrieved=3)


def with_profile(cfg: SparseSlamConfig, profile: SparseProfile) -> SparseSlamConfig:
    """``cfg`` with its unset (none) tracker-dependent keys given ``profile``'s values; set keys are kept."""
    loop = cfg.loop
    return replace(
        cfg,
        keyframe_threshold=profile.keyframe_threshold if cfg.keyframe_threshold is None else cfg.keyframe_threshold,
        keyframe_min_gap_frames=(profile.keyframe_min_gap_frames if cfg.keyframe_min_gap_frames is None
                                 else cfg.keyframe_min_gap_frames),
        loop=replace(loop, n_nearby=profile.loop_nearby if loop.n_nearby is None else loop.n_nearby,
                     n_random=profile.loop_random if loop.n_random is None else loop.n_random,
                     n_retrieved=profile.loop_retrieved if loop.n_retrieved is None else loop.n_retrieved,
                     closed_retrieved=(profile.loop_closed_retrieved if loop.closed_retrieved is None
                                       else loop.closed_retrieved)))


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
