"""Small statistics in plain Python: the back end's chi-square gate needs one quantile, and scipy.special's import
would cost every run's start 0.1 s of CPU for it."""

from __future__ import annotations

import math

#: Newton steps of :func:`chi2_quantile_6dof` at most (it converges in under ten from its start).
_QUANTILE_MAX_STEPS = 100
#: Its stopping rule: a step below this many ulps of the root.
_QUANTILE_TOL_ULPS = 4


def _lower_tail_3(y: float) -> float:
    """``P(3, y)``, the regularised lower incomplete gamma function of shape 3, by its series ``e^-y sum_{n>=3}
    y^n / n!`` (accurate where it is small, which the closed form ``1 - e^-y (1 + y + y^2/2)`` is not)."""
    term = y ** 3 / 6.0
    total, n = term, 3
    while term > math.ulp(total):
        n += 1
        term *= y / n
        total += term
    return math.exp(-y) * total


def chi2_quantile_6dof(q: float) -> float:
    """The chi-square quantile with 6 degrees of freedom (scipy's ``chi2.ppf(q, 6)``, ``2 P^-1(3, q)``), ``0 < q < 1``.

    With ``x = 2 y``: Newton's method on the logarithm of the upper tail ``1 - q = e^-y (1 + y + y^2 / 2)`` (the
    closed form for an even number of degrees of freedom) when ``q >= 1/2``, of the lower tail ``q = P(3, y)`` (its
    series) below. Both logarithms are concave in ``y``: the steps never overshoot. Within 1e-12 (relative) of
    scipy's, equal at the default quantile; it spares a run's start the import of scipy.special (0.1 s of CPU)."""
    upper = q >= 0.5
    target = math.log1p(-q) if upper else math.log(q)
    y = max(3.0, -target) if upper else (6.0 * q) ** (1.0 / 3.0)  # P(3, y) <= y^3 / 6: starts below the root
    for _ in range(_QUANTILE_MAX_STEPS):
        if upper:
            s = 1.0 + y + 0.5 * y * y
            step = (-y + math.log(s) - target) / (-0.5 * y * y / s)
        else:
            p = _lower_tail_3(y)
            step = (math.log(p) - target) / (0.5 * y * y * math.exp(-y) / p)
        y_next = y - step if y - step > 0 else 0.5 * y  # never across zero: halve instead
        done = abs(y_next - y) <= _QUANTILE_TOL_ULPS * math.ulp(y_next)
        y = y_next
        if done:
            break
    return 2.0 * y
