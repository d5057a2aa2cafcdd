"""The SLAM pipelines, as a list of stages.

Dense frame-to-model SLAM (:class:`DenseSlam`), per frame:

1. ``preprocess``: depth -> (2x2 block averaging down to the working level) -> optional bilateral filter ->
   vertex/normal pyramid (source).
2. ``predict``: constant-velocity guess of the new pose.
3. ``render``: the surfel map rendered at the previous pose -> vertex/normal pyramid (target).
4. ``track``: coarse-to-fine projective point-to-plane ICP, source -> target, from the prediction.
5. ``fuse``: on success, the frame is fused into the map at the tracked pose (merge, add, remove);
   on failure the frame is not fused, it is counted, and the pose is the prediction.
   ``relocalise``: after ``tracking.relocalise_after_failures`` failed frames in a row, a failed frame is
   registered to the map rendered at the last tracked pose from the shape-feature guess
   (:mod:`surfelslam.tracking.geometric`), and tracked and fused when ICP from it succeeds.

Working resolution: tracking (render + ICP) and fusion run at the finest pyramid level that is at most
``tracking.max_width_px`` / ``fusion.max_width_px`` wide (default 320 for both). 320x240 input is worked on
as it is; 640x480 input is first block-averaged 2x2 (which also halves the depth noise), so its map has the
density of a 320x240 map (one surfel per 2x2 input pixels; ~7 mm apart at 2 m, about Open3D's default
5.9 mm voxel) and a frame costs about what a 320x240 frame costs. Set both to 0 to work at full resolution
(a 4x denser map, about 4x the time).

Mapping with given poses (:class:`GivenPoseMapper`) runs ``preprocess`` and ``fuse`` only.

Sparse SLAM (:class:`OrbSlam`, tracker ``orb``) wraps :class:`surfelslam.backend.SparseSlam`: ORB/PnP
odometry against the last keyframe, loop closure, pose graph; the map is the voxel-filtered keyframe cloud
and the written trajectory is the optimised one.

Hybrid SLAM (:class:`HybridSlam`, tracker ``hybrid``) is dense SLAM with the sparse back end alongside:

1. ``match``: the frame is matched to the reference keyframe by PnP (``SparseSlam.match_reference_keyframe``):
   a pose and its inliers (keyframe points, sub-pixel pixels in the frame).
2. ``track``: ICP from the constant-velocity guess, as in dense SLAM, when the last step succeeded, jointly
   with the inliers' reprojection terms (``hybrid.joint_features``; off by default where colour and depth are
   not registered). When ICP fails (:func:`icp_failure`), reports degeneracy, or the velocity is not trusted
   (the last frame failed), the PnP pose becomes the initial guess: the map is rendered at that pose and ICP
   retried from it. After ``hybrid.relocalise_after_failures`` failed frames in a row,
   ``SparseSlam.relocalise`` (all keyframes) gives the guess instead, or, when it finds no pose, the shape
   guess of dense SLAM (against the map rendered at the current pose); on success fusing goes on.
   With ``hybrid.pnp_check`` every ICP pose is also compared with the PnP pose; one that disagrees is
   retried from the PnP pose and, if it still disagrees, the frame is not fused (ICP can slide along weakly
   constrained geometry while reporting a well-conditioned system).
3. ``sparse``: every tracked frame goes to ``SparseSlam.process(frame, T_world_cam_dense=pose)``, so
   keyframes carry dense poses and loop edges are verified by PnP between keyframes (in a background thread,
   applied at the next keyframe: ``sparse.background_loop_checks``).
4. ``correct``: loop edges move keyframes in the pose graph; the dense state follows. Choice made here:
   each frame is *anchored* to the last keyframe when it was processed, its pose kept as ``T_kf_cam``
   relative to that keyframe's pose *in the dense frame* (``T_kf_dense``, the ICP pose it was created
   with); each surfel is anchored to the anchor of the frame that created it (``first_seen`` -> anchor,
   a sorted frame-index table looked up with ``searchsorted``; surfels merged later keep their first
   anchor). A keyframe's correction is ``C_k = T_kf_graph inv(T_kf_dense)``. Dense poses are fed to the
   graph as ``C_last T_world_cam``, so odometry edges are exactly the dense relative motion whatever the
   pending correction. Corrections are applied to the surfels (positions and normals, one vectorised
   numpy step over all surfels, culling index rebuilt) and to the current pose during the run only when a
   keyframe moved by more than ``hybrid.live_correction_min_m`` (re-posing the live map for centimetre
   corrections smears it); otherwise once, in ``finish``. The written trajectory is every frame's
   ``T_kf_graph(final) T_kf_cam``.

Work that depends on the frame alone (the ``preprocess`` stage, the fusion colour image and, for the
trackers with a sparse part, ORB extraction) can be done ahead, in the reader thread: ``prepare(frame)``
returns a :class:`PreparedFrame` that ``process(frame, prepared)`` then uses instead of doing it again. The
results are the same either way (bit-identical trajectories); on 2 cores it overlaps that work with the
map stages of the previous frame. ``prepare`` may run in one other thread while ``process`` runs (it has
its own scratch buffers; pyramids come from a lock-protected pool).

Library code: no printing, no file reading (``write_map`` is the one output hook the CLI calls).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from surfelslam.backend.dense_edges import DenseEdgeConfig, DenseEdgeRefiner
from surfelslam.backend.sparse_slam import (
    DepthOdometryConfig,
    KeyframeMatch,
    SparseSlam,
    SparseSlamConfig,
    features_for_width,
)
from surfelslam.errors import ConfigError, GroundTruthError
from surfelslam.geometry import se3
from surfelslam.geometry.camera import ColourRegistrationConfig, colour_at_depth_pixels
from surfelslam.mapping.fusion import FusionConfig, fuse
from surfelslam.mapping.render import RenderConfig, render
from surfelslam.mapping.surfel_map import MapConfig, SurfelMap
from surfelslam.tracking.features import Features, on_occluding_contour, reprojection_inliers, reprojection_spread_px
from surfelslam.tracking.geometric import GeometricGuessConfig, geometric_guess
from surfelslam.tracking.icp import ICPConfig, ICPResult, ReprojectionTerm, icp, icp_failure, photometric_term
from surfelslam.tracking.photometric import (
    PHOTOMETRIC_MODES,
    IntensityPyramid,
    PhotometricTerm,
    colour_switch,
    intensity_from_rgb,
    intensity_pyramid,
)
from surfelslam.tracking.preprocess import (
    FramePyramid,
    PreprocessConfig,
    Preprocessor,
    level_for_width,
    pyramid_from_maps,
)
from surfelslam.types import ColourCamera, Intrinsics, PoseArray, RGBDFrame, Trajectory

TRACKERS = ("dense", "orb", "hybrid")


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
    """

    constant_velocity: bool = True
    max_failures_in_a_row_before_reset_velocity: int = 3
    frame_to_frame_init: bool = False
    max_width_px: int = 320
    photometric: str = "auto"
    relocalise_after_failures: int = 3
    shape_guess: GeometricGuessConfig = field(default_factory=GeometricGuessConfig)

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
    """Every setting of a run; saved as ``config.toml`` next to the outputs."""

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

    def __post_init__(self) -> None:
        if self.preprocess.pyramid_levels < self.icp.levels:
            raise ConfigError(
                f"config: preprocess.pyramid_levels ({self.preprocess.pyramid_levels}) must be >= icp.levels "
                f"({self.icp.levels})"
            )


@dataclass
class FrameResult:
    """What the pipeline did with one frame."""

    index: int
    timestamp: float
    T_world_cam: np.ndarray
    tracked: bool
    fused: bool
    reason: str | None
    timings_ms: dict[str, float]
    map_points: int
    icp: ICPResult | None = None


@dataclass
class PreparedFrame:
    """Per-frame work that needs the frame alone, done ahead of :meth:`process` (see the module docstring).

    Attributes:
        frame: the frame it was prepared from (``process`` checks it is given the same object).
        pyramid: the source vertex/normal pyramid (a pool buffer, owned by the pipeline from then on), or
            ``None`` for trackers without one.
        rgb_fuse: ``(h, w, 3)`` uint8 colour at the fusion level, or ``None``.
        features: ORB features of the frame (trackers with a sparse part), or ``None``.
        timings_ms: wall ms per stage spent preparing (reported as that stage's time).
        cpu_ms: CPU time of the preparing thread for this frame (ms).
        intensity: the frame's intensity pyramid at the tracking level (photometric tracking), or ``None``.
    """

    frame: RGBDFrame
    pyramid: FramePyramid | None = None
    rgb_fuse: np.ndarray | None = None
    features: Features | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    cpu_ms: float = 0.0
    intensity: IntensityPyramid | None = None


def _prepared_for(frame: RGBDFrame, prepared: PreparedFrame | None) -> PreparedFrame | None:
    """``prepared`` when it was made from this very frame, else ``None`` (the work is then done in ``process``)."""
    return prepared if prepared is not None and prepared.frame is frame else None


@dataclass
class SlamResult:
    """End of a run: the map and summary numbers (the per-frame poses were already streamed)."""

    map_points: int
    metrics: dict
    surfel_map: SurfelMap | None = None
    trajectory_override: Trajectory | None = None
    loop_stamps: list[tuple[float, float]] | None = None
    points_xyz: np.ndarray | None = None  # (M, 3) float32 world points (sparse map), when there is no surfel map
    points_rgb: np.ndarray | None = None  # (M, 3) uint8

    def map_arrays(self) -> dict[str, np.ndarray] | None:
        if self.surfel_map is None:
            if self.points_xyz is None:
                return None
            n = len(self.points_xyz)
            return {"position": self.points_xyz, "normal": np.zeros((n, 3), np.float32),
                    "colour": self.points_rgb.astype(np.float32), "confidence": np.ones(n, np.float32),
                    "first_seen": np.zeros(n, np.int32)}
        m = self.surfel_map
        return {"position": m.position, "normal": m.normal, "colour": m.colour,
                "confidence": m.confidence, "first_seen": m.first_seen}

    def write_map(self, path: str | Path) -> None:
        if self.surfel_map is not None:
            from surfelslam.io.ply import write_ply

            write_ply(path, self.surfel_map)
        elif self.points_xyz is not None:
            from surfelslam.io.ply import write_points_ply

            write_points_ply(path, self.points_xyz, self.points_rgb)


class _Timer:
    def __init__(self, prepared: PreparedFrame | None = None) -> None:
        self.ms: dict[str, float] = {} if prepared is None else dict(prepared.timings_ms)
        self._t = time.perf_counter()

    def lap(self, stage: str | None) -> None:
        """Add the time since the last lap to ``stage`` (``None``: not counted)."""
        now = time.perf_counter()
        if stage is None:
            self._t = now
            return
        self.ms[stage] = self.ms.get(stage, 0.0) + (now - self._t) * 1e3
        self._t = now


class _FusingMapper:
    """What the dense pipelines share: preprocessing into reused buffers, and fusion into a surfel map."""

    def __init__(self, intr: Intrinsics, cfg: SlamConfig, min_levels: int = 1, track_level: int | None = None,
                 colour_camera: ColourCamera | None = None):
        apply_compute(cfg.compute)
        self.intr = intr
        self.cfg = cfg
        # a separate colour camera (colour not registered to depth): the map's colours are sampled through it
        self.colour_camera = colour_camera
        self.fuse_level = level_for_width(intr.width, cfg.fusion.max_width_px)
        levels = max(cfg.preprocess.pyramid_levels, min_levels, self.fuse_level + 1)
        self.pre = Preprocessor(intr, replace(cfg.preprocess, pyramid_levels=levels))
        self._pre_ahead: Preprocessor | None = None  # the preparing thread's own (scratch buffers)
        self._pool: list[FramePyramid] = []  # free source pyramids (grows to what is in flight, then reused)
        self._pool_lock = threading.Lock()
        # finer pyramid levels are never used, so never computed
        self.first_level = self.fuse_level if track_level is None else min(self.fuse_level, track_level)
        self.source = self._acquire()
        self.previous: FramePyramid | None = None  # the last frame's pyramid (kept, not copied)
        self._rgb_fuse: np.ndarray | None = None  # the prepared fusion colour of the current frame
        self.map = SurfelMap(cfg.map)
        self.n_fused = 0

    def _acquire(self) -> FramePyramid:
        with self._pool_lock:
            if self._pool:
                return self._pool.pop()
        return self.pre.new_pyramid()

    def _release(self, pyr: FramePyramid | None) -> None:
        if pyr is not None:
            with self._pool_lock:
                self._pool.append(pyr)

    def _check_size(self, frame: RGBDFrame) -> None:
        if frame.depth_m.shape != self.intr.shape:
            raise ConfigError(
                f"frame {frame.index}: depth is {frame.depth_m.shape[1]}x{frame.depth_m.shape[0]}, "
                f"expected {self.intr.width}x{self.intr.height}"
            )

    def _fuse_rgb(self, frame: RGBDFrame) -> np.ndarray:
        rgb = frame_colour_at_depth(frame, self.intr, self.colour_camera, self.cfg.colour_registration)
        return rgb if self.fuse_level == 0 else block_average_rgb(rgb, self.fuse_level)

    def prepare(self, frame: RGBDFrame) -> PreparedFrame:
        """The frame-only work of :meth:`process`, for another thread to do ahead (one such thread at a time).

        Raises what :meth:`process` would raise for this frame (e.g. :class:`ConfigError` for a wrong size).
        """
        c0, t0 = time.thread_time(), time.perf_counter()
        self._check_size(frame)
        if self._pre_ahead is None:
            self._pre_ahead = Preprocessor(self.intr, self.pre.cfg)
        pyr = self._acquire()
        self._pre_ahead.process(frame.depth_m, out=pyr, first_level=self.first_level)
        rgb = self._fuse_rgb(frame)
        ms = {"preprocess": (time.perf_counter() - t0) * 1e3}
        return PreparedFrame(frame, pyr, rgb, None, ms, (time.thread_time() - c0) * 1e3)

    def discard(self, prepared: PreparedFrame | None) -> None:
        """A prepared frame that will not be processed (skipped): its pyramid goes back to the pool."""
        if prepared is not None and prepared.pyramid is not None:
            self._release(prepared.pyramid)
            prepared.pyramid = None

    def _preprocess(self, frame: RGBDFrame, prepared: PreparedFrame | None = None) -> FramePyramid:
        """Make the frame's pyramid the current source (the prepared one, or computed here)."""
        prepared = _prepared_for(frame, prepared)
        if prepared is not None and prepared.pyramid is not None:
            self.source, prepared.pyramid = prepared.pyramid, None
            self._rgb_fuse = prepared.rgb_fuse
            return self.source
        self._check_size(frame)
        if self.source is self.previous:
            self.source = self._acquire()
        self._rgb_fuse = None
        return self.pre.process(frame.depth_m, out=self.source, first_level=self.first_level)

    def _retire_source(self) -> None:
        """End of a frame: its pyramid becomes ``previous``; the one before goes back to the pool."""
        if self.previous is not self.source:
            self._release(self.previous)
        self.previous = self.source

    def _fuse(self, frame: RGBDFrame, T_world_cam: np.ndarray) -> None:
        lvl = self.source[self.fuse_level]
        rgb = self._rgb_fuse if self._rgb_fuse is not None else self._fuse_rgb(frame)
        fuse(self.map, lvl.vertex, lvl.normal, rgb, T_world_cam, lvl.intrinsics, frame.index, self.cfg.fusion)
        self.n_fused += 1

    def warmup(self) -> None:
        """Compile (or load from numba's cache) every kernel on a tiny synthetic scene; excluded from FPS."""
        warm_up(self.cfg)

    def _result(self, extra: dict) -> SlamResult:
        self.map.compact()
        return SlamResult(self.map.n_alive, {"frames_fused": self.n_fused, **extra}, self.map)


class DenseSlam(_FusingMapper):
    """Frame-to-model dense SLAM: track each frame against the map rendered at the previous pose, then fuse.

    ``colour_registered``: the sequence's colour and depth pixels see the same rays (``tracking.photometric``).
    ``colour_camera``: the sequence's separate colour camera, if known (the map's colours are sampled through it).
    """

    def __init__(self, intr: Intrinsics, cfg: SlamConfig, colour_registered: bool = True,
                 colour_camera: ColourCamera | None = None):
        mode = cfg.tracking.photometric
        self.photometric = cfg.icp.photometric_weight > 0 and colour_switch(mode, colour_registered)
        self._src_intensity: IntensityPyramid | None = None
        self._tgt_intensity: IntensityPyramid | None = None
        self.track_level = level_for_width(intr.width, cfg.tracking.max_width_px)
        super().__init__(intr, cfg, min_levels=self.track_level + cfg.icp.levels, track_level=self.track_level,
                         colour_camera=colour_camera)
        track_intr = self.pre.level_intrinsics[self.track_level]
        self.target = FramePyramid.empty(track_intr, len(self.pre.level_intrinsics) - self.track_level)
        self.T_world_cam: np.ndarray | None = None
        self.T_world_last_tracked: np.ndarray | None = None  # pose of the last tracked (fused) frame
        self.velocity = np.eye(4)  # T_prev_cur of the last good step
        self.failures = 0
        self.failures_in_a_row = 0
        self.failure_reasons: dict[str, int] = {}
        self.relocalisations = {"tried": 0, "tracked": 0}

    def predict(self) -> np.ndarray:
        """Constant-velocity prediction of ``T_world_cam`` for the next frame."""
        assert self.T_world_cam is not None
        if not self.cfg.tracking.constant_velocity:
            return self.T_world_cam.copy()
        return self.T_world_cam @ self.velocity

    def render_target(self, T_world_cam: np.ndarray) -> FramePyramid:
        """The map rendered at ``T_world_cam`` at the tracking resolution, straight into the target pyramid's
        level 0 (geometry, and the intensity pyramid of the rendered colour when tracking photometrically)."""
        lvl0 = self.target[0]
        view = render(self.map, T_world_cam, lvl0.intrinsics, self.cfg.render, vertex_out=lvl0.vertex,
                      normal_out=lvl0.normal, attributes=self.photometric)
        if self.photometric:
            self._tgt_intensity = intensity_pyramid(intensity_from_rgb(view.colour, view.valid), self.cfg.icp.levels,
                                                    gradients=True)
        return pyramid_from_maps(view.vertex_cam, view.normal_cam, lvl0.intrinsics, len(self.target),
                                 self.cfg.preprocess, out=self.target)

    def source_intensity(self, frame: RGBDFrame) -> IntensityPyramid:
        """The frame's intensity pyramid on the tracking levels' grid (2x2 block means down to the tracking
        level, then ``icp.levels`` levels)."""
        pyr = intensity_pyramid(intensity_from_rgb(frame.rgb), self.track_level + self.cfg.icp.levels,
                                gradients=False)
        return IntensityPyramid(pyr.intensity[self.track_level:])

    def prepare(self, frame: RGBDFrame) -> PreparedFrame:
        """Preprocessing (and the intensity pyramid when tracking photometrically), for another thread."""
        p = super().prepare(frame)
        if self.photometric:
            t0 = time.perf_counter()
            p.intensity = self.source_intensity(frame)
            p.timings_ms["preprocess"] += (time.perf_counter() - t0) * 1e3
        return p

    def _set_source_intensity(self, frame: RGBDFrame, prepared: PreparedFrame | None) -> None:
        if not self.photometric:
            return
        p = _prepared_for(frame, prepared)
        self._src_intensity = p.intensity if p is not None and p.intensity is not None else \
            self.source_intensity(frame)

    def photometric_term(self) -> PhotometricTerm | None:
        """The joint photometric term of the current source against the last rendered target (or ``None``)."""
        if not self.photometric or self._src_intensity is None or self._tgt_intensity is None:
            return None
        return photometric_term(self._src_intensity, self._tgt_intensity, self.cfg.icp)

    @property
    def track_source(self) -> FramePyramid:
        """The current frame's pyramid from the tracking level down (what ICP registers)."""
        return self._at_track_level(self.source)

    def _at_track_level(self, pyr: FramePyramid) -> FramePyramid:
        """The levels of ``pyr`` from the tracking level down (views, no copy)."""
        return FramePyramid(pyr.levels[self.track_level:])

    def process(self, frame: RGBDFrame, prepared: PreparedFrame | None = None) -> FrameResult:
        """Track ``frame`` and fuse it; ``prepared``: optional :meth:`prepare` output for this frame."""
        t = _Timer(prepared)
        self._preprocess(frame, prepared)
        self._set_source_intensity(frame, prepared)
        t.lap("preprocess" if prepared is None else None)
        if self.T_world_cam is None:  # the first frame defines the world frame
            self.T_world_cam = np.eye(4)
            self.T_world_last_tracked = self.T_world_cam.copy()
            self._fuse(frame, self.T_world_cam)
            t.lap("fuse")
            self._retire_source()
            return FrameResult(frame.index, frame.timestamp, self.T_world_cam.copy(), True, True, None, t.ms,
                               self.map.n_alive)
        T_prev = self.T_world_cam
        T_pred = self.predict()
        T_init = se3.orthonormalize(se3.invert(T_prev) @ T_pred)
        target = self.render_target(T_prev)
        t.lap("render")
        if self.cfg.tracking.frame_to_frame_init:
            f2f = icp(self.track_source, self._at_track_level(self.previous), T_init=T_init,
                      cfg=self.cfg.icp)
            if icp_failure(f2f) is None:
                T_init = f2f.T_target_source
        res = icp(self.track_source, target, T_init=T_init, cfg=self.cfg.icp, photometric=self.photometric_term())
        t.lap("icp")
        failure = icp_failure(res)
        T_ref = T_prev
        n_reloc = self.cfg.tracking.relocalise_after_failures
        if failure is not None and n_reloc > 0 and self.failures_in_a_row >= n_reloc:
            found = self._relocalise_shape()
            t.lap("relocalise")
            if found is not None:
                res, failure, T_ref = found[0], None, found[1]
        if failure is None:
            step, T_new = self._step_and_pose(T_ref, res)
            self.velocity = step if T_ref is T_prev else np.eye(4)  # a relocalised frame has no known velocity
            self.T_world_last_tracked = T_new.copy()
            self.failures_in_a_row = 0
            self._fuse(frame, T_new)
            t.lap("fuse")
        else:
            T_new = T_pred
            self.failures += 1
            self.failures_in_a_row += 1
            self.failure_reasons[failure] = self.failure_reasons.get(failure, 0) + 1
            if self.failures_in_a_row >= self.cfg.tracking.max_failures_in_a_row_before_reset_velocity:
                self.velocity = np.eye(4)
        self.T_world_cam = T_new
        self._retire_source()
        return FrameResult(frame.index, frame.timestamp, T_new.copy(), failure is None, failure is None,
                           res.reason, t.ms, self.map.n_alive, res)

    @staticmethod
    def _step_and_pose(T_ref: np.ndarray, res: ICPResult) -> tuple[np.ndarray, np.ndarray]:
        """``(step, T_world_cam)``: the ICP motion ``res.T_target_source`` re-projected onto SE(3) and the pose it
        gives from the render pose ``T_ref`` (both ``(4, 4)``). One formula for the dense and the hybrid
        trackers, so that their trajectories agree to the last bit where the hybrid adds nothing (real-data
        tracking amplifies rounding differences to about 0.5 % ATE)."""
        step = se3.orthonormalize(res.T_target_source)
        return step, se3.orthonormalize(T_ref @ step)

    def _relocalise_shape(self, T_world_render: np.ndarray | None = None) -> tuple[ICPResult, np.ndarray] | None:
        """The current source against the map rendered at ``T_world_render`` (default: the last tracked pose),
        from the shape-feature guess: ``(ICP result, T_world_render)`` when ICP from the guess succeeds, else
        ``None``."""
        self.relocalisations["tried"] += 1
        T_ref = self.T_world_last_tracked if T_world_render is None else T_world_render
        target = self.render_target(T_ref)
        src = self.track_source
        g = geometric_guess(src[0].vertex, src[0].normal, target[0].vertex, target[0].normal,
                            self.cfg.tracking.shape_guess)
        if g.T_target_source is None:
            return None
        res = icp(src, target, T_init=g.T_target_source, cfg=self.cfg.icp, photometric=self.photometric_term())
        if icp_failure(res) is not None:
            return None
        self.relocalisations["tracked"] += 1
        return res, T_ref

    def finish(self) -> SlamResult:
        return self._result({"tracking_failures": self.failures, "tracking_failure_reasons": self.failure_reasons,
                             "relocalisations_tried": self.relocalisations["tried"],
                             "relocalisations": self.relocalisations["tracked"],
                             "photometric": self.photometric})


def frame_colour_at_depth(frame: RGBDFrame, intr: Intrinsics, cam: ColourCamera | None,
                          cfg: ColourRegistrationConfig) -> np.ndarray:
    """``(H, W, 3)`` uint8 colour of each depth pixel: ``frame.rgb`` itself, or sampled through ``cam`` (when given
    and ``cfg.enabled``)."""
    if cam is None or not cfg.enabled:
        return frame.rgb
    return colour_at_depth_pixels(frame.rgb, frame.depth_m, intr, cam, cfg.fallback_depth_m)


def block_average_rgb(rgb: np.ndarray, levels: int) -> np.ndarray:
    """``(H, W, 3)`` uint8 colour averaged over ``2^levels`` square blocks, matching the pyramid's geometry
    (an odd last row / column is dropped at each halving)."""
    for _ in range(levels):
        h, w = rgb.shape[0] // 2, rgb.shape[1] // 2
        rgb = cv2.resize(rgb[: 2 * h, : 2 * w], (w, h), interpolation=cv2.INTER_AREA)
    return rgb


_WARMUP_INTRINSICS = Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)


def warm_up(cfg: SlamConfig) -> None:
    """Run two frames of a tilted-plane-and-bump scene through a throwaway :class:`DenseSlam`.

    Numba compiles for argument types, not sizes, so a 64x48 frame compiles everything a real run uses.
    """
    intr = _WARMUP_INTRINSICS
    v, u = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float32)
    depth = 1.5 + 0.004 * u + 0.002 * v + 0.1 * np.exp(-((u - 32) ** 2 + (v - 24) ** 2) / 60.0)
    rgb = np.zeros((intr.height, intr.width, 3), np.uint8)
    slam = DenseSlam(intr, cfg)
    for i in range(2):
        slam.process(RGBDFrame(i, i / 30.0, rgb, depth.astype(np.float32)))


class GivenPoseMapper(_FusingMapper):
    """Fuse frames at given poses (ground truth or a trajectory file); no tracking."""

    def process(self, frame: RGBDFrame, T_world_cam: np.ndarray, prepared: PreparedFrame | None = None
                ) -> FrameResult:
        t = _Timer(prepared)
        self._preprocess(frame, prepared)
        t.lap("preprocess" if prepared is None else None)
        self._fuse(frame, T_world_cam)
        t.lap("fuse")
        self._retire_source()
        return FrameResult(frame.index, frame.timestamp, np.asarray(T_world_cam).copy(), True, True, None, t.ms,
                           self.map.n_alive)

    def finish(self) -> SlamResult:
        return self._result({})


def _sparse_metrics(sparse: SparseSlam, res) -> dict:
    return {
        "keyframes": int(len(res.keyframe_indices)),
        "loops_found": len(res.loops_found),
        "loops_accepted": len(res.loops_accepted),
        "nearby_edges": int(res.n_nearby_edges),
        "reinitialisations": int(sparse.n_reinitialisations),
        "segments_merged": int(sparse.n_segments_merged),
        "lost_frames_placed": int(sparse.n_lost_placed),
        "sparse_rejected": dict(res.rejected),
        "edges_dense_refined": int(sparse.n_dense_refined),
        "edges_dense_rejected": int(sparse.n_dense_rejected),
        "edge_sigma_m": sparse.dense_edge_sigma_m,
        "edge_spread_m": sparse.dense_edge_spread_m,
        "edges_refined_trusted": sparse.dense_edges_trusted,
        "edge_residual_rad": sparse.dense_edge_residual_rad,
        "depth_only_edges": sparse.n_depth_only_edges,
    }


def _loop_stamps(res, stamp_of_frame: dict[int, float]) -> list[tuple[float, float]]:
    kf_frames = res.keyframe_indices
    return [(stamp_of_frame[int(kf_frames[i])], stamp_of_frame[int(kf_frames[j])]) for i, j, _ in res.loops_accepted]


class OrbSlam:
    """Tracker ``orb``: :class:`SparseSlam` behind the pipeline interface (``process`` / ``finish`` / ``warmup``).

    No surfel map: the map is the voxel-filtered keyframe cloud, and the trajectory written at the end is
    the pose-graph-optimised one (``SlamResult.trajectory_override``). With ``orb.depth_odometry`` (default) each
    frame's depth is registered to the reference keyframe's as well, and with ``orb.loop_icp`` the keyframe
    edges are refined by ICP behind a trust gate (:class:`OrbConfig`).
    """

    def __init__(self, intr: Intrinsics, cfg: SlamConfig, colour_camera: ColourCamera | None = None):
        self.intr = intr
        self.cfg = cfg
        cloud_rgb = None if colour_camera is None else partial(frame_colour_at_depth, intr=intr, cam=colour_camera,
                                                               cfg=cfg.colour_registration)
        oc = cfg.orb
        store = None
        if oc.loop_icp.enabled or oc.depth_odometry.enabled:  # the keyframes' depth is kept for either
            store = DenseEdgeRefiner(intr, cfg.preprocess, oc.loop_icp)
        self.sparse = SparseSlam(intr, cfg.sparse, cloud_rgb=cloud_rgb, edge_refiner=store,
                                 refine_edges=oc.loop_icp.enabled, depth_odometry=oc.depth_odometry)
        self._stamp_of_frame: dict[int, float] = {}
        self.failures = 0
        self.relocalisations = 0

    def warmup(self) -> None:
        """Compile the preprocessing and ICP kernels when depth is used (else nothing: OpenCV and gtsam are
        precompiled)."""
        if self.sparse.uses_depth or self.cfg.orb.loop_icp.enabled:
            warm_up(self.cfg)

    def prepare(self, frame: RGBDFrame) -> PreparedFrame:
        """ORB extraction and the depth pyramid, for another thread to do ahead (see :meth:`DenseSlam.prepare`)."""
        c0, t0 = time.thread_time(), time.perf_counter()
        feats = self.sparse.features(frame)
        t1 = time.perf_counter()
        timings = {"orb_extract": (t1 - t0) * 1e3}
        pyr = self.sparse.depth_pyramid(frame)
        if pyr is not None:
            timings["preprocess"] = (time.perf_counter() - t1) * 1e3
        return PreparedFrame(frame, pyramid=pyr, features=feats, timings_ms=timings,
                             cpu_ms=(time.thread_time() - c0) * 1e3)

    def process(self, frame: RGBDFrame, prepared: PreparedFrame | None = None) -> FrameResult:
        t = _Timer(prepared)
        p = _prepared_for(frame, prepared)
        feats = None if p is None else p.features
        r = self.sparse.process(frame, feats=feats, depth_pyramid=None if p is None else p.pyramid)
        t.lap("orb")
        self._stamp_of_frame[frame.index] = frame.timestamp
        if not r.ok:
            self.failures += 1
        self.relocalisations += int(r.relocalised)
        return FrameResult(frame.index, frame.timestamp, r.T_world_cam.copy(), r.ok or r.relocalised, False,
                           r.reason, t.ms, self.sparse.n_keyframes)

    def finish(self) -> SlamResult:
        res = self.sparse.finish()
        metrics = {"tracking_failures": self.failures,
                   "tracking_failure_reasons": dict(res.rejected),
                   "relocalisations": self.relocalisations,
                   "depth_odometry": dict(self.sparse.depth_counts) if self.sparse.uses_depth else None,
                   **_sparse_metrics(self.sparse, res)}
        return SlamResult(len(res.map_xyz), metrics, None, trajectory_override=res.trajectory,
                          loop_stamps=_loop_stamps(res, self._stamp_of_frame),
                          points_xyz=res.map_xyz, points_rgb=res.map_rgb)


class HybridSlam(DenseSlam):
    """Tracker ``hybrid``: dense frame-to-model SLAM + PnP guesses, relocalisation and loop correction.

    See the module docstring for the stages and the map-correction scheme.
    """

    def __init__(self, intr: Intrinsics, cfg: SlamConfig, colour_registered: bool = True,
                 colour_camera: ColourCamera | None = None):
        super().__init__(intr, cfg, colour_registered, colour_camera)
        mode = cfg.hybrid.joint_features
        self.joint = colour_switch(mode, colour_registered)
        # dense odometry edges carry no estimated information: every edge weighs isotropically here, so the
        # PnP loop edges' Hessians never outweigh the (more accurate) dense odometry by their scale alone
        sp = replace(cfg.sparse, graph=replace(cfg.sparse.graph, edge_information="isotropic"))
        # its PnP poses only guess or check ICP's: the PnP inlier bound stays as given at every width (scaled as for
        # the orb tracker, 640x480 7-Scenes went from dense's 25.06 to 25.32 mm: more PnP poses past the check)
        sp = replace(sp, features_reference_width_px=0)
        # nor does it drop the keypoints on occluding contours from the sparse side (features.depth_edge_rel: with
        # them off there its refined keyframe edges lost 1-10 % on synthetic sequences); its joint term leaves them
        # out instead (_pnp_match)
        self._contour_cfg = features_for_width(cfg.sparse, intr.width).features
        sp = replace(sp, features=replace(sp.features, depth_edge_rel=0.0))
        if cfg.hybrid.dense_odometry_sigma_m > 0:
            sp = replace(sp, graph=replace(sp.graph, odometry_information=cfg.hybrid.dense_odometry_sigma_m ** -2))
        refiner, refined_scale = None, None
        if cfg.hybrid.loop_icp.enabled:  # ICP-refined keyframe edges carry a tight sigma (see dense_edges)
            refiner = DenseEdgeRefiner(intr, cfg.preprocess, cfg.hybrid.loop_icp)
        if cfg.hybrid.loop_robust_scale_m > 0:  # the kernel's scale is in whitened units (loop sigmas)
            scale = cfg.hybrid.loop_robust_scale_m * np.sqrt(sp.graph.loop_information)
            sp = replace(sp, graph=replace(sp.graph, robust_scale_sigma=float(scale)))
            refined_scale = cfg.hybrid.loop_robust_scale_m / cfg.hybrid.loop_icp.sigma_m
        self.sparse = SparseSlam(intr, sp, edge_refiner=refiner, refined_robust_scale=refined_scale)
        self._kf_dense = PoseArray()  # keyframe poses in the dense (tracking and map) frame
        self._stamps: list[float] = []
        self._anchor: list[int] = []  # per frame: anchor keyframe (-1: before any keyframe, never happens)
        self._T_kf_cam: list[np.ndarray] = []
        self._fused_frames: list[int] = []  # frame index of each fused frame (increasing)
        self._fused_anchor: list[int] = []
        self._stamp_of_frame: dict[int, float] = {}
        self._feats: Features | None = None  # the current frame's ORB features (extracted at most once)
        self.counts = {"pnp_guesses_tried": 0, "pnp_guesses_tracked": 0, "relocalisations_tried": 0,
                       "relocalisations_tracked": 0, "map_corrections": 0,
                       "pnp_disagreements": 0, "loop_correction_skipped": 0}

    def prepare(self, frame: RGBDFrame) -> PreparedFrame:
        """Preprocessing and ORB extraction, for another thread to do ahead (see :meth:`DenseSlam.prepare`)."""
        p = super().prepare(frame)
        c0, t0 = time.thread_time(), time.perf_counter()
        p.features = self.sparse.features(frame)
        p.timings_ms["orb_extract"] = (time.perf_counter() - t0) * 1e3
        p.cpu_ms += (time.thread_time() - c0) * 1e3
        return p

    def _features(self, frame: RGBDFrame) -> Features:
        """The current frame's ORB features: the prepared ones, else extracted once here."""
        if self._feats is None:
            self._feats = self.sparse.features(frame)
        return self._feats

    def _icp_from(self, T_render: np.ndarray, T_init_rel: np.ndarray, match: KeyframeMatch | None = None):
        """ICP of the current source against the map rendered at ``T_render``, jointly with ``match``'s
        reprojection terms when ``hybrid.joint_features`` is on; returns (res, failure, T)."""
        target = self.render_target(T_render)
        term = self._reprojection_term(T_render, match)
        res = icp(self.track_source, target, T_init=se3.orthonormalize(T_init_rel), cfg=self.cfg.icp,
                  reprojection=term, photometric=self.photometric_term())
        return res, icp_failure(res), self._step_and_pose(T_render, res)[1]

    def _reprojection_term(self, T_render: np.ndarray, match: KeyframeMatch | None) -> ReprojectionTerm | None:
        h = self.cfg.hybrid
        if match is None or not self.joint or h.joint_weight == 0 or not self._trusted(match):
            return None
        pts_t = se3.transform_points(se3.invert(T_render), match.points_world)
        sigma = max(h.joint_sigma_px, self._match_spread_px(match))
        return ReprojectionTerm(pts_t, match.uv_cur, self.intr, sigma, h.joint_huber,
                                h.joint_weight * self.cfg.icp.finest_robust_scale_m ** 2)

    def _match_spread_px(self, match: KeyframeMatch) -> float:
        """Robust spread (px) of the inliers' reprojection residuals at the PnP pose: the data's own pixel noise
        (larger where colour and depth are misregistered or keypoints are poorly localised)."""
        X = se3.transform_points(se3.invert(match.T_world_cam), match.points_world)
        return reprojection_spread_px(X, match.uv_cur, self.intr)

    def process(self, frame: RGBDFrame, prepared: PreparedFrame | None = None) -> FrameResult:
        h = self.cfg.hybrid
        t = _Timer(prepared)
        p = _prepared_for(frame, prepared)
        self._feats = None if p is None else p.features
        self._preprocess(frame, prepared)
        self._set_source_intensity(frame, prepared)
        t.lap("preprocess" if prepared is None else None)
        self._stamp_of_frame[frame.index] = frame.timestamp
        if self.T_world_cam is None:
            T_new = np.eye(4)
            self._fuse(frame, T_new)
            t.lap("fuse")
            self._after_tracking(frame, T_new, True, t)
            self._retire_source()
            return FrameResult(frame.index, frame.timestamp, self.T_world_cam.copy(), True, True, None, t.ms,
                               self.map.n_alive)
        T_prev = self.T_world_cam
        T_pred = self.predict()
        res = failure = T_new = None
        guess = None
        from_prev = False  # whether the accepted ``res`` was tracked against the map rendered at ``T_prev``
        if self.failures_in_a_row >= h.relocalise_after_failures:
            self.counts["relocalisations_tried"] += 1
            found = self.sparse.relocalise(frame, feats=self._features(frame))
            t.lap("relocalise")
            if found is not None:
                found = (se3.orthonormalize(se3.invert(self._correction(found[1])) @ found[0]), found[1])
                res, failure, T_new = self._icp_from(found[0], np.eye(4))
                t.lap("icp")
                if failure is None:
                    self.counts["relocalisations_tracked"] += 1
                    self.velocity = np.eye(4)
                guess = found[0]
            if (res is None or failure is not None) and self.cfg.tracking.relocalise_after_failures > 0:
                shape = self._relocalise_shape(T_prev)  # no PnP pose (no texture): from the depth alone
                t.lap("relocalise")
                if shape is not None:
                    res, failure = shape[0], None
                    T_new = se3.orthonormalize(T_prev @ res.T_target_source)
                    self.velocity = np.eye(4)
        else:
            trusted = self.failures_in_a_row == 0 or not h.pnp_when_velocity_untrusted
            match = None
            if self.joint or h.pnp_check or not trusted:
                match = self._pnp_match(frame, T_pred)
                t.lap("pnp")
            if trusted:
                res, failure, T_new = self._icp_from(T_prev, se3.invert(T_prev) @ T_pred, match)
                from_prev = True
                t.lap("icp")
            bad = res is None or failure is not None or res.degenerate
            if match is None and h.pnp_retry and bad:
                match = self._pnp_match(frame, T_pred)
                t.lap("pnp")
            guess = None if match is None else match.T_world_cam
            first_ok = res is not None and failure is None
            if first_ok and guess is not None and h.pnp_check and self._disagrees(T_new, match):
                first_ok = False
                failure = "disagrees_with_pnp"
                self.counts["pnp_disagreements"] += 1
            if guess is not None and h.pnp_retry and (not first_ok or res.degenerate):
                self.counts["pnp_guesses_tried"] += 1
                r2, f2, T2 = self._icp_from(guess, np.eye(4), match)
                t.lap("icp")
                if f2 is None and h.pnp_check and self._disagrees(T2, match):
                    f2 = "disagrees_with_pnp"
                if f2 is None and (not r2.degenerate or not first_ok):
                    res, failure, T_new, from_prev = r2, None, T2, False
                    self.counts["pnp_guesses_tracked"] += 1
                elif not first_ok:
                    res, failure, T_new, from_prev = r2, f2, T2, False
            elif res is None:  # untrusted velocity and no PnP guess: the velocity guess after all
                res, failure, T_new = self._icp_from(T_prev, se3.invert(T_prev) @ T_pred)
                from_prev = True
                t.lap("icp")
        tracked = res is not None and failure is None
        if tracked:
            if self.failures_in_a_row < h.relocalise_after_failures:
                self.velocity = (self._step_and_pose(T_prev, res)[0] if from_prev
                                 else se3.orthonormalize(se3.invert(T_prev) @ T_new))
            self.failures_in_a_row = 0
            self._fuse(frame, T_new)
            t.lap("fuse")
        else:
            failure = failure or "relocalisation_failed"
            T_new = guess if guess is not None else T_pred
            self.failures += 1
            self.failures_in_a_row += 1
            self.failure_reasons[failure] = self.failure_reasons.get(failure, 0) + 1
            if self.failures_in_a_row >= self.cfg.tracking.max_failures_in_a_row_before_reset_velocity:
                self.velocity = np.eye(4)
        self._after_tracking(frame, T_new, tracked, t)
        self._retire_source()
        return FrameResult(frame.index, frame.timestamp, self.T_world_cam.copy(), tracked, tracked,
                           None if res is None else res.reason if tracked else failure, t.ms, self.map.n_alive,
                           res)

    def _after_tracking(self, frame: RGBDFrame, T_new: np.ndarray, tracked: bool, t: _Timer) -> None:
        """Feed the sparse back end, anchor the frame, apply large pose-graph corrections to the dense state."""
        K = self.sparse.n_keyframes
        sr = None
        if tracked:
            # the graph frame may differ from the dense frame by the last keyframe's pending correction:
            # feed the pose in the graph frame, so the odometry edge is exactly the dense relative motion
            T_feed = T_new if K == 0 else self._correction(K - 1) @ T_new
            sr = self.sparse.process(frame, T_world_cam_dense=se3.orthonormalize(T_feed),
                                     feats=self._features(frame))
            t.lap("sparse")
            if sr.is_keyframe:
                self._kf_dense.append(T_new)
        anchor = self.sparse.n_keyframes - 1
        if tracked:
            self._fused_frames.append(frame.index)
            self._fused_anchor.append(anchor)
        self._stamps.append(frame.timestamp)
        self._anchor.append(anchor)
        self._T_kf_cam.append(se3.invert(self._kf_dense.poses[anchor]) @ T_new)
        self.T_world_cam = T_new
        if sr is not None and sr.loops_added > 0 and self.cfg.hybrid.loop_correction:
            kf = self.sparse.keyframe_poses()
            C = self._corrections(kf)
            if np.linalg.norm(C[:, :3, 3], axis=1).max() > self.cfg.hybrid.live_correction_min_m:
                self._correct(kf, C)
                t.lap("correct")

    def _corrections(self, kf_new: np.ndarray) -> np.ndarray:
        """``(K, 4, 4)`` each keyframe's correction ``T_new inv(T_dense)`` for the graph poses ``kf_new``."""
        return kf_new @ se3.invert(self._kf_dense.poses)

    def _correct(self, kf_new: np.ndarray, C: np.ndarray | None = None) -> None:
        """Move the surfels and the current pose by each keyframe's correction ``C`` (:meth:`_corrections`)."""
        C = self._corrections(kf_new) if C is None else C
        self.counts["map_corrections"] += 1
        m = self.map
        n = m.size
        if n:
            frames = np.asarray(self._fused_frames, np.int64)
            anchors = np.asarray(self._fused_anchor, np.int64)
            row = np.clip(np.searchsorted(frames, m.first_seen), 0, len(frames) - 1)
            a = anchors[row]
            R = C[a, :3, :3].astype(np.float32)
            tr = C[a, :3, 3].astype(np.float32)
            m.position[:] = np.einsum("nij,nj->ni", R, m.position) + tr
            m.normal[:] = np.einsum("nij,nj->ni", R, m.normal)
            m._assign_blocks(0, n)  # positions moved: new culling blocks and a fresh grouping
            m.rebuild_index()
        self.T_world_cam = se3.orthonormalize(kf_new[self._anchor[-1]] @ self._T_kf_cam[-1])
        self._kf_dense.poses[:] = kf_new

    def _correction(self, k: int) -> np.ndarray:
        """``C_k = T_kf_graph inv(T_kf_dense)``: maps dense-frame poses near keyframe ``k`` into the graph frame."""
        return self.sparse.keyframe_poses()[k] @ se3.invert(self._kf_dense.poses[k])

    def _pnp_match(self, frame: RGBDFrame, T_pred: np.ndarray) -> KeyframeMatch | None:
        """PnP pose and inliers against the reference keyframe, in the dense frame (the graph frame may have
        moved: the keyframe's pending correction is undone). Without the joint term the pose only checks ICP
        (``pnp_check``, a 5 cm / 5 deg gate) or starts it again, so the coarse PnP pose is enough."""
        C = self._correction(self.sparse.n_keyframes - 1)
        m = self.sparse.match_reference_keyframe(frame, C @ T_pred, feats=self._features(frame),
                                                 coarse=not self.joint)
        if m is None:
            return None
        C_inv = se3.invert(self._correction(m.kf_id))
        # inliers on occluding contours (sparse.features.depth_edge_rel, in this frame's depth) are no fixed points:
        # left out of the joint term and the PnP check (in a plain-walled office, cabinet silhouettes against the
        # wall raised the hybrid's frame-to-frame error by 40 %)
        keep = ~on_occluding_contour(frame.depth_m, m.uv_cur, self._contour_cfg)
        return KeyframeMatch(se3.orthonormalize(C_inv @ m.T_world_cam), m.kf_id,
                             se3.transform_points(C_inv, m.points_world[keep]), m.uv_cur[keep])

    def _trusted(self, match: KeyframeMatch) -> bool:
        """Whether ``match`` has the inliers (``hybrid.pnp_trust_min_inliers``, at least one) for its PnP pose to add
        the joint term or check ICP."""
        return len(match.uv_cur) >= max(1, self.cfg.hybrid.pnp_trust_min_inliers)

    def _disagrees(self, T_icp: np.ndarray, match: KeyframeMatch) -> bool:
        """Whether the ICP pose ``T_icp`` and the PnP pose of ``match`` disagree: beyond the metric bounds
        (``hybrid.pnp_check_max_m`` / ``_deg``) and with too few of the PnP inliers consistent with the ICP pose
        (``hybrid.pnp_check_min_inlier_fraction``)."""
        h = self.cfg.hybrid
        if not self._trusted(match):
            return False
        dt, dr = se3.pose_error(T_icp, match.T_world_cam)
        if dt <= h.pnp_check_max_m and dr <= h.pnp_check_max_deg:
            return False
        if h.pnp_check_min_inlier_fraction <= 0:
            return True
        consistent = reprojection_inliers(se3.transform_points(se3.invert(T_icp), match.points_world), match.uv_cur,
                                          self.intr, self.sparse.cfg.features.reprojection_error_px)
        return np.count_nonzero(consistent) < h.pnp_check_min_inlier_fraction * len(consistent)

    def trajectory(self, kf_poses: np.ndarray | None = None) -> Trajectory:
        """Every frame's pose ``T_world_kf T_kf_cam`` with ``kf_poses`` ``(K, 4, 4)`` (default: the graph's)."""
        kf = self.sparse.keyframe_poses() if kf_poses is None else kf_poses
        T = kf[np.asarray(self._anchor)] @ np.asarray(self._T_kf_cam)
        return Trajectory(np.asarray(self._stamps), T)

    def _correction_is_noise(self, kf_new: np.ndarray) -> bool:
        """The refined edges are distrusted, and the final graph poses ``kf_new`` (the PnP edges') move no keyframe
        by more than ``untrusted_min_correction_m`` relative to the first (see :class:`HybridConfig`)."""
        if self.sparse.dense_edges_trusted is not False or len(kf_new) == 0:
            return False
        C0 = kf_new[0] @ se3.invert(self._kf_dense.poses[0])
        rel = se3.invert(C0) @ kf_new  # the first keyframe's (rigid) move taken out
        moved = np.linalg.norm(rel[:, :3, 3] - self._kf_dense.poses[:, :3, 3], axis=1)
        return bool(moved.max() <= self.cfg.hybrid.untrusted_min_correction_m)

    def finish(self) -> SlamResult:
        res = self.sparse.finish()
        kf_final = res.keyframe_poses
        if self.cfg.hybrid.loop_correction and len(self._kf_dense):
            if self._correction_is_noise(kf_final):
                self.counts["loop_correction_skipped"] = 1
                kf_final = self._kf_dense.poses.copy()
            else:
                self._correct(kf_final)
        out = self._result({"tracking_failures": self.failures, "tracking_failure_reasons": self.failure_reasons,
                            "photometric": self.photometric, "joint_features": self.joint, **self.counts,
                            "shape_relocalisations_tried": self.relocalisations["tried"],
                            "shape_relocalisations": self.relocalisations["tracked"],
                            # recovered frames by either route, the key every tracker reports
                            "relocalisations": self.counts["relocalisations_tracked"] + self.relocalisations["tracked"],
                            **_sparse_metrics(self.sparse, res)})
        # with nothing corrected at all, the frames keep their tracked poses (T_kf T_kf_cam would round them)
        if self.cfg.hybrid.loop_correction and self.counts["map_corrections"] > 0:
            out.trajectory_override = self.trajectory(kf_final)
        out.loop_stamps = _loop_stamps(res, self._stamp_of_frame)
        return out


def build_slam(intr: Intrinsics, cfg: SlamConfig, tracker: str, colour_registered: bool = True,
               colour_camera: ColourCamera | None = None):
    """The pipeline object for ``tracker`` (``dense`` ..., or ``given`` for mapping with given poses).

    ``colour_registered``: the sequence's colour and depth pixels see the same rays (see ``HybridConfig``).
    ``colour_camera``: the sequence's separate colour camera, if known: the maps' colours are sampled through it
    (``colour_registration``); tracking is unaffected."""
    if tracker == "dense":
        return DenseSlam(intr, cfg, colour_registered, colour_camera)
    if tracker == "orb":
        return OrbSlam(intr, cfg, colour_camera)
    if tracker == "hybrid":
        return HybridSlam(intr, cfg, colour_registered, colour_camera)
    if tracker == "given":
        return GivenPoseMapper(intr, cfg, colour_camera=colour_camera)
    raise ConfigError(f"unknown tracker {tracker!r}; known: {', '.join(TRACKERS)}")


def poses_for_mapping(seq, poses: str, cfg: SlamConfig) -> dict[int, np.ndarray]:
    """Pose of each selected frame (position -> ``T_world_cam``) from ``'gt'`` or a TUM trajectory file.

    Frames with no pose within ``cfg.given_poses.max_dt_s`` are absent from the dict (skipped, counted).
    """
    if poses == "gt":
        if seq.ground_truth is None:
            raise GroundTruthError(seq.root, "--poses gt: this sequence has no ground truth")
        traj = seq.ground_truth
    else:
        traj = Trajectory.read_tum(poses)
    T, valid = traj.lookup(seq.timestamps, cfg.given_poses.max_dt_s)
    if not valid.any():
        src = "ground truth" if poses == "gt" else poses
        raise GroundTruthError(seq.root, f"no frame has a pose in {src} within {cfg.given_poses.max_dt_s} s")
    return {int(i): T[i] for i in np.flatnonzero(valid)}
