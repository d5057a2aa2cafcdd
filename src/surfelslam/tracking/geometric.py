"""A registration guess from the depth alone: FPFH descriptors, mutual matching, rigid 3D consensus.

Two views far apart share little texture that survives the change of viewpoint (a few feature inliers, often
none), but the surfaces they share have the same shape. Fast Point Feature Histograms
(Rusu et al., ICRA 2009) describe the local shape around a point by the angles between its normal, its
neighbours' normals and the lines joining them, which a rigid motion leaves unchanged. Steps:

1. :func:`voxel_cloud`: the frame's vertex and normal maps averaged per voxel (``voxel_m``): an even sampling of
   the surface, whatever its distance to the camera.
2. :func:`fpfh`: per point, the histogram of three angles over its neighbours within ``feature_radius_m``
   (SPFH, 3 x ``bins``), then the FPFH: its SPFH plus the inverse-distance-weighted mean of its neighbours'.
   Neighbour pairs from scipy's k-d tree; one numba pass over them per step (:mod:`surfelslam.kernels.fpfh`,
   numpy references beside the kernels).
3. :func:`mutual_matches`: nearest neighbours in descriptor space, kept when each is the other's nearest.
4. The rigid motion of the largest set of matches that keep their pairwise 3D distances
   (:func:`surfelslam.tracking.consensus.rigid_consensus`, deterministic, no sampling), refitted on every match
   it brings within ``inlier_dist_m``.

The guess is coarse (centimetres, a few degrees: the points are voxel means) and meant as an ICP start.
Geometry that slides (a long counter, a corridor) has no unique answer; texture settles those, so
:func:`surfelslam.tracking.registration.register_pair` prefers the PnP guess and falls back on this one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surfelslam.config import Config, check, fmt_value, setting
from surfelslam.geometry import se3
from surfelslam.kernels import fpfh as kf
from surfelslam.kernels.voxel import voxel_keys
from surfelslam.tracking.consensus import rigid_consensus, rigid_fit

MATCH_BLOCK_ROWS = 1024  # descriptor rows per distance block in mutual_matches (4 MB per 1000 columns)
N_ANGLES = 3  # the pair features binned: the normals' twist, and two cosines


@dataclass(frozen=True)
class GeometricGuessConfig(Config):
    """A pose guess from depth alone: FPFH descriptors on voxel-sampled clouds, mutual matches, rigid consensus."""

    voxel_m: float = setting(0.04, unit="m", ge=0.005, le=1, doc="voxel size of the sampled clouds")
    min_normal_agreement: float = setting(0.7, ge=0, lt=1,
                                          doc="a voxel whose mean unit normal is shorter than this (an edge or a "
                                              "corner) is dropped")
    feature_radius_m: float = setting(0.20, unit="m", gt=0, le=10,
                                      doc="neighbours within this distance enter a point's histogram (time and memory "
                                          "grow with (feature_radius_m / voxel_m)^2)")
    bins: int = setting(11, ge=2, le=64, doc="bins per angle (a 3 * bins descriptor)")
    min_neighbours: int = setting(8, unit="points", ge=1, le=10_000, doc="points with fewer neighbours have no "
                                  "descriptor")
    consensus_abs_tol_m: float = setting(0.04, unit="m", gt=0, le=10,
                                         doc="two matches are consistent when their 3D distances in the two clouds "
                                             "differ by at most abs + rel * distance")
    consensus_rel_tol: float = setting(0.05, unit="fraction", ge=0, le=1, doc="the rel of that rule")
    consensus_seeds: int = setting(10, ge=1, le=10_000, doc="the consistent set is grown from this many "
                                   "best-connected matches")
    inlier_dist_m: float = setting(0.06, unit="m", gt=0, le=10,
                                   doc="after the consensus fit, the matches within this distance are refitted")
    refit_iterations: int = setting(3, ge=0, le=1000, doc="rounds of that refit")
    min_inliers: int = setting(10, unit="matches", ge=3, le=1_000_000, doc="fewer inliers: no guess")

    @check
    def _radius_in_voxels(self) -> str | None:
        """feature_radius_m <= 20 voxel_m (every neighbour pair is held at once)."""
        if self.feature_radius_m > 20 * self.voxel_m:
            return (f"feature_radius_m ({fmt_value(self.feature_radius_m)}) must be <= 20 voxel_m "
                    f"({fmt_value(20 * self.voxel_m)})")
        return None


@dataclass
class GeometricGuess:
    """Outcome of :func:`geometric_guess`.

    Attributes:
        T_target_source: ``(4, 4)`` guess (maps source-camera points into the target camera), ``None`` if rejected.
        reason: why there is no guess (``None`` when there is one).
        n_points: ``(source, target)`` points with a descriptor.
        n_matches: mutual descriptor matches.
        n_inliers: matches within ``inlier_dist_m`` of the final fit.
    """

    T_target_source: np.ndarray | None
    reason: str | None
    n_points: tuple[int, int]
    n_matches: int
    n_inliers: int


def voxel_cloud(vertex: np.ndarray, normal: np.ndarray, voxel_m: float,
                min_normal_agreement: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-voxel mean points and unit normals of a vertex/normal map.

    Args:
        vertex, normal: ``(H, W, 3)`` camera-frame maps (invalid pixels: zero normal).
        voxel_m: voxel size (m).
        min_normal_agreement: voxels whose mean unit normal is shorter are dropped.

    Returns:
        ``(points (M, 3), normals (M, 3))`` float64, ordered by voxel key.
    """
    v = np.asarray(vertex, np.float64).reshape(-1, 3)
    n = np.asarray(normal, np.float64).reshape(-1, 3)
    ok = np.any(n != 0, axis=1) & np.all(np.isfinite(v), axis=1) & np.all(np.isfinite(n), axis=1)
    v, n = v[ok], n[ok]
    if len(v) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    _, inv, count = np.unique(voxel_keys(v.astype(np.float32), voxel_m), return_inverse=True, return_counts=True)
    inv = inv.ravel()
    pts = np.stack([np.bincount(inv, v[:, k]) for k in range(3)], axis=1) / count[:, None]
    nrm = np.stack([np.bincount(inv, n[:, k]) for k in range(3)], axis=1) / count[:, None]
    length = np.linalg.norm(nrm, axis=1)
    keep = length >= max(min_normal_agreement, 1e-9)
    return pts[keep], nrm[keep] / length[keep, None]


def pair_features(p: np.ndarray, n: np.ndarray, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, ...]:
    """The three FPFH angles of point pairs ``(i, j)`` (see :func:`surfelslam.kernels.fpfh.pair_features_ref`)."""
    return kf.pair_features_ref(np.asarray(p, np.float64), np.asarray(n, np.float64), i, j)


def fpfh(points: np.ndarray, normals: np.ndarray, radius_m: float, bins: int,
         min_neighbours: int) -> tuple[np.ndarray, np.ndarray]:
    """Fast Point Feature Histograms.

    Args:
        points, normals: ``(N, 3)`` points and unit normals.
        radius_m: neighbourhood radius (m).
        bins: bins per angle.
        min_neighbours: points with fewer neighbours get no descriptor.

    Returns:
        ``(descriptors (K, 3 * bins) float32, index (K,) int64)``: each block of ``bins`` sums to 1; ``index``
        gives the point of each descriptor.
    """
    n_pts = len(points)
    width = N_ANGLES * bins
    if n_pts < 2:
        return np.zeros((0, width), np.float32), np.zeros(0, np.int64)
    from scipy.spatial import cKDTree  # here: scipy.spatial costs a run's start-up ~0.04 s, used only when lost

    p = np.ascontiguousarray(points, np.float64)
    n = np.ascontiguousarray(normals, np.float64)
    pairs = cKDTree(p).query_pairs(radius_m, output_type="ndarray").reshape(-1, 2).astype(np.int64)
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]  # a fixed order: the float sums below depend on it
    i, j = np.ascontiguousarray(pairs[:, 0]), np.ascontiguousarray(pairs[:, 1])
    spfh = np.zeros((n_pts, width))
    degree = np.zeros(n_pts, np.int64)
    kf.spfh_accumulate(p, n, i, j, bins, spfh, degree)
    spfh /= np.maximum(degree, 1)[:, None]
    acc = np.zeros_like(spfh)
    wsum = np.zeros(n_pts)
    kf.neighbour_sum(p, i, j, spfh, acc, wsum)
    desc = (spfh + acc / np.maximum(wsum, 1e-12)[:, None]).reshape(n_pts, N_ANGLES, bins)
    desc /= np.maximum(desc.sum(axis=2, keepdims=True), 1e-12)
    keep = np.flatnonzero(degree >= min_neighbours)
    return desc.reshape(n_pts, width)[keep].astype(np.float32), keep.astype(np.int64)


def mutual_matches(desc_a: np.ndarray, desc_b: np.ndarray, block_rows: int = MATCH_BLOCK_ROWS) -> np.ndarray:
    """``(K, 2)`` int64 index pairs ``(a, b)`` whose descriptors ``(Na, D)`` / ``(Nb, D)`` are each other's
    nearest neighbour (Euclidean; ties to the lower index). Brute force by matrix products, ``block_rows`` rows of
    ``desc_a`` at a time (a k-d tree is slow in 33 dimensions)."""
    na, nb = len(desc_a), len(desc_b)
    if na == 0 or nb == 0:
        return np.zeros((0, 2), np.int64)
    a = np.asarray(desc_a, np.float32)
    b = np.asarray(desc_b, np.float32)
    b_sq = np.einsum("ij,ij->i", b, b)
    ab = np.empty(na, np.int64)
    col_best = np.full(nb, np.inf, np.float32)
    ba = np.zeros(nb, np.int64)
    for r0 in range(0, na, block_rows):
        blk = a[r0:r0 + block_rows]
        d2 = (b_sq[None, :] - 2.0 * (blk @ b.T)) + np.einsum("ij,ij->i", blk, blk)[:, None]
        ab[r0:r0 + len(blk)] = np.argmin(d2, axis=1)
        rows = np.argmin(d2, axis=0)
        best = d2[rows, np.arange(nb)]
        better = best < col_best  # strict: an earlier block keeps a tie
        col_best[better] = best[better]
        ba[better] = rows[better] + r0
    keep = np.flatnonzero(ba[ab] == np.arange(na))
    return np.stack([keep, ab[keep]], axis=1).astype(np.int64)


def geometric_guess(vertex_src: np.ndarray, normal_src: np.ndarray, vertex_tgt: np.ndarray,
                    normal_tgt: np.ndarray, cfg: GeometricGuessConfig | None = None) -> GeometricGuess:
    """Relative pose of two depth views from their shape alone.

    Args:
        vertex_src, normal_src, vertex_tgt, normal_tgt: ``(H, W, 3)`` camera-frame vertex and normal maps of the
            source and target views (a :class:`~surfelslam.tracking.preprocess.PyramidLevel`'s).
        cfg: settings (defaults when ``None``).

    Returns:
        A :class:`GeometricGuess`; deterministic.
    """
    cfg = GeometricGuessConfig() if cfg is None else cfg
    clouds = [voxel_cloud(v, n, cfg.voxel_m, cfg.min_normal_agreement)
              for v, n in ((vertex_src, normal_src), (vertex_tgt, normal_tgt))]
    feats = [fpfh(p, n, cfg.feature_radius_m, cfg.bins, cfg.min_neighbours) for p, n in clouds]
    n_points = (len(feats[0][1]), len(feats[1][1]))
    m = mutual_matches(feats[0][0], feats[1][0])
    if len(m) < cfg.min_inliers:
        return GeometricGuess(None, "too_few_matches", n_points, len(m), 0)
    P_src = clouds[0][0][feats[0][1][m[:, 0]]]
    P_tgt = clouds[1][0][feats[1][1][m[:, 1]]]
    T, members = rigid_consensus(P_src, P_tgt, cfg.consensus_abs_tol_m, cfg.consensus_rel_tol,
                                 cfg.consensus_seeds, cfg.min_inliers)
    if T is None:
        return GeometricGuess(None, "no_consensus", n_points, len(m), len(members))
    inl = members
    for _ in range(cfg.refit_iterations):
        r = np.linalg.norm(se3.transform_points(T, P_src) - P_tgt, axis=1)
        inl = np.flatnonzero(r < cfg.inlier_dist_m)
        T_new = rigid_fit(P_src[inl], P_tgt[inl]) if len(inl) >= cfg.min_inliers else None
        if T_new is None:
            break
        T = T_new
    r = np.linalg.norm(se3.transform_points(T, P_src) - P_tgt, axis=1)
    n_inl = int(np.count_nonzero(r < cfg.inlier_dist_m))
    if n_inl < cfg.min_inliers:
        return GeometricGuess(None, "too_few_inliers", n_points, len(m), n_inl)
    return GeometricGuess(T, None, n_points, len(m), n_inl)
