"""Dense refinement of PnP keyframe edges: point-to-plane ICP between the two keyframes' depth maps.

A PnP edge between keyframes is only as precise as a few hundred keypoints (their pixel noise and the depth noise
at corners and edges), while the dense odometry uses every pixel; so in the hybrid tracker PnP loop edges carry a
loose weight and barely move the dense trajectory. Started at the PnP pose, ICP between the two keyframes' depth
maps (jointly with the PnP inliers as reprojection terms) uses every overlapping pixel, and the refined edge can
carry a tight weight. The check also drops PnP edges the depth disagrees with (ICP fails, is degenerate, or ends
more than a gate away from the PnP pose).

The trust gate (``max_trusted_residual_rad``): keyframe-to-keyframe ICP inherits the low-frequency distortion of
raw depth, which frame-to-model tracking averages out, and trusted biased edges make the trajectory worse than the
dense odometry alone. So the refined edges get a pose graph of their own (with the odometry), and at every
optimisation the robust spread of their rotation residuals at its optimum
(:meth:`DenseEdgeRefiner.loop_residual_spread`) says whether they are consistent with one another: unbiased edges
are, biased ones spread more. The translation residuals are tested too (``max_trusted_residual_m``): edges biased
along an axis their ICP barely constrains (a corridor's) agree in rotation but not along that axis. Above the gate
the poses come from the graph of the PnP edges (those the ICP rejected included), as without refinement. Known
limit: on orbits mildly distorted depth can stay under the gate (docs/trackers.md). Measurements:
``benchmarks/bench_hybrid.py``.

Keyframe depth is kept at a reduced size (``max_width_px``, 2x2 block averages) as 16-bit integers (steps of
``max_depth_m / 65535``). The pyramids of the last few keyframes used are cached (the nearby keyframes are checked
again at every new keyframe).
"""

from __future__ import annotations

import threading
from collections import OrderedDict, deque
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from surfelslam.config import Config, ordered, setting
from surfelslam.geometry import se3
from surfelslam.kernels import preprocess as kp
from surfelslam.tracking.features import reprojection_spread_px
from surfelslam.tracking.icp import ICPConfig, ICPResult, ReprojectionTerm, depth_scaled, icp, icp_failure
from surfelslam.tracking.preprocess import (
    MIN_LEVEL_WIDTH_PX,
    FramePyramid,
    PreprocessConfig,
    Preprocessor,
    PyramidLevel,
    level_for_width,
    pyramid_intrinsics,
)
from surfelslam.types import Intrinsics

_MAD_TO_SIGMA = 0.6745  # median |x| of a zero-mean Gaussian, in sigmas


#: ICP of a keyframe-to-keyframe registration: the ICP defaults with 3 levels (from a PnP start; at most the halvings
#: left at ``max_width_px``) and no solution remapping: remapping would leave the weakly constrained directions (e.g.
#: along the intersection of two planes) at the PnP estimate, while the feature terms constrain them. The finest
#: level keeps every second pixel: every pixel gives the same edges at twice the cost. (Formerly the
#: ``[hybrid.loop_icp.icp]`` and ``[orb.loop_icp.icp]`` tables, the same values in both.)
EDGE_ICP = ICPConfig(levels=3, weak_direction_ratio=0.0)


@dataclass(frozen=True)
class DenseEdgeConfig(Config):
    """Dense (ICP) check and refinement of PnP keyframe edges, behind a trust gate
    (:mod:`surfelslam.backend.dense_edges`)."""

    enabled: bool = setting(True, doc="refine every PnP keyframe edge by ICP between the two keyframes' depth; "
                            "edges that fail the check are dropped", user=True)
    max_width_px: int = setting(320, unit="px", ge=8, le=65536,
                                doc="keyframe depth is kept and registered at the finest pyramid level at most this "
                                    "wide")
    max_shift_m: float = setting(0.03, unit="m", gt=0, le=10,
                                 doc="ICP may move the edge at most this far from its PnP pose (farther: dropped)")
    max_shift_deg: float = setting(3.0, unit="deg", gt=0, le=180, doc="the same bound on the rotation")
    pnp_refinement: bool = setting(
        True, doc="a verified PnP edge is first refined on features (projection search, RGB-D refinement) before its "
                  "ICP; off: the ICP alone refines it, in about 60 % of the loop-check time (and the chi-square "
                  "gate weighs the edge by its sigma floors alone)")
    cached_pyramids: int = setting(16, unit="keyframes", ge=0, le=256,
                                   doc="keyframe pyramids kept between checks per thread, least recently used dropped "
                                       "first (2.4 MB each at 320x240); fewer than the keyframes one check touches "
                                       "rebuilds most of them every time")
    sigma_m: float = setting(0.003, unit="m and rad", gt=0, le=10,
                             doc="pose-graph sigma of a refined edge (isotropic): the floor of the sigma measured "
                                 "from the nearby edges' spread")
    max_trusted_residual_rad: float = setting(
        0.0003, unit="rad", gt=0, le=3.2,
        doc="the refined edges are trusted while the robust spread of their rotation residuals is at most this "
            "(biased depth spreads more); else the PnP edges' graph gives the poses")
    max_trusted_residual_m: float = setting(
        0.0005, unit="m", gt=0, le=100,
        doc="... and that of their translation residuals at most this (edges biased along a weakly constrained axis, "
            "e.g. a corridor's, disagree there and not in rotation)")
    min_spread_edges: int = setting(10, unit="edges", ge=1, le=1_000_000,
                                    doc="nearby edges needed before their spread is used, and refined edges before "
                                        "the trust gate decides (untrusted until then)")
    spread_window_edges: int = setting(200, unit="edges", ge=1, le=1_000_000,
                                       doc="the spread is taken over this many most recent nearby edges")
    feature_weight: float = setting(0.1, ge=0, le=1000,
                                    doc="the edge's PnP inliers enter its ICP as reprojection terms: one costs this "
                                        "many point-to-plane pairs; 0 = off")
    feature_sigma_px: float = setting(1.0, unit="px", gt=0, le=100,
                                      doc="floor of those terms' pixel noise (else their robust reprojection spread)")
    feature_huber: float = setting(2.0, unit="sigmas", gt=0, le=100, doc="Huber threshold of those terms")
    depth_only_nearby: bool = setting(True, doc="a nearby keyframe pair that PnP cannot verify is registered by ICP "
                                      "from the graph's relative pose, by depth alone (refined graph only)")
    weak_direction_ratio: float = setting(
        0.0, unit="ratio", ge=0, le=1e12,
        doc="a refined edge's information is lowered along the directions its ICP constrains less than 1/this of "
            "the best one (by that eigenvalue ratio of its depth-scaled Hessian), else isotropic; 0 = isotropic")
    min_weak_information: float = setting(1e-4, gt=0, le=1,
                                          doc="floor of that lowering (information relative to the isotropic)")
    depth_only_max_matches: int = setting(100, unit="matches", ge=0, le=1_000_000,
                                          doc="... only where the PnP verification had fewer good matches than this "
                                              "(texture too poor to verify)")
    odometry_nearby: bool = setting(
        False, doc="nearby keyframe pairs are checked from the odometry's relative pose (good to a few mm): the "
                   "guided matches it reprojects stand for PnP-RANSAC when they are at least half, and a verified "
                   "pair's ICP runs at the finest level only (a fifth less loop-check time); off: as older pairs")

    _spread_window = ordered("min_spread_edges", "spread_window_edges", strict=False)

    REMOVED_KEYS: ClassVar[dict[str, str]] = {
        "icp": "the keyframe-edge ICP is a constant of surfelslam.backend.dense_edges (EDGE_ICP)"}


@dataclass(frozen=True)
class RefinedEdge:
    """A dense-refined keyframe edge.

    Attributes:
        T_cur_ref: ``(4, 4)`` maps ref points into cur.
        information_shape: ``(6, 6)`` how the edge's isotropic information is spread over the directions of
            ``T_ref_cur`` (gtsam's right perturbation, ``(omega, v)``): eigenvalues 1 but below 1 along the
            directions ICP left weak (:func:`weak_direction_shape`); ``None``: isotropic.
    """

    T_cur_ref: np.ndarray
    information_shape: np.ndarray | None = None


def weak_direction_shape(normal_matrix: np.ndarray, mean_depth_m: float, T_target_source: np.ndarray,
                         weak_ratio: float, floor: float) -> np.ndarray | None:
    """Information shape ``(6, 6)`` of an ICP estimate ``T_target_source`` for gtsam's right perturbation: the
    identity, lowered along each eigen-direction of the depth-scaled normal matrix ``(6, 6)`` (left perturbation,
    :attr:`ICPResult.normal_matrix`) whose eigenvalue is below ``1 / weak_ratio`` of the largest, to
    ``max(floor, ratio * weak_ratio)``. ``None`` when no direction is that weak. Rotations are scaled by the mean
    depth, as in the condition number, so that a rotation and a translation moving points equally compare equal."""
    M, s = depth_scaled(normal_matrix, mean_depth_m)
    mu, V = np.linalg.eigh(M)
    if not mu[-1] > 0:
        return None
    w = np.clip(mu / mu[-1] * weak_ratio, floor, 1.0)
    weak = w < 1.0
    if not weak.any():
        return None
    # weak directions as twists of the right perturbation (xi_r = Ad(T^-1) S y), orthonormalised
    U, _ = np.linalg.qr(se3.adjoint(se3.invert(T_target_source)) @ np.diag(s) @ V[:, weak])
    return np.eye(6) - (U * (1.0 - w[weak])) @ U.T


class DenseEdgeRefiner:
    """Keyframe depth store and ICP refinement of keyframe edges (and of frames against keyframes).

    :meth:`add_keyframe` runs on the tracking thread; :meth:`refine` on the loop-check thread (one at a
    time); :meth:`frame_pyramid` and :meth:`refine_frame` (the orb tracker's depth odometry) on the reader and
    tracking threads. The store is append-only and guarded by a lock; each thread has its own preprocessing
    buffers and pyramid cache.

    Args:
        intr: camera of the depth images given to :meth:`add_keyframe`.
        pre_cfg: depth range and filter settings (the tracker's); the pyramid depth is ``icp_cfg.levels``.
        cfg: settings.
        icp_cfg: the registrations' ICP settings (:data:`EDGE_ICP`; its levels capped by ``cfg.max_width_px``).
    """

    def __init__(self, intr: Intrinsics, pre_cfg: PreprocessConfig, cfg: DenseEdgeConfig,
                 icp_cfg: ICPConfig = EDGE_ICP):
        self.cfg = cfg
        self._intr = intr
        self._pre_cfg = pre_cfg
        self._level = level_for_width(intr.width, cfg.max_width_px)
        self._intr_store = pyramid_intrinsics(intr, self._level + 1)[-1]
        levels = min(icp_cfg.levels, level_for_width(self._intr_store.width, MIN_LEVEL_WIDTH_PX) + 1)
        self._icp_cfg = replace(icp_cfg, levels=levels)
        self._icp_cfg_finest = replace(icp_cfg, levels=1)  # from a start already in the finest level's basin
        self._pre_cfg_store = replace(pre_cfg, pyramid_levels=levels)
        self._depth_unit_m = pre_cfg.max_depth_m / np.iinfo(np.uint16).max
        self._depth: dict[int, np.ndarray] = {}  # kf_id -> (h, w) uint16 depth in units of _depth_unit_m
        self._lock = threading.Lock()
        self._local = threading.local()  # per thread: .pre (Preprocessor, scratch buffers), .cache (pyramids)
        # |log(edge^-1 graph)| components of the recent nearby edges (tracking thread only)
        self._spread: deque[float] = deque(maxlen=6 * cfg.spread_window_edges)
        # their robust spread (:meth:`spread`), computed once per change: every edge added asks for it, a median over
        # the whole window each time (a floor's back end asked about 7000 times per 3000 frames)
        self._spread_cached: tuple[float | None] | None = None

    @property
    def intrinsics(self) -> Intrinsics:
        """Camera of the stored depth maps."""
        return self._intr_store

    def _reduce(self, depth_m: np.ndarray) -> np.ndarray:
        """``(H, W)`` float32 metres reduced to the stored size (2x2 block averages)."""
        c = self._pre_cfg
        depth = np.asarray(depth_m, np.float32)
        for lvl in range(self._level):
            out = np.empty((depth.shape[0] // 2, depth.shape[1] // 2), np.float32)
            kp.downsample_depth(depth, c.min_depth_m, c.max_depth_m, c.pyramid_max_depth_diff_m * 2.0 ** lvl, out)
            depth = out
        return depth

    def frame_pyramid(self, depth_m: np.ndarray) -> FramePyramid:
        """Pyramid of a frame's depth ``(H, W)`` float32 metres at the stored size (for :meth:`refine_frame`)."""
        return self._thread_state().pre.process(self._reduce(depth_m))

    def add_keyframe(self, kf_id: int, depth_m: np.ndarray) -> None:
        """Keep keyframe ``kf_id``'s depth ``(H, W)`` float32 metres (reduced to ``max_width_px``)."""
        c = self._pre_cfg
        depth = self._reduce(depth_m)
        valid = (depth >= c.min_depth_m) & (depth <= c.max_depth_m)
        stored = np.where(valid, np.rint(depth / self._depth_unit_m), 0).astype(np.uint16)
        with self._lock:
            self._depth[kf_id] = stored

    def observe_nearby(self, T_i_j_edge: np.ndarray, T_i_j_odometry: np.ndarray) -> None:
        """Record a refined nearby edge ``T_i_j`` ``(4, 4)`` against the odometry's relative pose ``(4, 4)``."""
        d = se3.log(se3.invert(np.asarray(T_i_j_edge, np.float64)) @ np.asarray(T_i_j_odometry, np.float64))
        self._spread.extend(np.abs(d).tolist())
        self._spread_cached = None

    def spread(self) -> float | None:
        """Robust spread (m and rad) of the recent nearby edges against the odometry, ``None`` before
        ``min_spread_edges`` were seen."""
        if self._spread_cached is None:
            enough = len(self._spread) >= 6 * self.cfg.min_spread_edges
            self._spread_cached = (float(np.median(np.fromiter(self._spread, float))) / _MAD_TO_SIGMA
                                   if enough else None,)
        return self._spread_cached[0]

    def loop_residual_spread(self, T_ij: np.ndarray, i: np.ndarray, j: np.ndarray, poses_world_kf: np.ndarray,
                             residuals: LoopResiduals | None = None) -> tuple[float, float] | None:
        """Robust spreads ``(rad, m)`` of the rotation and translation residuals of the refined loop edges, stacked
        as :meth:`PoseGraph.loop_edges` keeps them (``T_i_j`` ``(L, 4, 4)``, ``i`` and ``j`` ``(L,)``), at the poses
        ``(K, 4, 4)`` their graph was optimised to; ``None`` with fewer than ``min_spread_edges`` of them.
        ``residuals``: the same edges' residuals kept from the previous call (:class:`LoopResiduals`: only the edges
        that are new or whose keyframes moved are recomputed; the same result)."""
        if len(T_ij) < self.cfg.min_spread_edges:
            return None
        if residuals is None:
            residuals = LoopResiduals()
        r = residuals.update(T_ij, i, j, poses_world_kf)
        return (float(np.median(r[:, :3])) / _MAD_TO_SIGMA, float(np.median(r[:, 3:])) / _MAD_TO_SIGMA)

    def trusted(self, spread: tuple[float, float] | None) -> bool:
        """Whether refined edges whose graph leaves the residual ``spread`` ``(rad, m)`` (:meth:`loop_residual_spread`)
        are trusted (``None``, too few edges to tell: not trusted)."""
        return (spread is not None and spread[0] <= self.cfg.max_trusted_residual_rad
                and spread[1] <= self.cfg.max_trusted_residual_m)

    def edge_sigma(self) -> float:
        """Sigma (m and rad) of a refined edge: ``max(sigma_m, spread of the recent nearby edges)``."""
        s = self.spread()
        return self.cfg.sigma_m if s is None else max(self.cfg.sigma_m, s)

    def depth_m(self, kf_id: int) -> np.ndarray:
        """Keyframe ``kf_id``'s stored depth ``(h, w)`` float32 metres (camera :attr:`intrinsics`; 0 = invalid)."""
        with self._lock:
            stored = self._depth[kf_id]
        return stored.astype(np.float32) * np.float32(self._depth_unit_m)

    def keyframe_pyramid(self, pyramid: FramePyramid) -> FramePyramid | None:
        """A copy of the levels :meth:`refine` registers, taken from the tracker's own pyramid of a new keyframe
        (``pyramid``: built with this refiner's preprocessing settings, its finest level computed), or ``None`` when
        that pyramid is not the one :meth:`refine` would build: the keyframe depth is stored reduced, or the sizes
        differ. Handed to :meth:`adopt`, it saves rebuilding the new keyframe's pyramid (a bilateral filter and
        normals: about as much as one refinement) for its first checks; it differs from a rebuild only by the
        stored depth's rounding (``max_depth_m / 65535``)."""
        levels = self._icp_cfg.levels
        if self._level != 0 or pyramid.intrinsics != self._intr_store or len(pyramid) < levels:
            return None
        return FramePyramid([PyramidLevel(lv.vertex.copy(), lv.normal.copy(), lv.intrinsics)
                             for lv in pyramid.levels[:levels]])

    def adopt(self, kf_id: int, pyramid: FramePyramid) -> None:
        """Use ``pyramid`` (:meth:`keyframe_pyramid`) as keyframe ``kf_id``'s in the calling thread's cache."""
        self._cache_put(self._thread_state().cache, kf_id, pyramid)

    def _cache_put(self, cache: OrderedDict, kf_id: int, pyramid: FramePyramid) -> None:
        if self.cfg.cached_pyramids > 0:
            cache[kf_id] = pyramid
            cache.move_to_end(kf_id)
            while len(cache) > self.cfg.cached_pyramids:
                cache.popitem(last=False)

    def _thread_state(self) -> threading.local:
        st = self._local
        if not hasattr(st, "pre"):
            st.pre = Preprocessor(self._intr_store, self._pre_cfg_store)
            st.cache = OrderedDict()  # kf_id -> FramePyramid, least recently used first
        return st

    def _pyramid(self, kf_id: int) -> FramePyramid:
        st = self._thread_state()
        pyr = st.cache.get(kf_id)
        if pyr is not None:
            st.cache.move_to_end(kf_id)
            return pyr
        pyr = st.pre.process(self.depth_m(kf_id))
        self._cache_put(st.cache, kf_id, pyr)
        return pyr

    def refine(self, ref_id: int, cur_id: int, T_cur_ref: np.ndarray, points_ref: np.ndarray | None = None,
               uv_cur: np.ndarray | None = None, finest_only: bool = False) -> RefinedEdge | None:
        """ICP of keyframe ``cur_id`` against ``ref_id`` from the PnP edge ``T_cur_ref`` ``(4, 4)`` (maps ref
        points into cur), jointly with the PnP inliers ``points_ref`` ``(M, 3)`` (ref camera, m) observed at
        ``uv_cur`` ``(M, 2)`` (pixels of the cur image, the camera given at construction); returns the refined
        edge, or ``None`` when the check fails. ``finest_only``: ``T_cur_ref`` is within a few mm (a nearby pair's
        odometry, :attr:`DenseEdgeConfig.odometry_nearby`): the ICP skips the coarser levels."""
        c = self.cfg
        res = self._register(ref_id, self._pyramid(cur_id), T_cur_ref, points_ref, uv_cur, c.max_shift_m,
                             c.max_shift_deg, self._icp_cfg_finest if finest_only else self._icp_cfg)
        if res is None:
            return None
        shape = None
        if c.weak_direction_ratio > 0:
            shape = weak_direction_shape(res.normal_matrix, res.mean_depth_m, res.T_target_source,
                                         c.weak_direction_ratio, c.min_weak_information)
        return RefinedEdge(se3.orthonormalize(se3.invert(res.T_target_source)), shape)

    def refine_frame(self, ref_id: int, source: FramePyramid, T_cur_ref: np.ndarray,
                     points_ref: np.ndarray | None, uv_cur: np.ndarray | None,
                     max_shift_m: float, max_shift_deg: float) -> np.ndarray | None:
        """:meth:`refine` for a frame given by its :meth:`frame_pyramid` ``source`` (camera :attr:`intrinsics`)
        instead of a keyframe, with its own bounds on the move from ``T_cur_ref`` (m, deg; ``inf``: only ICP's
        own implausible-motion bounds, ``ICPConfig.max_translation_m`` / ``max_rotation_deg``)."""
        res = self._register(ref_id, source, T_cur_ref, points_ref, uv_cur, max_shift_m, max_shift_deg)
        return None if res is None else se3.orthonormalize(se3.invert(res.T_target_source))

    def _register(self, ref_id: int, source: FramePyramid, T_cur_ref: np.ndarray, points_ref: np.ndarray | None,
                  uv_cur: np.ndarray | None, max_shift_m: float, max_shift_deg: float,
                  icp_cfg: ICPConfig | None = None) -> ICPResult | None:
        """The ICP of :meth:`refine_frame` (with ``icp_cfg``, default the refiner's), or ``None`` when it fails its
        checks."""
        target = self._pyramid(ref_id)
        T_cur_ref = np.asarray(T_cur_ref, np.float64)
        T_init = se3.invert(T_cur_ref)  # T_ref_cur = T_target_source
        term = self._feature_term(T_cur_ref, points_ref, uv_cur)
        res = icp(source, target, T_init=T_init, cfg=icp_cfg or self._icp_cfg, reprojection=term)
        if icp_failure(res) is not None or res.degenerate:
            return None
        dt_m, dr_deg = se3.pose_error(res.T_target_source, T_init)
        if dt_m > max_shift_m or dr_deg > max_shift_deg:
            return None
        return res

    def _feature_term(self, T_cur_ref: np.ndarray, points_ref: np.ndarray | None,
                      uv_cur: np.ndarray | None) -> ReprojectionTerm | None:
        c = self.cfg
        if c.feature_weight == 0 or points_ref is None or uv_cur is None or len(points_ref) == 0:
            return None
        pts = np.asarray(points_ref, np.float64)
        uv = np.asarray(uv_cur, np.float64)
        spread = reprojection_spread_px(se3.transform_points(T_cur_ref, pts), uv, self._intr)
        return ReprojectionTerm(pts, uv, self._intr, max(c.feature_sigma_px, spread), c.feature_huber,
                                c.feature_weight * self._icp_cfg.finest_robust_scale_m ** 2)


def loop_residuals(T_ij: np.ndarray, i: np.ndarray, j: np.ndarray, poses_world_kf: np.ndarray) -> np.ndarray:
    """``(L, 6)`` absolute rotation (rad) and translation (m) residuals ``T_i_j^-1 T_world_i^-1 T_world_j`` of the
    edges ``T_i_j`` ``(L, 4, 4)`` between keyframes ``i`` and ``j`` ``(L,)`` at the poses ``(K, 4, 4)``, as one
    batch (each row depends on its own edge alone)."""
    P = np.asarray(poses_world_kf, np.float64)
    Rt_ij = np.swapaxes(T_ij[:, :3, :3], 1, 2)
    Rt_i = np.swapaxes(P[i, :3, :3], 1, 2)
    rot = se3.so3_log(Rt_ij @ Rt_i @ P[j, :3, :3])
    t_rel = np.einsum("kab,kb->ka", Rt_i, P[j, :3, 3] - P[i, :3, 3])
    trans = np.einsum("kab,kb->ka", Rt_ij, t_rel - T_ij[:, :3, 3])
    return np.abs(np.concatenate([rot, trans], axis=1))


class LoopResiduals:
    """The :func:`loop_residuals` of a list of edges that only grows (each edge's ``T_i_j``, ``i`` and ``j`` fixed
    once added), kept between calls: a call recomputes only the new edges and those with a keyframe whose pose is
    not bit-for-bit the one of the previous call, so a graph optimisation that moved a few keyframes costs what it
    moved (the result equals a full recomputation)."""

    def __init__(self) -> None:
        self._res = np.zeros((0, 6))  # (L, 6) per edge, at self._poses
        self._poses = np.zeros((0, 4, 4))  # the poses of the last call

    def update(self, T_ij: np.ndarray, i: np.ndarray, j: np.ndarray, poses_world_kf: np.ndarray) -> np.ndarray:
        """``(L, 6)`` residuals of the edges (the previous call's followed by new ones) at ``poses_world_kf``."""
        P = np.asarray(poses_world_kf, np.float64)
        n_old, k_old = len(self._res), min(len(self._poses), len(P))
        moved = np.ones(len(P), bool)
        moved[:k_old] = np.any(P[:k_old] != self._poses[:k_old], axis=(1, 2))
        redo = np.flatnonzero(moved[i[:n_old]] | moved[j[:n_old]])
        res = np.empty((len(T_ij), 6))
        res[:n_old] = self._res
        if len(redo):
            res[redo] = loop_residuals(T_ij[redo], i[redo], j[redo], P)
        if len(T_ij) > n_old:
            res[n_old:] = loop_residuals(T_ij[n_old:], i[n_old:], j[n_old:], P)
        self._res, self._poses = res, P.copy()
        return res
