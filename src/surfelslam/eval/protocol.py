"""The evaluation protocol's numbers that callers need without the evaluation itself.

:mod:`surfelslam.eval.metrics` imports evo (and with it scipy.spatial: about 0.05 s); a run's start-up needs only these
defaults, and evo at its end.
"""

from __future__ import annotations

DEFAULT_MAX_DIFF_S = 0.02  # TUM association window: 20 ms
