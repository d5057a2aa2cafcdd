"""JSON output of numpy values (numbers and arrays)."""

from __future__ import annotations

import numpy as np


def json_default(o):
    """``json.dumps(default=...)`` hook: numpy scalars become Python numbers, arrays become lists."""
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON-serialisable: {type(o)}")

