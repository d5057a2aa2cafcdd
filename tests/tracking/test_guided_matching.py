"""Guided descriptor matching: the kernel against its reference, and PnP with it against brute force."""

from dataclasses import replace

import numpy as np
import pytest

from surfelslam.geometry.se3 import invert, pose_error
from surfelslam.kernels import hamming
from surfelslam.tracking.features import FeatureConfig, estimate_motion, extract, match
from surfelslam.types import Intrinsics, RGBDFrame

from helpers import ROOM_INTR, look_pose, render_room

CFG = FeatureConfig(n_features=600)


@pytest.mark.parametrize("seed", range(4))
def test_guided_kernel_equals_the_masked_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, m = int(rng.integers(0, 300)), int(rng.integers(0, 300))
    q = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    t = rng.integers(0, 256, (m, 32), dtype=np.uint8)
    k = min(n, m) // 3
    q[:k] = t[:k]  # exact matches
    q[k:2 * k] &= 3  # few bits set: many equal distances, so ties decide
    t[k:2 * k] &= 3
    train_uv = rng.uniform(-5, 330, (m, 2))  # some keypoints off the image: border cells
    pred_uv = rng.uniform(-40, 360, (n, 2))
    pred_uv[::7] = np.nan  # no prediction: no match
    got = hamming.nearest_mutual_within_words(hamming.as_words(q), pred_uv, hamming.as_words(t), train_uv, 20.0,
                                              320, 240)
    want = hamming.nearest_mutual_within_ref(q, pred_uv, t, train_uv, 20.0)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
    if n and m:
        assert (got[1] >= 0).any() and (got[1] < 0).any()


def _frames(intr: Intrinsics):
    T_a = look_pose(np.array([0.1, 0.0, -0.3]), 0.1)
    T_b = look_pose(np.array([0.16, 0.03, -0.25]), 0.16, 0.04)
    fa, fb = (RGBDFrame(i, float(i), *render_room(T, intr)) for i, T in enumerate((T_a, T_b)))
    return invert(T_b) @ T_a, extract(fa.rgb, fa.depth_m, intr, CFG), extract(fb.rgb, fb.depth_m, intr, CFG)


@pytest.mark.parametrize("fy_sign", [1, -1], ids=["fy_pos", "fy_neg"])
def test_guided_matching_recovers_the_pose_from_a_rough_prediction(fy_sign: int) -> None:
    intr = replace(ROOM_INTR, fy=fy_sign * ROOM_INTR.fy)
    T_gt, a, b = _frames(intr)
    T_rough = T_gt.copy()
    T_rough[:3, 3] += [0.01, -0.01, 0.005]  # a prediction about 5 px off
    guided = replace(CFG, guided_radius_px=16.0, guided_min_matches=30)
    res = estimate_motion(a, b, intr, guided, T_init_cur_ref=T_rough)
    brute = estimate_motion(a, b, intr, CFG, T_init_cur_ref=T_rough)
    assert res.ok and brute.ok
    assert pose_error(res.T_cur_ref, T_gt)[0] < 0.02 and pose_error(res.T_cur_ref, T_gt)[1] < 0.5
    # guided matches are among the reference keypoints with depth, and at least as many survive PnP
    assert a.valid[res.pairs[:, 0]].all()
    assert res.n_inliers >= 0.9 * brute.n_inliers
    # a prediction far off gives wrong guided matches and too few PnP inliers: the result is brute force's
    T_far = T_gt.copy()
    T_far[:3, 3] += [0.5, 0.0, 0.0]
    far = estimate_motion(a, b, intr, guided, T_init_cur_ref=T_far)
    np.testing.assert_array_equal(far.pairs, estimate_motion(a, b, intr, CFG, T_init_cur_ref=T_far).pairs)


def test_match_without_prediction_is_brute_force() -> None:
    _, a, b = _frames(ROOM_INTR)
    guided = replace(CFG, guided_radius_px=16.0)
    np.testing.assert_array_equal(match(a, b, guided).pairs, match(a, b, CFG).pairs)
