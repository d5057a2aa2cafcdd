"""The statistics helpers against scipy (the reference they stand in for)."""

from __future__ import annotations

import numpy as np

from surfelslam.backend.loop_consistency import LoopConsistencyConfig
from surfelslam.geometry.stats import chi2_quantile_6dof


def test_chi2_quantile_matches_scipy():
    """The closed-form 6-dof chi-square quantile equals scipy's over the setting's range (1e-12 relative), and to
    the last bit at the default 0.99 (the gate's threshold, so the loop decisions are unchanged)."""
    from scipy.stats import chi2

    qs = np.concatenate([np.linspace(1e-4, 1 - 1e-4, 501), [1e-8, 0.5, 0.9, 0.95, 0.999, 1 - 1e-6, 1 - 1e-10]])
    ours = np.array([chi2_quantile_6dof(float(q)) for q in qs])
    np.testing.assert_allclose(ours, chi2.ppf(qs, 6), rtol=1e-12, atol=0)
    q = LoopConsistencyConfig().quantile
    assert chi2_quantile_6dof(q) == float(chi2.ppf(q, 6))
    assert abs(chi2_quantile_6dof(0.99) - 16.811893829770927) < 1e-12  # the chi-square table's 16.812
