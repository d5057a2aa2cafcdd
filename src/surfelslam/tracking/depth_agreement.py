"""How well a relative pose explains two depth images, without ground truth.

The source depth is back-projected, moved into the target camera by ``T_target_source`` and projected to the
nearest target pixel; where the target has depth, ``|z_target - z_moved|`` is the disagreement. Pixels whose
disagreement exceeds ``max_abs_dz_m`` (occlusions, parts seen by one camera only) are left out, so the median
is that of the overlap. Comparing it at two poses (an estimate and a ground-truth pose) says which one the depth
data prefer: a registration whose median is lower than the ground truth's fits the data better than the
ground truth does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surfelslam.errors import ConfigError
from surfelslam.types import Intrinsics

DEFAULT_MAX_ABS_DZ_M = 0.1  # larger disagreements are occlusions or non-overlap, not registration error


@dataclass(frozen=True)
class DepthAgreement:
    """Result of :func:`depth_agreement`.

    Attributes:
        median_abs_dz_m: median ``|z_target - z_moved|`` over the overlap (m); NaN when there is no overlap.
        overlap_pixels: source pixels that land on target depth within ``max_abs_dz_m``.
        overlap_fraction: ``overlap_pixels`` / valid source pixels.
    """

    median_abs_dz_m: float
    overlap_pixels: int
    overlap_fraction: float


def depth_agreement(src_depth_m: np.ndarray, tgt_depth_m: np.ndarray, intr: Intrinsics,
                    T_target_source: np.ndarray, max_abs_dz_m: float = DEFAULT_MAX_ABS_DZ_M) -> DepthAgreement:
    """Disagreement of two depth images ``(H, W)`` (metres, 0 = invalid; same camera ``intr``) under a pose.

    Args:
        T_target_source: ``(4, 4)`` maps source-camera points into the target camera.
        max_abs_dz_m: disagreements above this are not overlap (m).
    """
    src = np.asarray(src_depth_m)
    tgt = np.asarray(tgt_depth_m)
    if src.shape != intr.shape or tgt.shape != intr.shape:
        raise ConfigError(f"depth_agreement: depth images must be {intr.width}x{intr.height}, got "
                          f"{src.shape[::-1]} and {tgt.shape[::-1]}")
    T = np.asarray(T_target_source, np.float64)
    if T.shape != (4, 4):
        raise ConfigError(f"depth_agreement: T_target_source must be 4x4, got {T.shape}")
    v, u = np.nonzero(np.isfinite(src) & (src > 0))
    n_valid = len(u)
    z = src[v, u].astype(np.float64)
    P = np.column_stack([(u - intr.cx) / intr.fx * z, (v - intr.cy) / intr.fy * z, z])
    Q = P @ T[:3, :3].T + T[:3, 3]
    front = Q[:, 2] > 0
    Q = Q[front]
    uq = np.floor(intr.fx * Q[:, 0] / Q[:, 2] + intr.cx + 0.5)
    vq = np.floor(intr.fy * Q[:, 1] / Q[:, 2] + intr.cy + 0.5)
    inside = (uq >= 0) & (uq < intr.width) & (vq >= 0) & (vq < intr.height)
    zt = tgt[vq[inside].astype(np.int64), uq[inside].astype(np.int64)].astype(np.float64)
    dz = np.abs(zt - Q[inside, 2])
    keep = np.isfinite(zt) & (zt > 0) & (dz <= max_abs_dz_m)
    n = int(keep.sum())
    med = float(np.median(dz[keep])) if n else float("nan")
    return DepthAgreement(med, n, n / n_valid if n_valid else 0.0)
