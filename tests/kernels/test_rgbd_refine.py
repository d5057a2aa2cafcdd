"""The RGB-D pose refinement kernel against its numpy reference, and on a known pose."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from surfelslam.geometry.se3 import exp as se3_exp
from surfelslam.geometry.se3 import pose_error
from surfelslam.tracking.features.config import FeatureConfig
from surfelslam.tracking.features.refine import refine_rgbd, refine_rgbd_ref
from surfelslam.types import Intrinsics

INTR = Intrinsics(262.5, -262.5, 159.5, 119.5, 320, 240)  # fy < 0: no sign assumption


def _problem(n: int, seed: int, pixel_noise: float = 0.5, depth_holes: float = 0.2, outliers: int = 0):
    """``n`` reference points seen from a known pose: (T_true, T_start, P, uv, inverse depth with NaN holes)."""
    rng = np.random.default_rng(seed)
    P = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-0.7, 0.7, n), rng.uniform(1, 3, n)])
    T_true = se3_exp(np.array([0.02, -0.03, 0.01, 0.03, -0.01, 0.05]))
    X = P @ T_true[:3, :3].T + T_true[:3, 3]
    uv = np.column_stack([INTR.fx * X[:, 0] / X[:, 2] + INTR.cx, INTR.fy * X[:, 1] / X[:, 2] + INTR.cy])
    uv += rng.normal(0, pixel_noise, uv.shape)
    uv[:outliers] += rng.uniform(-30, 30, (outliers, 2))
    inv = 1 / X[:, 2] + rng.normal(0, 0.002, n)
    inv[rng.random(n) < depth_holes] = np.nan
    T_start = se3_exp(np.array([0.005, 0.004, -0.003, 0.01, 0.01, -0.01])) @ T_true
    return T_true, T_start, P, uv, inv


@pytest.mark.parametrize("n, seed, outliers", [(200, 0, 0), (60, 1, 6), (12, 2, 0), (8, 3, 0)])
def test_kernel_matches_the_reference(n, seed, outliers):
    _, T0, P, uv, inv = _problem(n, seed, outliers=outliers)
    cfg = FeatureConfig()
    T_k, H_k = refine_rgbd(T0, P, uv, inv, INTR, cfg, with_information=True)
    T_r, H_r = refine_rgbd_ref(T0, P, uv, inv, INTR, cfg, with_information=True)
    np.testing.assert_allclose(T_k, T_r, rtol=0, atol=1e-10)
    np.testing.assert_allclose(H_k, H_r, rtol=1e-8, atol=1e-8 * np.abs(H_r).max())
    np.testing.assert_allclose(refine_rgbd(T0, P, uv, inv, INTR, cfg), T_k, rtol=0, atol=0)


def test_refinement_recovers_the_pose_and_stops_where_the_reference_does():
    T_true, T0, P, uv, inv = _problem(300, 4, pixel_noise=0.3, outliers=10)
    cfg = FeatureConfig()
    T = refine_rgbd(T0, P, uv, inv, INTR, cfg)
    dt0, dr0 = pose_error(T0, T_true)
    dt, dr = pose_error(T, T_true)
    assert dt < 0.002 and dr < 0.05 and dt < dt0 / 5, (dt, dr, dt0, dr0)
    # no iterations: the start; a point behind the camera: the start, and no information
    np.testing.assert_array_equal(refine_rgbd(T0, P, uv, inv, INTR, replace(cfg, rgbd_refine_iterations=0)), T0)
    behind = P.copy()
    behind[0] = [0.0, 0.0, -5.0]
    T_b, info = refine_rgbd(T0, behind, uv, inv, INTR, cfg, with_information=True)
    T_rb, info_r = refine_rgbd_ref(T0, behind, uv, inv, INTR, cfg, with_information=True)
    np.testing.assert_array_equal(T_b, T0)
    np.testing.assert_array_equal(T_rb, T0)
    assert info is None and info_r is None


def test_the_kernels_median_is_numpys_to_the_bit():
    """The hand-written median of the robust spreads equals ``np.median`` exactly: odd and even counts, ties, one
    element; NaN when empty or when a NaN is among the values (as numpy)."""
    from surfelslam.kernels.rgbd_refine import median

    rng = np.random.default_rng(3)
    for n in [*range(1, 40), 256, 1001]:
        # the reversed order copied: contiguous, as the kernel's callers pass (a strided view compiles another twin)
        for v in (rng.normal(size=n), rng.integers(0, 4, n).astype(np.float64),
                  np.sort(rng.normal(size=n))[::-1].copy()):
            assert median(v) == np.median(v), (n, v)
    assert np.isnan(median(np.zeros(0))) and np.isnan(median(np.array([1.0, np.nan, 3.0])))
