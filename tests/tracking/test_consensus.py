"""Rigid 3D consensus of feature matches: numba kernels against their numpy references, recovery of a known
motion at inlier fractions where PnP-RANSAC's samples fail, and the fallback inside ``estimate_motion``."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from surfelslam.geometry.se3 import make_T, pose_error, so3_exp
from surfelslam.kernels import consensus as kc
from surfelslam.tracking.consensus import (
    greedy_clique,
    has_consistent_set,
    pairwise_consistency,
    rigid_consensus,
    rigid_fit,
)
from surfelslam.tracking.features import FeatureConfig, Features, estimate_motion
from surfelslam.types import Intrinsics

from helpers import INTR

INTR_NEG = Intrinsics(262.5, -262.5, 159.5, 119.5, 320, 240)
T_TRUE = make_T(so3_exp([0.1, -0.4, 0.05]), [0.35, -0.05, 0.2])  # 0.4 m and 24 deg: a wide baseline
T_VIEW = make_T(so3_exp([0.05, -0.12, 0.02]), [0.3, -0.05, 0.1])  # 0.3 m and 7.5 deg: views that overlap


def _matches(n: int, n_true: int, noise_m: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` matches ``(P_ref, P_cur)``; the first ``n_true`` follow ``T_TRUE``, the rest are random points."""
    rng = np.random.default_rng(seed)
    P = rng.uniform([-1.5, -1.0, 1.0], [1.5, 1.0, 4.0], (n, 3))
    Q = P @ T_TRUE[:3, :3].T + T_TRUE[:3, 3] + rng.normal(0.0, noise_m, (n, 3))
    Q[n_true:] = rng.uniform([-1.5, -1.0, 1.0], [1.5, 1.0, 4.0], (n - n_true, 3))
    return P, Q


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_kernels_equal_numpy_references(seed: int) -> None:
    P, Q = _matches(250, 40, 0.005, seed)
    C = pairwise_consistency(P, Q, 0.03, 0.05)
    np.testing.assert_array_equal(C, kc.consistency_matrix_ref(P, Q, 0.03, 0.05))
    assert C.sum() > 0 and not C.all()
    degree = C.sum(axis=1).astype(np.int64)
    seeds = np.argsort(-degree, kind="stable")[:10].astype(np.int64)
    for min_size, stop_at in ((1, 0), (30, 0), (10_000, 0), (10, 10), (30, 25)):
        members = np.empty(len(C), np.int64)
        k = kc.greedy_clique(C, seeds, degree, min_size, stop_at, members)
        np.testing.assert_array_equal(members[:k], kc.greedy_clique_ref(C, seeds, degree, min_size, stop_at))
    assert len(greedy_clique(C, 10, min_size=10_000)) == 0
    # stopping early: a set of exactly that size, a prefix of the full growth from the same seed
    full, early = greedy_clique(C, 10), greedy_clique(C, 10, stop_at=10)
    assert len(full) >= 40 and len(early) == 10 and np.isin(early, full).all()
    assert has_consistent_set(P, Q, 0.03, 0.05, 10, len(full)) and not has_consistent_set(P, Q, 0.03, 0.05, 10, 60)


def test_clique_members_are_pairwise_consistent() -> None:
    P, Q = _matches(200, 30, 0.005, 4)
    C = pairwise_consistency(P, Q, 0.03, 0.05)
    m = greedy_clique(C, 10)
    sub = C[np.ix_(m, m)]
    assert np.all(sub | np.eye(len(m), dtype=bool))


@pytest.mark.parametrize("n_true", [15, 30, 60])
def test_rigid_consensus_recovers_the_motion_among_outliers(n_true: int) -> None:
    """300 matches, 5-20 % correct: the consensus is the correct matches and the motion is recovered."""
    P, Q = _matches(300, n_true, 0.0, 5)
    T, members = rigid_consensus(P, Q, 0.03, 0.05, 10)
    assert T is not None
    assert np.all(members < n_true) and len(members) >= n_true - 1, (len(members), n_true)
    dt, dr = pose_error(T, T_TRUE)
    assert dt < 1e-9 and dr < 1e-7
    # with 5 mm noise on the current points the fit is still within a centimetre and half a degree
    P, Q = _matches(300, n_true, 0.005, 6)
    T, members = rigid_consensus(P, Q, 0.03, 0.05, 10)
    assert np.mean(members < n_true) > 0.9
    dt, dr = pose_error(T, T_TRUE)
    assert dt < 0.01 and dr < 0.5, (dt, dr)


def test_rigid_consensus_ignores_missing_depth_and_rejects_degenerate_sets() -> None:
    P, Q = _matches(100, 40, 0.0, 7)
    Q[:10] = np.nan  # no current depth at these keypoints
    T, members = rigid_consensus(P, Q, 0.03, 0.05, 10)
    assert T is not None and members.min() >= 10 and pose_error(T, T_TRUE)[0] < 1e-9
    line = np.column_stack([np.linspace(0, 1, 10), np.zeros(10), np.full(10, 2.0)])
    assert rigid_fit(line, line) is None  # collinear: rotation about the line is free
    assert rigid_fit(P[:2], Q[:2]) is None
    T, members = rigid_consensus(P, Q, 0.03, 0.05, 10, min_size=50)
    assert T is None and len(members) == 0


def _features(uv: np.ndarray, pts: np.ndarray, desc: np.ndarray) -> Features:
    valid = np.all(np.isfinite(pts), axis=1)
    return Features(uv.astype(np.float32), desc, pts.astype(np.float32), valid, np.ones(len(uv), np.float32))


def _project(X: np.ndarray, intr: Intrinsics) -> np.ndarray:
    return np.column_stack([intr.fx * X[:, 0] / X[:, 2] + intr.cx, intr.fy * X[:, 1] / X[:, 2] + intr.cy])


def _scene(intr: Intrinsics, n: int, n_true: int, seed: int) -> tuple[Features, Features]:
    """``n`` descriptor matches between two views ``T_VIEW`` apart, each with depth on both sides; the first
    ``n_true`` are correct, the current side of the others is another random point of the current view."""
    rng = np.random.default_rng(seed)
    # reference points in view of both cameras
    P = rng.uniform([-1.0, -0.7, 2.0], [1.0, 0.7, 3.5], (4 * n, 3))
    X = P @ T_VIEW[:3, :3].T + T_VIEW[:3, 3]
    uv_ref, uv_cur = _project(P, intr), _project(X, intr)
    inside = np.all((uv_cur > 5) & (uv_cur < [intr.width - 5, intr.height - 5]), axis=1) & (X[:, 2] > 0)
    P, X, uv_ref, uv_cur = P[inside][:n], X[inside][:n], uv_ref[inside][:n], uv_cur[inside][:n]
    wrong = np.arange(n_true, n)
    X[wrong] = rng.uniform([-1.0, -0.7, 2.0], [1.0, 0.7, 3.5], (len(wrong), 3))
    uv_cur[wrong] = _project(X[wrong], intr)
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)  # identical descriptors: match i <-> i
    return _features(uv_ref, P, desc), _features(uv_cur, X, desc)


@pytest.mark.parametrize("intr", [INTR, INTR_NEG], ids=["fy_pos", "fy_neg"])
def test_estimate_motion_falls_back_to_the_consensus(intr: Intrinsics) -> None:
    """300 descriptor matches of which 36 (12 %) are correct, each with depth on both sides: 300 EPnP samples
    of 5 almost never come out clean, so PnP-RANSAC alone fails; the consensus recovers the motion."""
    n, n_true = 300, 36
    ref, cur = _scene(intr, n, n_true, 8)
    cfg = replace(FeatureConfig(), max_motion_norm=2.0, lk_refine=False, rgbd_refine_iterations=0)
    plain = estimate_motion(ref, cur, intr, replace(cfg, consensus_fallback=False))
    assert not plain.ok or pose_error(plain.T_cur_ref, T_VIEW)[0] > 0.05  # RANSAC alone misses it
    res = estimate_motion(ref, cur, intr, cfg)
    assert res.ok, res.reason
    assert res.n_inliers >= n_true - 2 and not res.inlier_mask[n_true:].any()
    dt, dr = pose_error(res.T_cur_ref, T_VIEW)
    assert dt < 1e-6 and dr < 1e-5, (dt, dr)
    # the result does not depend on the call
    again = estimate_motion(ref, cur, intr, cfg)
    np.testing.assert_array_equal(again.T_cur_ref, res.T_cur_ref)


def test_consistency_pretest_rejects_views_that_do_not_overlap() -> None:
    """``min_consistent``: 150 good matches of which 6 are correct (two keyframes that barely overlap) hold no
    rigidly consistent set of 10, so the pair is rejected before RANSAC (``too_few_consistent``); with 36 correct
    ones the pre-test passes and the result is the one without it, bit for bit."""
    cfg = replace(FeatureConfig(), max_motion_norm=2.0, lk_refine=False, rgbd_refine_iterations=0)
    ref, cur = _scene(INTR, 150, 6, 3)
    res = estimate_motion(ref, cur, INTR, cfg, min_consistent=10)
    assert not res.ok and res.reason == "too_few_consistent" and res.n_inliers == 0
    _, members = rigid_consensus(ref.points_cam, cur.points_cam, cfg.consensus_abs_tol_m, cfg.consensus_rel_tol,
                                 cfg.consensus_seeds)
    assert 6 <= len(members) < 10  # the six correct matches (plus any chance agreement) are all there is
    ref, cur = _scene(INTR, 300, 36, 8)
    with_test = estimate_motion(ref, cur, INTR, cfg, min_consistent=30)
    without = estimate_motion(ref, cur, INTR, cfg)
    assert with_test.ok and pose_error(with_test.T_cur_ref, T_VIEW)[0] < 1e-6
    np.testing.assert_array_equal(with_test.T_cur_ref, without.T_cur_ref)
    assert estimate_motion(ref, cur, INTR, cfg, min_consistent=37).reason == "too_few_consistent"
