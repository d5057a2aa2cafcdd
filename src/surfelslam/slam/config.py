"""Every setting of a run: :class:`SlamConfig` gathers each subsystem's config (saved as ``config.toml``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from surfelslam.backend.dense_edges import DenseEdgeConfig
from surfelslam.backend.sparse_slam import (
    DepthOdometryConfig,
    SparseSlamConfig,
)
from surfelslam.datasets.base import DatasetOptions
from surfelslam.geometry.camera import ColourRegistrationConfig
from surfelslam.mapping.fusion import FusionConfig
from surfelslam.mapping.render import RenderConfig
from surfelslam.mapping.surfel_map import MapConfig
from surfelslam.settings import Config, check, setting
from surfelslam.slam.registry import registered
from surfelslam.tracking.geometric import GeometricGuessConfig
from surfelslam.tracking.icp import ICPConfig
from surfelslam.tracking.photometric import (
    PHOTOMETRIC_MODES,
)
from surfelslam.tracking.preprocess import (
    PreprocessConfig,
)


@dataclass(frozen=True)
class IOConfig(Config):
    """Reading frames: a background reader thread decodes (and prepares) frames ahead of the tracker."""

    prefetch_frames: int = setting(3, unit="frames", ge=0, le=64,
                                   doc="frames decoded ahead in a background thread; 0 = synchronous", user=True)
    prepare_in_reader: bool = setting(True, doc="the reader thread also does the frame-only work (depth pyramid, "
                                      "fusion colour, ORB features); same results; needs prefetch_frames > 0")


@dataclass(frozen=True)
class ComputeConfig(Config):
    """Numba kernels: serial or parallel."""

    parallel_kernels: bool = setting(False, doc="run the per-pixel kernels' parallel twins (bit-identical results) "
                                     "when numba has at least 2 threads; off: on 2 cores the frame reader needs "
                                     "the second one", user=True)


def apply_compute(cfg: ComputeConfig) -> None:
    """Switch every dual kernel to the setting of ``cfg`` (process-wide)."""
    import numba

    from surfelslam.kernels import threads

    threads.set_parallel(cfg.parallel_kernels and numba.config.NUMBA_NUM_THREADS >= 2)


@dataclass(frozen=True)
class TrackingConfig(Config):
    """Frame-to-model tracking policy: prediction, working resolution, photometric term, relocalisation."""

    constant_velocity: bool = setting(True, doc="predict each pose by repeating the last inter-frame motion (else: "
                                      "the last pose)", user=True)
    max_failures_in_a_row_before_reset_velocity: int = setting(
        3, unit="frames", ge=0, le=1_000_000,
        doc="after this many failed frames in a row the predicted velocity is reset to zero")
    frame_to_frame_init: bool = setting(False, doc="first register the frame to the previous frame, then refine "
                                        "against the model (one more ICP; helps under fast motion)", user=True)
    max_width_px: int = setting(320, user=True, unit="px", ge=0, le=65536,
                                doc="render the model and run ICP at the finest pyramid level of the input at most "
                                    "this wide (640x480 input: its 320x240 block means); 0 = full resolution")
    photometric: str = setting("auto", choices=PHOTOMETRIC_MODES,
                               doc="joint photometric term in ICP (weights in [icp] photometric_*); auto: on unless "
                                   "colour and depth are not registered (e.g. 7-Scenes)", user=True)
    relocalise_after_failures: int = setting(
        3, unit="frames", ge=0, le=1_000_000,
        doc="once this many frames in a row failed, relocalise each further failed frame (every tracker: dense and "
            "hybrid from the depth alone, shape guess against the map then ICP; hybrid and orb first by PnP against "
            "all keyframes); 0 = never", user=True)
    shape_guess: GeometricGuessConfig = setting(default_factory=GeometricGuessConfig,
                                                doc="settings of the relocalisation's shape guess")
    fuse_weak_frames: bool = setting(
        True, doc="fuse the frame of a degenerate registration (one plane, a corridor: the pose along the directions "
                  "the view constrains, the prediction along the others); off: refuse it, not fused", user=True)
    weak_velocity_decay_s: float = setting(
        0.0, unit="s", ge=0, le=1000, allow_inf=True,
        doc="through weak frames the prediction carries the last fully tracked frame's velocity on, fading by "
            "exp(-t / this) (a walk down a corridor); 0 = the camera is predicted to hold still (a sway in front of a "
            "wall)")
    frozen_velocity_gain: float = setting(
        0.5, unit="fraction", ge=0, le=1,
        doc="along the directions the finest ICP level left at the prediction (icp.weak_direction_ratio), the "
            "velocity moves only this fraction of the way to the frame's step: there the step is the prediction "
            "plus what the coarser levels did (1 = the whole step)")
    relocalise_max_speed_m_s: float = setting(
        2.0, unit="m/s", gt=0, le=1000, allow_inf=True,
        doc="a relocalised pose farther from the last tracked pose than this speed allows in the time since it "
            "(plus relocalise_slack_m) is refused: a wrong match, not a camera motion (a brisk walk is 1.3 m/s)")
    relocalise_max_rate_deg_s: float = setting(120.0, unit="deg/s", gt=0, le=100_000, allow_inf=True,
                                               doc="the same bound on the rotation (plus relocalise_slack_deg)")
    relocalise_slack_m: float = setting(0.1, unit="m", ge=0, le=100, doc="slack added to the translation bound")
    relocalise_slack_deg: float = setting(10.0, unit="deg", ge=0, le=180, doc="slack added to the rotation bound")
    max_velocity_change_m_s: float = setting(
        1.0, unit="m/s", gt=0, le=1000, allow_inf=True,
        doc="hybrid: a registration correcting the constant-velocity prediction by more than this change of "
            "velocity allows since the last posed frame (plus 2 cm) is a slide, not a motion: unless PnP confirms "
            "it, the frame is held at the prediction, not fused; inf = off")
    max_rate_change_deg_s: float = setting(180.0, unit="deg/s", gt=0, le=100_000, allow_inf=True,
                                           doc="the same bound on the rotation (plus a 2 deg slack)")
    max_held_frames: int = setting(
        10, unit="frames", ge=0, le=1_000_000,
        doc="frames held at the prediction in a row at most; a further untrusted registration is a failure (then "
            "relocalisation); 0 = such frames are failures at once")


@dataclass(frozen=True)
class GivenPosesConfig(Config):
    """Mapping with given poses (``--poses``)."""

    max_dt_s: float = setting(0.02, unit="s", ge=0, le=10,
                              doc="a frame takes the pose whose timestamp is nearest, within this", user=True)


@dataclass(frozen=True)
class MapReuseConfig(Config):
    """Saving the map for a later run (``map.npz``) and localising a new sequence in a saved map (``--map``)."""

    save: bool = setting(True, doc="write map.npz (surfels, keyframes, pose graph, config) so that a later run can "
                         "continue from it with --map (surfel trackers)", user=True)
    keyframe_motion: float = setting(
        0.15, unit="m + rad", gt=0, le=100,
        doc="a tracked frame this far (motion norm) from the last saved keyframe becomes one: its ORB features and "
            "depth are saved for relocalisation (hybrid: the first such frame its back end makes a keyframe, whose "
            "features are extracted anyway)")
    keyframe_depth_max_width_px: int = setting(
        160, unit="px", ge=1, le=65536,
        doc="a saved keyframe's depth is block-subsampled to at most this width (2x2 steps)")
    localise_max_frames: int = setting(
        30, unit="frames", ge=1, le=1_000_000,
        doc="with --map, the first frames are localised in the saved map; after this many frames without a "
            "verified pose the run gives up and starts a new map frame at the next frame", user=True)
    localise_candidates: int = setting(
        5, unit="keyframes", ge=1, le=1000,
        doc="saved keyframes proposed by place recognition (descriptor voting) and verified by PnP per frame")
    localise_min_inlier_fraction: float = setting(
        0.4, unit="fraction", gt=0, le=1,
        doc="a relocalisation is accepted only if dense ICP against the saved surfels keeps at least this fraction "
            "of the frame's points as inliers (the overlap)")
    localise_max_rmse_m: float = setting(
        0.015, unit="m", gt=0, le=10,
        doc="... and their RMS point-to-plane residual is at most this")
    localise_max_shift_m: float = setting(
        0.1, unit="m", gt=0, le=100,
        doc="... and ICP moved the PnP pose at most this far (farther: the PnP pose was wrong)")
    localise_max_shift_deg: float = setting(10.0, unit="deg", gt=0, le=180, doc="the same bound on the rotation")


def _hybrid_loop_icp() -> DenseEdgeConfig:
    """The hybrid's keyframe-edge ICP: without the feature refinement before it (``pnp_refinement`` off), which
    costs about 40 % of the loop-check time for little gain once ICP refines the edge; an edge's information lowered
    along the directions its depth leaves weak (``weak_direction_ratio`` 100), so that edges between views of a
    ceiling and a wall do not pull the trajectory along the planes' intersection; the PnP inliers weighing as much as
    a point-to-plane pair each (``feature_weight`` 1): at 0.1 keyframe-to-keyframe ICP slid millimetres along the
    direction of motion where the depth constrains it weakly, and those biased edges, not the odometry, held the
    fast-motion keyframes 3x farther from the truth than the orb tracker's; nearby pairs checked from the dense
    odometry's relative pose (``odometry_nearby``: no RANSAC, finest ICP level only)."""
    return DenseEdgeConfig(pnp_refinement=False, weak_direction_ratio=100.0, feature_weight=1.0, odometry_nearby=True)


def _frame_to_model_icp() -> ICPConfig:
    """The trackers' frame-to-model ICP: a level stops at a 1e-3 update (the tighter class default suits one-off
    and keyframe-edge registrations). Frame to model, the next frame corrects what a level leaves, so the last sub-mm
    updates cost iterations without making the trajectory better."""
    return ICPConfig(min_update_norm=1e-3)


#: the tracker a run uses unless told otherwise (``SlamConfig.tracker``'s default)
DEFAULT_TRACKER = "hybrid"

JOINT_MODES = PHOTOMETRIC_MODES  # the same auto | on | off colour switch (tracking.photometric.colour_switch)
FRAME_FEATURE_MODES = ("tracked", "extracted")
JOINT_WEIGHT_UNITS = ("robust_scale", "depth_noise")  # hybrid.joint_weight_unit


#: what an older run's config.toml also needs: it holds the orb tracker's [sparse] keyframe and loop values
_OLD_RUN_CONFIG = ("in an older run's config.toml delete its [sparse] keyframe_threshold, [sparse.loop] n_nearby, "
                   "n_random, n_retrieved too")


@dataclass(frozen=True)
class HybridConfig(Config):
    """The hybrid tracker: dense ICP checked and helped by PnP against keyframes, with the sparse back end's loop
    corrections applied to the dense trajectory and map."""

    pnp_retry: bool = setting(True, doc="when ICP fails or is degenerate, retry it from the PnP pose against the last "
                              "keyframe", user=True)
    pnp_when_velocity_untrusted: bool = setting(True, doc="after a failed frame, start ICP from the PnP pose instead "
                                                "of the constant-velocity guess")
    pnp_check: bool = setting(False, doc="every frame, compare the ICP pose with the PnP pose; on disagreement retry "
                              "ICP from PnP, and do not fuse a frame that still disagrees", user=True)
    pnp_check_max_m: float = setting(0.05, unit="m", gt=0, le=100, doc="disagreement bound on the translation")
    pnp_check_max_deg: float = setting(5.0, unit="deg", gt=0, le=180, doc="disagreement bound on the rotation")
    pnp_check_min_inlier_fraction: float = setting(
        0.5, unit="fraction", ge=0, le=1,
        doc="a difference counts as disagreement only if fewer than this fraction of the PnP inliers reproject "
            "within the inlier bound under the ICP pose (a PnP pose on one distant plane is ambiguous); 0 = the "
            "metric bounds alone")
    pnp_trust_min_inliers: int = setting(
        30, unit="inliers", ge=0, le=1_000_000,
        doc="a PnP pose with fewer inliers neither adds the joint feature term nor overrules ICP in the check")
    loop_correction: bool = setting(True, user=True,
                                    doc="apply pose-graph corrections to the dense trajectory and the surfel map")
    live_correction_min_m: float = setting(
        0.03, unit="m", ge=0, le=100,
        doc="during the run the map and pose follow a graph optimisation only when it moves some keyframe's surfels "
            "more than this; smaller corrections are applied once, at the end")
    live_correction_keyframe_min_m: float = setting(
        0.01, unit="m", ge=0, le=100,
        doc="a live correction moves only the keyframes (and their surfels) it moves more than this, the others at "
            "a later one or at the end; 0 moves all")
    untrusted_min_correction_m: float = setting(
        0.001, unit="m", ge=0, le=100,
        doc="at the end, when the refined edges are not trusted, the PnP graph's correction is applied only if some "
            "keyframe moves more than this; 0 applies every correction")
    loop_icp: DenseEdgeConfig = setting(default_factory=_hybrid_loop_icp,
                                        doc="dense (ICP) refinement of the PnP keyframe edges, behind a trust gate")
    joint_features: str = setting(
        "auto", choices=JOINT_MODES,
        doc="add the PnP inliers against the reference keyframe as reprojection terms to every ICP iteration (ORB "
            "features and PnP on every frame); auto: on unless colour and depth are not registered", user=True)
    frame_features: str = setting(
        "tracked", choices=FRAME_FEATURE_MODES,
        doc="how each frame's points against the reference keyframe are found: tracked = followed by Lucas-Kanade "
            "from the predicted pose (ORB only for keyframes and relocalisation); extracted = ORB and PnP-RANSAC in "
            "every frame (slower)", user=True)
    joint_sigma_px: float = setting(1.0, unit="px", gt=0, le=100, doc="pixel noise of those terms (residual unit)")
    joint_huber: float = setting(2.0, unit="sigmas", gt=0, le=100, doc="Huber threshold of their residual norm")
    joint_weight: float = setting(
        100.0, ge=0, le=1e6,
        doc="a feature residual of joint_sigma_px costs this many point-to-plane pairs with a residual of one "
            "joint_weight_unit")
    joint_fine_match: bool = setting(
        False, doc="the joint term's PnP match also searches by projection, and refines on RGB-D jointly even with "
                   "pnp_rgbd_refine off (about 1.5x the per-frame time at 320x240); the inliers are sub-pixel tracked "
                   "either way", user=True)
    pnp_rgbd_refine: bool = setting(
        True, doc="refine the per-frame PnP pose on the keypoints' pixels and depths jointly ([sparse.features] "
                  "rgbd_refine_iterations): the joint term's pixel noise, the inliers' spread at that pose, then also "
                  "shows where colour keypoints and depth disagree")
    joint_weight_unit: str = setting(
        "depth_noise", choices=JOINT_WEIGHT_UNITS,
        doc="robust_scale: [icp] finest_robust_scale_m; depth_noise: the depth's own point-to-plane noise, measured "
            "in the last tracked frame's ICP (noisier depth, as from a real sensor, gives the features more say)")
    # the former copies of [sparse] keys (issue 67): the hybrid's values are its profile (slam/hybrid_profile.py)
    REMOVED_KEYS: ClassVar[dict[str, str]] = {
        "relocalise_after_failures": "one setting for every tracker: [tracking] relocalise_after_failures",
        "keyframe_threshold": "set [sparse] keyframe_threshold (unset: the running tracker's own, the hybrid's "
                              "0.12); " + _OLD_RUN_CONFIG,
        "keyframe_min_gap_frames": "set [sparse] keyframe_min_gap_frames (unset: the running tracker's own, the "
                                   "hybrid's 3); " + _OLD_RUN_CONFIG,
        "loop_nearby": "set [sparse.loop] n_nearby (unset: the running tracker's own, the hybrid's 3); "
                       + _OLD_RUN_CONFIG,
        "loop_random": "set [sparse.loop] n_random (unset: the running tracker's own, the hybrid's 0); "
                       + _OLD_RUN_CONFIG,
        "graph_edge_information": "the hybrid's is a constant (isotropic, EDGE_INFORMATION in "
                                  "surfelslam/slam/hybrid_profile.py); [sparse.graph] edge_information is the orb's",
        "pnp_reference_width_px": "the hybrid's is a constant (0, FEATURES_REFERENCE_WIDTH_PX in "
                                  "surfelslam/slam/hybrid_profile.py); [sparse] features_reference_width_px is the "
                                  "orb's",
        "pnp_depth_edge_rel": "the hybrid's is a constant (0, DEPTH_EDGE_REL in surfelslam/slam/hybrid_profile.py); "
                              "[sparse.features] depth_edge_rel is the orb's",
        "guided_match_deg": "the hybrid's is a constant (2.6 deg, GUIDED_MATCH_DEG in "
                            "surfelslam/slam/hybrid_profile.py); [sparse.features] guided_radius_px is the orb's",
        "dense_odometry_sigma_m": "the hybrid's is a constant (0.003 m, DENSE_ODOMETRY_SIGMA_M in "
                                  "surfelslam/slam/hybrid_profile.py); [sparse.graph] odometry_information is the "
                                  "orb's",
        "loop_robust_scale_m": "the hybrid's is a constant (0.03 m, LOOP_ROBUST_SCALE_M in "
                               "surfelslam/slam/hybrid_profile.py); [sparse.graph] robust_scale_sigma is the orb's"}


def _orb_loop_icp() -> DenseEdgeConfig:
    """The orb tracker's keyframe ICP: the PnP refinement before it, the PnP inliers at ``feature_weight`` 0.3, no
    weak-direction shaping, and no depth-only nearby edges (its odometry is keyframe ICP already)."""
    return DenseEdgeConfig(feature_weight=0.3, depth_only_nearby=False)


@dataclass(frozen=True)
class OrbConfig(Config):
    """Settings of the ``orb`` tracker beyond the shared sparse ones (``[sparse]``)."""

    depth_odometry: DepthOdometryConfig = setting(
        default_factory=DepthOdometryConfig,
        doc="frames registered to the reference keyframe by ICP on depth as well as by PnP")
    loop_icp: DenseEdgeConfig = setting(
        default_factory=_orb_loop_icp,
        doc="the keyframes' depth store and ICP settings (depth odometry too), and the refined keyframe edges")


@dataclass(frozen=True)
class SlamConfig(Config):
    """Every setting of a run, with its tracker and dataset options (``[dataset]``, the ``--start`` ...
    ``--depth-scale`` options; unset ones are left out): saved as ``config.toml``, the whole recipe of the run."""

    tracker: str = setting(DEFAULT_TRACKER, user=True,
                           doc="the tracker: hybrid, dense or orb (the registered ones; --tracker)")
    dataset: DatasetOptions = setting(default_factory=DatasetOptions,
                                      doc="how the sequence is read (the CLI's dataset options)")
    io: IOConfig = setting(default_factory=IOConfig, doc="frame reading")
    compute: ComputeConfig = setting(default_factory=ComputeConfig, doc="numba kernels")
    preprocess: PreprocessConfig = setting(default_factory=PreprocessConfig, doc="depth preprocessing")
    icp: ICPConfig = setting(default_factory=_frame_to_model_icp, doc="frame-to-model ICP")
    render: RenderConfig = setting(default_factory=RenderConfig, doc="model rendering")
    fusion: FusionConfig = setting(default_factory=FusionConfig, doc="surfel fusion")
    map: MapConfig = setting(default_factory=MapConfig, doc="surfel map storage")
    tracking: TrackingConfig = setting(default_factory=TrackingConfig, doc="tracking policy")
    given_poses: GivenPosesConfig = setting(default_factory=GivenPosesConfig, doc="mapping with given poses")
    hybrid: HybridConfig = setting(default_factory=HybridConfig, doc="the hybrid tracker")
    sparse: SparseSlamConfig = setting(default_factory=SparseSlamConfig, doc="the sparse back end")
    orb: OrbConfig = setting(default_factory=OrbConfig, doc="the orb tracker")
    colour_registration: ColourRegistrationConfig = setting(default_factory=ColourRegistrationConfig,
                                                            doc="colour through a separate colour camera")
    map_reuse: MapReuseConfig = setting(default_factory=MapReuseConfig,
                                        doc="saving the map (map.npz) and localising in a saved one (--map)")

    @check
    def _tracker_registered(self) -> str | None:
        """tracker is one of the registered trackers (dense, orb, hybrid)."""
        trackers = [name for name in registered() if name != "given"]
        if trackers and self.tracker not in trackers:
            return f"tracker must be one of {', '.join(trackers)}, got {self.tracker!r}"
        return None

    @check
    def _pyramid_deep_enough(self) -> str | None:
        """[preprocess] pyramid_levels >= [icp] levels."""
        if self.preprocess.pyramid_levels < self.icp.levels:
            return (f"[preprocess] pyramid_levels ({self.preprocess.pyramid_levels}) must be >= [icp] levels "
                    f"({self.icp.levels})")
        return None


def relocalise_due(tracking: TrackingConfig, failures_in_a_row: int) -> bool:
    """Whether a frame after ``failures_in_a_row`` failed ones is relocalised (``[tracking] relocalise_after_failures``;
    0 = never)."""
    return 0 < tracking.relocalise_after_failures <= failures_in_a_row

