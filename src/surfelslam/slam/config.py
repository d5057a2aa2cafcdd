"""Every setting of a run: :class:`SlamConfig` gathers each subsystem's config (saved as ``config.toml``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from surfelslam.backend.dense_edges import DenseEdgeConfig
from surfelslam.backend.sparse_slam import (
    DepthOdometryConfig,
    SparseSlamConfig,
)
from surfelslam.config import check, setting
from surfelslam.datasets.base import DatasetOptions
from surfelslam.errors import ConfigError
from surfelslam.geometry.camera import ColourRegistrationConfig
from surfelslam.mapping.fusion import FusionConfig
from surfelslam.mapping.render import RenderConfig
from surfelslam.mapping.surfel_map import MapConfig
from surfelslam.tracking.geometric import GeometricGuessConfig
from surfelslam.tracking.icp import ICPConfig
from surfelslam.tracking.photometric import (
    PHOTOMETRIC_MODES,
)
from surfelslam.tracking.preprocess import (
    PreprocessConfig,
)


@dataclass
class IOConfig:
    """Reading.

    Attributes:
        prefetch_frames: frames decoded ahead in a background thread (0 = synchronous).
        prepare_in_reader: the reader thread also does the pipeline's frame-only work (``prepare``: depth
            pyramid, fusion colour, ORB features), overlapping it with the previous frame's map stages.
            Same results either way; needs ``prefetch_frames > 0``.
    """

    prefetch_frames: int = 3
    prepare_in_reader: bool = True


@dataclass
class ComputeConfig:
    """Numba kernels.

    Attributes:
        parallel_kernels: run the per-pixel kernels' ``parallel=True`` twins (bit-identical results, see
            :mod:`surfelslam.kernels.threads`) when numba has at least 2 threads. Off by default: on 2 cores
            the background frame reader needs the second core. Measured on 2 cores: ``surfelslam run`` on
            7-Scenes (200 frames, files decoded by the reader thread) 41 FPS serial vs 36-40 parallel;
            frames generated in memory (``benchmarks/bench_pipeline.py``, nothing to read) 30-34 serial vs
            41 parallel. Worth switching on with more cores, or when frames come from memory.
    """

    parallel_kernels: bool = False


def apply_compute(cfg: ComputeConfig) -> None:
    """Switch every dual kernel to the setting of ``cfg`` (process-wide)."""
    import numba

    from surfelslam.kernels import threads

    threads.set_parallel(cfg.parallel_kernels and numba.config.NUMBA_NUM_THREADS >= 2)


@dataclass
class TrackingConfig:
    """Frame-to-model tracking policy.

    Attributes:
        constant_velocity: predict each pose by repeating the last inter-frame motion (else: last pose).
        frame_to_frame_init: first register the frame to the previous frame (from the prediction), then
            refine against the model from there (costs one more ICP; helps under fast motion).
        max_failures_in_a_row_before_reset_velocity: after this many failed frames in a row the velocity is
            reset to zero (the prediction stops extrapolating).
        max_width_px: tracking (rendering the model and ICP) runs at the finest pyramid level of the input that
            is at most this wide (pixels); fusion has its own ``FusionConfig.max_width_px``. 640x480 input is tracked
            at its 2x2 block-averaged 320x240 level: the model is rendered at 320x240 (a quarter of the
            splatting work) and ICP sees the same number of points as at 320x240 input. 0 = always track at
            full resolution.
        photometric: ``auto | on | off``. On: ICP minimises the intensity difference between each frame pixel
            and the model's rendered colour jointly with the point-to-plane distances (ElasticFusion's joint
            ICP + RGB tracking; :mod:`surfelslam.tracking.photometric`, weights in ``icp.photometric_*``).
            Texture then holds the pose along directions the geometry leaves weak, where ICP slides.
            ``auto``: on unless colour and depth are not registered (``RGBDSequence.colour_registered``,
            e.g. 7-Scenes, where a depth pixel's colour belongs to another ray).
        relocalise_after_failures: once this many frames in a row failed, each further failed frame is
            relocalised from the depth alone: the shape-feature guess (:mod:`surfelslam.tracking.geometric`)
            between the frame and the map rendered at the last tracked pose, then ICP from it; on success the
            frame is tracked and fused (0: never). It costs about 0.2 s per attempt, paid only while lost. Synthetic
            room, slow orbit, 60 frames (2 s) dropped (78 cm and 36 deg): dense without it fails on every frame
            after the gap; with it, the fourth frame after the gap is tracked again, within 3 mm. The hybrid
            tracker uses it (rendered at its current pose) when its PnP relocalisation finds no pose (no texture).
        shape_guess: settings of that guess.
        fuse_weak_frames: a degenerate registration (one plane, two planes, a corridor) still gives the pose along
            the directions the view constrains, the prediction along the others (``icp.weak_direction_ratio``), and
            the frame is fused; off: such frames are refused, not fused, and the pose is the prediction.
        relocalise_max_speed_m_s, relocalise_max_rate_deg_s: a relocalised pose further from the last tracked pose
            than these speeds (m/s, deg/s) allow in the time since it, plus ``relocalise_slack_m`` (m) and
            ``relocalise_slack_deg`` (deg), is refused: a wrong match, not a camera motion.
    """

    constant_velocity: bool = True
    max_failures_in_a_row_before_reset_velocity: int = 3
    frame_to_frame_init: bool = False
    max_width_px: int = 320
    photometric: str = "auto"
    relocalise_after_failures: int = 3
    shape_guess: GeometricGuessConfig = field(default_factory=GeometricGuessConfig)
    fuse_weak_frames: bool = True
    relocalise_max_speed_m_s: float = 1.0
    relocalise_max_rate_deg_s: float = 120.0
    relocalise_slack_m: float = 0.1
    relocalise_slack_deg: float = 10.0

    def __post_init__(self) -> None:
        if self.relocalise_after_failures < 0:
            raise ConfigError(f"tracking: relocalise_after_failures must be >= 0, got {self.relocalise_after_failures}")
        if self.max_width_px < 0:
            raise ConfigError(f"tracking: max_width_px must be >= 0, got {self.max_width_px}")
        if self.photometric not in PHOTOMETRIC_MODES:
            raise ConfigError(f"tracking: photometric must be one of {', '.join(PHOTOMETRIC_MODES)}, "
                              f"got {self.photometric!r}")


@dataclass
class GivenPosesConfig:
    """Mapping with given poses: a frame takes the pose whose timestamp is nearest, within ``max_dt_s``."""

    max_dt_s: float = 0.02


JOINT_MODES = PHOTOMETRIC_MODES  # the same auto | on | off colour switch (tracking.photometric.colour_switch)


@dataclass
class HybridConfig:
    """Hybrid tracking policy (dense ICP + sparse back end).

    Attributes:
        pnp_retry: when ICP fails or is degenerate, retry ICP from the PnP pose against the last keyframe.
        pnp_when_velocity_untrusted: when the previous frame failed, start ICP from the PnP pose instead of
            the constant-velocity guess (falls back to the velocity guess when PnP is rejected).
        pnp_check: every frame, compare the ICP pose with the PnP pose against the last keyframe; when they
            differ by more than ``pnp_check_max_m`` or ``pnp_check_max_deg``, ICP is retried from the PnP pose,
            and a frame whose ICP still disagrees is not fused (ICP can slide along repetitive or weakly
            constrained geometry while reporting a well-conditioned system). Costs one ORB extraction + PnP.
        pnp_check_min_inlier_fraction: a difference beyond those bounds counts as a disagreement only if fewer
            than this fraction of the PnP inliers reproject within the PnP inlier bound
            (``sparse.features.reprojection_error_px``) under the ICP pose, i.e. the features contradict ICP
            (0 = the metric bounds alone). A PnP pose whose inliers all lie on one distant textured plane (a
            poster on a plain wall) is ambiguous between a small rotation and a sideways translation, and can be
            far off while the correct ICP pose explains its inliers as well: 6 cm / 1.2 deg off with 80 inliers at
            2.7-3.5 m in a synthetic plain-walled office (ICP 4 mm from the truth), where the metric bounds alone
            overruled ICP (hybrid 7.5 mm ATE, dense 2.1). ICP sliding along a wall moves the features by many
            pixels and is still caught.
        pnp_trust_min_inliers: a PnP pose with fewer inliers neither adds the joint feature term nor can overrule
            ICP in the PnP check (it still starts ICP again when ICP fails). With a handful of keypoints (cabinet
            corners against plain walls) RANSAC can settle on a wrong consensus: 8-20 inliers and 1-18 cm off in a
            synthetic plain-walled office, whose joint term doubled the hybrid's frame-to-frame error (ATE 3.92 mm
            against dense's 2.82; 3.45 with a bound of 20, 2.91 with 30). 30 is also ORB-SLAM's bar for a tracked
            frame.
        relocalise_after_failures: failed frames in a row after which the frame is relocalised against all
            keyframes (``SparseSlam.relocalise``) and ICP is started from that pose. 3, as the dense tracker's
            ``tracking.relocalise_after_failures`` (5 before 2026-11-27): after a 2 s gap in 7-Scenes (frames
            200-259 of 150-299 dropped, 44 cm and 10 deg) the PnP guess against the last keyframe is rejected
            as too large a motion, so the frames wait for relocalisation; with 3 the hybrid is back on its
            no-gap trajectory from frame 263, as dense (within 4 mm), instead of 265.
        loop_correction: apply pose-graph corrections to the dense trajectory and the surfel map.
        dense_odometry_sigma_m: sigma (m and rad) of the odometry edges between keyframes, which carry dense
            (ICP) poses: far more precise than PnP, so they get this sigma instead of
            ``sparse.graph.odometry_information`` (0 keeps the sparse setting). Against the refined loop edges'
            3 mm (``loop_icp.sigma_m``) it sets how far loops move the dense trajectory. 1 mm (2 mm before
            2026-11-27): the 640x480 room replay 0.39 -> 0.35 mm (dense 0.36, the one sequence where the hybrid was
            above dense), office replay 0.59 -> 0.52, 320x240 replays 0.61 / 1.08 / 0.66 -> 0.55 / 0.95 / 0.59 mm;
            orbits within +-0.02 mm except the 640x480 office fast orbit 0.37 -> 0.49 (dense 0.87), and where the
            dense odometry is biased (colour taken before depth) the loops correct less: 0.09 / 0.27 / 0.35 / 0.30
            -> 0.12 / 0.37 / 0.36 / 0.47 cm (dense 0.61 / 1.38 / 0.57 / 2.07). 0.5 mm took the orbits further up
            (640x480 fast 0.70 mm). 7-Scenes (refined edges untrusted) 2.48 cm either way (2.46 since the hybrid's
            pose arithmetic became dense's, 27 Nov).
        live_correction_min_m: during the run, the dense map and pose follow a graph optimisation only when a
            keyframe moved by more than this (m); smaller corrections are applied once, in ``finish``
            (re-posing the live map for centimetre corrections smears it and costs more than it helps).
        untrusted_min_correction_m: in ``finish``, when the refined edges are not trusted (their residuals say the
            depth is biased: real Kinect depth, a distorted sensor) and the poses come from the PnP edges' graph,
            its correction is applied only when some keyframe moves by more than this (m) relative to the first
            keyframe. The PnP edges' points come from the same biased depth and weigh as 0.1 m sigmas against
            the dense odometry's 1 mm, so without drift to remove the graph moves keyframes by a fraction of a
            millimetre, which left the ATE up or down by 0.01-0.02 mm at random (7-Scenes segments at 320x240:
            0.15-0.34 mm moves; hybrid 23.32 against dense 23.30 mm on frames 250-499, 16.88 against 16.90 on
            100-349). Below this the hybrid's trajectory is the dense one, to the last bit
            (``loop_correction_skipped`` in the metrics); 0 applies every correction. With ``loop_icp`` off no
            edge says whether the depth is biased, and every correction is applied: on unbiased synthetic depth the
            PnP edges' sub-millimetre corrections are real (room fast seed 1, 320x240: 3.14 mm with them, 3.37
            without, dense 3.5).
        loop_robust_scale_m: scale (m, of the loop edge's residual) of the Cauchy kernel on its loop edges
            (``sparse.graph.robust_kernel``); 0 keeps ``sparse.graph.robust_scale_sigma``. The loop edges'
            isotropic sigma is 0.1 m, so the sparse default (1 sigma) leaves them quadratic up to 10 cm, while
            a correct PnP loop edge is within a few millimetres: edges centimetres off are mostly wrong solutions
            on repeated texture, and at 3 cm they weigh a tenth at 9 cm. ATE (cm), 3 cm / 10 cm: a 500-frame replay
            of the 7-Scenes hand-held motion in the synthetic room 0.17 / 0.21 (dense 0.15), the same at 3x
            0.21 / 0.22 (dense 0.23); synthetic fast 0.14 / 0.12 (dense 0.35), slow 0.13 / 0.13, walking loop
            0.33 / 0.33, office replays 0.14 / 0.14, 7-Scenes 0-499 2.48 / 2.48.
        loop_icp: dense (ICP) refinement of the PnP keyframe edges (:mod:`surfelslam.backend.dense_edges`): 2-4x
            lower ATE on synthetic sequences; on 7-Scenes the refined edges are biased (2.48 -> 3.76 cm), which its
            trust gate detects (``max_trusted_residual_rad``), using the PnP edges instead (2.48 cm then; 2.4643
            with the shared pose arithmetic; now 2.4648 = dense, see ``untrusted_min_correction_m``).
        joint_features: ``auto | on | off``. On: track by joint dense + sparse optimisation: the PnP inliers
            against the reference keyframe (keyframe points, sub-pixel current pixels) add reprojection terms to
            every ICP iteration (:class:`~surfelslam.tracking.icp.ReprojectionTerm`). Texture then constrains the
            directions geometry leaves weak (a wall, a shelf front), where point-to-plane ICP slides. ``auto``:
            on unless the sequence's colour and depth are not registered (``RGBDSequence.colour_registered``,
            e.g. 7-Scenes): features there measure the colour camera, not the depth camera, and pull the pose
            off the depth data's optimum (7-Scenes 500 frames: 2.46 cm dense, 2.90 cm with the joint term).
        joint_sigma_px: pixel noise of those terms (residual unit).
        joint_huber: Huber threshold of their residual norm, in units of ``joint_sigma_px``.
        joint_weight: a feature residual of ``joint_sigma_px`` costs this many point-to-plane pairs with a
            residual of ``icp.finest_robust_scale_m``. 0.1 lets the few hundred features settle what geometry
            leaves weak while the tens of thousands of depth pairs keep the rest: weights 0.1 / 0.3 / 1 all rescued
            the synthetic cases where dense slides (0.25-0.79 cm vs 3-300 cm), and 0.1 moves the pose least where
            colour and depth disagree (7-Scenes with the term forced on: 1.87 / 1.90 / 1.99 cm, dense 1.85).
    """

    pnp_retry: bool = True
    pnp_when_velocity_untrusted: bool = True
    relocalise_after_failures: int = 3
    pnp_check: bool = True
    pnp_check_max_m: float = 0.05
    pnp_check_max_deg: float = 5.0
    pnp_check_min_inlier_fraction: float = 0.5
    pnp_trust_min_inliers: int = 30
    loop_correction: bool = True
    dense_odometry_sigma_m: float = 0.001
    live_correction_min_m: float = 0.03
    untrusted_min_correction_m: float = 0.001
    loop_robust_scale_m: float = 0.03
    loop_icp: DenseEdgeConfig = field(default_factory=DenseEdgeConfig)
    joint_features: str = "auto"
    joint_sigma_px: float = 1.0
    joint_huber: float = 2.0
    joint_weight: float = 0.1

    def __post_init__(self) -> None:
        if self.joint_features not in JOINT_MODES:
            raise ConfigError(f"hybrid: joint_features must be one of {', '.join(JOINT_MODES)}, "
                              f"got {self.joint_features!r}")
        for name in ("joint_sigma_px", "joint_huber"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"hybrid: {name} must be > 0, got {getattr(self, name)}")
        if not self.joint_weight >= 0:
            raise ConfigError(f"hybrid: joint_weight must be >= 0, got {self.joint_weight}")
        if not self.untrusted_min_correction_m >= 0:
            raise ConfigError(f"hybrid: untrusted_min_correction_m must be >= 0, got {self.untrusted_min_correction_m}")
        if not self.loop_robust_scale_m >= 0:
            raise ConfigError(f"hybrid: loop_robust_scale_m must be >= 0, got {self.loop_robust_scale_m}")
        if self.relocalise_after_failures < 1:
            raise ConfigError(f"hybrid: relocalise_after_failures must be >= 1, got {self.relocalise_after_failures}")


def _orb_loop_icp() -> DenseEdgeConfig:
    """The orb tracker's keyframe ICP: the hybrid's, with the PnP inliers weighing 3x more (``feature_weight``
    0.3) and no depth-only nearby edges (its odometry is keyframe ICP already: ``DenseEdgeConfig.depth_only_nearby``).

    Here the features are the odometry's main measurement, not a check on dense ICP's. ATE with weights 0.1 / 0.3 /
    1 (mm): textured office hand-held 0.82 / 0.48 / 0.26 (dense 0.45), plain-walled office replay 0.86 / 0.97 /
    1.19 (dense 1.47), plain room hand-held 1.85 / 1.00 / 0.73 (dense 2.97); 7-Scenes 0-499 (320x240) 36.51 / 36.18
    / 35.10 (dense 24.65). But where colour is taken before depth (``benchmarks/bench_hybrid.py``'s sequences: the
    features see another pose than the depth, as on TUM's unsynchronised Kinect) a heavy feature term pulls the
    pose off the depth's: room fast seed 0 0.30 / 0.66 / 2.88 cm (dense 1.38), seed 2 0.19 / 0.87 / 1.18 (dense
    2.07). 0.3 keeps the orb tracker within 1.1x dense on every synthetic sequence measured and below it there.
    """
    return DenseEdgeConfig(feature_weight=0.3, depth_only_nearby=False)


@dataclass
class OrbConfig:
    """Settings of the ``orb`` tracker beyond the shared sparse ones (``[sparse]``).

    Attributes:
        depth_odometry: frames registered to the reference keyframe by ICP on depth as well as by PnP
            (:class:`~surfelslam.backend.sparse_slam.DepthOdometryConfig`).
        loop_icp: the keyframes' depth store and ICP settings (used by ``depth_odometry`` too), and with
            ``loop_icp.enabled`` the dense refinement of keyframe edges behind its trust gate, as the hybrid's
            (:mod:`surfelslam.backend.dense_edges`): the refined edges are what bring the orb tracker below
            the dense one on synthetic depth (plain-walled office replay: 6.22 mm without them, 0.97 with; dense
            1.47), and the gate leaves them out on biased real depth (7-Scenes).
    """

    depth_odometry: DepthOdometryConfig = field(default_factory=DepthOdometryConfig)
    loop_icp: DenseEdgeConfig = field(default_factory=_orb_loop_icp)


@dataclass
class SlamConfig:
    """Every setting of a run, with its tracker and dataset options (``[dataset]``, the ``--start`` ...
    ``--depth-scale`` options; unset ones are left out): saved as ``config.toml``, the whole recipe of the run."""

    tracker: str = setting("dense", doc="The tracker: dense, orb or hybrid (the registered ones; --tracker).")
    dataset: DatasetOptions = field(default_factory=DatasetOptions)
    io: IOConfig = field(default_factory=IOConfig)
    compute: ComputeConfig = field(default_factory=ComputeConfig)
    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)
    icp: ICPConfig = field(default_factory=ICPConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    map: MapConfig = field(default_factory=MapConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    given_poses: GivenPosesConfig = field(default_factory=GivenPosesConfig)
    hybrid: HybridConfig = field(default_factory=HybridConfig)
    sparse: SparseSlamConfig = field(default_factory=SparseSlamConfig)
    orb: OrbConfig = field(default_factory=OrbConfig)
    colour_registration: ColourRegistrationConfig = field(default_factory=ColourRegistrationConfig)

    @check
    def _tracker_registered(self) -> str | None:
        """``tracker`` is one of the registered trackers (``dense``, ``orb``, ``hybrid``)."""
        from surfelslam.slam.protocol import registered  # the registry imports this module

        trackers = [name for name in registered() if name != "given"]
        if trackers and self.tracker not in trackers:
            return f"tracker must be one of {', '.join(trackers)}, got {self.tracker!r}"
        return None

    def __post_init__(self) -> None:
        if self.preprocess.pyramid_levels < self.icp.levels:
            raise ConfigError(
                f"config: preprocess.pyramid_levels ({self.preprocess.pyramid_levels}) must be >= icp.levels "
                f"({self.icp.levels})"
            )
