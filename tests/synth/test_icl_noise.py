"""The ``icl`` noise model (ICL-NUIM's synthetic sensor noise) on known depth images."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from surfelslam.synth.noise import frame_rng, noisy_depth
from surfelslam.synth.writer import ICL_NOISE, default_intrinsics, noise_config

INTR = default_intrinsics(320, 240)
FACING = np.zeros((240, 320, 3), np.float32)
FACING[..., 2] = -1.0  # surfaces facing the camera
STEP_M = ICL_NOISE.baseline_m * ICL_NOISE.disparity_focal_px / ICL_NOISE.disparity_step_px  # z * disparity steps


def test_icl_depth_is_on_the_disparity_steps_with_one_sixth_step_of_noise():
    """A wall at 4 m: disparity 351.3 / 4 = 87.8 steps. Rounded after noise of 1/6 step, 88 steps (3.992 m) is the
    usual value, 87 (4.038 m) comes with probability P(N < -0.33 / (1/6)) = 2.5 % and 89 with P(N > 4.05) = 3e-5;
    every pixel keeps a depth."""
    assert noise_config("icl") is ICL_NOISE
    z = noisy_depth(np.full((240, 320), 4.0, np.float32), FACING, INTR, ICL_NOISE, frame_rng(0, 0))
    assert np.all(z > 0)
    steps = STEP_M / z.astype(np.float64)
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-3)
    share = {k: float(np.mean(np.round(steps) == k)) for k in (86, 87, 88, 89)}
    assert share[88] > 0.95 and 0.01 < share[87] < 0.05 and share[86] == 0.0 and share[89] < 1e-3, share


def test_icl_jitter_mixes_depth_edges_but_never_holes():
    """Left half at 2 m, right half at 3 m: the bilinear lookup at jittered positions gives depths in between along
    the edge, and none without the jitter. Next to a hole (no depth) nothing is mixed with 0."""
    step = np.where(np.arange(320) < 160, 2.0, 3.0).astype(np.float32)[None, :].repeat(240, 0)
    z = noisy_depth(step, FACING, INTR, ICL_NOISE, frame_rng(0, 1))
    between = (z > 2.1) & (z < 2.9)
    assert between[:, 150:170].sum() > 50 and not between[:, :150].any() and not between[:, 170:].any()
    still = noisy_depth(step, FACING, INTR, replace(ICL_NOISE, lateral_jitter_px=0.0), frame_rng(0, 1))
    assert not ((still > 2.1) & (still < 2.9)).any()
    hole = step.copy()
    hole[:, :160] = 0.0
    z = noisy_depth(hole, FACING, INTR, ICL_NOISE, frame_rng(0, 2))
    assert np.all((z == 0) | (z > 2.9)) and (z[:, 165:] > 0).all() and not z[:, :155].any()
