"""Sparse RGB-D SLAM: ORB/PnP odometry against the last keyframe, keyframes, loops, pose graph.

Per frame (:meth:`SparseSlam.process`):

1. ORB features are extracted and matched against the reference keyframe (the last one); PnP-
   RANSAC gives ``T_cur_kf`` with the rejection rules of :mod:`surfelslam.tracking.features`.
2. Accepted: ``T_world_cam = T_world_kf T_kf_cam``. If the motion norm from the keyframe reaches
   ``keyframe_threshold`` the frame becomes a keyframe: a graph node with an odometry edge, then
   loop candidates (nearby, appearance-retrieved, random; :mod:`loops`) are verified by PnP and
   accepted ones become robust loop edges. The graph is optimised whenever an edge to an older
   (non-nearby) keyframe is accepted, and in :meth:`finish`.
3. Rejected: the reason is counted and the frame gets the constant-velocity prediction
   (``rejected_pose = "constant_velocity"``) or the last pose (``"last"``); it never becomes a
   keyframe. After ``relocalise_after_failures`` consecutive rejections, :meth:`relocalise`
   searches all keyframes and, on success, tracking resumes against the keyframe found. When nothing is
   found for ``reinit_after_failures`` frames (the view after a gap shares no feature with any keyframe), a
   frame with enough keypoints starts a new segment: a keyframe at the last pose, joined to the old one by an
   edge that all but ignores the unknown motion (``reinit_sigma_*``). The first accepted edge (nearby or loop)
   from the new segment to a keyframe before it moves the segment rigidly onto it, then the graph is optimised.

With depth odometry (:class:`DepthOdometryConfig`, the orb tracker's default) step 1 also registers the frame's
depth to the reference keyframe's by point-to-plane ICP (:class:`~surfelslam.backend.dense_edges.DenseEdgeRefiner`),
jointly with the PnP inliers as reprojection terms, from the PnP pose; where PnP is weak (fewer than
``trust_min_inliers`` inliers) or rejected, from the constant-velocity prediction, without them. Features then
decide where texture is rich and geometry where it is not (plain walls, one poster in view), as RGB-D ICP mapping
does (Henry et al., IJRR 2012).

Every frame pose is stored relative to its reference keyframe, so graph corrections move whole
stretches of the trajectory rigidly with their keyframe.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np

from surfelslam.backend.dense_edges import DenseEdgeRefiner
from surfelslam.backend.keyframes import Keyframe, MapConfig, keyframe_cloud
from surfelslam.backend.loops import Candidate, LoopConfig, loop_candidates, verify_edge
from surfelslam.backend.place_recognition import DescriptorIndex, select_descriptors
from surfelslam.backend.pose_graph import PoseEdge, PoseGraph, PoseGraphConfig
from surfelslam.geometry.se3 import invert, motion_norm, orthonormalize, so3_log, transform_points
from surfelslam.kernels.voxel import voxel_filter
from surfelslam.tracking.features import FeatureConfig, Features, MotionResult, estimate_motion, extract
from surfelslam.tracking.preprocess import FramePyramid
from surfelslam.types import Intrinsics, PoseArray, RGBDFrame, Trajectory

REJECTED_POSE_MODES = ("constant_velocity", "last")


@dataclass(frozen=True)
class LoopCheck:
    """One verified loop candidate of a new keyframe (:meth:`SparseSlam._check_loops`).

    Attributes:
        candidate: the candidate keyframe and where it came from.
        result: its PnP verification (``result.T_cur_ref`` maps candidate points into the new keyframe).
        refined_T_cur_ref: ``(4, 4)`` the dense-refined ``T_cur_ref``, or ``None`` (no refiner, PnP failed, or the
            dense check rejected the edge).
        dense_rejected: the PnP edge passed but the dense check rejected it (it then enters the PnP graph only).
        depth_only: PnP failed on this nearby candidate and ``refined_T_cur_ref`` is ICP from the graph's relative
            pose, by depth alone (``DenseEdgeConfig.depth_only_nearby``; it enters the refined edges' graph only).
    """

    candidate: Candidate
    result: MotionResult
    refined_T_cur_ref: np.ndarray | None = None
    dense_rejected: bool = False
    depth_only: bool = False


@dataclass
class KeyframeMatch:
    """A frame registered to a keyframe by PnP (:meth:`SparseSlam.match_reference_keyframe`).

    Attributes:
        T_world_cam: ``(4, 4)`` the frame's pose (graph world frame).
        kf_id: the keyframe matched.
        points_world: ``(M, 3)`` float64 the PnP inliers' keyframe points (from the keyframe's depth), world frame.
        uv_cur: ``(M, 2)`` float64 their pixels in the frame (full resolution, sub-pixel tracked).
    """

    T_world_cam: np.ndarray
    kf_id: int
    points_world: np.ndarray
    uv_cur: np.ndarray


@dataclass(frozen=True)
class DepthOdometryConfig:
    """Depth in the frame-to-keyframe odometry of the sparse tracker (module docstring).

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
            least ``reinit_min_keypoints`` keypoints with depth starts a new segment (module docstring); 0 = never.
            Without it a view that shares no feature with any keyframe (7-Scenes after 60 dropped frames) was lost
            for the rest of the run.
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


@dataclass
class SparseFrameResult:
    """Outcome of one :meth:`SparseSlam.process` call.

    Attributes:
        T_world_cam: ``(4, 4)`` current estimate of the frame's pose.
        is_keyframe: the frame became a keyframe.
        ok: odometry accepted (False: ``reason`` names the rejection rule).
        n_inliers: PnP inliers against the reference keyframe (-1: not computed, a dense pose was given).
        loops_added: edges to older keyframes accepted for this keyframe (nearby edges excluded).
        relocalised: the pose came from :meth:`SparseSlam.relocalise`.
    """

    T_world_cam: np.ndarray
    is_keyframe: bool
    ok: bool
    reason: str | None
    n_inliers: int
    loops_added: int
    relocalised: bool = False


@dataclass
class SparseSlamResult:
    """Outcome of :meth:`SparseSlam.finish`.

    Attributes:
        trajectory: every processed frame, after the final optimisation.
        keyframe_indices: ``(K,)`` frame index of each keyframe.
        keyframe_poses: ``(K, 4, 4)`` optimised ``T_world_kf``.
        loops_found: ``[(kf_old, kf_new, n_inliers)]`` older-keyframe candidates whose PnP succeeded.
        loops_accepted: the subset that became graph edges.
        n_nearby_edges: accepted edges to nearby keyframes.
        rejected: ``{reason: count}`` of rejected frames.
        map_xyz: ``(M, 3)`` float32 world points (voxel-filtered keyframe clouds).
        map_rgb: ``(M, 3)`` uint8 colours.
    """

    trajectory: Trajectory
    keyframe_indices: np.ndarray
    keyframe_poses: np.ndarray
    loops_found: list[tuple[int, int, int]]
    loops_accepted: list[tuple[int, int, int]]
    n_nearby_edges: int
    rejected: dict[str, int]
    map_xyz: np.ndarray
    map_rgb: np.ndarray


class SparseSlam:
    """Frame-by-frame sparse SLAM (see the module docstring).

    Args:
        intr: intrinsics of the frames that will be processed (``fy`` may be negative).
        cfg: settings.
        T_world_first: pose of the first frame (default identity).
        edge_refiner: optional dense check of keyframe edges (:mod:`dense_edges`): every PnP-verified edge
            (nearby or loop) is refined by ICP between the keyframes' depth maps, or dropped when that fails. While
            the refined edges are not consistent enough to be trusted, the poses come from the PnP edges' graph.
        refined_robust_scale: scale (whitened units) of the loop kernel on refined edges (``None``: the config's).
        cloud_rgb: the colour of each depth pixel of a frame for the keyframe clouds, ``(H, W, 3)`` uint8 (``None``:
            ``frame.rgb``; e.g. colour sampled through a separate colour camera).
        refine_edges: use ``edge_refiner`` for the keyframe edges (False: it only serves the depth odometry).
        depth_odometry: register frames to the reference keyframe by ICP too (module docstring; needs
            ``edge_refiner``, which keeps the keyframes' depth); ``None`` or disabled: PnP alone.
    """

    def __init__(self, intr: Intrinsics, cfg: SparseSlamConfig | None = None,
                 T_world_first: np.ndarray | None = None, edge_refiner: DenseEdgeRefiner | None = None,
                 refined_robust_scale: float | None = None,
                 cloud_rgb: Callable[[RGBDFrame], np.ndarray] | None = None, refine_edges: bool = True,
                 depth_odometry: DepthOdometryConfig | None = None) -> None:
        self.intr = intr
        self.cfg = features_for_width(cfg or SparseSlamConfig(), intr.width)
        # the settings of ``match_reference_keyframe(coarse=True)``: PnP-RANSAC and its inlier refinement only
        self._coarse_features = replace(self.cfg.features, projection_search=False, rgbd_refine_iterations=0)
        self._depth_cfg = depth_odometry if depth_odometry is not None and depth_odometry.enabled else None
        if self._depth_cfg is not None and edge_refiner is None:
            raise ValueError("depth odometry needs an edge_refiner (the keyframes' depth store)")
        self._store = edge_refiner  # keyframe depth (edge refinement and depth odometry)
        self._refiner = edge_refiner if refine_edges else None
        # frames whose PnP pose ICP refined / that ICP tracked from the prediction (of them: PnP rejected) / where
        # ICP failed (the PnP pose or the rejection stands)
        self.depth_counts = {"refined": 0, "from_prediction": 0, "rescued": 0, "icp_failed": 0}
        self._cloud_rgb = cloud_rgb
        self._refined_robust_scale = refined_robust_scale
        self._T_world_first = np.eye(4) if T_world_first is None else np.asarray(T_world_first, np.float64)
        self._graph = PoseGraph(self.cfg.graph)
        self._index = DescriptorIndex(self.cfg.loop.retrieval)
        self._rng = np.random.default_rng(self.cfg.loop.seed)
        self._kfs: list[Keyframe] = []
        self._kf_pose_buf = PoseArray()  # current estimates T_world_kf
        self._kf_odometry: list[np.ndarray] = []  # T_world_kf chained from odometry edges alone (never optimised)
        self._ref_kf = -1
        # per processed frame: timestamp, reference keyframe, pose relative to it
        self._timestamps: list[float] = []
        self._frame_kf: list[int] = []
        self._T_kf_cam: list[np.ndarray] = []
        self._velocity = np.eye(4)  # T_prev_last: last inter-frame motion (camera frame)
        self._n_failures = 0
        self.loops_found: list[tuple[int, int, int]] = []
        self.loops_accepted: list[tuple[int, int, int]] = []
        self.n_nearby_edges = 0
        self.n_dense_refined = 0  # edges refined by the dense check
        self.n_dense_rejected = 0  # PnP-verified edges the dense check dropped
        # with an edge refiner, a second graph holds the refined edges (self._graph the PnP ones); each
        # optimisation checks the refined edges' consistency there and takes its poses from the trusted graph
        self._graph_refined = None if self._refiner is None else PoseGraph(self.cfg.graph)
        self._refined_trusted = False  # until enough refined edges show they are consistent (DenseEdgeRefiner.trusted)
        self._refined_residual_rad: float | None = None
        self.rejected: Counter[str] = Counter()
        self._pool: ThreadPoolExecutor | None = None
        self._pending: Future | None = None  # loop checks of the last keyframe, not applied yet
        self._unreported_loops = 0  # loops applied since the last frame result
        self.n_reinitialisations = 0  # segments started after a long loss
        self.n_segments_merged = 0  # of them, moved onto the older map by a loop edge
        self._open_bridges: list[int] = []  # first keyframes of segments no loop edge has joined to the old map
        self._lost: list[tuple[int, Features]] = []  # (frame slot, features) of the lost frames in a row
        self.n_lost_placed = 0  # lost frames placed afterwards against the keyframe of a new segment
        self.n_depth_only_edges = 0  # nearby edges from depth alone where PnP could not verify (refined graph only)

    # --- state -------------------------------------------------------------------------------------

    @property
    def dense_edge_sigma_m(self) -> float | None:
        """Sigma (m and rad) that new dense-refined edges get now; ``None`` without an edge refiner."""
        return None if self._refiner is None else self._refiner.edge_sigma()

    @property
    def dense_edge_spread_m(self) -> float | None:
        """Robust spread (m and rad) of the dense-refined nearby edges against the odometry (``None`` without an
        edge refiner or before enough edges)."""
        return None if self._refiner is None else self._refiner.spread()

    @property
    def dense_edges_trusted(self) -> bool | None:
        """Whether the poses come from the graph of dense-refined edges (else from the PnP edges' graph);
        ``None`` without an edge refiner."""
        return None if self._refiner is None else self._refined_trusted

    @property
    def dense_edge_residual_rad(self) -> float | None:
        """Robust spread (rad) of the refined edges' rotation residuals at the last optimisation of their graph
        (``None`` without an edge refiner or before one)."""
        return self._refined_residual_rad

    @property
    def n_keyframes(self) -> int:
        return len(self._kfs)

    @property
    def _kf_poses(self) -> np.ndarray:
        return self._kf_pose_buf.poses

    def keyframe_poses(self) -> np.ndarray:
        """Current (optimised) keyframe poses ``T_world_kf`` ``(K, 4, 4)``; ids = keyframe ids."""
        return self._kf_poses.copy()

    def keyframe_frame_indices(self) -> np.ndarray:
        """``(K,)`` frame index of each keyframe."""
        return np.array([k.frame_index for k in self._kfs], dtype=np.int64)

    def _last_pose(self) -> np.ndarray:
        return self._kf_poses[self._frame_kf[-1]] @ self._T_kf_cam[-1]

    def _predict(self) -> np.ndarray:
        """Constant-velocity prediction of the next ``T_world_cam``."""
        return orthonormalize(self._last_pose() @ self._velocity)

    # --- processing ----------------------------------------------------------------------------------

    def features(self, frame: RGBDFrame) -> Features:
        """ORB features of ``frame`` with this SLAM's settings (thread-safe: no state is touched).

        Pass them as ``feats`` to :meth:`process`, :meth:`relocalise` or
        :meth:`pose_guess_against_last_keyframe` so a frame is extracted once (possibly ahead, in another thread).
        """
        return extract(frame.rgb, frame.depth_m, self.intr, self.cfg.features)

    @property
    def uses_depth(self) -> bool:
        """Whether frames are registered by ICP too (depth odometry), i.e. :meth:`process` uses a
        :meth:`depth_pyramid`."""
        return self._depth_cfg is not None

    def depth_pyramid(self, frame: RGBDFrame) -> FramePyramid | None:
        """The frame's depth pyramid for the depth odometry (thread-safe; ``None`` without depth odometry).

        Pass it as ``depth_pyramid`` to :meth:`process` so it can be built ahead, in another thread."""
        return None if self._depth_cfg is None else self._store.frame_pyramid(frame.depth_m)

    def process(self, frame: RGBDFrame, T_world_cam_dense: np.ndarray | None = None,
                feats: Features | None = None, depth_pyramid: FramePyramid | None = None) -> SparseFrameResult:
        """Track one frame; may add a keyframe, loop edges and re-optimise the graph.

        Args:
            frame: the next frame (any resolution matching ``intr``).
            T_world_cam_dense: optional pose from another tracker (hybrid mode). When given it is the
                frame's pose and the odometry measurement of a new keyframe, and no PnP runs here (the
                keyframe decision uses that pose; the hybrid tracker does its own PnP check).
            feats: the frame's :meth:`features`, when already extracted.
            depth_pyramid: the frame's :meth:`depth_pyramid`, when already built.
        """
        feats = self.features(frame) if feats is None else feats
        if not self._kfs:
            T0 = self._T_world_first if T_world_cam_dense is None else np.asarray(T_world_cam_dense, np.float64)
            self._add_keyframe(frame, feats, T0, None, None)
            self._record(frame.timestamp, 0, np.eye(4), None)
            return SparseFrameResult(T0.copy(), True, True, None, 0, 0)

        T_pred = self._predict()
        T_world_kf = self._kf_poses[self._ref_kf]
        ref = self._kfs[self._ref_kf]
        relocalised = False
        res = None
        information = None  # of the measurement behind a new keyframe's edge (None: a dense pose, isotropic)
        if T_world_cam_dense is None:
            T_pred_cur_ref = invert(T_pred) @ T_world_kf
            res = estimate_motion(ref.features, feats, self.intr, self.cfg.features, T_init_cur_ref=T_pred_cur_ref)
            if self._depth_cfg is not None:
                pyr = self.depth_pyramid(frame) if depth_pyramid is None else depth_pyramid
                res = self._with_depth(res, T_pred_cur_ref, pyr)
        if T_world_cam_dense is not None:
            T_world_cam = np.asarray(T_world_cam_dense, np.float64)
            T_kf_cam = invert(T_world_kf) @ T_world_cam
            ok = True
        elif res.ok:
            T_kf_cam = invert(res.T_cur_ref)
            T_world_cam = T_world_kf @ T_kf_cam
            ok = True
            information = res.information
        else:
            ok = False
            self.rejected[res.reason or "pnp_failed"] += 1
            self._n_failures += 1
            reloc = None
            if self._n_failures >= self.cfg.relocalise_after_failures:
                reloc = self._relocalise_features(feats)
            if reloc is None and self._may_reinitialise(feats):
                return self._reinitialise(frame, feats, res)
            if reloc is None:
                extrapolate = (self.cfg.rejected_pose == "constant_velocity"
                               and self._n_failures <= self.cfg.velocity_reset_after_failures)
                T_world_cam = T_pred if extrapolate else self._last_pose()
                if self.cfg.reinit_after_failures > 0:  # a new segment may place it later (_reinitialise)
                    self._lost.append((len(self._timestamps), feats))
                    del self._lost[: max(0, len(self._lost) - self.cfg.reinit_after_failures)]  # the last ones
                self._record(frame.timestamp, self._ref_kf, invert(T_world_kf) @ T_world_cam, T_world_cam)
                return SparseFrameResult(T_world_cam.copy(), False, False, res.reason, res.n_inliers, 0)
            # Relocalised: the keyframe rule below applies as to a tracked frame. From the keyframe it was found
            # against, the next frames are as far as this one (up to relocalise_max_norm), beyond the odometry's
            # motion bound, so without a keyframe here every one of them was rejected and relocalised again.
            T_world_cam, self._ref_kf, reloc_res = reloc
            relocalised = True
            T_kf_cam = invert(self._kf_poses[self._ref_kf]) @ T_world_cam
            information = reloc_res.information

        self._n_failures = 0
        self._lost = []
        is_kf = motion_norm(T_kf_cam) >= self.cfg.keyframe_threshold
        if is_kf:
            self._add_keyframe(frame, feats, T_world_cam, self._ref_kf, T_kf_cam, information)
            T_world_cam = self._kf_poses[-1]
            self._record(frame.timestamp, self.n_keyframes - 1, np.eye(4), T_world_cam)
        else:
            self._record(frame.timestamp, self._ref_kf, T_kf_cam, T_world_cam)
        if relocalised:
            self._velocity = np.eye(4)  # the motion across the loss is unknown
            return SparseFrameResult(T_world_cam.copy(), is_kf, False, res.reason, res.n_inliers, 0, True)
        loops_added, self._unreported_loops = self._unreported_loops, 0
        return SparseFrameResult(T_world_cam.copy(), is_kf, ok, None, -1 if res is None else res.n_inliers,
                                 loops_added)

    def _with_depth(self, res: MotionResult, T_pred_cur_ref: np.ndarray, source: FramePyramid) -> MotionResult:
        """``res`` (PnP against the reference keyframe) with its pose registered by ICP of the frame's depth
        ``source`` to the keyframe's (:class:`DepthOdometryConfig`); ``res`` itself when ICP fails."""
        c = self._depth_cfg
        ref = self._kfs[self._ref_kf].features
        from_pnp = res.ok and res.n_inliers >= c.trust_min_inliers
        if from_pnp:
            inl = res.inlier_mask
            pts = ref.points_cam[res.pairs[inl, 0]]
            uv = None if res.uv_cur is None else res.uv_cur[inl]
            T = self._store.refine_frame(self._ref_kf, source, res.T_cur_ref, pts, uv, c.max_shift_m, c.max_shift_deg)
        else:
            T = self._store.refine_frame(self._ref_kf, source, T_pred_cur_ref, None, None, np.inf, np.inf)
        if T is None or motion_norm(T) > self.cfg.features.max_motion_norm:
            self.depth_counts["icp_failed"] += 1
            return res
        if from_pnp:
            self.depth_counts["refined"] += 1
        else:
            self.depth_counts["from_prediction"] += 1
            self.depth_counts["rescued"] += int(not res.ok)
        # a PnP pose refined keeps its information as the keyframe edge's weight; a pose from depth alone has
        # none (the graph's isotropic odometry weight)
        return replace(res, T_cur_ref=T, ok=True, reason=None, rvec=so3_log(T[:3, :3]), tvec=T[:3, 3].copy(),
                       information=res.information if from_pnp else None)

    def _may_reinitialise(self, feats: Features) -> bool:
        n = self.cfg.reinit_after_failures
        return n > 0 and self._n_failures >= n and np.count_nonzero(feats.valid) >= self.cfg.reinit_min_keypoints

    def _reinitialise(self, frame: RGBDFrame, feats: Features, res: MotionResult) -> SparseFrameResult:
        """Start a new segment at this (lost) frame: a keyframe at the last pose, joined to the reference keyframe
        by a weak edge (``reinit_sigma_*``); tracking goes on against it, and the frames lost just before it that
        PnP places against it join it."""
        T_world_cam = self._last_pose()
        T_kf_cam = invert(self._kf_poses[self._ref_kf]) @ T_world_cam
        # information in gtsam's tangent order (rotation, translation)
        info = np.diag([self.cfg.reinit_sigma_rad ** -2] * 3 + [self.cfg.reinit_sigma_m ** -2] * 3)
        self._add_keyframe(frame, feats, T_world_cam, self._ref_kf, T_kf_cam, info)
        kf = self.n_keyframes - 1
        self._open_bridges.append(kf)
        self.n_reinitialisations += 1
        self._n_failures = 0
        # the frames lost just before are mostly close to this one: placed by PnP against it, they join the segment
        for slot, lost in self._lost:
            r = estimate_motion(self._kfs[kf].features, lost, self.intr, self.cfg.features)
            if r.ok:
                self._frame_kf[slot], self._T_kf_cam[slot] = kf, invert(r.T_cur_ref)
                self.n_lost_placed += 1
        self._lost = []
        T_world_cam = self._kf_poses[-1]
        self._record(frame.timestamp, self.n_keyframes - 1, np.eye(4), T_world_cam)
        self._velocity = np.eye(4)  # the motion across the loss is unknown
        return SparseFrameResult(T_world_cam.copy(), True, False, res.reason, res.n_inliers, 0)

    def _merge_segment(self, i: int, j: int, T_i_j: np.ndarray) -> None:
        """An edge ``i -> j`` from the newest segment (keyframe ``j``) to a keyframe ``i`` before it: move the
        segment rigidly so that the edge holds (the graph's start; the optimisation does the rest)."""
        if not self._open_bridges or not i < self._open_bridges[-1] <= j:
            return
        b = self._open_bridges.pop()
        C = orthonormalize(self._kf_poses[i] @ T_i_j @ invert(self._kf_poses[j]))
        for k in range(b, self.n_keyframes):
            T = orthonormalize(C @ self._kf_poses[k])
            self._kf_poses[k] = T
            for g in (self._graph, self._graph_refined):
                if g is not None:
                    g.set_pose(k, T)
        self.n_segments_merged += 1

    def _record(self, timestamp: float, kf: int, T_kf_cam: np.ndarray, T_world_cam: np.ndarray | None) -> None:
        if T_world_cam is not None and self._timestamps:
            self._velocity = invert(self._last_pose()) @ T_world_cam
        self._timestamps.append(float(timestamp))
        self._frame_kf.append(kf)
        self._T_kf_cam.append(np.asarray(T_kf_cam, np.float64).copy())

    def _add_keyframe(self, frame: RGBDFrame, feats: Features, T_world_cam: np.ndarray,
                      prev_kf: int | None, T_prev_new: np.ndarray | None,
                      information: np.ndarray | None = None) -> None:
        """Add a keyframe and its odometry edge, and start its loop checks (the previous keyframe's are applied
        first: they may move ``prev_kf``, and the new keyframe is placed by its odometry from there).

        ``information``: ``(6, 6)`` of the odometry measurement (the PnP's, see ``MotionResult.information``), or
        ``None`` (a dense pose: isotropic weight)."""
        if prev_kf is not None:
            T_prev_before = self._kf_poses[prev_kf].copy()
        self._collect_loop_checks()
        if prev_kf is not None and not np.array_equal(self._kf_poses[prev_kf], T_prev_before):
            # the graph moved the previous keyframe: keep the new one's pose relative to it
            T_world_cam = orthonormalize(self._kf_poses[prev_kf] @ invert(T_prev_before) @ T_world_cam)
        kf_id = self._graph.add_node(T_world_cam)
        if self._graph_refined is not None:
            self._graph_refined.add_node(T_world_cam)
        if self._store is not None:
            self._store.add_keyframe(kf_id, frame.depth_m)
        xyz, rgb = keyframe_cloud(frame, self.intr, self.cfg.map,
                                  None if self._cloud_rgb is None else self._cloud_rgb(frame))
        self._kf_pose_buf.append(T_world_cam)
        self._kf_odometry.append(np.asarray(T_world_cam, np.float64).copy() if prev_kf is None or T_prev_new is None
                                 else self._kf_odometry[prev_kf] @ T_prev_new)
        # a keyframe is only ever the reference side of a pair: it keeps its grey image (sub-pixel tracking)
        # but not the depth image (only the current side's depth is used)
        self._kfs.append(Keyframe(kf_id, frame.index, frame.timestamp, replace(feats, depth_m=None), xyz, rgb))
        self._ref_kf = kf_id
        if prev_kf is not None and T_prev_new is not None:
            self._add_edge(PoseEdge(prev_kf, kf_id, T_prev_new, "odometry", information_matrix=information))
        if prev_kf is None:
            self._index.add(self._query_descriptors(feats))
            return
        if self.cfg.background_loop_checks:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="loop-checks")
            self._pending = self._pool.submit(self._check_loops, kf_id, feats, self._nearby_poses(kf_id))
        else:
            self._apply_loop_checks(*self._check_loops(kf_id, feats, self._nearby_poses(kf_id)))

    def _nearby_poses(self, kf_id: int) -> dict[int, np.ndarray]:
        """Copies of ``T_world_kf`` of keyframe ``kf_id`` and its nearby loop candidates (:func:`loop_candidates`)."""
        return {k: self._kf_poses[k].copy() for k in range(max(0, kf_id - 1 - self.cfg.loop.n_nearby), kf_id + 1)}

    def _query_descriptors(self, feats: Features) -> np.ndarray:
        n_max = self.cfg.loop.retrieval.max_descriptors_per_keyframe
        return select_descriptors(feats.descriptors, feats.response, feats.valid, n_max)

    def _check_loops(self, kf_id: int, feats: Features,
                     poses: dict[int, np.ndarray]) -> tuple[int, list[LoopCheck]]:
        """Verify keyframe ``kf_id``'s loop candidates, then add it to the retrieval index.

        ``poses``: the :meth:`_nearby_poses` of ``kf_id`` when it was added (the start of depth-only nearby edges).

        Runs in the loop-check thread (or inline): it reads keyframe features (never changed once added) and is
        the only user of the index and the candidate generator between two :meth:`_collect_loop_checks`.
        Returns ``(kf_id, checks)``.
        """
        q = self._query_descriptors(feats)
        checked = []
        for cand in loop_candidates(kf_id, q, self._index, self._rng, self.cfg.loop):
            res = verify_edge(self._kfs[cand.kf_id].features, feats, self.intr, self.cfg.features, self.cfg.loop)
            refined = None
            if res.ok and self._refiner is not None:
                inl = res.pairs[res.inlier_mask]
                uv = None if res.uv_cur is None else res.uv_cur[res.inlier_mask]
                refined = self._refiner.refine(cand.kf_id, kf_id, res.T_cur_ref,
                                               self._kfs[cand.kf_id].features.points_cam[inl[:, 0]], uv)
            elif (not res.ok and cand.source == "nearby" and self._refiner is not None
                  and self._refiner.cfg.depth_only_nearby
                  and res.n_good < self._refiner.cfg.depth_only_max_matches):
                # texture too poor to verify: the depth alone, from the graph's estimate (the odometry's)
                refined = self._refiner.refine(cand.kf_id, kf_id, invert(poses[kf_id]) @ poses[cand.kf_id])
                if refined is not None:
                    checked.append(LoopCheck(cand, res, refined, depth_only=True))
                continue
            checked.append(LoopCheck(cand, res, refined, res.ok and self._refiner is not None and refined is None))
        self._index.add(q)
        return kf_id, checked

    def _apply_loop_checks(self, kf_id: int, checked: list[LoopCheck]) -> None:
        """Add the verified edges of keyframe ``kf_id``; optimise when one reaches an older (non-nearby) keyframe or
        joins the newest segment to the keyframes before it (which first moves the segment, :meth:`_merge_segment`)."""
        n_loops = 0
        # (inliers, edge) of the best accepted edge (nearby or not) from the newest segment to a keyframe before it
        bridging: tuple[int, PoseEdge] | None = None
        b = self._open_bridges[-1] if self._open_bridges else None
        for check in checked:
            cand, res, refined = check.candidate, check.result, check.refined_T_cur_ref
            far = cand.source != "nearby"
            if far and res.reason != "too_few_matches" and res.n_inliers >= self.cfg.features.min_inliers \
                    and res.reason != "motion_too_large":
                self.loops_found.append((cand.kf_id, kf_id, res.n_inliers))
            if check.depth_only:
                self.n_depth_only_edges += 1
                self._add_edge(None, PoseEdge(cand.kf_id, kf_id, invert(refined), "loop",
                                              robust_scale=self._refined_robust_scale))
                continue
            if not res.ok:
                continue
            # T_i_j = T_cur_ref^-1: a left perturbation of T_cur_ref is minus a right one of T_i_j (same information)
            pnp = PoseEdge(cand.kf_id, kf_id, invert(res.T_cur_ref), "loop", information_matrix=res.information)
            if check.dense_rejected:  # in the PnP edges' graph only
                self.n_dense_rejected += 1
                added = self._add_edge(pnp, dense_rejected=True)
            elif refined is not None:
                self.n_dense_refined += 1
                T_i_j = invert(refined)
                if not far:  # compared with the odometry alone (the graph has been pulled towards the edges)
                    odo = self._kf_odometry
                    self._refiner.observe_nearby(T_i_j, invert(odo[cand.kf_id]) @ odo[kf_id])
                # weighed by the refined edges' sigma (isotropic), set when it enters their graph
                added = self._add_edge(pnp, PoseEdge(pnp.i, pnp.j, T_i_j, "loop",
                                                     robust_scale=self._refined_robust_scale))
            else:
                added = self._add_edge(pnp)
            if added and far:
                self.loops_accepted.append((cand.kf_id, kf_id, res.n_inliers))
                n_loops += 1
            elif added:
                self.n_nearby_edges += 1
            crosses = b is not None and cand.kf_id < b <= kf_id
            if added and crosses and (bridging is None or res.n_inliers > bridging[0]):
                bridging = (res.n_inliers, pnp)
        if bridging is not None:
            self._merge_segment(bridging[1].i, bridging[1].j, bridging[1].T_i_j)
        if n_loops > 0 or bridging is not None:
            self._optimise()
        self._unreported_loops += n_loops

    def _collect_loop_checks(self) -> None:
        """Wait for the background loop checks of the last keyframe, if any, and apply them."""
        if self._pending is not None:
            pending, self._pending = self._pending, None
            self._apply_loop_checks(*pending.result())

    def _optimise(self) -> None:
        if self._graph_refined is None:
            self._kf_poses[:] = self._graph.optimise()
            return
        poses = self._graph_refined.optimise()
        self._refined_residual_rad = self._refiner.residual_spread(self._graph_refined.edges, poses)
        self._refined_trusted = self._refiner.trusted(self._refined_residual_rad)
        self._kf_poses[:] = poses if self._refined_trusted else self._graph.optimise()

    def _add_edge(self, pnp: PoseEdge | None, refined: PoseEdge | None = None, dense_rejected: bool = False) -> bool:
        """Add an edge: ``pnp`` (odometry or PnP-verified; ``None``: a depth-only edge, in the refined graph only)
        and, with an edge refiner, its refined version (``None``: none, the same edge in both graphs) unless
        ``dense_rejected`` (the dense check rejected it: in the PnP graph only). Returns whether the graph that is
        trusted now got an edge."""
        if pnp is not None:
            self._graph.add_edge(pnp)
        if self._graph_refined is None:
            return True
        if dense_rejected:
            return not self._refined_trusted
        if refined is None:
            self._graph_refined.add_edge(pnp)
            return True
        self._graph_refined.add_edge(replace(refined, information=self._refiner.edge_sigma() ** -2))
        return True

    # --- queries for the dense pipeline ---------------------------------------------------------------

    def _relocalise_features(self, feats: Features) -> tuple[np.ndarray, int, MotionResult] | None:
        self._collect_loop_checks()  # the retrieval index must hold every keyframe
        cands = [k for k, _ in self._index.query(self._query_descriptors(feats), self.cfg.loop.n_retrieved)]
        last = self.n_keyframes - 1
        if last >= 0 and last not in cands:
            cands.append(last)
        loop_cfg = replace(self.cfg.loop, max_norm_loop=self.cfg.relocalise_max_norm)
        best: tuple[np.ndarray, int, MotionResult] | None = None
        for k in cands:
            res = verify_edge(self._kfs[k].features, feats, self.intr, self.cfg.features, loop_cfg)
            if res.ok and (best is None or res.n_inliers > best[2].n_inliers):
                best = (self._kf_poses[k] @ invert(res.T_cur_ref), k, res)
        return best

    def relocalise(self, frame: RGBDFrame, feats: Features | None = None) -> tuple[np.ndarray, int] | None:
        """Pose of ``frame`` found by retrieval over all keyframes + PnP verification.

        Returns:
            ``(T_world_cam (4, 4), kf_id)`` of the best-verified keyframe, or ``None``. State is unchanged.
        """
        feats = self.features(frame) if feats is None else feats
        best = self._relocalise_features(feats)
        return None if best is None else (best[0], best[1])

    def pose_guess_against_last_keyframe(self, frame: RGBDFrame, T_world_cam_pred: np.ndarray | None = None,
                                         feats: Features | None = None) -> np.ndarray | None:
        """PnP pose ``T_world_cam`` of ``frame`` against the reference keyframe (an ICP initial guess).

        Args:
            T_world_cam_pred: optional prediction used as PnP initial guess.

        Returns:
            ``(4, 4)`` or ``None`` when a rejection rule fired. State is unchanged.
        """
        m = self.match_reference_keyframe(frame, T_world_cam_pred, feats)
        return None if m is None else m.T_world_cam

    def match_reference_keyframe(self, frame: RGBDFrame, T_world_cam_pred: np.ndarray | None = None,
                                 feats: Features | None = None, coarse: bool = False) -> KeyframeMatch | None:
        """PnP pose of ``frame`` against the reference keyframe, with the inlier correspondences.

        ``coarse``: PnP-RANSAC and its inlier refinement only, without search by projection and the joint RGB-D
        refinement (:func:`~surfelslam.tracking.features.estimate_motion`; same rejection rules): enough for a
        sanity check or an ICP start, at a third to half the cost.

        Returns:
            :class:`KeyframeMatch` (poses and points in the graph's world frame), or ``None`` when there is no
            keyframe yet or a rejection rule fired. State is unchanged.
        """
        if not self._kfs:
            return None
        feats = self.features(frame) if feats is None else feats
        kf = self._ref_kf
        T_world_kf = self._kf_poses[kf]
        init = None if T_world_cam_pred is None else invert(T_world_cam_pred) @ T_world_kf
        ref = self._kfs[kf].features
        fcfg = self._coarse_features if coarse else self.cfg.features
        res = estimate_motion(ref, feats, self.intr, fcfg, init)
        if not res.ok or res.uv_cur is None:
            return None
        inl = res.inlier_mask
        pts_kf = ref.points_cam[res.pairs[inl, 0]].astype(np.float64)
        return KeyframeMatch(T_world_kf @ invert(res.T_cur_ref), kf, transform_points(T_world_kf, pts_kf),
                             res.uv_cur[inl].astype(np.float64))

    # --- results -------------------------------------------------------------------------------------

    def trajectory(self) -> Trajectory:
        """Current estimate of every processed frame's pose."""
        kf = np.asarray(self._frame_kf, dtype=np.int64)
        T = self._kf_poses[kf] @ np.asarray(self._T_kf_cam).reshape(-1, 4, 4)
        return Trajectory(np.asarray(self._timestamps), T)

    def map_points(self) -> tuple[np.ndarray, np.ndarray]:
        """Keyframe clouds in the world frame, joined and voxel-filtered: ``(xyz (M, 3) f32, rgb (M, 3) u8)``."""
        if not self._kfs:
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
        n = sum(len(k.cloud_xyz_cam) for k in self._kfs)
        xyz = np.empty((n, 3), np.float32)
        rgb = np.empty((n, 3), np.uint8)
        i = 0
        for k, T in zip(self._kfs, self._kf_poses, strict=True):
            m = len(k.cloud_xyz_cam)
            xyz[i : i + m] = transform_points(T, k.cloud_xyz_cam.astype(np.float64))
            rgb[i : i + m] = k.cloud_rgb
            i += m
        out_xyz, out_rgb, _ = voxel_filter(xyz, rgb, self.cfg.map.voxel_size_m)
        return out_xyz, out_rgb

    def finish(self) -> SparseSlamResult:
        """Optimise the graph once more and return trajectory, keyframes, loops and the map."""
        self._collect_loop_checks()
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
        if self.n_keyframes > 1:
            self._optimise()
        xyz, rgb = self.map_points()
        return SparseSlamResult(
            trajectory=self.trajectory(),
            keyframe_indices=self.keyframe_frame_indices(),
            keyframe_poses=self.keyframe_poses(),
            loops_found=list(self.loops_found),
            loops_accepted=list(self.loops_accepted),
            n_nearby_edges=self.n_nearby_edges,
            rejected=dict(self.rejected),
            map_xyz=xyz,
            map_rgb=rgb,
        )
