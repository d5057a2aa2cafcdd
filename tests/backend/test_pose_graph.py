"""Pose graph: loop closure corrects drift; the robust kernel limits a wrong loop edge."""

from __future__ import annotations

import numpy as np
import pytest

from surfelslam.backend.pose_graph import PoseEdge, PoseGraph, PoseGraphConfig, optimise
from surfelslam.geometry.se3 import exp, invert, make_T, so3_exp

from helpers import ate_m, square_walk


def _square_loop(n_side: int = 5, side_m: float = 2.0) -> np.ndarray:
    return square_walk(n_side, side_m)


def _drifted_odometry(gt: np.ndarray, seed: int = 0) -> tuple[np.ndarray, list[PoseEdge]]:
    """Odometry edges with a systematic yaw bias plus noise, and the dead-reckoned initial poses."""
    rng = np.random.default_rng(seed)
    edges, init = [], [gt[0]]
    for k in range(len(gt) - 1):
        rel = invert(gt[k]) @ gt[k + 1]
        noise = exp(np.concatenate([[0.0, 0.0, 0.03], [0.0, 0.0, 0.0]]) + rng.normal(0, 0.003, 6))
        meas = rel @ noise
        edges.append(PoseEdge(k, k + 1, meas, "odometry"))
        init.append(init[-1] @ meas)
    return np.array(init), edges


def test_loop_edge_corrects_drift() -> None:
    gt = _square_loop()
    init, edges = _drifted_odometry(gt)
    n = len(gt)
    loop = PoseEdge(n - 1, 0, invert(gt[n - 1]) @ gt[0], "loop")
    before = ate_m(init, gt)
    after_odo = ate_m(optimise(init, edges), gt)
    after = ate_m(optimise(init, edges + [loop]), gt)
    assert before > 0.3  # the bias drifts a lot
    assert after_odo == pytest.approx(before, rel=1e-3)  # odometry alone cannot fix it
    assert after < 0.25 * before
    # the first pose stays anchored
    np.testing.assert_allclose(optimise(init, edges + [loop])[0], gt[0], atol=1e-6)


def test_edge_robust_scale_overrides_the_config() -> None:
    """A loop edge's own ``robust_scale`` replaces ``robust_scale_sigma``: a tight kernel ignores a wrong loop."""
    gt = _square_loop()
    init, edges = _drifted_odometry(gt)
    n = len(gt)
    wrong = PoseEdge(n - 1, 0, invert(gt[n - 1]) @ gt[0] @ make_T(so3_exp(np.zeros(3)), np.array([1.0, 0, 0])),
                     "loop")
    loose = optimise(init, edges + [wrong], PoseGraphConfig(robust_scale_sigma=100.0))
    tight = optimise(init, edges + [PoseEdge(wrong.i, wrong.j, wrong.T_i_j, "loop", robust_scale=0.01)],
                     PoseGraphConfig(robust_scale_sigma=100.0))
    assert ate_m(tight, gt) < ate_m(loose, gt) - 0.1


@pytest.mark.parametrize("kernel", ["huber", "cauchy"])
def test_robust_kernel_downweights_outlier_loop(kernel: str) -> None:
    gt = _square_loop()
    init, edges = _drifted_odometry(gt, seed=1)
    n = len(gt)
    good = PoseEdge(n - 1, 0, invert(gt[n - 1]) @ gt[0], "loop")
    # wrong loop: claims node 10 sits 1.5 m and 60 deg away from node 2's true relation
    bad_rel = invert(gt[2]) @ gt[10] @ make_T(so3_exp([0.0, 0.0, 1.0]), [1.5, -1.0, 0.0])
    bad = PoseEdge(2, 10, bad_rel, "loop")
    plain = ate_m(optimise(init, edges + [good, bad], PoseGraphConfig(robust_kernel="none")), gt)
    robust = ate_m(optimise(init, edges + [good, bad], PoseGraphConfig(robust_kernel=kernel)), gt)
    clean = ate_m(optimise(init, edges + [good], PoseGraphConfig(robust_kernel=kernel)), gt)
    if kernel == "huber":  # bounded (linear) influence: helps, but the outlier still pulls
        assert robust < 0.75 * plain
    else:  # redescending: the outlier is essentially ignored
        assert robust < 0.5 * plain
        assert robust < clean + 0.05


def test_incremental_graph_matches_batch() -> None:
    gt = _square_loop(n_side=3)
    init, edges = _drifted_odometry(gt, seed=2)
    loop = PoseEdge(len(gt) - 1, 0, invert(gt[-1]) @ gt[0], "loop")
    g = PoseGraph()
    for T in init:
        g.add_node(T)
    for e in edges + [loop]:
        g.add_edge(e)
    inc = g.optimise()
    np.testing.assert_allclose(inc, optimise(init, edges + [loop]), atol=1e-9)
    np.testing.assert_allclose(inc, optimise(init, edges + [loop], PoseGraphConfig(solver="batch")), atol=2e-3)
    assert g.last_error_after < g.last_error_before
    with pytest.raises(ValueError):
        g.add_edge(PoseEdge(0, 99, np.eye(4)))


def test_last_errors_stay_those_of_the_last_optimisation_when_estimates_change_after_it() -> None:
    """The errors before/after the last optimisation are kept without copying the estimates: a later set_pose (which
    moves an estimate far off) or add_node does not change them, and the next optimisation starts from the moved
    estimate."""
    gt = _square_loop(n_side=3)
    init, edges = _drifted_odometry(gt, seed=4)
    g = PoseGraph()
    for T in init:
        g.add_node(T)
    for e in edges + [PoseEdge(len(gt) - 1, 0, invert(gt[-1]) @ gt[0], "loop")]:
        g.add_edge(e)
    g.optimise()
    before, after = g.last_error_before, g.last_error_after
    assert after < before
    g.set_pose(3, init[3] @ make_T(np.eye(3), [1.0, 0, 0]))
    g.add_node(init[-1])
    assert (g.last_error_before, g.last_error_after) == (before, after)
    g.add_edge(PoseEdge(len(gt) - 1, len(gt), np.eye(4)))
    g.optimise()
    assert g.last_error_before > after + 1.0  # started from the moved keyframe (1 m off, sigma 0.1)


def test_estimated_information_weighs_each_axis_by_its_own_certainty() -> None:
    """Two conflicting measurements of node 1: the optimum is their information-weighted mean, per axis
    (translation-only disagreement, diagonal information: exact); the isotropic mode takes the plain mean."""
    t_a, t_b = np.array([1.0, 0.0, 0.0]), np.array([1.1, 0.2, -0.1])
    info_a = np.diag([1e4, 1e4, 1e4, 400.0, 100.0, 50.0])  # (omega, v): a is sure about x
    info_b = np.diag([1e4, 1e4, 1e4, 100.0, 400.0, 50.0])  # b about y; z equal
    edges = [PoseEdge(0, 1, make_T(np.eye(3), t_a), information_matrix=info_a),
             PoseEdge(0, 1, make_T(np.eye(3), t_b), information_matrix=info_b)]
    init = np.array([np.eye(4), make_T(np.eye(3), t_a)])
    est_cfg = PoseGraphConfig(estimated_robust_kernel="none")
    t = optimise(init, edges, est_cfg)[1][:3, 3]
    wa, wb = np.diag(info_a)[3:], np.diag(info_b)[3:]
    np.testing.assert_allclose(t, (wa * t_a + wb * t_b) / (wa + wb), atol=1e-6)
    t_iso = optimise(init, edges, PoseGraphConfig(edge_information="isotropic"))[1][:3, 3]
    np.testing.assert_allclose(t_iso, 0.5 * (t_a + t_b), atol=1e-6)
    with pytest.raises(ValueError):
        PoseEdge(0, 1, np.eye(4), information_matrix=np.eye(3))
    with pytest.raises(ValueError):
        PoseGraphConfig(edge_information="learned")


def test_an_information_shape_frees_the_edge_along_its_weak_direction() -> None:
    """Two conflicting isotropic measurements of node 1 meet half-way (Gaussian, no kernel); when one of them is
    weak along x (information shape 1e-4 there), x follows the other one and y is still the plain mean."""
    t_a, t_b = np.array([1.0, 0.0, 0.0]), np.array([1.1, 0.2, 0.0])
    shape = np.diag([1.0, 1.0, 1.0, 1e-4, 1.0, 1.0])
    cfg = PoseGraphConfig(robust_kernel="none", edge_information="isotropic")
    init = np.array([np.eye(4), make_T(np.eye(3), t_a)])
    plain = [PoseEdge(0, 1, make_T(np.eye(3), t_a), "loop", information=1e4),
             PoseEdge(0, 1, make_T(np.eye(3), t_b), "loop", information=1e4)]
    np.testing.assert_allclose(optimise(init, plain, cfg)[1][:3, 3], 0.5 * (t_a + t_b), atol=1e-6)
    shaped = [plain[0], PoseEdge(0, 1, make_T(np.eye(3), t_b), "loop", information=1e4, information_shape=shape)]
    t = optimise(init, shaped, cfg)[1][:3, 3]
    np.testing.assert_allclose(t, [1.0, 0.1, 0.0], atol=5e-4)  # without the shape: x = 1.05
    with pytest.raises(ValueError):
        PoseEdge(0, 1, np.eye(4), information_shape=np.eye(5))


def _ring_run(cfg: PoseGraphConfig, n: int = 240, every: int = 10, back: int = 60) -> tuple[np.ndarray, PoseGraph]:
    """Laps of a 5 m circle (60 nodes a lap) with biased odometry; from node ``back`` on, every ``every``-th node gets
    a loop edge to the node a lap before and the graph is optimised then (as the back end does), new nodes starting
    from the last estimate. Returns the final poses and the graph."""
    rng = np.random.default_rng(3)
    gt = np.array([make_T(so3_exp([0.0, 0.0, 2 * np.pi * k / back + np.pi / 2]),
                          [5 * np.cos(2 * np.pi * k / back), 5 * np.sin(2 * np.pi * k / back), 0.1 * np.sin(k / 7)])
                   for k in range(n)])
    g = PoseGraph(cfg)
    cur = gt[0]
    g.add_node(cur)
    for k in range(1, n):
        meas = invert(gt[k - 1]) @ gt[k] @ exp(np.r_[0.0, 0.0, 0.004, 0.0, 0.0, 0.0] + rng.normal(0, 0.003, 6))
        cur = cur @ meas
        g.add_node(cur)
        g.add_edge(PoseEdge(k - 1, k, meas, "odometry"))
        if k >= back and k % every == 0:
            g.add_edge(PoseEdge(k - back, k, invert(gt[k - back]) @ gt[k] @ exp(rng.normal(0, 0.002, 6)), "loop"))
            cur = g.optimise()[k]
    return g.optimise(), g


def test_incremental_solver_agrees_with_the_batch_one_over_many_loops():
    """isam2, fed each loop's new factors, ends within 2 mm and 1 mrad of Levenberg-Marquardt re-solving the whole
    graph each time, at the same error (to 1 %); an overwritten estimate (set_pose) rebuilds it to the same result,
    and a full solve reaches the batch optimum."""
    inc, g_inc = _ring_run(PoseGraphConfig(edge_information="isotropic"))
    batch, g_batch = _ring_run(PoseGraphConfig(edge_information="isotropic", solver="batch"))
    assert np.abs(inc[:, :3, 3] - batch[:, :3, 3]).max() < 2e-3
    R_rel = np.einsum("nji,njk->nik", inc[:, :3, :3], batch[:, :3, :3])
    assert np.arccos(np.clip((np.trace(R_rel, axis1=1, axis2=2) - 1) / 2, -1, 1)).max() < 1e-3
    assert g_inc.last_error_after == pytest.approx(g_batch.last_error_after, rel=0.01)
    assert g_inc.last_error_after <= g_inc.last_error_before + 1e-9
    g_inc.set_pose(5, inc[5] @ make_T(np.eye(3), [0.3, 0.0, 0.0]))  # knocked off: the rebuilt smoother restores it
    np.testing.assert_allclose(g_inc.optimise()[:, :3, 3], inc[:, :3, 3], atol=2e-3)
    # a full solve (as at the end of a run) is the batch solver's optimum, whatever the path
    np.testing.assert_allclose(g_inc.optimise(full=True)[:, :3, 3], batch[:, :3, 3], atol=1e-4)
    assert g_inc.optimise()[100, 0, 3] == pytest.approx(batch[100, 0, 3], abs=1e-4)  # the smoother rebuilt there


def test_isam2_falls_back_to_the_damped_batch_solve_on_an_indeterminate_system():
    """A node held along five directions only (information 0 along the sixth) stops isam2's Gauss-Newton; that
    optimisation is Levenberg-Marquardt's, which still meets the measurement."""
    g = PoseGraph(PoseGraphConfig(estimated_robust_kernel="none"))
    g.add_node(np.eye(4))
    g.add_node(make_T(np.eye(3), [1.0, 0.0, 0.0]))
    g.add_edge(PoseEdge(0, 1, make_T(np.eye(3), [1.1, 0.0, 0.0]), information_matrix=np.diag([1e4] * 5 + [0.0])))
    P = g.optimise()
    assert g.n_batch_fallbacks == 1
    np.testing.assert_allclose(P[1][:3, 3], [1.1, 0.0, 0.0], atol=1e-6)
