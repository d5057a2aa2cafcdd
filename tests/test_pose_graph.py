"""Pose graph: loop closure corrects drift; the robust kernel limits a wrong loop edge."""

from __future__ import annotations

import numpy as np
import pytest

from surfelslam.backend.pose_graph import PoseEdge, PoseGraph, PoseGraphConfig, optimise
from surfelslam.geometry.se3 import exp, invert, make_T, so3_exp


def _square_loop(n_side: int = 5, side_m: float = 2.0) -> np.ndarray:
    """Ground-truth poses walking a square (turning 90 deg at the corners), ``(4 n_side, 4, 4)``."""
    poses = []
    T = np.eye(4)
    step = make_T(np.eye(3), [side_m / n_side, 0.0, 0.0])
    turn = make_T(so3_exp([0.0, 0.0, np.pi / 2]), [0.0, 0.0, 0.0])
    for k in range(4 * n_side):
        poses.append(T.copy())
        T = T @ step
        if (k + 1) % n_side == 0:
            T = T @ turn
    return np.array(poses)


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


def _ate(est: np.ndarray, gt: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((est[:, :3, 3] - gt[:, :3, 3]) ** 2, axis=1))))


def test_loop_edge_corrects_drift() -> None:
    gt = _square_loop()
    init, edges = _drifted_odometry(gt)
    n = len(gt)
    loop = PoseEdge(n - 1, 0, invert(gt[n - 1]) @ gt[0], "loop")
    before = _ate(init, gt)
    after_odo = _ate(optimise(init, edges), gt)
    after = _ate(optimise(init, edges + [loop]), gt)
    assert before > 0.3  # the bias drifts a lot
    assert after_odo == pytest.approx(before, rel=1e-3)  # odometry alone cannot fix it
    assert after < 0.25 * before
    # the first pose stays anchored
    np.testing.assert_allclose(optimise(init, edges + [loop])[0], gt[0], atol=1e-6)


@pytest.mark.parametrize("kernel", ["huber", "cauchy"])
def test_robust_kernel_downweights_outlier_loop(kernel: str) -> None:
    gt = _square_loop()
    init, edges = _drifted_odometry(gt, seed=1)
    n = len(gt)
    good = PoseEdge(n - 1, 0, invert(gt[n - 1]) @ gt[0], "loop")
    # wrong loop: claims node 10 sits 1.5 m and 60 deg away from node 2's true relation
    bad_rel = invert(gt[2]) @ gt[10] @ make_T(so3_exp([0.0, 0.0, 1.0]), [1.5, -1.0, 0.0])
    bad = PoseEdge(2, 10, bad_rel, "loop")
    plain = _ate(optimise(init, edges + [good, bad], PoseGraphConfig(robust_kernel="none")), gt)
    robust = _ate(optimise(init, edges + [good, bad], PoseGraphConfig(robust_kernel=kernel)), gt)
    clean = _ate(optimise(init, edges + [good], PoseGraphConfig(robust_kernel=kernel)), gt)
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
    assert g.last_error_after < g.last_error_before
    with pytest.raises(ValueError):
        g.add_edge(PoseEdge(0, 99, np.eye(4)))
