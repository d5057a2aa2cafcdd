"""False-loop-closure guard: loop edges that disagree with the odometry chain never enter the graph."""

from __future__ import annotations

import numpy as np
import pytest

from surfelslam.backend.loop_consistency import LoopConsistencyConfig, OdometryChain
from surfelslam.backend.loops import Candidate
from surfelslam.backend.pose_graph import PoseEdge, PoseGraphConfig
from surfelslam.backend.sparse_slam.graph import KeyframeGraph
from surfelslam.backend.sparse_slam.results import LoopCheck
from surfelslam.geometry.se3 import adjoint, exp, invert, make_T, so3_exp
from surfelslam.tracking.features import MotionResult

from helpers import ate_m, square_walk

N_SIDE = 6  # keyframes per side of the square walk (24 in all, 1.5 m sides)


def _square(n_side: int = N_SIDE, side_m: float = 1.5) -> np.ndarray:
    return square_walk(n_side, side_m)


def _odometry(gt: np.ndarray, seed: int = 0) -> list[np.ndarray]:
    """Relative keyframe motions with a yaw bias (4 mrad a step, ~5 deg around the square) and noise."""
    rng = np.random.default_rng(seed)
    return [invert(gt[k]) @ gt[k + 1] @ exp(np.r_[0, 0, 0.004, 0, 0, 0] + rng.normal(0, 0.001, 6))
            for k in range(len(gt) - 1)]


# information of a PnP edge as the RGB-D refinement estimates it (sigma 2 mrad and 5 mm): the graph weighs such edges
# by it under a Huber kernel, whose influence on a wrong edge is bounded but never vanishes
PNP_INFORMATION = np.diag([0.002 ** -2] * 3 + [0.005 ** -2] * 3)


def _check(i: int, T_i_j: np.ndarray, source: str = "retrieved") -> LoopCheck:
    """A PnP-verified loop candidate ``i`` whose edge to the new keyframe is ``T_i_j``."""
    res = MotionResult(invert(T_i_j), True, None, 300, 200, 150, np.zeros(3), np.zeros(3),
                       np.ones(200, bool), np.zeros((200, 2), np.int64), information=PNP_INFORMATION)
    return LoopCheck(Candidate(i, source), res)


def _graph(gt: np.ndarray, consistency: LoopConsistencyConfig) -> KeyframeGraph:
    """The keyframes of ``gt`` chained by :func:`_odometry` (no loop edge yet)."""
    g = KeyframeGraph(PoseGraphConfig(), None, None, consistency)
    g.add_node(gt[0], None, None)
    for k, T in enumerate(_odometry(gt)):
        g.add_node(g.poses[k] @ T, k, T)
        g.add_edge(PoseEdge(k, k + 1, T, "odometry"))
    return g


def _wrong_edges(gt: np.ndarray) -> list[LoopCheck]:
    """Perceptual aliasing: the last keyframe matched to keyframes that only look like the start (0.5 m to 1.5 m
    and 0.3 rad off), and one edge between the right keyframes but 0.5 m off."""
    n = len(gt)
    true_last = invert(gt[0]) @ gt[n - 1]
    return [_check(3, true_last),  # keyframe 3 taken for keyframe 0
            _check(N_SIDE, true_last @ make_T(so3_exp([0, 0, 0.3]), [0.5, 0, 0])),
            _check(1, invert(gt[1]) @ gt[n - 1] @ make_T(np.eye(3), [0, 0.5, 0]), "random")]


def test_wrong_loop_edges_are_rejected_and_the_right_one_closes_the_loop():
    gt = _square()
    n = len(gt)
    right = _check(0, invert(gt[0]) @ gt[n - 1])
    odometry_only = _graph(gt, LoopConsistencyConfig())
    ate_odometry = ate_m(odometry_only.poses, gt)

    gated = _graph(gt, LoopConsistencyConfig())
    assert gated.apply_loop_checks(n - 1, [right, *_wrong_edges(gt)], min_inliers=30) == 1
    assert gated.n_loops_rejected_inconsistent == 3
    assert gated.loops_accepted == [(0, n - 1, 150)]
    assert [d2 > gated.gate_threshold for _, _, d2 in gated.gate_d2] == [False, True, True, True]
    ate_gated = ate_m(gated.poses, gt)

    # the same edges without the gate: the Huber kernel alone lets the wrong ones bend the map
    open_gate = _graph(gt, LoopConsistencyConfig(enabled=False))
    assert open_gate.apply_loop_checks(n - 1, [right, *_wrong_edges(gt)], min_inliers=30) == 4
    assert open_gate.n_loops_rejected_inconsistent == 0
    ate_open = ate_m(open_gate.poses, gt)

    assert ate_odometry > 0.04  # measured 0.053 m
    assert ate_gated < 0.1 * ate_odometry  # measured 0.003 m
    assert ate_open > 5 * ate_odometry  # measured 0.77 m


def test_consistent_loop_edges_are_all_kept_and_change_nothing():
    """Right edges (1 cm / 5 mrad noise) from every keyframe of the last side back to the first: none is rejected,
    and the poses are exactly those of the graph without the gate."""
    gt = _square()
    n = len(gt)
    rng = np.random.default_rng(3)
    checks = {j: [_check(i, invert(gt[i]) @ gt[j] @ exp(np.r_[rng.normal(0, 0.005, 3), rng.normal(0, 0.01, 3)]))
                  for i in range(3)] for j in range(n - 3, n)}
    graphs = [_graph(gt, LoopConsistencyConfig(enabled=on)) for on in (True, False)]
    for g in graphs:
        for j in range(n - 3, n):
            g.apply_loop_checks(j, checks[j], min_inliers=30)
    gated, open_gate = graphs
    assert gated.n_loops_rejected_inconsistent == 0 and len(gated.loops_accepted) == 9
    assert len(gated.gate_d2) == 9 and max(d2 for *_, d2 in gated.gate_d2) < gated.gate_threshold
    np.testing.assert_array_equal(gated.poses, open_gate.poses)
    assert ate_m(gated.poses, gt) < 0.3 * ate_m(_graph(gt, LoopConsistencyConfig()).poses, gt)


def test_the_gate_follows_the_chi_square_law_of_the_drift_model():
    """Chains drawn from the drift model itself (a turning walk, so rotation drift moves the far end): the squared
    distance of a right edge has the chi-square mean (6) and the quantile rejects about its share."""
    cfg = LoopConsistencyConfig(drift_m_per_sqrt_m=0.01, drift_rad_per_sqrt_m=0.01, drift_rad_per_sqrt_rad=0.01,
                                edge_sigma_m=0.002, edge_sigma_rad=0.002, quantile=0.9)
    gt = _square(n_side=4)
    steps = [invert(gt[k]) @ gt[k + 1] for k in range(len(gt) - 1)]
    ref = OdometryChain(cfg)
    ref.add(gt[0], None, None)
    for k, T in enumerate(steps):
        ref.add(ref.poses[k] @ T, k, T)
    sd = np.sqrt(np.stack([np.diag(ref.step_covariance(k)) for k in range(1, len(ref))]))
    rng = np.random.default_rng(0)
    i, j = 1, len(gt) - 2
    d2 = []
    for _ in range(200):
        chain = OdometryChain(cfg)
        chain.add(gt[0], None, None)
        for k, T in enumerate(steps):
            noisy = T @ exp(rng.normal(0, 1, 6) * sd[k])
            chain.add(chain.poses[k] @ noisy, k, noisy)
        edge = invert(gt[i]) @ gt[j] @ exp(rng.normal(0, 0.002, 6))
        d2.append(chain.mahalanobis2(i, j, edge, None))
    d2 = np.array(d2)
    assert np.mean(d2) == pytest.approx(6.0, rel=0.12)
    assert np.mean(d2 > chain.threshold) == pytest.approx(0.1, abs=0.04)
    from scipy.stats import chi2  # here, not at the top: importing scipy.stats costs every test worker a second

    for q in (0.5, 0.9, 0.99, 0.9999):  # the threshold is the chi-square quantile itself (a few ulps; the default's
        # to the last bit, test_chi2_quantile_matches_scipy)
        assert OdometryChain(LoopConsistencyConfig(quantile=q)).threshold == pytest.approx(chi2.ppf(q, 6), rel=1e-14)
    # without the adjoints (drift added in place), the far end's rotation-induced drift is missed
    assert np.trace(ref.covariance(i, j, ref.path(i, j))[3:, 3:]) > 3 * np.sum(sd[i:j, 3:] ** 2)


def test_edges_across_an_unknown_step_or_between_unconnected_chains_are_not_tested():
    chain = OdometryChain(LoopConsistencyConfig())
    step = make_T(np.eye(3), [0.1, 0, 0])
    chain.add(np.eye(4), None, None)
    chain.add(step, 0, step)
    chain.add(step @ step, 1, step)
    chain.add(np.eye(4), None, None)  # a second root
    far_off = make_T(np.eye(3), [5.0, 0, 0])
    assert chain.mahalanobis2(0, 2, far_off, None) > chain.threshold
    assert chain.mahalanobis2(0, 3, far_off, None) is None and chain.consistent(None)
    chain.mark_unknown(2)
    assert chain.path(0, 2) is None and chain.path(0, 1) == [1]
    assert chain.mahalanobis2(0, 2, far_off, None) is None


def test_nearby_edges_are_gated_only_on_request():
    gt = _square()
    n = len(gt)
    bad = _check(n - 3, invert(gt[n - 3]) @ gt[n - 1] @ make_T(np.eye(3), [0.3, 0, 0]), "nearby")
    for gate_nearby, kept in ((False, 1), (True, 0)):
        g = _graph(gt, LoopConsistencyConfig(gate_nearby=gate_nearby))
        g.apply_loop_checks(n - 1, [bad], min_inliers=30)
        assert g.n_nearby_edges == kept and g.n_nearby_rejected_inconsistent == 1 - kept
        assert g.n_loops_rejected_inconsistent == 0


@pytest.mark.parametrize(("field", "value"), [("quantile", 1.0), ("quantile", 0.0), ("edge_sigma_m", 0.0),
                                              ("drift_m_per_sqrt_m", -1.0)])
def test_bad_gate_settings_are_rejected(field, value):
    with pytest.raises(ValueError, match=field):
        LoopConsistencyConfig(**{field: value})


def test_nearby_pnp_edges_stay_out_of_the_pnp_graph_when_switched_off():
    """``pnp_nearby`` off (``loop.pnp_nearby_edges`` auto on unregistered colour and depth): a verified nearby edge
    does not enter the PnP graph (here it has no refined version, so no graph), unless it joins a new segment to
    the old map."""
    gt = _square()
    n = len(gt)
    near = _check(n - 3, invert(gt[n - 3]) @ gt[n - 1] @ make_T(np.eye(3), [0.02, 0, 0]), "nearby")
    for pnp_nearby, kept in ((True, 1), (False, 0)):
        g = KeyframeGraph(PoseGraphConfig(), None, None, LoopConsistencyConfig(), pnp_nearby=pnp_nearby)
        g.add_node(gt[0], None, None)
        for k, T in enumerate(_odometry(gt)):
            g.add_node(g.poses[k] @ T, k, T)
            g.add_edge(PoseEdge(k, k + 1, T, "odometry"))
        g.apply_loop_checks(n - 1, [near], min_inliers=30)
        assert g.n_nearby_edges == kept and g.n_nearby_pnp_left_out == 1 - kept
    # a new segment starting at keyframe n-2 (placed 1 m off): the nearby edge back to n-3 still merges it
    g = KeyframeGraph(PoseGraphConfig(), None, None, LoopConsistencyConfig(), pnp_nearby=False)
    g.add_node(gt[0], None, None)
    for k in range(1, n):
        if k == n - 2:
            g.add_node(gt[k] @ make_T(np.eye(3), [1.0, 0, 0]), None, None)
            g.start_segment(k)
        else:
            T = invert(gt[k - 1]) @ gt[k]
            g.add_node(g.poses[k - 1] @ T, k - 1, T)
            g.add_edge(PoseEdge(k - 1, k, T, "odometry"))
    g.apply_loop_checks(n - 1, [_check(n - 3, invert(gt[n - 3]) @ gt[n - 1], "nearby")], min_inliers=30)
    assert g.n_segments_merged == 1 and g.n_nearby_pnp_left_out == 0
    assert np.abs(g.poses[n - 1][:3, 3] - gt[n - 1][:3, 3]).max() < 1e-6


def test_path_variance_is_the_step_by_step_sum_and_gate_distances_keep_the_newest(monkeypatch):
    """The chain's path variance (the graph gate's search limit) is, to the last bit, the sum of the steps' variances
    added one at a time in path order; the gated distances (diagnostics) keep only the newest ``GATE_D2_KEPT``."""
    from surfelslam.backend.sparse_slam import graph as graph_module

    gt = _square(n_side=60, side_m=12.0)  # 240 keyframes
    chain = OdometryChain(LoopConsistencyConfig())
    chain.add(gt[0], None, None)
    for k, T in enumerate(_odometry(gt)):
        chain.add(chain.poses[k] @ T, k, T)
    for i, j in [(0, 239), (3, 200), (100, 101), (5, 5), (150, 17)]:
        path = chain.path(i, j)
        expected = 0
        for k in path:
            expected += np.sum(chain.step_covariance(k).diagonal())
        assert chain.path_variance(path) == float(expected)
    assert chain.path_variance(chain.path(0, 239)) > 0.0 and chain.path_variance([]) == 0.0

    monkeypatch.setattr(graph_module, "GATE_D2_KEPT", 2)
    gt = _square()
    n = len(gt)
    gated = _graph(gt, LoopConsistencyConfig())
    assert gated.apply_loop_checks(n - 1, [_check(0, invert(gt[0]) @ gt[n - 1]), *_wrong_edges(gt)], 30) == 1
    assert [d2 > gated.gate_threshold for _, _, d2 in gated.gate_d2] == [True, True]  # the last two of four


def test_paths_inside_and_across_runs_of_the_chain_are_the_tree_walk():
    """A path within one run of keyframes that each hang from the one before is a range of ids (no walk); across a
    branch (a keyframe tracked against an older one), a second root or an unknown step, it is the tree walk's."""
    chain = OdometryChain(LoopConsistencyConfig())
    step = make_T(np.eye(3), [0.1, 0, 0])
    parents = [None, 0, 1, 2, 3, 1, 5, 6, None, 8, 9, 7, 11]  # branches at 5 and 11, a second root at 8
    for p in parents:
        chain.add(np.eye(4) if p is None else chain.poses[p] @ step, p, None if p is None else step)
    assert chain.path(1, 4) == [4, 3, 2] and chain.path(4, 1) == [4, 3, 2]
    assert chain.path(4, 6) == [6, 5, 4, 3, 2] and chain.path(3, 12) == [12, 11, 7, 6, 5, 3, 2]
    assert chain.path(2, 9) is None and chain.path(8, 10) == [10, 9]

    def walk(a, b):  # up the tree from both ends, the newer first
        out = []
        while a != b:
            if a < 0 or b < 0:
                return None
            out.append(max(a, b))
            a, b = (chain.parent(a), b) if a > b else (a, chain.parent(b))
        return out

    for i in range(len(parents)):
        for j in range(len(parents)):
            assert chain.path(i, j) == walk(i, j)
    chain.mark_unknown(6)
    assert chain.path(5, 7) is None and chain.path(6, 7) == [7] and chain.path(2, 12) is None


def test_a_path_inside_one_run_sums_its_steps_covariance_in_constant_time():
    """The covariance over a run's path (a difference of running world-frame sums) equals the sum over its steps
    moved into keyframe j's frame one by one, on a 2000-keyframe walk 40 m from the origin; a path across runs (a
    second branch from keyframe 1000) is summed step by step as before."""
    rng = np.random.default_rng(3)
    chain = OdometryChain(LoopConsistencyConfig())
    chain.add(make_T(np.eye(3), [40.0, -25.0, 1.5]), None, None)
    for k in range(1999):
        step = exp(np.concatenate([rng.normal(0, 0.02, 3), [0.02, 0.0, 0.0] + rng.normal(0, 0.005, 3)]))
        parent = 1000 if k == 1500 else k  # keyframe 1501 hangs from 1000: a second run
        chain.add(chain.poses[parent] @ step, parent, step)

    def explicit(i, j, path):
        rows = np.asarray(path, np.intp)
        A = adjoint(invert(chain.poses[j])[None] @ chain.poses[rows])
        return np.einsum("nab,nb,ncb->ac", A, np.stack([np.diag(chain.step_covariance(k)) for k in rows]), A)

    for i, j in [(3, 1499), (1499, 3), (0, 1), (1502, 1999), (10, 1000)]:
        path = chain.path(i, j)
        assert path == list(range(max(i, j), min(i, j), -1))
        cov = chain.covariance(i, j, path)
        np.testing.assert_allclose(cov, explicit(i, j, path), rtol=1e-9, atol=1e-12 * np.abs(cov).max())
    across = chain.path(1400, 1600)
    assert across != list(range(1600, 1400, -1))
    np.testing.assert_array_equal(chain.covariance(1400, 1600, across), explicit(1400, 1600, across))
