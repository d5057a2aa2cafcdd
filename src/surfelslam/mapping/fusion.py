"""Point-based fusion of a frame into a :class:`SurfelMap` (Keller et al. 2013, as the reference assignment
defines it).

Per frame, at the frame's pose ``T_world_cam``:

1. association (pass 1): the culled map surfels in front of the camera are projected into the frame and
   bucketed by the pixel their centre falls in (Keller's supersampled index map taken to the limit: every
   surfel lands in exactly one pixel, none is hidden by a z-test). A pixel's bucket holds its candidates;
   only pixels with valid depth in ``[min_depth_m, max_depth_m]`` and a normal take part.
2. filter (pass 2): a candidate must satisfy ``|p - q| < dist_diff_m`` (world frame) and an angle between
   the normals below ``angle_diff_deg``; the most confident passing candidate is chosen (ties: nearest,
   then lowest row).
3. merge: confidence-weighted average of position, normal (renormalised), colour and radius, done only if
   the measurement's radius is at most ``merge_max_radius_ratio`` x the surfel's (a farther view must not
   blur a close one); confidence always grows by the pixel weight, ``last_seen = frame``, ``hits += 1``.
4. add: a valid pixel with no passing candidate becomes a new surfel, unless a neighbouring pixel's cells
   (within ``cover_radius_px``) hold a surfel passing the same tests (the surface is already in the map;
   this limits duplicates when surfels project just across a pixel border). ``cover_radius_px = 0`` is
   Keller's strict rule.
5. removal (``remove_unstable``): (a) the reference assignment's dormant rule: a surfel older than
   ``unstable_max_age_frames`` that was observed in fewer than ``stable_min_hits`` frames is removed
   (each surfel is checked once, when it passes that age: O(new surfels) per frame); (b) Keller's rule
   among the surfels in view: confidence below ``stable_min_confidence`` and not updated for more than
   ``unstable_max_age_frames`` frames. Removed surfels are flagged at once (skipped by rendering and
   fusion) and compacted when they exceed ``compact_dead_fraction`` of the map.
6. duplicates (``remove_duplicates``): in a pixel whose measurement was merged into surfel ``b``, the other
   surfels of the pixel's bucket with normals within ``duplicate_angle_deg`` of ``b``'s and no more confidence
   are flagged dead when within ``duplicate_dist_m`` of ``b``, or in front of ``b`` (towards the camera, along
   its normal) by less than ``dist_diff_m`` with the two discs overlapping along it: a layer the sensor saw
   through (e.g. one a pose-graph correction left a few cm off the wall: it would be what the
   renderer draws). Without this rule revisits keep adding near-copies (noise, small pose errors), the surfels
   in view grow with time and so does the per-frame cost (``benchmarks/bench_pipeline.py`` measures it over
   long hand-held runs).

Weights: ``weight_mode = "keller"``: ``w = exp(-gamma^2 / (2 sigma^2))`` with ``gamma`` the pixel's distance
from the principal point divided by the distance of the farthest image corner, ``sigma =
radial_weight_sigma``; ``"constant"``: ``w = 1`` (the reference assignment's; then confidence == hits).

New radius: ``new_radius_px * z / f / max(|cos(normal, ray)|, radius_min_cos)``, at most ``max_radius_m``,
with ``f = (|fx| + |fy|) / 2``.

Default angle: the reference assignment uses 5 deg, which rejects many correct matches with Kinect-noise normals
(their spread is ~10 deg at 2 m, more with Kinect quantisation); unmerged noisy duplicates then bias the rendered
model towards the camera. The default is 45 deg with ``dist_diff_m`` 5 cm. Set ``angle_diff_deg = 5`` and
``dist_diff_m = 0.03`` for the reference behaviour.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from surfelslam.config import Config, ordered, setting
from surfelslam.geometry import se3
from surfelslam.kernels import fusion as kf
from surfelslam.mapping.surfel_map import SurfelMap
from surfelslam.types import Intrinsics

WEIGHT_MODES = ("keller", "constant")


@dataclass(frozen=True)
class FusionConfig(Config):
    """Fusion of a frame into the surfel map (the module docstring describes the rules)."""

    dist_diff_m: float = setting(0.05, unit="m", gt=0, le=10,
                                 doc="a map surfel merges a measurement only within this distance")
    angle_diff_deg: float = setting(45.0, unit="deg", gt=0, le=180,
                                    doc="... and with normals within this angle (5 deg rejects many correct matches "
                                        "with Kinect-noise normals)")
    weight_mode: str = setting("keller", choices=WEIGHT_MODES,
                               doc="pixel weight: keller (Gaussian in the distance from the principal point) or "
                                   "constant (confidence = hits)")
    radial_weight_sigma: float = setting(0.6, unit="corner distances", gt=0, le=100,
                                         doc="sigma of the keller weight, in units of the centre-to-corner distance")
    cover_radius_px: int = setting(1, unit="px", ge=0, le=20,
                                   doc="a pixel adds no surfel when a neighbour within this radius holds a matching "
                                       "one (0: Keller's strict rule)")
    min_depth_m: float = setting(0.1, unit="m", gt=0, le=100, doc="nearer pixels are not fused", user=True)
    max_depth_m: float = setting(4.0, unit="m", gt=0, le=100, doc="farther pixels are not fused", user=True)
    new_radius_px: float = setting(0.75, unit="pixel footprints", gt=0, le=100,
                                   doc="new surfel radius at its depth (>= 0.71 covers a pixel)")
    radius_min_cos: float = setting(0.3, gt=0, le=1,
                                    doc="clamps the 1/cos growth of the radius on slanted surfaces")
    max_radius_m: float = setting(0.05, unit="m", gt=0, le=10, doc="largest surfel radius")
    merge_max_radius_ratio: float = setting(1.5, ge=1, le=1000,
                                            doc="a measurement merges only if its radius is at most this times the "
                                                "surfel's (a farther view must not blur a close one)")
    remove_unstable: bool = setting(True, doc="remove surfels that stay unconfirmed (the dormant-point and "
                                    "Keller's rules)", user=True)
    unstable_max_age_frames: int = setting(30, unit="frames", ge=0, le=1_000_000,
                                           doc="age after which an unconfirmed surfel is removed")
    stable_min_hits: int = setting(5, unit="frames", ge=0, le=1_000_000,
                                   doc="a surfel seen in fewer frames by that age is removed")
    stable_min_confidence: float = setting(3.0, ge=0, le=1e6,
                                           doc="surfels in view below this confidence, not updated for "
                                               "unstable_max_age_frames, are removed")
    compact_dead_fraction: float = setting(0.05, unit="fraction", ge=0, lt=1,
                                           doc="removed surfels are compacted away once they exceed this share of "
                                               "the map")
    cull_backfaces: bool = setting(True, doc="skip surfels whose normal faces away from the camera")
    remove_duplicates: bool = setting(True, doc="flag near-copies of a surfel that a measurement merged into, and "
                                      "layers in front of it within dist_diff_m (else revisits keep adding them)",
                                      user=True)
    duplicate_dist_m: float = setting(0.02, unit="m", ge=0, le=10, doc="near-copies are within this distance")
    duplicate_angle_deg: float = setting(30.0, unit="deg", gt=0, le=180, doc="... and this normal angle")
    max_width_px: int = setting(320, unit="px", ge=0, le=65536,
                                doc="fuse the finest pyramid level at most this wide; 0 = full resolution", user=True)

    _depth_range = ordered("min_depth_m", "max_depth_m")


@dataclass
class FusionStats:
    """What one :func:`fuse` call did (counts of pixels / surfels)."""

    merged: int  # pixels merged into an existing surfel
    added: int  # new surfels
    removed: int  # surfels flagged for removal this frame (duplicates + dormant + stale)
    covered: int  # valid pixels neither merged nor added (a neighbouring surfel explains them)
    invalid: int  # pixels without a usable measurement (depth 0 / out of range / no normal)
    candidates: int  # surfels that passed block culling
    compacted: int  # surfels physically removed by a compaction this frame
    map_size: int  # live surfels after the frame


_weight_cache: dict[tuple, np.ndarray] = {}


def pixel_weights(intr: Intrinsics, mode: str, sigma: float) -> np.ndarray:
    """``(H, W)`` float32 per-pixel fusion weight (see the module docstring); cached per setting."""
    key = (intr, mode, sigma)
    w = _weight_cache.get(key)
    if w is None:
        if mode == "constant":
            w = np.ones(intr.shape, np.float32)
        else:
            v, u = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float64)
            corner = max(
                math.hypot(cu - intr.cx, cv - intr.cy)
                for cu in (0.0, intr.width - 1.0) for cv in (0.0, intr.height - 1.0)
            )
            gamma2 = ((u - intr.cx) ** 2 + (v - intr.cy) ** 2) / corner**2
            w = np.exp(-gamma2 / (2.0 * sigma**2)).astype(np.float32)
        if len(_weight_cache) > 16:
            _weight_cache.clear()
        _weight_cache[key] = w
    return w


def _check_frame(vertex: np.ndarray, normal: np.ndarray, rgb: np.ndarray, intr: Intrinsics) -> None:
    H, W = intr.shape
    if vertex.shape != (H, W, 3) or normal.shape != (H, W, 3):
        raise ValueError(
            f"fuse: vertex/normal maps must be {(H, W, 3)} (intrinsics), got {vertex.shape} and {normal.shape}"
        )
    if rgb.shape != (H, W, 3) or rgb.dtype != np.uint8:
        raise ValueError(f"fuse: frame_rgb must be uint8 {(H, W, 3)}, got {rgb.dtype} {rgb.shape}")


def fuse(
    smap: SurfelMap,
    frame_vertex_cam: np.ndarray,
    frame_normal_cam: np.ndarray,
    frame_rgb: np.ndarray,
    T_world_cam: np.ndarray,
    intr: Intrinsics,
    frame_index: int,
    cfg: FusionConfig | None = None,
) -> FusionStats:
    """Fuse one frame into ``smap`` in place.

    Args:
        smap: the map (world frame).
        frame_vertex_cam: ``(H, W, 3)`` float32 camera-frame vertices, z = 0 where invalid.
        frame_normal_cam: ``(H, W, 3)`` float32 camera-frame unit normals (facing the camera), 0 where invalid.
        frame_rgb: ``(H, W, 3)`` uint8 RGB.
        T_world_cam: ``(4, 4)`` camera-to-world pose of the frame.
        intr: intrinsics matching the maps.
        frame_index: index of the frame (stored in ``first_seen``/``last_seen``; drives the removal rules).
        cfg: :class:`FusionConfig`.
    """
    cfg = cfg or FusionConfig()
    _check_frame(frame_vertex_cam, frame_normal_cam, frame_rgb, intr)
    vertex = np.ascontiguousarray(frame_vertex_cam, np.float32)
    normal = np.ascontiguousarray(frame_normal_cam, np.float32)
    rgb = np.ascontiguousarray(frame_rgb)
    if not rgb.flags.writeable:  # e.g. a camera's or a bag's buffer: numba would compile a read-only twin mid-run
        rgb = rgb.copy()
    T = np.asarray(T_world_cam, np.float64)
    R = np.ascontiguousarray(T[:3, :3])
    t = np.ascontiguousarray(T[:3, 3])
    frame = int(frame_index)
    weight = pixel_weights(intr, cfg.weight_mode, cfg.radial_weight_sigma)
    cos_angle = math.cos(math.radians(cfg.angle_diff_deg))
    radius_per_depth = cfg.new_radius_px / (0.5 * (abs(intr.fx) + abs(intr.fy)))

    cand = smap.visible_candidates(T, intr, cfg.min_depth_m, cfg.max_depth_m)
    T_cam_world = se3.invert(T)
    H, W = intr.shape
    bstart = smap.scratch("fusion_bucket_start", H * W + 1, np.int32)
    border = smap.scratch("fusion_bucket_order", len(cand), np.int32)
    pix = smap.scratch("fusion_bucket_pixel", len(cand), np.int32)
    arr = smap.raw()
    kf.bucket_by_pixel(
        cand, len(cand), arr["position"], arr["normal"], np.ascontiguousarray(T_cam_world[:3, :3]),
        np.ascontiguousarray(T_cam_world[:3, 3]), float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy),
        H, W, float(cfg.min_depth_m), float(cfg.max_depth_m), bool(cfg.cull_backfaces), pix, bstart, border,
    )
    assoc = np.empty(intr.shape, np.int32)
    kf.associate(
        vertex, normal, bstart, border, arr["position"], arr["normal"], arr["confidence"], R, t,
        float(cfg.dist_diff_m), cos_angle, float(cfg.min_depth_m), float(cfg.max_depth_m),
        int(cfg.cover_radius_px), assoc,
    )
    n_dup = 0
    if cfg.remove_duplicates:
        n_dup = int(kf.flag_duplicates(
            assoc, bstart, border, arr["position"], arr["normal"], arr["radius"], arr["confidence"],
            float(cfg.duplicate_dist_m), math.cos(math.radians(cfg.duplicate_angle_deg)), float(cfg.dist_diff_m),
            arr["dead"],
        ))
        smap.add_dead_count(n_dup)
    kf.merge(
        assoc, vertex, normal, rgb, weight, R, t, frame, float(cfg.merge_max_radius_ratio), radius_per_depth,
        float(cfg.radius_min_cos), float(cfg.max_radius_m), arr["position"], arr["normal"], arr["colour"],
        arr["confidence"], arr["radius"], arr["last_seen"], arr["hits"],
    )
    n_merged = int(np.count_nonzero(assoc >= 0))
    n_new = int(np.count_nonzero(assoc == kf.ASSOC_NEW))
    n_covered = int(np.count_nonzero(assoc == kf.ASSOC_COVERED))
    n_invalid = int(np.count_nonzero(assoc == kf.ASSOC_INVALID))

    s0 = smap.size
    smap.reserve(s0 + n_new)
    arr = smap.raw()
    added = kf.add_new(
        assoc, vertex, normal, rgb, weight, R, t, frame, radius_per_depth, float(cfg.radius_min_cos),
        float(cfg.max_radius_m), s0, arr["position"], arr["normal"], arr["colour"], arr["confidence"],
        arr["radius"], arr["first_seen"], arr["last_seen"], arr["hits"], arr["dead"],
    )
    smap.commit_appended(s0, s0 + added)
    smap.latest_frame = max(smap.latest_frame, frame)

    removed = 0
    if cfg.remove_unstable:
        cursor, k1 = kf.dormant_scan(
            arr["first_seen"], arr["hits"], arr["dead"], smap.dormant_cursor, smap.size, frame,
            int(cfg.unstable_max_age_frames), int(cfg.stable_min_hits),
        )
        smap.dormant_cursor = int(cursor)
        k2 = kf.stale_unstable(
            cand, len(cand), arr["confidence"], arr["last_seen"], arr["dead"], frame,
            int(cfg.unstable_max_age_frames), float(cfg.stable_min_confidence),
        )
        smap.add_dead_count(int(k1) + int(k2))
        removed = int(k1) + int(k2)
    removed += n_dup
    compacted = 0
    if smap.n_dead > 0 and smap.n_dead >= cfg.compact_dead_fraction * smap.size:
        compacted = smap.compact()
    smap.maybe_reorder()  # memory locality of the blocks (rows the dormant rule is done with)
    return FusionStats(
        merged=n_merged, added=int(added), removed=removed, covered=n_covered, invalid=n_invalid,
        candidates=len(cand), compacted=compacted, map_size=smap.n_alive,
    )
