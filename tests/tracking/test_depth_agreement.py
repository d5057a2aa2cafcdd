"""The depth agreement of a relative pose (:mod:`surfelslam.tracking.depth_agreement`) on exact synthetic depth."""

from __future__ import annotations

import numpy as np
import pytest

from surfelslam.errors import ConfigError
from surfelslam.geometry import se3
from surfelslam.synth import make_scene, render
from surfelslam.synth.trajectories import look_at
from surfelslam.tracking.depth_agreement import depth_agreement
from surfelslam.types import Intrinsics


def test_depth_agreement_prefers_the_true_pose():
    """Exact synthetic depth: the true relative pose explains the two images to a fraction of a millimetre; a
    pose 2 cm off does not; no overlap gives NaN; wrong sizes are a clear error."""
    intr = Intrinsics(262.5, 262.5, 159.5, 119.5, 320, 240)
    scene = make_scene("room")
    T_w_t = look_at(np.array([2.5, 2.0, 1.4]), np.array([2.5, 0.0, 0.8]))[0]
    T_t_s = se3.exp(np.array([0.02, -0.05, 0.03, 0.06, -0.02, 0.04]))
    dt = render(scene, T_w_t, intr).depth_m.copy()
    ds = render(scene, T_w_t @ T_t_s, intr).depth_m.copy()
    good = depth_agreement(ds, dt, intr, T_t_s)
    off = depth_agreement(ds, dt, intr, se3.exp(np.array([0, 0, 0, 0.0, 0.0, 0.02])) @ T_t_s)
    assert good.median_abs_dz_m < 1.5e-3 and good.overlap_fraction > 0.8, good  # nearest-pixel sampling
    assert off.median_abs_dz_m > 10 * good.median_abs_dz_m, (good, off)
    away = se3.exp(np.array([0.0, np.pi, 0.0, 0.0, 0.0, 0.0]))  # facing the other way: nothing in view
    none = depth_agreement(ds, dt, intr, away)
    assert none.overlap_pixels == 0 and np.isnan(none.median_abs_dz_m)
    with pytest.raises(ConfigError, match="320x240"):
        depth_agreement(ds[:-1], dt, intr, T_t_s)
