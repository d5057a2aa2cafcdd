"""Compile (or load from numba's on-disk cache) the JIT kernels ahead of a session, in parts.

numba compiles a kernel on its first call and caches it beside the source. A fresh checkout has no cache, and
processes that start together (test workers, batch jobs) would each compile the same kernels. Warming up first, one
process per part running at the same time, compiles each kernel once::

    python -m surfelslam.warmup dense & python -m surfelslam.warmup outputs & python -m surfelslam.warmup sparse shape
    wait

``dense``: the dense trackers' kernels (preprocessing, rendering, ICP with the photometric term, fusion), at the
working resolution and reduced from a larger input, the map's geometry-only render and compaction. ``shape``: the
shape-feature guess of relocalisation (dense and hybrid trackers), a part of its own so that it can go into any
process (``make warmup`` runs it after ``sparse``). ``sparse``: the synthetic renderer and the feature side (ORB
matching, PnP and its consensus fallback, the keyframe cloud's voxel filter, the loop checks' brute-force matching
and joint-term ICP).
``outputs``: the map figures' splat renderer and the mesh's TSDF and marching cubes. ``parallel``: the
``parallel=True`` twins of the dense kernels.
"""

from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np

_SMALL = (80, 60)  # px: numba compiles for types, not sizes, so tiny frames compile what a real run uses
_SHAPE_BUMPS = 12  # the shape guess's synthetic surface: enough bumps for distinct FPFH features everywhere


def _dense() -> None:
    from surfelslam.kernels.icp import se3_exp_left_update
    from surfelslam.slam import SlamConfig, build_slam
    from surfelslam.slam.dense import warm_up
    from surfelslam.types import Intrinsics, RGBDFrame

    # first: the pose update both parts call (3 s to compile), cached before the sparse part reaches it
    se3_exp_left_update(np.zeros(6), np.eye(4), np.empty((4, 4)))
    cfg = SlamConfig()
    warm_up(cfg)  # tracking and fusion at the input's resolution
    # tracking and fusion at a block-averaged level of the input (640x480 input worked on at 320x240)
    half = replace(cfg, tracking=replace(cfg.tracking, max_width_px=32), fusion=replace(cfg.fusion, max_width_px=32))
    warm_up(half)
    intr = Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)
    v, u = np.mgrid[0:48, 0:64].astype(np.float32)
    depth = (1.5 + 0.004 * u + 0.002 * v).astype(np.float32)
    mapper = build_slam(intr, cfg, "given")
    mapper.process(RGBDFrame(0, 0.0, np.zeros((48, 64, 3), np.uint8), depth), T_world_cam=np.eye(4))
    mapper.map.rebuild_index()  # the culling blocks' grouping (after pose-graph corrections and reorders)
    _map_extras(intr, mapper.map)
    mapper.finish()  # compaction of the map


def _map_extras(intr, smap) -> None:
    """Map kernels a short dense run does not reach but map reuse and loop corrections do: the geometry-only render
    and the map's compaction."""
    from surfelslam.mapping.render import render

    render(smap, np.eye(4), intr, attributes=False)
    smap.mark_dead(np.arange(min(4, smap.size)))
    smap.compact()


def _shape() -> None:
    """The shape relocalisation's guess (FPFH features, their matching and the rigid consensus), registering a
    surface of random bumps to itself (every match right, so that every stage runs; planes give no distinct
    features)."""
    from surfelslam.tracking.geometric import geometric_guess
    from surfelslam.tracking.preprocess import PreprocessConfig, Preprocessor
    from surfelslam.types import Intrinsics

    intr = Intrinsics(60.0, 60.0, 31.5, 23.5, *_SMALL)
    rng = np.random.default_rng(0)
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float32)
    depth = np.full(u.shape, 1.5, np.float32)
    for _ in range(_SHAPE_BUMPS):  # Gaussian bumps 5-20 cm high, a few pixels wide
        u0, v0 = rng.uniform(0, intr.width), rng.uniform(0, intr.height)
        height_m, spread_px2 = rng.uniform(0.05, 0.2), rng.uniform(20.0, 80.0)
        depth -= (height_m * np.exp(-((u - u0) ** 2 + (v - v0) ** 2) / spread_px2)).astype(np.float32)
    a = Preprocessor(intr, PreprocessConfig(pyramid_levels=1)).process(depth)
    geometric_guess(a[0].vertex, a[0].normal, a[0].vertex, a[0].normal)


def _feature_extras(intr, pyr) -> None:
    """Kernels a short orb run does not reach but loop checks and relocalisation do: brute-force and gridded
    Hamming matching, ICP with the joint feature term and the plain Cholesky step (its other kernels are the dense
    part's, cached by then) on the one-level pyramid ``pyr``. The inputs are arbitrary: numba compiles for argument
    types, not values."""
    from surfelslam.kernels import hamming
    from surfelslam.tracking.icp import ICPConfig, ReprojectionTerm, icp

    words = hamming.as_words(np.random.default_rng(0).integers(0, 256, (16, 32)).astype(np.uint8))
    uv = np.column_stack([np.arange(16.0) * 3.0, np.arange(16.0) * 2.0])
    hamming.nearest_two_words(words, words[::-1].copy())
    hamming.nearest_mutual_within_words(words, uv, words, uv, 8.0, intr.width, intr.height)
    z = np.full(len(uv), 1.5)
    pts = np.column_stack([(uv[:, 0] - intr.cx) / intr.fx * z, (uv[:, 1] - intr.cy) / intr.fy * z, z])
    term = ReprojectionTerm(pts, uv, intr, 1.0, 2.0, 1e-6)
    icp(pyr, pyr, cfg=ICPConfig(levels=1, iterations=(3,), weak_direction_ratio=0.0), reprojection=term)


def _parallel() -> None:
    """The ``parallel=True`` twins of the dense kernels (``compute.parallel_kernels``; bit-identical results)."""
    from surfelslam.kernels import threads
    from surfelslam.slam import SlamConfig
    from surfelslam.slam.dense import warm_up

    threads.set_parallel(True)
    try:
        warm_up(SlamConfig())
    finally:
        threads.set_parallel(False)


def _outputs() -> None:
    """The figures' splat renderer and the mesh's TSDF and marching cubes."""
    from surfelslam.mapping.mesh import TsdfVolume
    from surfelslam.types import Intrinsics
    from surfelslam.viz.map_figures import ViewCamera, render

    intr = Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)
    v, u = np.mgrid[0:48, 0:64].astype(np.float32)
    depth = (1.0 + 0.004 * u + 0.002 * v).astype(np.float32)
    vol = TsdfVolume(0.02, 0.08, initial_blocks=1)  # room for one block: the volume grows, so rehash compiles too
    vol.integrate(depth, np.zeros((48, 64, 3), np.uint8), intr, np.eye(4))
    mesh = vol.extract_mesh()
    cam = ViewCamera(np.eye(3), np.zeros(3), 64, 48, 31.5, 23.5, f_px=60.0)
    render(cam, mesh.vertices, mesh.normals, np.full(len(mesh.vertices), 0.01, np.float32))


def _sparse() -> None:
    from surfelslam.slam import SlamConfig, build_slam
    from surfelslam.synth.scenes import make_scene
    from surfelslam.synth.trajectories import make_trajectory
    from surfelslam.synth.writer import default_intrinsics, iter_frames, noise_config
    from surfelslam.tracking.preprocess import PreprocessConfig, Preprocessor

    intr = default_intrinsics(*_SMALL)
    scene = make_scene("room")
    frames = list(iter_frames(scene, make_trajectory("slow", 6, scene), intr, noise_config("kinect")))
    cfg = SlamConfig()
    cfg = replace(cfg, orb=replace(cfg.orb, depth_odometry=replace(cfg.orb.depth_odometry, enabled=False),
                                   loop_icp=replace(cfg.orb.loop_icp, enabled=False)))
    orb = build_slam(intr, cfg, "orb")
    for f in frames:
        orb.process(f)
    orb.finish()
    pre = Preprocessor(intr, PreprocessConfig(pyramid_levels=1))
    _feature_extras(intr, pre.process(frames[0].depth_m))  # last: the dense part has cached the ICP kernels by now


PARTS = {"dense": _dense, "shape": _shape, "sparse": _sparse, "outputs": _outputs, "parallel": _parallel}


def warm(*parts: str) -> None:
    """Compile the kernels of ``parts`` (default: every part, one after the other)."""
    for name in parts or tuple(PARTS):
        PARTS[name]()


if __name__ == "__main__":
    unknown = [p for p in sys.argv[1:] if p not in PARTS]
    if unknown:
        raise SystemExit(f"error: unknown warm-up part(s) {', '.join(unknown)}; known: {', '.join(PARTS)}")
    warm(*sys.argv[1:])
