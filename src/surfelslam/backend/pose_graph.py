"""Keyframe pose graph optimised with gtsam (ISAM2, or Levenberg-Marquardt over the whole graph).

Nodes are keyframe poses ``T_world_kf``; the first one is anchored by a tight prior. Edges are
relative-pose measurements ``T_i_j = T_world_i^-1 T_world_j`` (gtsam ``BetweenFactorPose3``).
Odometry edges use a Gaussian noise model; loop edges a robust one (Huber or Cauchy m-estimator on
the whitened error) so that a wrong loop closure is down-weighted instead of bending the map.
The reference assignment uses information ``100 I`` on every edge (sigma 0.1 in metres and radians) and 100 LM
iterations.

Solvers: ``batch`` re-solves the whole graph by Levenberg-Marquardt at every :meth:`PoseGraph.optimise` (its cost
grows with the keyframes); ``isam2`` (default) keeps gtsam's incremental smoother and hands it only the factors and
nodes added since, plus a few relinearising updates, so a loop costs what it changes (an overwritten estimate,
:meth:`PoseGraph.set_pose`, rebuilds it once from the whole graph; a system too poorly conditioned for its
undamped Gauss-Newton steps is solved by the batch solver that time, and the smoother rebuilt).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from surfelslam.config import Config, setting
from surfelslam.types import GrowingRows, PoseArray

ROBUST_KERNELS = ("huber", "cauchy", "none")
EDGE_INFORMATION_MODES = ("isotropic", "estimated")
EDGE_KINDS = ("odometry", "loop")
SOLVERS = ("isam2", "batch")
# isam2: a variable is relinearised when its update exceeds this (tangent norm, rad and m); 0.01 keeps the result
# within millimetres of the batch solve on the floor walk while touching only what a loop moved
ISAM2_RELINEARIZE_THRESHOLD = 0.01


@dataclass(frozen=True)
class PoseGraphConfig(Config):
    """Pose-graph edge weights, robust kernels and solver settings."""

    edge_information: str = setting(
        "estimated", choices=EDGE_INFORMATION_MODES,
        doc="isotropic: every edge weighs odometry_information / loop_information; estimated: an edge with its own "
            "information matrix (the Hessian of its RGB-D refinement) uses it")
    estimated_information_scale: float = setting(1.0, gt=0, le=1e6,
                                                 doc="factor on estimated information matrices (< 1: the Hessian is "
                                                     "over-confident)")
    estimated_robust_kernel: str = setting("huber", choices=ROBUST_KERNELS,
                                           doc="m-estimator on every edge weighted by an estimated information")
    estimated_robust_scale: float = setting(3.0, unit="whitened", gt=0, le=1e12, doc="its scale")
    odometry_information: float = setting(100.0, unit="1/sigma^2", gt=0, le=1e16,
                                          doc="isotropic information of odometry edges (sigma in m and rad)")
    loop_information: float = setting(100.0, unit="1/sigma^2", gt=0, le=1e16,
                                      doc="isotropic information of loop edges")
    prior_sigma: float = setting(1e-6, unit="m and rad", gt=0, le=10,
                                 doc="sigma of the prior anchoring the first keyframe")
    robust_kernel: str = setting("cauchy", choices=ROBUST_KERNELS, doc="m-estimator on loop edges")
    robust_scale_sigma: float = setting(1.0, unit="whitened", gt=0, le=1e12,
                                        doc="its scale, in multiples of the edge sigma")
    robust_odometry: bool = setting(False, doc="also apply the kernel to odometry edges")
    solver: str = setting("isam2", choices=SOLVERS,
                          doc="isam2: incremental (cost follows what a loop changes); batch: Levenberg-Marquardt over "
                              "the whole graph at every optimisation")
    isam2_max_updates: int = setting(10, unit="updates", ge=1, le=1000,
                                     doc="isam2: at most this many relinearising updates per optimisation")
    max_iterations: int = setting(100, unit="iterations", ge=1, le=100_000,
                                  doc="Levenberg-Marquardt iterations (batch solver)")
    relative_error_tol: float = setting(1e-6, ge=0, le=1,
                                        doc="LM stops when the relative error decrease is below this")


@dataclass(frozen=True)
class PoseEdge:
    """Relative-pose measurement between keyframes ``i`` and ``j``.

    Attributes:
        i, j: node indices.
        T_i_j: ``(4, 4)`` pose of node ``j`` in the frame of node ``i`` (maps j-points into i).
        kind: ``"odometry"`` or ``"loop"``.
        information: isotropic information overriding the config's (``None``: use the config).
        information_matrix: ``(6, 6)`` estimated information of ``T_i_j`` for a perturbation in gtsam's tangent
            ``(omega, v)`` (used in the ``"estimated"`` mode; ``None``: isotropic).
        robust_scale: scale (whitened units) of the m-estimator of a loop edge with isotropic information,
            overriding ``robust_scale_sigma`` (``None``: use the config).
        information_shape: ``(6, 6)`` symmetric, eigenvalues in ``(0, 1]``: how the isotropic information is spread
            over the directions of the same tangent (below 1 where the measurement is weak; ``None``: 1 everywhere).
    """

    i: int
    j: int
    T_i_j: np.ndarray
    kind: str = "odometry"
    information: float | None = None
    information_matrix: np.ndarray | None = None
    robust_scale: float | None = None
    information_shape: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.kind not in EDGE_KINDS:
            raise ValueError(f"edge kind must be one of {EDGE_KINDS}, got {self.kind!r}")
        if self.information_matrix is not None and np.shape(self.information_matrix) != (6, 6):
            raise ValueError(f"information_matrix must be (6, 6), got {np.shape(self.information_matrix)}")
        if self.information_shape is not None and np.shape(self.information_shape) != (6, 6):
            raise ValueError(f"information_shape must be (6, 6), got {np.shape(self.information_shape)}")


def _noise(edge: PoseEdge, cfg: PoseGraphConfig):
    if cfg.edge_information == "estimated" and edge.information_matrix is not None:
        info_matrix = 0.5 * (edge.information_matrix + edge.information_matrix.T) * cfg.estimated_information_scale
        gauss = gtsam.noiseModel.Gaussian.Information(np.asarray(info_matrix, np.float64))
        return _robust(gauss, cfg.estimated_robust_kernel, cfg.estimated_robust_scale)
    info = edge.information
    if info is None:
        info = cfg.loop_information if edge.kind == "loop" else cfg.odometry_information
    if edge.information_shape is None:
        gauss = gtsam.noiseModel.Isotropic.Sigma(6, float(1.0 / np.sqrt(info)))
    else:
        shape = np.asarray(edge.information_shape, np.float64)
        gauss = gtsam.noiseModel.Gaussian.Information(info * 0.5 * (shape + shape.T))
    if edge.kind == "loop" or cfg.robust_odometry:
        return _robust(gauss, cfg.robust_kernel, cfg.robust_scale_sigma if edge.robust_scale is None
                       else edge.robust_scale)
    return gauss


def _robust(gauss, kernel: str, scale: float):
    """``gauss`` wrapped in the m-estimator ``kernel`` (scale in whitened units), or ``gauss`` for ``"none"``."""
    if kernel == "none":
        return gauss
    est = (gtsam.noiseModel.mEstimator.Huber if kernel == "huber" else gtsam.noiseModel.mEstimator.Cauchy).Create(scale)
    return gtsam.noiseModel.Robust.Create(est, gauss)


def _pose3(T: np.ndarray) -> gtsam.Pose3:
    T = np.asarray(T, dtype=np.float64)
    # re-orthonormalise: gtsam requires a proper rotation
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return gtsam.Pose3(gtsam.Rot3(R), gtsam.Point3(*T[:3, 3]))


class PoseGraph:
    """Incremental keyframe pose graph.

    ``add_node`` appends a keyframe with its initial pose; ``add_edge`` appends a measurement;
    ``optimise`` solves from the current estimate (config ``solver``) and stores the result; ``poses`` returns it.
    """

    def __init__(self, cfg: PoseGraphConfig | None = None) -> None:
        self.cfg = cfg or PoseGraphConfig()
        self._graph = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()
        self._n = 0
        self.edges: list[PoseEdge] = []
        # the loop edges among them, stacked as they come: T_i_j, and (i, j)
        self._loop_T = PoseArray()
        self._loop_ij = GrowingRows((2,), np.intp)
        # isam2: the smoother, and what it has not been given yet (None: rebuild it from the whole graph)
        self._isam: gtsam.ISAM2 | None = None
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self.n_batch_fallbacks = 0  # isam2 optimisations solved by the batch solver instead (nearly singular system)
        # the graph's size and the estimates before and after the last optimisation (errors computed when asked)
        self._last = (0, gtsam.Values(), gtsam.Values())

    def __len__(self) -> int:
        return self._n

    def add_node(self, T_world_kf: np.ndarray) -> int:
        """Add a keyframe with its initial pose ``(4, 4)``; returns its index. The first is anchored."""
        k = self._n
        self._values.insert(k, _pose3(T_world_kf))
        self._new_values.insert(k, _pose3(T_world_kf))
        if k == 0:
            prior = gtsam.noiseModel.Isotropic.Sigma(6, self.cfg.prior_sigma)
            self._add_factor(gtsam.PriorFactorPose3(0, _pose3(T_world_kf), prior))
        self._n += 1
        return k

    def add_edge(self, edge: PoseEdge) -> None:
        if not (0 <= edge.i < self._n and 0 <= edge.j < self._n) or edge.i == edge.j:
            raise ValueError(f"edge ({edge.i}, {edge.j}) needs two distinct existing nodes (have {self._n})")
        self._add_factor(gtsam.BetweenFactorPose3(edge.i, edge.j, _pose3(edge.T_i_j), _noise(edge, self.cfg)))
        self.edges.append(edge)
        if edge.kind == "loop":
            self._loop_T.append(edge.T_i_j)
            self._loop_ij.append((edge.i, edge.j))

    def loop_edges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The loop edges so far, in the order they came: ``T_i_j`` ``(L, 4, 4)`` float64, ``i`` and ``j`` ``(L,)``
        (views: valid until the next edge)."""
        ij = self._loop_ij.rows
        return self._loop_T.poses, ij[:, 0], ij[:, 1]

    def _add_factor(self, factor) -> None:
        self._graph.add(factor)
        self._new_factors.add(factor)

    def set_pose(self, k: int, T_world_kf: np.ndarray) -> None:
        """Overwrite node ``k``'s current estimate (e.g. an initial guess)."""
        if self._last[2] is self._values:  # the last optimisation's result keeps its estimate
            self._last = (self._last[0], self._last[1], gtsam.Values(self._values))
        self._values.update(k, _pose3(T_world_kf))
        if self._new_values.exists(k):
            self._new_values.update(k, _pose3(T_world_kf))
        else:
            self._isam = None  # the smoother holds the old estimate: rebuilt at the next optimisation

    def optimise(self, full: bool = False) -> np.ndarray:
        """Solve (config ``solver``; ``full``: by the batch solver whatever it is, e.g. once at the end, so that the
        result does not depend on when the edges came) from the current estimate; returns and stores the poses
        ``(K, 4, 4)``."""
        if self._n == 0:
            return np.zeros((0, 4, 4))
        # the estimate the solve starts from: the solvers copy it and self._values is replaced by their result, so the
        # object itself stays as it was (no O(K) copy per optimisation)
        before = self._values
        if self.cfg.solver == "batch" or full:
            self._values = self._batch_solve()
            self._isam = None  # isam2: its linearisation point is stale, rebuilt at the next optimisation
        else:
            try:
                self._values = self._isam2_solve()
            except RuntimeError:  # gtsam: a nearly indeterminate system, which Gauss-Newton cannot solve
                self._isam = None  # rebuilt at the next optimisation, from the damped solve's result
                self.n_batch_fallbacks += 1
                self._values = self._batch_solve()
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        # the result is self._values itself until set_pose changes an estimate (it copies it first; add_node only
        # inserts new ones, which the last optimisation's factors do not read)
        self._last = (self._graph.size(), before, self._values)
        return self.poses()

    def _batch_solve(self) -> gtsam.Values:
        """Levenberg-Marquardt over the whole graph from the current estimate (damped: solves nearly indeterminate
        systems too)."""
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(self.cfg.max_iterations)
        params.setRelativeErrorTol(self.cfg.relative_error_tol)
        return gtsam.LevenbergMarquardtOptimizer(self._graph, self._values, params).optimize()

    def _isam2_solve(self) -> gtsam.Values:
        """Hand the smoother what is new (or the whole graph when it must be rebuilt), then update until an update
        relinearises nothing (the estimate no longer changes) or ``isam2_max_updates`` are done; returns the
        estimate."""
        if self._isam is None:
            params = gtsam.ISAM2Params()
            params.setRelinearizeThreshold(ISAM2_RELINEARIZE_THRESHOLD)
            params.relinearizeSkip = 1
            self._isam = gtsam.ISAM2(params)
            result = self._isam.update(self._graph, self._values)
        else:
            result = self._isam.update(self._new_factors, self._new_values)
        for _ in range(self.cfg.isam2_max_updates - 1):
            if result.getVariablesRelinearized() == 0:
                break
            result = self._isam.update()
        return self._isam.calculateEstimate()

    @property
    def last_error_before(self) -> float:
        """The graph's error (as of the last optimisation) at the estimate it started from."""
        return self._error(self._last[1])

    @property
    def last_error_after(self) -> float:
        """The graph's error (as of the last optimisation) at its result."""
        return self._error(self._last[2])

    def _error(self, values: gtsam.Values) -> float:
        n = self._last[0]
        if n == self._graph.size():
            return float(self._graph.error(values))
        graph = gtsam.NonlinearFactorGraph()
        for f in range(n):
            graph.add(self._graph.at(f))
        return float(graph.error(values))

    def poses(self) -> np.ndarray:
        """Current estimate ``(K, 4, 4)`` of ``T_world_kf``."""
        out = np.zeros((self._n, 4, 4))
        if self._n:
            flat = gtsam.utilities.extractPose3(self._values)  # (K, 12): rotation row-major, then translation
            out[:, :3, :3] = flat[:, :9].reshape(-1, 3, 3)
            out[:, :3, 3] = flat[:, 9:]
            out[:, 3, 3] = 1.0
        return out


def optimise(
    poses_world_kf: np.ndarray, edges: list[PoseEdge], cfg: PoseGraphConfig | None = None
) -> np.ndarray:
    """Optimise keyframe poses ``(K, 4, 4)`` (initial ``T_world_kf``) under ``edges``; returns ``(K, 4, 4)``.

    The first pose is held fixed by a tight prior.
    """
    graph = PoseGraph(cfg)
    for T in np.asarray(poses_world_kf, dtype=np.float64).reshape(-1, 4, 4):
        graph.add_node(T)
    for e in edges:
        graph.add_edge(e)
    return graph.optimise()
