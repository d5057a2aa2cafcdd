"""Keyframe edges from the old map itself (ElasticFusion's local loop closure, with the hybrid's keyframe anchors).

Loop edges of the back end need an appearance match between keyframes (ORB retrieval + PnP): a camera that comes
back to a place facing another way retrieves no old keyframe, and its drifted pose leaves the old surfels beside the
ones it fuses now. But every surfel is anchored to a keyframe (:class:`KeyframeAnchors`), and ``kf_dense[k]`` is where
keyframe ``k``'s surfels are. So at each new keyframe the *inactive* map (surfels not fused into for
:data:`INACTIVE_AFTER_S`) is rendered at its pose and its frame registered to it by ICP; the main anchor ``k_old``
of the visit that anchors most inlier pixels (:func:`dominant_visit`) gives ``inv(kf_dense[k_old]) T_registered``:
an edge ``k_old -> new`` that needs no appearance match and holds from any viewing direction. A large one closes a
loop; a tiny one (below ICP's noise) is still a constraint the graph otherwise lacks (frames that partly see the old
map).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from surfelslam.backend.sparse_slam import SparseSlam
from surfelslam.backend.sparse_slam.loop_checks import CLOSED_LOOP_SHIFT_DEG, CLOSED_LOOP_SHIFT_M
from surfelslam.geometry import se3
from surfelslam.mapping.render import RenderConfig, render
from surfelslam.slam.frontend import TARGET_FAR_SLACK_M
from surfelslam.slam.hybrid_anchors import KeyframeAnchors
from surfelslam.slam.motion import step_and_pose
from surfelslam.tracking.icp import ICPConfig, ICPResult, ICPStatus, depth_scaled, icp, icp_failure
from surfelslam.tracking.preprocess import FramePyramid, PreprocessConfig, pyramid_from_maps

#: s: a surfel not fused into for this long is inactive (ElasticFusion: not seen in the last 200 frames at 30 Hz). The
#: active map is what the tracker registers to anyway; the inactive one is where drift since the last visit shows
INACTIVE_AFTER_S = 200 / 30
#: fraction of the view the unoccluded inactive render must cover for a check: a tenth of it holds 4x the finest
#: ICP level's minimum inliers (``icp.min_inliers`` at its source stride); a smaller patch of the old map constrains
#: the 6 DoF of an edge too weakly, and the check would run at most keyframes for nothing
MIN_COVERAGE = 0.1
#: fraction of the inlier pixels the dominant visit's keyframes must hold (:func:`dominant_visit`): below it the pixels
#: mix surfels from several visits (two copies of a wall), and the edge to one of them is not what the registration
#: measured. One visit's surfels are spread over many keyframes (a room swept for a minute: 20 of them, none with
#: more than a tenth), but they were fused by one odometry run and lie as its keyframes do
MIN_DOMINANT_SHARE = 0.5
#: the ICP's inliers must be at least this fraction of the frame's points that land on the rendered old map (a wrong
#: place's render overlaps the view but most of its pixels do not fit; the tracker's own overlap test uses its
#: ``icp.min_inlier_fraction``, this is stricter: an edge carries a millimetre sigma)
MIN_OVERLAP_INLIER_FRACTION = 0.6
#: m and deg: an edge needs the previous keyframe's registration to the old map to have found the same correction of
#: the dense pose (compared at the new keyframe) within these: a drift changes little from one keyframe to the next,
#: a slide of ICP along weak geometry does not repeat itself (ICP's own noise is millimetres, the drift's change
#: between keyframes less)
AGREE_M = 0.02
AGREE_DEG = 1.0


@dataclass
class MapEdgeCounts:
    """What the map-edge checks did (``metrics.json``: ``map_edges_*``)."""

    tried: int = 0  # inactive render covered enough of the view: ICP run
    registered: int = 0  # ... ICP accepted and a dominant old visit found
    repeated: int = 0  # ... the previous keyframe's registration agreed
    accepted: int = 0  # ... the back end's gates passed: an edge
    closures: int = 0  # ... of them farther than ICP's noise from the graph's estimate (the graph was optimised)
    ms: list[float] = field(default_factory=list)  # tracking-thread time per tried check
    checks: int = 0  # keyframes checked (the inactive render drawn)
    total_ms: float = 0.0  # tracking-thread time of every check

    def as_metrics(self) -> dict:
        return {"map_edges_tried": self.tried, "map_edges_registered": self.registered,
                "map_edges_repeated": self.repeated, "map_edges_accepted": self.accepted,
                "map_edges_closures": self.closures,
                "map_edge_ms_median": float(np.median(self.ms)) if self.ms else None,
                "map_edge_ms_per_keyframe": self.total_ms / self.checks if self.checks else None}


@dataclass
class MapRegistration:
    """A keyframe registered to the inactive map: the old keyframe, the measured ``T_old_new``, the ICP result."""

    kf_old: int
    T_old_new: np.ndarray
    res: ICPResult
    share: float  # the dominant visit's share of the inlier pixels


def _unoccluded(view, depth_m: np.ndarray) -> np.ndarray:
    """``(H, W)`` the pixels of the inactive render ``view`` within :data:`TARGET_FAR_SLACK_M` (the largest depth
    change a correction ICP may find makes) of the frame's own depth ``depth_m`` ``(H, W)`` (0: none): without the
    active map in front of it, the inactive render shows the rooms behind the walls the camera sees, and surfaces it
    cannot see (:func:`_clear_outside` removes them)."""
    z = view.vertex_cam[..., 2]
    return (view.index >= 0) & (depth_m > 0) & (np.abs(z - depth_m) <= TARGET_FAR_SLACK_M)


def _clear_outside(view, keep: np.ndarray) -> None:
    """Clear the pixels of ``view`` outside ``keep`` ``(H, W)`` (no surfel, no vertex, no normal). Only for a view
    that passes the coverage test: most checks end before it, and masked copies cost milliseconds per view."""
    drop = ~keep
    np.copyto(view.index, -1, where=drop)
    np.copyto(view.vertex_cam, 0.0, where=drop[..., None])
    np.copyto(view.normal_cam, 0.0, where=drop[..., None])


def dominant_visit(anchors: np.ndarray, kf_stamps: Callable[[np.ndarray], np.ndarray],
                   gap: float) -> tuple[int, float]:
    """``(k_old, share)``: the visit that anchors most of the inlier pixels, and its keyframe with most of them.

    ``anchors`` ``(N,)`` int64 anchor keyframe per inlier pixel; ``kf_stamps`` gives the stamps of keyframe ids. A
    visit is a run of the voting keyframes (in id order, so in time) whose stamps follow each other by at most
    ``gap``: a camera away from a place for longer left its surfels inactive, and came back with another drift.
    ``share`` is the visit's fraction of the ``N`` pixels."""
    votes = np.bincount(anchors)
    voters = np.flatnonzero(votes)
    visit = np.concatenate([[0], np.cumsum(np.diff(kf_stamps(voters)) > gap)])
    per_visit = np.bincount(visit, weights=votes[voters])
    best = int(np.argmax(per_visit))
    members = voters[visit == best]
    return int(members[np.argmax(votes[members])]), float(per_visit[best]) / len(anchors)


def weakest_sigma_m(res: ICPResult) -> float:
    """Standard deviation (m; a rotation as the motion it gives at the mean depth) of ``res``'s pose along its least
    constrained direction: the finest level's point-to-plane noise over the square root of the smallest eigenvalue of
    its depth-scaled normal matrix. A patch of old floor and one wall lets ICP slide along the wall by tens of
    centimetres with a condition number below the degeneracy bound; this says how far it could."""
    if res.normal_matrix is None:
        return float("inf")
    lam = np.linalg.eigvalsh(depth_scaled(res.normal_matrix, res.mean_depth_m)[0])[0]
    return float(res.levels[-1].geometric_noise_m / np.sqrt(lam)) if lam > 0 else float("inf")


class MapEdges:
    """The map-edge check of each new keyframe (see the module docstring).

    Args:
        anchors: the keyframes' dense poses and the surfels' anchors.
        sparse: the back end that takes the edges (:meth:`SparseSlam.add_map_edge`).
        icp_cfg: the tracker's ICP settings (the check uses them without the weak-direction remapping: it accepts
            only a well-conditioned result).
        render_cfg: the tracking render's settings; pre_cfg: the preprocessing (the target pyramid's).
        sigma: the edges' sigma (m and rad) now, as a refined loop edge's.
    """

    def __init__(self, anchors: KeyframeAnchors, sparse: SparseSlam, icp_cfg: ICPConfig, render_cfg: RenderConfig,
                 pre_cfg: PreprocessConfig):
        self.anchors = anchors
        self.sparse = sparse
        self.icp_cfg = replace(icp_cfg, weak_direction_ratio=0.0)
        self.render_cfg = render_cfg
        self.pre_cfg = pre_cfg
        self.counts = MapEdgeCounts()
        self._target: FramePyramid | None = None
        self._last: tuple[int, np.ndarray] | None = None  # (keyframe, correction T_reg inv(T_kf)) of the last check

    def register(self, smap, source: FramePyramid, T_world_kf: np.ndarray, stamp: float, frame_index: int,
                 sigma: float, seconds_per_stamp: float = 1.0) -> MapRegistration | None:
        """Register ``source`` (the new keyframe's pyramid at the tracking level, frame ``frame_index`` stamped
        ``stamp``, in units of ``seconds_per_stamp``) at ``T_world_kf`` (dense frame) to the inactive part of ``smap``
        rendered there; ``None`` when too little of it is in view, ICP fails, leaves a direction looser than the
        edge's ``sigma`` (m), or no visit dominates."""
        old_frame = min(self.anchors.last_frame_before(stamp - INACTIVE_AFTER_S / seconds_per_stamp), frame_index - 1)
        if old_frame < 0 or smap.size == 0:
            return None
        intr = source[0].intrinsics
        last_seen = smap.last_seen
        view = render(smap, T_world_kf, intr, self.render_cfg, attributes=False,
                      select=lambda cand: cand[last_seen[cand] <= old_frame])
        valid = _unoccluded(view, source[0].vertex[..., 2])
        if np.count_nonzero(valid) < MIN_COVERAGE * valid.size:
            return None
        _clear_outside(view, valid)
        self.counts.tried += 1
        if self._target is None or self._target[0].intrinsics != intr or len(self._target) != len(source):
            self._target = FramePyramid.empty(intr, len(source))
        target = pyramid_from_maps(view.vertex_cam, view.normal_cam, intr, len(source), self.pre_cfg,
                                   out=self._target)
        res = icp(source, target, T_init=np.eye(4), cfg=self.icp_cfg)
        if not self._usable(res, sigma):
            return None
        rows = self._inlier_rows(source, view, res)
        if len(rows) == 0:
            return None
        k_old, share = dominant_visit(self.anchors.anchors_of(smap.first_seen[rows]), self.anchors.keyframe_stamps,
                                      INACTIVE_AFTER_S / seconds_per_stamp)
        if share < MIN_DOMINANT_SHARE:
            return None
        T_reg = step_and_pose(T_world_kf, res)[1]
        return MapRegistration(k_old, se3.orthonormalize(se3.invert(self.anchors.kf_dense.poses[k_old]) @ T_reg),
                               res, share)

    def _usable(self, res: ICPResult, sigma: float) -> bool:
        """A converged, well-conditioned result with enough inliers among the points on the rendered old map
        (``icp_failure``; its inlier fraction of the whole view is replaced by that of the overlap) that pins every
        direction within the edge's ``sigma`` (:func:`weakest_sigma_m`)."""
        fine = res.levels[-1]
        if (res.degenerate or fine.stop not in ("update", "residual") or fine.inliers < self.icp_cfg.min_inliers
                or weakest_sigma_m(res) > sigma):
            return False
        failure = icp_failure(res)
        if failure is not None and failure != ICPStatus.TOO_FEW_INLIERS:
            return False
        return fine.overlap_inlier_fraction >= MIN_OVERLAP_INLIER_FRACTION

    def _inlier_rows(self, source: FramePyramid, view, res: ICPResult) -> np.ndarray:
        """Surfel rows drawn at the pixels where the source's points (every ICP-stride-th) land within the finest
        association gate of the rendered point, at the registered pose."""
        s = self.icp_cfg.finest_source_stride_px
        v = source[0].vertex[::s, ::s].reshape(-1, 3)
        v = v[v[:, 2] > 0]
        T = res.T_target_source
        p = v @ T[:3, :3].T + T[:3, 3]
        intr = source[0].intrinsics
        z = p[:, 2]
        ok = z > 0
        u = np.rint(intr.fx * p[:, 0] / np.where(ok, z, 1.0) + intr.cx).astype(np.int64)
        w = np.rint(intr.fy * p[:, 1] / np.where(ok, z, 1.0) + intr.cy).astype(np.int64)
        ok &= (u >= 0) & (u < intr.width) & (w >= 0) & (w < intr.height)
        u, w, p = u[ok], w[ok], p[ok]
        idx = view.index[w, u]
        d = np.linalg.norm(view.vertex_cam[w, u] - p, axis=1)
        return idx[(idx >= 0) & (d <= self.icp_cfg.dist_thresh_m[0])]

    def check(self, smap, source: FramePyramid, T_world_kf: np.ndarray, stamp: float, frame_index: int,
              sigma: float, seconds_per_stamp: float = 1.0) -> bool:
        """The new (last) keyframe's map-edge check: registered (:meth:`register`) and handed to the back end with
        ``sigma`` (m and rad). Returns whether the back end re-optimised its graph (a correction to apply). Its time
        goes into :attr:`counts` (metrics, not a decision)."""
        c0, tried = time.perf_counter(), self.counts.tried
        closes = self._check(smap, source, T_world_kf, stamp, frame_index, sigma, seconds_per_stamp)
        ms = (time.perf_counter() - c0) * 1e3
        self.counts.checks += 1
        self.counts.total_ms += ms
        if self.counts.tried > tried:
            self.counts.ms.append(ms)
        return closes

    def _check(self, smap, source: FramePyramid, T_world_kf: np.ndarray, stamp: float, frame_index: int,
               sigma: float, seconds_per_stamp: float) -> bool:
        reg = self.register(smap, source, T_world_kf, stamp, frame_index, sigma, seconds_per_stamp)
        kf_new = self.sparse.n_keyframes - 1
        last, self._last = self._last, None
        if reg is None:
            return False
        self.counts.registered += 1
        T_reg = self.anchors.kf_dense.poses[reg.kf_old] @ reg.T_old_new
        self._last = (kf_new, T_reg @ se3.invert(T_world_kf))
        if last is None or last[0] != kf_new - 1 or reg.kf_old >= kf_new:
            return False
        dt_m, dr_deg = se3.pose_error(last[1] @ T_world_kf, T_reg)
        if dt_m > AGREE_M or dr_deg > AGREE_DEG:
            return False
        self.counts.repeated += 1
        T_graph = se3.invert(self.sparse.keyframe_pose(reg.kf_old)) @ self.sparse.keyframe_pose(kf_new)
        dt_m, dr_deg = se3.pose_error(reg.T_old_new, T_graph)
        if not self.sparse.add_map_edge(reg.kf_old, kf_new, reg.T_old_new, sigma, CLOSED_LOOP_SHIFT_M,
                                        CLOSED_LOOP_SHIFT_DEG):
            return False
        self.counts.accepted += 1
        closes = dt_m > CLOSED_LOOP_SHIFT_M or dr_deg > CLOSED_LOOP_SHIFT_DEG
        self.counts.closures += int(closes)
        return closes
