"""The JIT warm-up, in one place: what each tracker compiles before its timed loop, the throwaway run, and the
kernel parts that ``python -m surfelslam.warmup`` (``make warmup``) and batches compile ahead of a session.

numba compiles a kernel on its first call (or loads it from its on-disk cache). A tracker's ``warmup()`` is one
line, :func:`warm_up_tracker`, so that the run loop times the compilation apart from the frames (``warmup_s``)
instead of counting it in the first frames' FPS. The policy per tracker:

- ``dense``, ``given``: :func:`warm_up_dense` (preprocessing, rendering, ICP, fusion on two tiny frames);
- ``hybrid``: the dense kernels, the feature side's (:func:`~surfelslam.tracking.features.warmup.warm_up_features`),
  then :func:`warm_up_run` (keyframes, loop checks, edge refinement, the joint ICP term, map compaction);
- ``orb``: the feature side's, the dense kernels when depth is used, then :func:`warm_up_run`;
- a tracker not listed: :func:`warm_up_run` alone (it compiles whatever the tracker's frames reach).

Parts (:data:`PARTS`), compiled by separate processes side by side so that each kernel is compiled once:
``dense``: the dense trackers' kernels at the working resolution and reduced from a larger input, the map's
geometry-only render and compaction. ``shape``: the shape-feature guess of relocalisation (dense and hybrid).
``sparse``: the synthetic renderer and the feature side (ORB matching, PnP and its consensus fallback, the keyframe
cloud's voxel filter, the loop checks' matching and joint-term ICP). ``parallel``: the ``parallel=True`` twins of
the dense kernels. The figures' and mesh's part is the command's (:mod:`surfelslam.warmup`, above ``viz/``).

Tests skip the throwaway run by patching :func:`warm_up_run` here (``tests/conftest.py``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import replace

import numpy as np

from surfelslam.slam.config import SlamConfig
from surfelslam.slam.registry import build_tracker
from surfelslam.tracking.features.warmup import block_texture, warm_up_features
from surfelslam.types import Intrinsics, RGBDFrame

# numba compiles for argument types, not sizes: tiny frames compile what a real run uses
_DENSE_INTR = Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)
_DENSE_FRAMES = 2  # the first frame starts the map, the second is tracked against it and fused
# the throwaway run: wider than the 320 px working width, so that the reduced-input paths run too
_RUN_INTR = Intrinsics(130.0, 130.0, 175.5, 63.5, 352, 128)
_RUN_FRAMES = 18  # five or six keyframes at the default spacing, with nearby loop checks (orb's loop ICP needs them)
#: trackers whose throwaway run can be shorter: the hybrid loads the same numba kernels (signature for signature) by
#: its fourth frame as in all 18; the other frames would cost a run's start about 0.25 s of ORB and PnP work
_RUN_FRAMES_BY_TRACKER = {"hybrid": 4}
_RUN_SHIFT_PX = 3  # the camera moves sideways by this much of the image per frame
_SMALL = (80, 60)  # px: the parts' synthetic frames
_SHAPE_BUMPS = 12  # the shape guess's synthetic surface: enough bumps for distinct FPFH features everywhere
_HALF_WIDTH_PX = 32  # max_width_px that works on the 64 px warm-up frame block-averaged (as 640 px input at 320)


def _no_map_saving(cfg: SlamConfig) -> SlamConfig:
    return replace(cfg, map_reuse=replace(cfg.map_reuse, save=False))


def warm_up_dense(cfg: SlamConfig) -> None:
    """Run two frames of a tilted-plane-and-bump scene through a throwaway ``dense`` tracker with ``cfg``."""
    intr = _DENSE_INTR
    v, u = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float32)
    depth = 1.5 + 0.004 * u + 0.002 * v + 0.1 * np.exp(-((u - 32) ** 2 + (v - 24) ** 2) / 60.0)
    rgb = np.zeros((intr.height, intr.width, 3), np.uint8)
    slam = build_tracker("dense", intr, _no_map_saving(cfg))
    for i in range(_DENSE_FRAMES):
        slam.process(RGBDFrame(i, i / 30.0, rgb, depth.astype(np.float32)))


def _run_frames(n: int = _RUN_FRAMES) -> list[RGBDFrame]:
    """``n`` frames of a textured plane at 1.5 m with a bump (the depth constrains ICP), passing sideways across the
    view."""
    h, w = _RUN_INTR.height, _RUN_INTR.width
    rgb = block_texture(h, w)
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    depth_m = (1.5 - 0.15 * np.exp(-((u - w / 2) ** 2 + (v - h / 2) ** 2) / 300.0)).astype(np.float32)
    return [RGBDFrame(k, k / 30.0, np.roll(rgb, -_RUN_SHIFT_PX * k, axis=1),
                      np.roll(depth_m, -_RUN_SHIFT_PX * k, axis=1)) for k in range(n)]


def warm_up_run(cfg: SlamConfig, tracker: str) -> None:
    """A throwaway run of ``tracker`` with ``cfg`` (map saving off) on :func:`_run_frames`, finished; nothing is
    kept (``tests/slam/test_warmup_run.py`` checks that it changes no result)."""
    slam = build_tracker(tracker, _RUN_INTR, _no_map_saving(cfg))
    for frame in _run_frames(_RUN_FRAMES_BY_TRACKER.get(tracker, _RUN_FRAMES)):
        slam.process(frame)
    slam.finish()
    _graph_gate_extras()  # a short run closes no far loop: the graph gate's search is compiled apart
    _long_run_extras()


def _graph_gate_extras() -> None:
    """The graph gate's path search (:mod:`surfelslam.kernels.graph_search`) on two keyframes and one edge, with
    the argument types :class:`~surfelslam.backend.edge_graph_gate.EdgeGraph` passes."""
    from surfelslam.kernels.graph_search import NO_NODE, shortest_path

    pred = np.empty(2, np.int64)
    shortest_path(np.array([0, 1], np.int64), np.full(2, NO_NODE, np.int64), np.array([[0, 1]], np.int64),
                  np.ones(1), 0, 1, float(np.inf), pred)


def _long_run_extras() -> None:
    """Kernels the full-length warm-up run reaches and the hybrid's short one does not, or only later in a long run
    (each would otherwise stall a first run's frames for seconds): the back end's (:func:`_back_end_extras`) and the
    map's (:func:`_map_extras`)."""
    _back_end_extras()
    _map_extras()


def _back_end_extras() -> None:
    """Retrieval over the place index's word columns and, once the index is large, its hash tables; the rotation
    logarithm of a stack of poses (argument types as their callers pass them; the values are arbitrary)."""
    from surfelslam.backend.place_recognition import DescriptorIndex, RetrievalConfig
    from surfelslam.geometry.se3 import so3_log
    from surfelslam.kernels import hamming

    desc = np.random.default_rng(0).integers(0, 256, (4, 32)).astype(np.uint8)
    words = hamming.as_words(desc)
    hamming.nearest_two_columns_words(words, words.T.copy(), len(words))
    hashed = DescriptorIndex(RetrievalConfig(exact_below_descriptors=0))  # hashed from its first keyframe
    hashed.add(desc)
    hashed.add(desc)
    hashed.query(desc, 1)
    so3_log(np.stack([np.eye(3), np.eye(3)]))


def _dense_tracker(tracker) -> None:
    warm_up_dense(tracker.cfg)


def _hybrid_tracker(tracker) -> None:
    warm_up_dense(tracker.cfg)
    warm_up_features(tracker.sparse.cfg.features)
    warm_up_run(tracker.cfg, tracker.name)


def _orb_tracker(tracker) -> None:
    warm_up_features(tracker.sparse.cfg.features)
    if tracker.sparse.uses_depth or tracker.cfg.orb.loop_icp.enabled:  # OpenCV and gtsam are precompiled
        warm_up_dense(tracker.cfg)
    warm_up_run(tracker.cfg, tracker.name)


#: tracker name -> what its ``warmup()`` compiles (see the module docstring)
TRACKER_WARM_UP: dict[str, Callable[[object], None]] = {
    "dense": _dense_tracker, "given": _dense_tracker, "hybrid": _hybrid_tracker, "orb": _orb_tracker}


def warm_up_tracker(tracker) -> None:
    """Compile (or load from numba's cache) every kernel ``tracker`` (a built tracker: ``name``, ``cfg``, and
    ``sparse`` for the feature trackers) uses, on throwaway synthetic frames; its own state is not touched."""
    policy = TRACKER_WARM_UP.get(tracker.name)
    if policy is None:
        warm_up_run(tracker.cfg, tracker.name)
    else:
        policy(tracker)


# ------------------------------------------------------------------------------ parts, compiled ahead of a session
def _dense_part() -> None:
    from surfelslam.kernels.icp import se3_exp_left_update

    # first: the pose update both parts call (3 s to compile), cached before the sparse part reaches it
    se3_exp_left_update(np.zeros(6), np.eye(4), np.empty((4, 4)))
    cfg = SlamConfig()
    warm_up_dense(cfg)  # tracking and fusion at the input's resolution
    # tracking and fusion at a block-averaged level of the input (640x480 input worked on at 320x240)
    warm_up_dense(replace(cfg, tracking=replace(cfg.tracking, max_width_px=_HALF_WIDTH_PX),
                          fusion=replace(cfg.fusion, max_width_px=_HALF_WIDTH_PX)))
    _map_extras()


def _map_extras() -> None:
    """Map kernels a short dense run does not reach but map reuse, map edges and loop corrections do: the culling
    blocks' grouping, the geometry-only render and the map's compaction on a one-frame map of a ``given`` run; the map
    correction's per-group surfel transform and its block test (argument types as their callers pass them)."""
    from surfelslam.kernels import surfels as ks
    from surfelslam.mapping.render import render

    intr = _DENSE_INTR
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float32)
    depth = (1.5 + 0.004 * u + 0.002 * v).astype(np.float32)
    mapper = build_tracker("given", intr, _no_map_saving(SlamConfig()))
    mapper.process(RGBDFrame(0, 0.0, np.zeros((intr.height, intr.width, 3), np.uint8), depth),
                   T_world_cam=np.eye(4))
    smap = mapper.map
    smap.rebuild_index()  # the culling blocks' grouping (after pose-graph corrections and reorders)
    render(smap, np.eye(4), intr, attributes=False)
    smap.mark_dead(np.arange(min(4, smap.size)))
    smap.compact()
    mapper.finish()
    xyz = np.zeros((2, 3), np.float32)
    rows = np.arange(2, dtype=np.int64)
    ks.transform_rows(xyz, xyz.copy(), rows, np.zeros(2, np.int64), np.eye(3, dtype=np.float32)[None].copy(),
                      np.zeros((1, 3), np.float32))
    ks.rows_off_block(xyz, rows, np.zeros(2, np.int32), np.zeros((1, 3), np.int32), np.float32(4.0))


def _shape_part() -> None:
    """The shape relocalisation's guess (FPFH features, their matching and the rigid consensus), registering a
    surface of random bumps to itself (every match right, so that every stage runs; planes give no distinct
    features)."""
    from surfelslam.tracking.geometric import geometric_guess
    from surfelslam.tracking.preprocess import PreprocessConfig, Preprocessor

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


def _feature_extras(intr: Intrinsics, pyr) -> None:
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


def _sparse_part() -> None:
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
    orb = build_tracker("orb", intr, cfg)
    for f in frames:
        orb.process(f)
    orb.finish()
    pre = Preprocessor(intr, PreprocessConfig(pyramid_levels=1))
    _feature_extras(intr, pre.process(frames[0].depth_m))  # last: the dense part has cached the ICP kernels by now
    _graph_gate_extras()
    _back_end_extras()  # the map's extras are the dense part's


def _parallel_part() -> None:
    """The ``parallel=True`` twins of the dense kernels (``compute.parallel_kernels``; bit-identical results)."""
    from surfelslam.kernels import threads

    threads.set_parallel(True)
    try:
        warm_up_dense(SlamConfig())
    finally:
        threads.set_parallel(False)


#: part name -> the kernels it compiles (see the module docstring)
PARTS: dict[str, Callable[[], None]] = {
    "dense": _dense_part, "shape": _shape_part, "sparse": _sparse_part, "parallel": _parallel_part}
#: tracker -> the parts a session of it uses (a batch warms these before dispatching its jobs)
TRACKER_PARTS: dict[str, tuple[str, ...]] = {
    "dense": ("dense", "shape"), "hybrid": ("dense", "shape", "sparse"), "orb": ("sparse",)}


def parts_for(trackers: Iterable[str]) -> tuple[str, ...]:
    """The parts of :data:`PARTS` the sessions of ``trackers`` use, in :data:`PARTS` order."""
    wanted = {part for name in trackers for part in TRACKER_PARTS.get(name, ())}
    return tuple(p for p in PARTS if p in wanted)
