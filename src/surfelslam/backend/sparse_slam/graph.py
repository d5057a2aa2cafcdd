"""The keyframes' pose graph of the sparse SLAM: odometry and verified loop edges, the optional graph of dense-refined
edges and its trust gate, and the rigid move that joins a new segment to the older map."""

from __future__ import annotations

from collections import deque
from dataclasses import replace

import numpy as np

from surfelslam.backend.dense_edges import DenseEdgeRefiner, LoopResiduals, RefinedEdge
from surfelslam.backend.edge_graph_gate import EdgeGraph
from surfelslam.backend.loop_consistency import LoopConsistencyConfig, OdometryChain
from surfelslam.backend.pose_graph import PoseEdge, PoseGraph, PoseGraphConfig
from surfelslam.backend.sparse_slam.results import LoopCheck
from surfelslam.geometry.se3 import invert, orthonormalize, pose_error
from surfelslam.types import PoseArray

# the graph gate searches paths up to the odometry chain's variance times this (the chain is such a path: the margin
# only absorbs rounding, so that a graph of odometry edges alone finds the chain itself)
_LIMIT_MARGIN = 1.000001
# gated edges whose distances (gate_d2, gate_d2_graph: diagnostics) are kept, the newest: bounded memory on a long run
GATE_D2_KEPT = 10_000


class KeyframeGraph:
    """Keyframe poses and the graph(s) that optimise them.

    With an edge refiner a second graph holds the refined edges (the first the PnP ones); each optimisation checks the
    refined edges' consistency there and takes its poses from the trusted graph. A verified edge that disagrees with
    the odometry chain between its keyframes (:mod:`~surfelslam.backend.loop_consistency`) enters neither graph; nor
    does a far one that disagrees with the graph of the edges accepted so far
    (:mod:`~surfelslam.backend.edge_graph_gate`).

    Args:
        cfg: pose-graph weights and solver (both graphs).
        refiner: the dense check of keyframe edges, or ``None`` (one graph, of PnP edges).
        refined_robust_scale: scale (whitened units) of the loop kernel on refined edges (``None``: the config's).
        consistency: the chi-square gate of edges against the odometry chain (``None``: the defaults).
        pnp_nearby: whether PnP edges to nearby keyframes enter the PnP edges' graph (off: only their refined
            versions enter the refined graph, and a nearby edge that joins a new segment to the old map).
    """

    def __init__(self, cfg: PoseGraphConfig, refiner: DenseEdgeRefiner | None,
                 refined_robust_scale: float | None, consistency: LoopConsistencyConfig | None = None,
                 pnp_nearby: bool = True) -> None:
        self._refiner = refiner
        self._pnp_nearby = pnp_nearby
        self._refined_robust_scale = refined_robust_scale
        self._graph = PoseGraph(cfg)
        self._graph_refined = None if refiner is None else PoseGraph(cfg)
        self._loop_residuals = LoopResiduals()  # the refined loop edges' residuals, kept between optimisations
        self._pose_buf = PoseArray()  # current estimates T_world_kf
        # T_world_kf chained from odometry edges alone (never optimised), and the gate against it
        self._chain = OdometryChain(consistency or LoopConsistencyConfig())
        # the accepted edges as measured (refined where refined), the graph gate of far edges against them
        self._edge_graph = EdgeGraph()
        self.refined_trusted = False  # until enough refined edges show they are consistent (DenseEdgeRefiner.trusted)
        self.refined_residual_rad: float | None = None
        self.refined_residual_m: float | None = None
        self._open_bridges: list[int] = []  # first keyframes of segments no loop edge has joined to the old map
        self.loops_found: list[tuple[int, int, int]] = []
        self.loops_accepted: list[tuple[int, int, int]] = []
        self.n_nearby_edges = 0
        self.n_dense_refined = 0  # edges refined by the dense check
        self.n_weak_shaped = 0  # refined (or depth-only) edges weighed less along directions their ICP left weak
        self.n_dense_rejected = 0  # PnP-verified edges the dense check dropped
        self.n_depth_only_edges = 0  # nearby edges from depth alone where PnP could not verify (refined graph only)
        self.n_segments_merged = 0  # segments moved onto the older map by a loop edge
        self.n_loops_rejected_inconsistent = 0  # verified far edges a gate (odometry chain or graph) rejected
        self.n_loops_rejected_graph = 0  # ... of them, those the odometry chain passed and the graph gate rejected
        self.n_nearby_rejected_inconsistent = 0  # ... nearby ones (``gate_nearby``)
        self.n_nearby_pnp_left_out = 0  # verified nearby PnP edges kept out of the PnP graph (``pnp_nearby`` off)
        self.n_map_edges = 0  # edges from registrations to the old map accepted (:meth:`add_map_edge`)
        self.n_map_edges_rejected = 0  # ... that a gate (odometry chain or graph) rejected
        # (kf_old, kf_new, squared distance) of the last GATE_D2_KEPT gated edges, and the same for the graph gate
        self.gate_d2: deque[tuple[int, int, float]] = deque(maxlen=GATE_D2_KEPT)
        self.gate_d2_graph: deque[tuple[int, int, float]] = deque(maxlen=GATE_D2_KEPT)

    @property
    def gate_threshold(self) -> float:
        """Squared Mahalanobis distance above which the odometry-chain gate rejects an edge (see :attr:`gate_d2`)."""
        return self._chain.threshold

    def edge_counts(self) -> dict[str, int]:
        """The edge and segment counters, by their ``metrics.json`` names."""
        return {"loops_rejected_inconsistent": self.n_loops_rejected_inconsistent,
                "loops_rejected_graph": self.n_loops_rejected_graph,
                "nearby_rejected_inconsistent": self.n_nearby_rejected_inconsistent,
                "nearby_pnp_left_out": self.n_nearby_pnp_left_out,
                "segments_merged": self.n_segments_merged,
                "map_edges_accepted": self.n_map_edges,
                "map_edges_rejected_inconsistent": self.n_map_edges_rejected,
                "edges_dense_refined": self.n_dense_refined,
                "edges_dense_rejected": self.n_dense_rejected,
                "depth_only_edges": self.n_depth_only_edges,
                "edges_weak_shaped": self.n_weak_shaped,
                "graph_batch_fallbacks": self._graph.n_batch_fallbacks}

    def dense_edge_stats(self) -> dict[str, float | bool | None]:
        """The refined edges' gate by their ``metrics.json`` names: ``edge_sigma_m`` (the sigma, m and rad, new
        refined edges get now), ``edge_spread_m`` (their robust spread against the odometry), whether they are
        trusted, and the robust spreads of their rotation (rad) and translation (m) residuals at the last
        optimisation of their graph; ``None`` without an edge refiner or before enough edges."""
        ref = self._refiner
        return {"edge_sigma_m": None if ref is None else ref.edge_sigma(),
                "edge_spread_m": None if ref is None else ref.spread(),
                "edges_refined_trusted": None if ref is None else self.refined_trusted,
                "edge_residual_rad": self.refined_residual_rad,
                "edge_residual_m": self.refined_residual_m}

    @property
    def poses(self) -> np.ndarray:
        """``(K, 4, 4)`` current estimates ``T_world_kf`` (a view: writes go to the graph's pose store)."""
        return self._pose_buf.poses

    def __len__(self) -> int:
        return len(self._pose_buf)

    def add_node(self, T_world_kf: np.ndarray, prev_kf: int | None, T_prev_new: np.ndarray | None) -> int:
        """Add a keyframe at ``T_world_kf`` ``(4, 4)``, reached from keyframe ``prev_kf`` by the odometry
        ``T_prev_new`` (``None``: the first keyframe or a dense pose); returns its id. The edge is added separately
        (:meth:`add_edge`)."""
        kf_id = self._graph.add_node(T_world_kf)
        if self._graph_refined is not None:
            self._graph_refined.add_node(T_world_kf)
        self._pose_buf.append(T_world_kf)
        self._chain.add(T_world_kf, prev_kf, T_prev_new)
        self._edge_graph.add_node()
        if prev_kf is not None and T_prev_new is not None:
            self._edge_graph.add_edge(prev_kf, kf_id, T_prev_new, self._chain.step_covariance(kf_id))
        return kf_id

    def start_segment(self, kf_id: int) -> None:
        """Keyframe ``kf_id`` starts a new segment (after a long loss): the first accepted edge from it or a later
        keyframe to one before it moves the segment onto the older map (:meth:`merge_segment`)."""
        self._open_bridges.append(kf_id)
        self._chain.mark_unknown(kf_id)
        self._edge_graph.remove_edge(self._chain.parent(kf_id), kf_id)

    def apply_loop_checks(self, kf_id: int, checked: list[LoopCheck], min_inliers: int) -> int:
        """Add the verified edges of keyframe ``kf_id``; optimise when one reaches an older (non-nearby) keyframe or
        joins the newest segment to the keyframes before it (which first moves the segment, :meth:`merge_segment`).

        ``min_inliers``: PnP inliers of a far candidate to count as a loop found. Returns the loops accepted."""
        n_loops = 0
        # (inliers, edge) of the best accepted edge (nearby or not) from the newest segment to a keyframe before it
        bridging: tuple[int, PoseEdge] | None = None
        b = self._open_bridges[-1] if self._open_bridges else None
        for check in checked:
            cand, res, refined = check.candidate, check.result, check.refined
            far = cand.source != "nearby"
            if far and res.reason != "too_few_matches" and res.n_inliers >= min_inliers \
                    and res.reason != "motion_too_large":
                self.loops_found.append((cand.kf_id, kf_id, res.n_inliers))
            if check.depth_only:
                self.n_depth_only_edges += 1
                self.add_edge(None, PoseEdge(cand.kf_id, kf_id, invert(refined.T_cur_ref), "loop",
                                             robust_scale=self._refined_robust_scale,
                                             information_shape=refined.information_shape))
                continue
            if not res.ok or not self._consistent(cand.kf_id, kf_id, res, far):
                continue
            crosses = b is not None and cand.kf_id < b <= kf_id
            if not (far or crosses or self._pnp_nearby):
                self._add_refined_nearby(cand.kf_id, kf_id, None if check.dense_rejected else refined)
                continue
            # T_i_j = T_cur_ref^-1: a left perturbation of T_cur_ref is minus a right one of T_i_j (same information)
            pnp = PoseEdge(cand.kf_id, kf_id, invert(res.T_cur_ref), "loop", information_matrix=res.information)
            if check.dense_rejected:  # in the PnP edges' graph only
                self.n_dense_rejected += 1
                added = self.add_edge(pnp, dense_rejected=True)
            elif refined is not None:
                added = self.add_edge(pnp, self._refined_edge(cand.kf_id, kf_id, refined, far))
            else:
                added = self.add_edge(pnp)
            if added and far:
                self.loops_accepted.append((cand.kf_id, kf_id, res.n_inliers))
                n_loops += 1
            elif added:
                self.n_nearby_edges += 1
            if added and crosses and (bridging is None or res.n_inliers > bridging[0]):
                bridging = (res.n_inliers, pnp)
        if bridging is not None:
            self.merge_segment(bridging[1].i, bridging[1].j, bridging[1].T_i_j)
        if n_loops > 0 or bridging is not None:
            self.optimise()
        return n_loops

    def add_map_edge(self, i: int, j: int, T_i_j: np.ndarray, sigma: float, shift_m: float,
                     shift_deg: float) -> bool:
        """A measured ``T_i_j`` ``(4, 4)`` between an old keyframe ``i`` and a newer one ``j`` with isotropic ``sigma``
        (m and rad), e.g. keyframe ``j`` registered to the map anchored to ``i``: through the gates of a far loop edge
        (the odometry chain, then the accepted edges' graph), into both graphs like a refined edge (the refined loop
        kernel). The graph is optimised when the edge is farther than ``shift_m`` / ``shift_deg`` from its estimate of
        the pair (else the next optimisation takes it in). Returns whether the edge was added."""
        T_i_j = np.asarray(T_i_j, np.float64)
        info = np.eye(6) * sigma ** -2
        c = self._chain.cfg
        if c.enabled:
            d2 = self._chain.mahalanobis2(i, j, T_i_j, info)
            passed = self._chain.consistent(d2)
            if passed and c.graph_gate:
                path = self._chain.path(i, j)
                limit = np.inf if path is None else self._chain.path_variance(path) * _LIMIT_MARGIN
                d2g = self._edge_graph.mahalanobis2(i, j, T_i_j, self._chain.edge_covariance(info), limit)
                passed = self._chain.consistent(d2g)
            if not passed:
                self.n_map_edges_rejected += 1
                return False
        dt_m, dr_deg = pose_error(T_i_j, invert(self.poses[i]) @ self.poses[j])
        edge = PoseEdge(i, j, T_i_j, "loop", information=sigma ** -2, robust_scale=self._refined_robust_scale)
        self.add_edge(edge, edge if self._graph_refined is not None else None)
        self.n_map_edges += 1
        if dt_m > shift_m or dr_deg > shift_deg:
            self.optimise()
        return True

    def _refined_edge(self, i: int, j: int, refined: RefinedEdge, far: bool) -> PoseEdge:
        """The refined version of a verified edge ``i -> j`` (counted; a nearby one is also compared with the
        odometry alone, as the graph has been pulled towards the edges). It is weighed by the refined edges' sigma,
        set when it enters their graph (:meth:`add_edge`), spread over directions by its information shape."""
        self.n_dense_refined += 1
        T_i_j = invert(refined.T_cur_ref)
        if not far:
            odo = self._chain.poses
            self._refiner.observe_nearby(T_i_j, invert(odo[i]) @ odo[j])
        return PoseEdge(i, j, T_i_j, "loop", robust_scale=self._refined_robust_scale,
                        information_shape=refined.information_shape)

    def _add_refined_nearby(self, i: int, j: int, refined: RefinedEdge | None) -> None:
        """A verified nearby edge ``i -> j`` kept out of the PnP graph: its refined version (``None``: none, or the
        dense check rejected it) enters the refined graph alone."""
        self.n_nearby_pnp_left_out += 1
        if refined is None or self._graph_refined is None:
            return
        self.add_edge(None, self._refined_edge(i, j, refined, far=False))
        self.n_nearby_edges += 1

    def _consistent(self, i: int, j: int, res, far: bool) -> bool:
        """Whether the PnP edge ``res`` from keyframe ``i`` to ``j`` passes the odometry-chain gate (counts the
        rejections; nearby edges pass untested unless ``gate_nearby``)."""
        c = self._chain.cfg
        if not c.enabled or not (far or c.gate_nearby):
            return True
        d2 = self._chain.mahalanobis2(i, j, invert(res.T_cur_ref), res.information)
        if d2 is not None:
            self.gate_d2.append((i, j, d2))
        passed = self._chain.consistent(d2)
        if passed and far and c.graph_gate:  # a far edge must also agree with the accepted edges' graph
            passed = self._graph_consistent(i, j, res)
        if passed:
            return True
        if far:
            self.n_loops_rejected_inconsistent += 1
        else:
            self.n_nearby_rejected_inconsistent += 1
        return False

    def _graph_consistent(self, i: int, j: int, res) -> bool:
        """Whether the PnP edge ``res`` from keyframe ``i`` to ``j`` passes the gate against the accepted edges' graph
        (a path no cheaper than the odometry chain's is not searched: the chain has judged it; counts the
        rejections)."""
        path = self._chain.path(i, j)
        limit = np.inf if path is None else self._chain.path_variance(path) * _LIMIT_MARGIN
        d2 = self._edge_graph.mahalanobis2(i, j, invert(res.T_cur_ref), self._chain.edge_covariance(res.information),
                                           limit)
        if d2 is None:
            return True
        self.gate_d2_graph.append((i, j, d2))
        if self._chain.consistent(d2):
            return True
        self.n_loops_rejected_graph += 1
        return False

    def optimise(self, full: bool = False) -> None:
        """Optimise (``full``: by the batch solver, :meth:`PoseGraph.optimise`), and take the poses from the refined
        edges' graph when it is trusted, else from the PnP one."""
        if self._graph_refined is None:
            self.poses[:] = self._graph.optimise(full)
            return
        poses = self._graph_refined.optimise(full)
        spread = self._refiner.loop_residual_spread(*self._graph_refined.loop_edges(), poses, self._loop_residuals)
        self.refined_residual_rad, self.refined_residual_m = (None, None) if spread is None else spread
        self.refined_trusted = self._refiner.trusted(spread)
        self.poses[:] = poses if self.refined_trusted else self._graph.optimise(full)

    def add_edge(self, pnp: PoseEdge | None, refined: PoseEdge | None = None, dense_rejected: bool = False) -> bool:
        """Add an edge: ``pnp`` (odometry or PnP-verified; ``None``: a depth-only edge, in the refined graph only)
        and, with an edge refiner, its refined version (``None``: none, the same edge in both graphs) unless
        ``dense_rejected`` (the dense check rejected it: in the PnP graph only). Returns whether the graph that is
        trusted now got an edge."""
        if pnp is not None:
            self._graph.add_edge(pnp)
        if not dense_rejected:
            self._add_to_edge_graph(pnp, refined)
        if self._graph_refined is None:
            return True
        if dense_rejected:
            return not self.refined_trusted
        if refined is None:
            self._graph_refined.add_edge(pnp)
            return True
        self.n_weak_shaped += refined.information_shape is not None
        self._graph_refined.add_edge(replace(refined, information=self._refiner.edge_sigma() ** -2))
        return True

    def _add_to_edge_graph(self, pnp: PoseEdge | None, refined: PoseEdge | None) -> None:
        """An accepted loop or nearby edge into the graph gate's graph: its refined version where there is one (the
        dense check's measurement, with the refined edges' sigma), else the PnP one (its information); both with the
        sigma floors. Odometry edges are there already (:meth:`add_node`), with the chain's drift model."""
        if refined is not None:
            cov = self._chain.edge_covariance(None) + np.eye(6) * self._refiner.edge_sigma() ** 2
            self._edge_graph.add_edge(refined.i, refined.j, refined.T_i_j, cov)
        elif pnp is not None and pnp.kind != "odometry":
            self._edge_graph.add_edge(pnp.i, pnp.j, pnp.T_i_j, self._chain.edge_covariance(pnp.information_matrix))

    def merge_segment(self, i: int, j: int, T_i_j: np.ndarray) -> None:
        """An edge ``i -> j`` from the newest segment (keyframe ``j``) to a keyframe ``i`` before it: move the
        segment rigidly so that the edge holds (the graph's start; the optimisation does the rest)."""
        if not self._open_bridges or not i < self._open_bridges[-1] <= j:
            return
        b = self._open_bridges.pop()
        poses = self.poses
        C = orthonormalize(poses[i] @ T_i_j @ invert(poses[j]))
        for k in range(b, len(self)):
            T = orthonormalize(C @ poses[k])
            poses[k] = T
            for g in (self._graph, self._graph_refined):
                if g is not None:
                    g.set_pose(k, T)
        self.n_segments_merged += 1
