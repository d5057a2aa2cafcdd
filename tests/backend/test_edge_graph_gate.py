"""The graph gate: a far loop edge is judged against the accepted edges' graph, not only the odometry chain."""

from __future__ import annotations

import numpy as np
import pytest

from surfelslam.backend.edge_graph_gate import EdgeGraph
from surfelslam.backend.loop_consistency import LoopConsistencyConfig, OdometryChain
from surfelslam.backend.loops import Candidate
from surfelslam.backend.pose_graph import PoseEdge, PoseGraphConfig
from surfelslam.backend.sparse_slam.graph import KeyframeGraph
from surfelslam.backend.sparse_slam.results import LoopCheck
from surfelslam.geometry.se3 import exp, invert, make_T
from surfelslam.tracking.features import MotionResult

from helpers import square_walk

N_SIDE = 40  # keyframes per side: a 12 m square (0.3 m a step, 48 m a lap), walked twice
PNP_INFORMATION = np.diag([0.002 ** -2] * 3 + [0.005 ** -2] * 3)


def _two_laps() -> np.ndarray:
    lap = square_walk(N_SIDE, 12.0)
    return np.concatenate([lap, lap])


def _check(i: int, T_i_j: np.ndarray) -> LoopCheck:
    res = MotionResult(invert(T_i_j), True, None, 300, 200, 150, np.zeros(3), np.zeros(3),
                       np.ones(200, bool), np.zeros((200, 2), np.int64), information=PNP_INFORMATION)
    return LoopCheck(Candidate(i, "retrieved"), res)


def _graph(gt: np.ndarray, cfg: LoopConsistencyConfig, n: int) -> KeyframeGraph:
    """The first ``n`` keyframes of ``gt`` chained by odometry with a small yaw bias (1 mrad a step) and noise."""
    rng = np.random.default_rng(0)
    g = KeyframeGraph(PoseGraphConfig(), None, None, cfg)
    g.add_node(gt[0], None, None)
    for k in range(n - 1):
        T = invert(gt[k]) @ gt[k + 1] @ exp(np.r_[0, 0, 0.001, 0, 0, 0] + rng.normal(0, 0.0005, 6))
        g.add_node(g.poses[k] @ T, k, T)
        g.add_edge(PoseEdge(k, k + 1, T, "odometry"))
    return g


def _true(gt: np.ndarray, i: int, j: int, offset_m: float = 0.0) -> np.ndarray:
    return invert(gt[i]) @ gt[j] @ make_T(np.eye(3), [offset_m, 0, offset_m / 3])


@pytest.mark.parametrize("graph_gate", [True, False])
def test_a_look_alike_metres_off_passes_the_chain_but_not_the_graph(graph_gate):
    """A lap (48 m, no loop on the way), a genuine loop closed back to the start, a few steps on, then a look-alike
    1.5 m off: the odometry chain over the lap allows it (d2 < threshold); the graph, through the loop just closed,
    rejects it, and keeps a genuine edge between the same keyframes."""
    gt = _two_laps()
    lap = 4 * N_SIDE
    cfg = LoopConsistencyConfig(graph_gate=graph_gate)
    g = _graph(gt, cfg, lap + 12)
    # the first loop after the long excursion: no shorter path than the chain, judged by it alone
    assert g.apply_loop_checks(lap + 5, [_check(5, _true(gt, 5, lap + 5))], min_inliers=30) == 1
    assert len(g.gate_d2_graph) == 0 or g.gate_d2_graph[0][2] == pytest.approx(g.gate_d2[0][2], rel=1e-6)
    look_alike = _check(10, _true(gt, 10, lap + 10, offset_m=1.5))
    n = g.apply_loop_checks(lap + 10, [look_alike], min_inliers=30)
    d2_chain = g.gate_d2[-1][2]
    assert d2_chain < g.gate_threshold  # the chain alone lets it in
    if not graph_gate:
        assert n == 1 and g.n_loops_rejected_inconsistent == 0
        return
    assert n == 0 and g.n_loops_rejected_graph == 1 and g.n_loops_rejected_inconsistent == 1
    assert g.gate_d2_graph[-1][2] > 50 * g.gate_threshold
    genuine = _check(11, _true(gt, 11, lap + 11, offset_m=0.01))
    assert g.apply_loop_checks(lap + 11, [genuine], min_inliers=30) == 1
    assert g.gate_d2_graph[-1][2] < 0.5 * g.gate_threshold
    assert g.loops_accepted == [(5, lap + 5, 150), (11, lap + 11, 150)]


def test_on_odometry_alone_the_graph_gate_is_the_chain_gate():
    """With no loop edge, the least-variance path is the odometry chain: the same relative pose, covariance and
    distance as :class:`OdometryChain` gives."""
    gt = square_walk(6, 1.5)
    cfg = LoopConsistencyConfig()
    chain, eg = OdometryChain(cfg), EdgeGraph()
    chain.add(gt[0], None, None)
    eg.add_node()
    rng = np.random.default_rng(1)
    steps = [invert(gt[k]) @ gt[k + 1] @ exp(rng.normal(0, 0.002, 6)) for k in range(len(gt) - 1)]
    for k, T in enumerate(steps):
        chain.add(chain.poses[k] @ T, k, T)
        eg.add_node()
        eg.add_edge(k, k + 1, T, chain.step_covariance(k + 1))
    i, j = 2, len(gt) - 3
    path = eg.path(i, j)
    assert path == list(range(i, j + 1))
    T_ij, cov = eg.relative(path)
    np.testing.assert_allclose(T_ij, chain.relative(i, j), atol=1e-12)
    np.testing.assert_allclose(cov, chain.covariance(i, j, chain.path(i, j)), atol=1e-15)
    edge = _true(gt, i, j, 0.3)
    d2 = eg.mahalanobis2(i, j, edge, chain.edge_covariance(None))
    assert d2 == pytest.approx(chain.mahalanobis2(i, j, edge, None), rel=1e-9)
    # stored the other way round (j -> i), the edges compose to the same pose and covariance
    back = EdgeGraph()
    for _ in range(len(gt)):
        back.add_node()
    for k, T in enumerate(steps):
        back.add_edge(k + 1, k, invert(T), _moved(T, chain.step_covariance(k + 1)))
    T_back, cov_back = back.relative(back.path(i, j))
    np.testing.assert_allclose(T_back, T_ij, atol=1e-12)
    np.testing.assert_allclose(cov_back, cov, atol=1e-15)
    # a search bounded below the path's variance finds nothing, and an unknown step cuts the path
    assert eg.path(i, j, limit=0.5 * chain.path_variance(chain.path(i, j))) is None
    eg.remove_edge(j, j - 1)
    assert eg.path(i, j) is None and eg.mahalanobis2(i, j, edge, chain.edge_covariance(None)) is None


def _moved(T_i_j: np.ndarray, cov_j: np.ndarray) -> np.ndarray:
    """The covariance of ``T_j_i`` (right perturbation at ``i``) from that of ``T_i_j`` (at ``j``)."""
    from surfelslam.geometry.se3 import adjoint

    A = adjoint(T_i_j)
    return A @ cov_j @ A.T


def test_the_incremental_search_finds_scipys_path_on_a_growing_graph():
    """The linked adjacency lists, kept edge by edge (odometry chain, nearby and far loop edges, a better edge
    replacing a pair's, removed edges), give the path ``scipy.sparse.csgraph.dijkstra`` gives on a matrix rebuilt
    from the same edges, with and without a limit, for every queried pair."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    rng = np.random.default_rng(3)
    g, weights, n_checked, n_none = EdgeGraph(), {}, 0, 0
    cov = lambda: np.diag(rng.uniform(1e-6, 1e-4, 6))  # noqa: E731
    for k in range(300):
        g.add_node()
        new = [(k - 1, k)] if k else []
        new += [(int(rng.integers(max(0, k - 6), k)), k)] if k > 1 else []
        new += [(k, int(rng.integers(0, k)))] if k > 10 and rng.random() < 0.1 else []  # far, stored reversed
        for a, b in new:
            c = cov()
            g.add_edge(a, b, exp(rng.normal(0, 0.1, 6)), c)
            key = (min(a, b), max(a, b))
            weights[key] = min(weights.get(key, np.inf), float(np.trace(c)) + 1e-12)
        if k > 10 and rng.random() < 0.05:
            a, b = k - 1 - int(rng.integers(0, 3)), k
            g.remove_edge(a, b)
            weights.pop((min(a, b), max(a, b)), None)
        if k % 10 or k < 20:
            continue
        e = np.array(list(weights), np.int64)
        W = coo_matrix((list(weights.values()), (e[:, 0], e[:, 1])), shape=(k + 1, k + 1)).tocsr()
        for _ in range(10):
            i, j = (int(x) for x in rng.choice(k + 1, 2, replace=False))
            limit = np.inf if rng.random() < 0.5 else float(rng.uniform(0, 2e-4 * abs(i - j)))
            _, pred = dijkstra(W, directed=False, indices=i, return_predecessors=True, limit=limit)
            ref = None if pred[j] < 0 else [j]
            while ref is not None and ref[-1] != i:
                ref.append(int(pred[ref[-1]]))
            assert g.path(i, j, limit) == (None if ref is None else ref[::-1])
            n_checked, n_none = n_checked + 1, n_none + (ref is None)
    assert n_checked == 280 and 20 < n_none < 200  # both outcomes exercised


def test_the_warm_up_compiles_the_search_the_gate_calls():
    """The warm-up's call of the path search has the argument types of :meth:`EdgeGraph.path`: the gate's first
    search compiles nothing more (a short warm-up run closes no far loop)."""
    from surfelslam.kernels.graph_search import shortest_path
    from surfelslam.slam.warmup import _graph_gate_extras

    _graph_gate_extras()
    compiled = set(shortest_path.signatures)
    g = EdgeGraph()
    for _ in range(3):
        g.add_node()
    g.add_edge(0, 1, np.eye(4), np.eye(6))
    g.add_edge(2, 1, np.eye(4), np.eye(6))
    assert g.path(0, 2) == [0, 1, 2] and g.path(0, 2, limit=np.float64(1.0)) is None
    assert set(shortest_path.signatures) == compiled
