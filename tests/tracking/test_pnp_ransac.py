"""PnP-RANSAC estimators of ``FeatureConfig.ransac_method``: both recover a known pose through outliers; USAC is
deterministic and leaves guessed calls on the classic path."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from surfelslam.errors import ConfigError
from surfelslam.geometry.se3 import so3_exp, so3_log
from surfelslam.tracking.features.config import FeatureConfig
from surfelslam.tracking.features.motion import pnp_ransac

K = np.array([[262.5, 0.0, 159.5], [0.0, 262.5, 119.5], [0.0, 0.0, 1.0]])
R_TRUE = so3_exp(np.array([0.05, -0.12, 0.03]))
T_TRUE = np.array([0.15, -0.05, 0.2])


def _correspondences(n: int, outlier_fraction: float, seed: int):
    """``(obj (n, 3), img (n, 2), is_inlier (n,))``: points 1-4 m ahead seen at the true pose with 0.3 px noise;
    the outliers' pixels are uniform over the 320x240 image."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(1.0, 4.0, n)
    obj = np.column_stack([rng.uniform(-0.5, 0.5, n) * z, rng.uniform(-0.4, 0.4, n) * z, z])
    cam = obj @ R_TRUE.T + T_TRUE
    img = (cam @ K.T)[:, :2] / cam[:, 2:3] + rng.normal(0.0, 0.3, (n, 2))
    is_inlier = rng.random(n) >= outlier_fraction
    img[~is_inlier] = rng.uniform([0, 0], [320, 240], (int((~is_inlier).sum()), 2))
    return obj, img, is_inlier


def _pose_error(rvec, tvec) -> tuple[float, float]:
    """(translation error m, rotation error deg) against the true pose."""
    dR = so3_exp(np.asarray(rvec, float).reshape(3)) @ R_TRUE.T
    dt_m = float(np.linalg.norm(np.asarray(tvec, float).reshape(3) - T_TRUE))
    return dt_m, float(np.degrees(np.linalg.norm(so3_log(dR))))


@pytest.mark.parametrize("method", ["ransac", "usac"])
def test_both_estimators_recover_the_pose_through_half_outliers(method):
    obj, img, is_inlier = _correspondences(300, 0.5, seed=3)
    cfg = replace(FeatureConfig(), ransac_method=method)
    mask, rvec, tvec, reason = pnp_ransac(obj, img, K, None, None, False, cfg)
    assert reason is None
    dt, dr = _pose_error(rvec, tvec)
    assert dt < 0.01 and dr < 0.3
    assert (mask & is_inlier).sum() >= 0.9 * is_inlier.sum()
    assert (mask & ~is_inlier).sum() <= 0.05 * (~is_inlier).sum()


def test_usac_finds_the_pose_among_many_outliers_and_is_deterministic():
    obj, img, is_inlier = _correspondences(200, 0.75, seed=5)
    cfg = replace(FeatureConfig(), ransac_method="usac")
    first = pnp_ransac(obj, img, K, None, None, False, cfg)
    second = pnp_ransac(obj, img, K, None, None, False, cfg)
    dt, dr = _pose_error(first[1], first[2])
    assert dt < 0.02 and dr < 0.5
    assert (first[0] & is_inlier).sum() >= 0.9 * is_inlier.sum()
    for a, b in zip(first[:3], second[:3], strict=True):
        assert np.array_equal(a, b)


def test_a_guessed_call_ignores_the_method():
    obj, img, _ = _correspondences(150, 0.3, seed=7)
    rvec0 = so3_log(R_TRUE).reshape(3, 1) + 0.01
    tvec0 = T_TRUE.reshape(3, 1) + 0.02
    out = [pnp_ransac(obj, img, K, rvec0.copy(), tvec0.copy(), True, replace(FeatureConfig(), ransac_method=m))
           for m in ("ransac", "usac")]
    for a, b in zip(out[0][:3], out[1][:3], strict=True):
        assert np.array_equal(a, b)


def test_an_unknown_method_is_refused_by_name():
    with pytest.raises(ConfigError, match="ransac_method"):
        FeatureConfig(ransac_method="lmeds")
