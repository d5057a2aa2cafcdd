"""Mesh quality against the exact surfaces of a synthetic scene (``surfelslam synth``).

* **accuracy**: the distance from the mesh to the true surface (:meth:`Scene.distance_to_surface`), over points
  sampled uniformly on the mesh's area (:func:`sample_surface`): mean, median and 90th percentile.
* **completeness**: the share of the true *visible* surface within ``threshold_m`` (1 cm) of the mesh. The truth
  is sampled as the exact depth of the frames (rendered without noise at the ground-truth poses), back-projected
  and thinned to one point per ``spacing_m`` cube (so that a surface seen in many frames does not count more),
  :func:`visible_surface_points`; the distance of each to the mesh is exact (point to triangle, over the
  ``k`` triangles with the nearest centroids, :func:`distance_to_mesh`).

The mesh must be in the scene's frame: the ground truth of a synthetic sequence is (``groundtruth.txt`` holds
``T_world_cam`` in the scene's frame), a run's estimate starts at the identity and is moved onto the first
ground-truth pose (:func:`first_pose_alignment`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from surfelslam.errors import InputError
from surfelslam.types import Intrinsics

DEFAULT_THRESHOLD_M = 0.01


def first_pose_alignment(T_est_first: np.ndarray, T_gt_first: np.ndarray) -> np.ndarray:
    """``(4, 4)`` transform taking the estimate's frame onto the ground truth's: the first poses coincide."""
    return np.asarray(T_gt_first, np.float64) @ np.linalg.inv(np.asarray(T_est_first, np.float64))


def scene_of_sequence(root: str | Path):
    """The :class:`~surfelslam.synth.scenes.Scene` a ``surfelslam synth`` sequence was rendered from (its INFO.txt:
    scene, seed, texture)."""
    from surfelslam.datasets.metadata import read_metadata
    from surfelslam.synth.scenes import make_scene
    from surfelslam.synth.textures import TextureConfig

    meta = read_metadata(Path(root))
    if not meta.is_synthetic or "scene" not in meta.fields:
        raise InputError(root, "not a `surfelslam synth` sequence (its INFO.txt names no generated scene)")
    f = meta.fields
    return make_scene(f["scene"], int(f.get("seed", "0")), TextureConfig(style=f.get("texture", "rich")))


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """``(n, 3)`` points uniformly distributed over the mesh's area (seeded)."""
    v = np.asarray(vertices, np.float64)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    if len(faces) == 0 or area.sum() <= 0:
        return np.zeros((0, 3))
    rng = np.random.default_rng(seed)
    tri = rng.choice(len(faces), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    return ((1 - s)[:, None] * a[tri] + (s * (1 - r2))[:, None] * b[tri] + (s * r2)[:, None] * c[tri])


def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``(N, 3)`` closest point of triangle ``(a, b, c)`` to ``p`` (row by row; Ericson, Real-Time Collision
    Detection 5.1.5, its regions checked in the reverse order so that the first matching one wins)."""
    ab, ac, ap = b - a, c - a, p - a
    bp, cp = p - b, p - c
    d1, d2 = (ab * ap).sum(1), (ac * ap).sum(1)
    d3, d4 = (ab * bp).sum(1), (ac * bp).sum(1)
    d5, d6 = (ab * cp).sum(1), (ac * cp).sum(1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        out = a + ab * (vb / denom)[:, None] + ac * (vc / denom)[:, None]
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        m = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
        out = np.where(m[:, None], b + w[:, None] * (c - b), out)
        w = d2 / (d2 - d6)
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        out = np.where(m[:, None], a + w[:, None] * ac, out)
        out = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, out)
        v = d1 / (d1 - d3)
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        out = np.where(m[:, None], a + v[:, None] * ab, out)
        out = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, out)
        out = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, out)
    return out


def distance_to_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, k: int = 16,
                     chunk: int = 100_000) -> np.ndarray:
    """``(N,)`` distance (m) from each point to the nearest of the ``k`` triangles whose centroids are nearest
    (exact for meshes of small, even triangles such as marching cubes'; ``inf`` for an empty mesh)."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if len(faces) == 0:
        return np.full(len(pts), np.inf)
    v = np.asarray(vertices, np.float64)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    tree = cKDTree((a + b + c) / 3.0)
    k = min(k, len(faces))
    out = np.empty(len(pts))
    for s in range(0, len(pts), chunk):
        p = pts[s : s + chunk]
        _, idx = tree.query(p, k=k)
        idx = idx.reshape(len(p), k)
        rep = np.repeat(p, k, axis=0)
        t = idx.ravel()
        q = _closest_on_triangles(rep, a[t], b[t], c[t])
        d = np.linalg.norm(q - rep, axis=1)
        # degenerate triangles (zero area): the nearest of their corners
        bad = ~np.isfinite(d)
        if bad.any():
            d[bad] = np.min(np.stack([np.linalg.norm(rep[bad] - x[t[bad]], axis=1) for x in (a, b, c)]), axis=0)
        out[s : s + chunk] = d.reshape(len(p), k).min(axis=1)
    return out


def visible_surface_points(scene, poses: np.ndarray, intr: Intrinsics, min_depth_m: float = 0.1,
                           max_depth_m: float = 4.0, pixel_step: int = 2, spacing_m: float = 0.005) -> np.ndarray:
    """``(M, 3)`` points on the scene's surfaces seen from ``poses`` (``T_world_cam``, the scene's frame): exact
    depth rendered at every pose, every ``pixel_step``-th pixel within the depth range back-projected, one point
    kept per ``spacing_m`` cube."""
    from surfelslam.synth.render import render

    v, u = np.mgrid[0 : intr.height : pixel_step, 0 : intr.width : pixel_step]
    rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(u.shape)], -1).reshape(-1, 3)
    keys_all, pts_all = [], []
    buf = None
    for T in poses:
        buf = render(scene, T, intr, out=buf)
        z = buf.depth_m[::pixel_step, ::pixel_step].reshape(-1).astype(np.float64)
        ok = (z >= min_depth_m) & (z <= max_depth_m)
        p = (rays[ok] * z[ok, None]) @ T[:3, :3].T + T[:3, 3]
        key = np.floor(p / spacing_m).astype(np.int64)
        keys_all.append(key)
        pts_all.append(p)
    if not pts_all:
        return np.zeros((0, 3))
    keys = np.concatenate(keys_all)
    pts = np.concatenate(pts_all)
    _, first = np.unique(keys, axis=0, return_index=True)
    return pts[np.sort(first)]


def mesh_quality(vertices: np.ndarray, faces: np.ndarray, scene, truth_points: np.ndarray,
                 threshold_m: float = DEFAULT_THRESHOLD_M, samples: int = 200_000, seed: int = 0) -> dict:
    """Accuracy (mesh to true surface: ``accuracy_mean_m``, ``accuracy_median_m``, ``accuracy_p90_m``) and
    completeness (``completeness``: share of ``truth_points`` within ``threshold_m`` of the mesh), with the
    counts behind them."""
    pts = sample_surface(vertices, faces, samples, seed)
    acc = scene.distance_to_surface(pts) if len(pts) else np.full(1, np.nan)
    d = distance_to_mesh(truth_points, vertices, faces)
    return {
        "vertices": int(len(vertices)),
        "faces": int(len(faces)),
        "accuracy_mean_m": float(np.mean(acc)),
        "accuracy_median_m": float(np.median(acc)),
        "accuracy_p90_m": float(np.percentile(acc, 90)),
        "completeness": float(np.mean(d <= threshold_m)) if len(d) else 0.0,
        "completeness_threshold_m": float(threshold_m),
        "truth_points": int(len(truth_points)),
        "mesh_samples": int(len(pts)),
    }
