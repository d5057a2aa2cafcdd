"""A map saved for a later run: surfels, keyframes, pose graph, config, format version (``map.npz``).

:class:`SavedMap` is what a surfel tracker hands over at the end of a run (``SlamResult.saved_map``) and what
``--map`` gives the next run. :func:`to_arrays` / :func:`from_arrays` turn it into named arrays and back (every
array checked: shape, dtype, count); the file itself is written and read by :mod:`surfelslam.slam.map_file`. The
format is documented in ``docs/outputs.md`` (Saved map).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

import numpy as np

from surfelslam.errors import ConfigError
from surfelslam.geometry.se3 import invert
from surfelslam.slam.map_keyframes import MapKeyframes
from surfelslam.tracking.features import Features
from surfelslam.types import Intrinsics

#: ``format`` in the manifest: what the file is
MAP_FORMAT = "surfelslam-map"
#: ``version`` in the manifest: this code reads exactly this version
MAP_VERSION = 1
#: the surfel arrays: name -> (dtype, trailing shape)
SURFEL_FIELDS: dict[str, tuple[str, tuple[int, ...]]] = {
    "position": ("float32", (3,)), "normal": ("float32", (3,)), "colour": ("float32", (3,)),
    "confidence": ("float32", ()), "radius": ("float32", ()), "first_seen": ("int32", ()),
    "last_seen": ("int32", ()), "hits": ("int32", ()),
}


class MapFormatProblem(ValueError):
    """What is wrong with a map's arrays (the reader adds the file name: :class:`~surfelslam.errors.MapFileError`)."""


@dataclass
class SavedMap:
    """A map to continue from.

    Attributes:
        surfels: ``{name: (N, ...)}`` the live surfels (:data:`SURFEL_FIELDS`), world frame; ``first_seen`` /
            ``last_seen`` are frame indices of the session that saved it (earlier sessions' are negative).
        keyframes: the keyframes (poses in the same world frame, features, subsampled depth).
        graph_edges: ``(E, 2)`` int64 keyframe pairs ``(i, j)`` of the pose graph.
        graph_T_i_j: ``(E, 4, 4)`` float64 their relative poses (``T_world_i^-1 T_world_j`` of the saved poses).
        intrinsics: the camera of the run that saved it.
        tracker: that run's tracker.
        config_toml: that run's ``config.toml`` (the whole recipe).
        sequence: that run's sequence (as given).
    """

    surfels: dict[str, np.ndarray]
    keyframes: MapKeyframes
    graph_edges: np.ndarray
    graph_T_i_j: np.ndarray
    intrinsics: Intrinsics
    tracker: str
    config_toml: str = ""
    sequence: str = ""

    @property
    def n_surfels(self) -> int:
        return len(self.surfels["position"])


def chain_graph(T_world_kf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The odometry chain of keyframe poses ``(K, 4, 4)``: edges ``(K-1, 2)`` and relative poses ``(K-1, 4, 4)``."""
    k = len(T_world_kf)
    edges = np.stack([np.arange(k - 1), np.arange(1, k)], 1).astype(np.int64) if k > 1 else np.zeros((0, 2), np.int64)
    rel = np.asarray([invert(T_world_kf[i]) @ T_world_kf[j] for i, j in edges], np.float64).reshape(-1, 4, 4)
    return edges, rel


def to_arrays(m: SavedMap) -> dict[str, np.ndarray]:
    """Named arrays of ``m`` (``manifest``: the JSON manifest as uint8 bytes); keyframe features are concatenated,
    ``kf_feature_start`` ``(K + 1,)`` delimiting them, and so are the depth images (``kf_depth_shape``)."""
    kf = m.keyframes
    n_kf = len(kf)
    starts = np.zeros(n_kf + 1, np.int64)
    starts[1:] = np.cumsum([len(f) for f in kf.features])

    def cat(name: str, dtype, width: int) -> np.ndarray:
        parts = [np.asarray(getattr(f, name), dtype).reshape(-1, width) for f in kf.features]
        return np.concatenate(parts) if parts else np.zeros((0, width), dtype)

    shapes = np.asarray([d.shape for d in kf.depth_m], np.int64).reshape(n_kf, 2)
    depth = np.concatenate([d.reshape(-1) for d in kf.depth_m]) if n_kf else np.zeros(0, np.float32)
    manifest = {
        "format": MAP_FORMAT, "version": MAP_VERSION, "tracker": m.tracker, "sequence": m.sequence,
        "intrinsics": [m.intrinsics.fx, m.intrinsics.fy, m.intrinsics.cx, m.intrinsics.cy, m.intrinsics.width,
                       m.intrinsics.height],
        "surfels": m.n_surfels, "keyframes": n_kf, "graph_edges": len(m.graph_edges),
        "keyframe_depth_step": kf.depth_step, "config_toml": m.config_toml,
    }
    out = {"manifest": np.frombuffer(json.dumps(manifest).encode(), np.uint8)}
    for name, (dtype, _) in SURFEL_FIELDS.items():
        out[f"surfel_{name}"] = np.ascontiguousarray(m.surfels[name], dtype)
    out.update(
        kf_T_world_kf=np.asarray(kf.T_world_kf, np.float64).reshape(n_kf, 4, 4),
        kf_frame_index=np.asarray(kf.frame_index, np.int64), kf_timestamp=np.asarray(kf.timestamp, np.float64),
        kf_session=np.asarray(kf.session, np.int32), kf_feature_start=starts,
        kf_keypoints_uv=cat("keypoints_uv", np.float32, 2), kf_descriptors=cat("descriptors", np.uint8, 32),
        kf_points_cam=cat("points_cam", np.float32, 3), kf_valid=cat("valid", bool, 1).reshape(-1),
        kf_response=cat("response", np.float32, 1).reshape(-1), kf_depth_shape=shapes,
        kf_depth_m=np.asarray(depth, np.float32),
        graph_edges=np.asarray(m.graph_edges, np.int64).reshape(-1, 2),
        graph_T_i_j=np.asarray(m.graph_T_i_j, np.float64).reshape(-1, 4, 4),
    )
    return out


def read_manifest(arrays: Any) -> dict:
    """The manifest of a map's arrays (a mapping, e.g. an open ``NpzFile``), checked for format and version.

    Raises:
        MapFormatProblem: no manifest, not a surfelslam map, or another format version.
    """
    if "manifest" not in arrays:
        raise MapFormatProblem("not a surfelslam map (no manifest)")
    raw = np.asarray(arrays["manifest"])
    if raw.dtype != np.uint8:  # casting another dtype warns (complex, NaN) or changes the text
        raise MapFormatProblem(f"unreadable manifest (an array of {raw.dtype}, not of bytes)")
    try:
        manifest = json.loads(bytes(raw).decode())
    except (ValueError, UnicodeDecodeError) as exc:
        raise MapFormatProblem(f"unreadable manifest ({exc})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != MAP_FORMAT:
        raise MapFormatProblem("not a surfelslam map (manifest format is not 'surfelslam-map')")
    if manifest.get("version") != MAP_VERSION:
        raise MapFormatProblem(f"map format version {manifest.get('version')}, this surfelslam reads version "
                               f"{MAP_VERSION} only (remake the map with this version)")
    return manifest


def _get(arrays: Any, name: str, dtype: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """``arrays[name]`` checked for dtype and shape (``None``: any length)."""
    if name not in arrays:
        raise MapFormatProblem(f"array {name} is missing")
    a = np.asarray(arrays[name])
    if a.dtype != np.dtype(dtype) or a.ndim != len(shape) or any(s is not None and s != d
                                                                for s, d in zip(shape, a.shape, strict=True)):
        want = "x".join("N" if s is None else str(s) for s in shape)
        raise MapFormatProblem(f"array {name} is {a.dtype} {a.shape}, expected {dtype} ({want})")
    return a


def from_arrays(arrays: Any) -> SavedMap:
    """The :class:`SavedMap` of :func:`to_arrays`'s output (or an open ``NpzFile`` of it), every array checked.

    Raises:
        MapFormatProblem: another format or version, a missing array, a wrong dtype, shape or count.
    """
    man = read_manifest(arrays)
    try:
        n, k, e = int(man["surfels"]), int(man["keyframes"]), int(man["graph_edges"])
        fx, fy, cx, cy, w, h = man["intrinsics"]
        fx, fy, cx, cy, w, h = float(fx), float(fy), float(cx), float(cy), int(w), int(h)
        step = int(man["keyframe_depth_step"])
    except (KeyError, TypeError, ValueError, OverflowError, ConfigError) as exc:  # Overflow: Infinity counts
        raise MapFormatProblem(f"incomplete manifest ({exc})") from None
    if not (np.all(np.isfinite([fx, fy, cx, cy])) and fx > 0 and fy > 0 and w > 0 and h > 0 and step > 0):
        raise MapFormatProblem(f"manifest intrinsics {[fx, fy, cx, cy, w, h]} or keyframe_depth_step {step} are not "
                               "a camera (finite, positive focal lengths and size)")
    intr = Intrinsics(fx, fy, cx, cy, w, h)
    surfels = {name: _get(arrays, f"surfel_{name}", dtype, (n, *trail))
               for name, (dtype, trail) in SURFEL_FIELDS.items()}
    starts = _get(arrays, "kf_feature_start", "int64", (k + 1,))
    n_feat = int(starts[-1])
    if starts[0] != 0 or np.any(np.diff(starts) < 0):
        raise MapFormatProblem("array kf_feature_start is not increasing from 0")
    uv = _get(arrays, "kf_keypoints_uv", "float32", (n_feat, 2))
    desc = _get(arrays, "kf_descriptors", "uint8", (n_feat, 32))
    pts = _get(arrays, "kf_points_cam", "float32", (n_feat, 3))
    valid = _get(arrays, "kf_valid", "bool", (n_feat,))
    resp = _get(arrays, "kf_response", "float32", (n_feat,))
    shapes = _get(arrays, "kf_depth_shape", "int64", (k, 2))
    depth = _get(arrays, "kf_depth_m", "float32", (int(np.prod(shapes, axis=1).sum()) if k else 0,))
    if np.any(shapes < 0):
        raise MapFormatProblem("array kf_depth_shape has negative sizes")
    feats, depths, d0 = [], [], 0
    for i in range(k):
        s = slice(int(starts[i]), int(starts[i + 1]))
        feats.append(Features(uv[s], desc[s], pts[s], valid[s], resp[s]))
        size = int(shapes[i, 0] * shapes[i, 1])
        depths.append(depth[d0 : d0 + size].reshape(int(shapes[i, 0]), int(shapes[i, 1])))
        d0 += size
    kfs = MapKeyframes(_get(arrays, "kf_T_world_kf", "float64", (k, 4, 4)),
                       _get(arrays, "kf_frame_index", "int64", (k,)), _get(arrays, "kf_timestamp", "float64", (k,)),
                       _get(arrays, "kf_session", "int32", (k,)), feats, depths, step)
    edges = _get(arrays, "graph_edges", "int64", (e, 2))
    if e and (edges.min() < 0 or edges.max() >= k):
        raise MapFormatProblem("array graph_edges names keyframes that are not in the map")
    return SavedMap(surfels, kfs, edges, _get(arrays, "graph_T_i_j", "float64", (e, 4, 4)), intr,
                    str(man.get("tracker", "")), str(man.get("config_toml", "")), str(man.get("sequence", "")))


#: Largest surfel coordinate (m) of a loaded map: an indoor RGB-D map spans tens of metres; beyond this a coordinate
#: is a corrupt value, not a place.
MAX_MAP_COORDINATE_M = 1.0e4
#: Largest deviation of a surfel normal's length from 1 (they are saved normalised, in float32).
MAX_NORMAL_LENGTH_ERROR = 1.0e-3
#: Largest deviation from a rotation (max |R R^T - I|) of a saved keyframe or graph pose: the trajectory files'
#: tolerance (poses may pass through float32 on the way); a corrupt pose is far beyond it.
MAX_POSE_ROTATION_ERROR = 1.0e-3
#: Colours are 8-bit values, as floats.
COLOUR_RANGE = (0.0, 255.0)


def check_map_values(m: SavedMap) -> None:
    """Check every value of a map read back, beyond its structure (:func:`from_arrays` checked shapes and dtypes):
    finite surfels within :data:`MAX_MAP_COORDINATE_M`, unit normals, colours in :data:`COLOUR_RANGE`, positive radii,
    non-negative confidences and hits, rigid finite keyframe and graph poses, finite stamps, finite non-negative
    keyframe depth, finite keypoints (and camera points where valid).

    Raises:
        MapFormatProblem: naming the array and the first bad entry.
    """
    s = m.surfels
    _require(s["position"], "surfel_position",
             lambda a: np.isfinite(a).all(1) & (np.abs(a) <= MAX_MAP_COORDINATE_M).all(1),
             f"finite, within {MAX_MAP_COORDINATE_M:g} m")
    _require(s["normal"], "surfel_normal", lambda a: np.abs(np.linalg.norm(a, axis=1) - 1) <= MAX_NORMAL_LENGTH_ERROR,
             "a unit vector")
    _require(s["colour"], "surfel_colour", lambda a: ((a >= COLOUR_RANGE[0]) & (a <= COLOUR_RANGE[1])).all(1),
             f"in {COLOUR_RANGE[0]:g}-{COLOUR_RANGE[1]:g}")
    _require(s["radius"], "surfel_radius", lambda a: np.isfinite(a) & (a > 0), "finite and positive")
    _require(s["confidence"], "surfel_confidence", lambda a: np.isfinite(a) & (a >= 0), "finite, not negative")
    _require(s["hits"], "surfel_hits", lambda a: a >= 0, "not negative")
    kf = m.keyframes
    _require(np.asarray(kf.T_world_kf), "kf_T_world_kf", _rigid, "a finite rigid transform")
    _require(np.asarray(m.graph_T_i_j), "graph_T_i_j", _rigid, "a finite rigid transform")
    _require(np.asarray(kf.timestamp), "kf_timestamp", np.isfinite, "finite")
    for i, (f, d) in enumerate(zip(kf.features, kf.depth_m, strict=True)):
        _require(d.reshape(-1), f"kf_depth_m (keyframe {i})", lambda a: np.isfinite(a) & (a >= 0), "finite, >= 0")
        _require(np.asarray(f.keypoints_uv), f"kf_keypoints_uv (keyframe {i})", lambda a: np.isfinite(a).all(1),
                 "finite")
        pts, ok = np.asarray(f.points_cam), np.asarray(f.valid, bool)
        _require(pts, f"kf_points_cam (keyframe {i})", lambda a, ok=ok: ~ok | np.isfinite(a).all(1),
                 "finite where kf_valid")


def _rigid(T: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: which of ``(N, 4, 4)`` poses are finite rigid transforms."""
    if not len(T):
        return np.ones(0, bool)
    finite = np.isfinite(T).all((1, 2))
    Tf = np.where(finite[:, None, None], T, np.eye(4))
    R = Tf[:, :3, :3]
    ortho = np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max((1, 2)) <= MAX_POSE_ROTATION_ERROR
    bottom = np.all(Tf[:, 3] == (0.0, 0.0, 0.0, 1.0), axis=1)
    return finite & ortho & bottom & (np.abs(Tf[:, :3, 3]) <= MAX_MAP_COORDINATE_M).all(1)


def _require(a: np.ndarray, name: str, ok, what: str) -> None:
    """MapFormatProblem naming ``name`` and its first entry where ``ok(a)`` (one bool per entry) is False."""
    with np.errstate(invalid="ignore", over="ignore"):
        good = np.asarray(ok(a), bool)
    if not good.all():
        bad = int(np.argmin(good))
        raise MapFormatProblem(f"array {name}: entry {bad} is {np.asarray(a[bad]).tolist()}, not {what} "
                               f"({int((~good).sum())} of {len(good)} bad)")


def check_map_options(tracker: str, prior_map: object | None, localize_only: bool, poses: str | None) -> None:
    """Refuse ``--map`` / ``--localize-only`` where they cannot apply (one line, :class:`ConfigError`); ``prior_map``:
    the map or its path, ``None`` without ``--map``."""
    if localize_only and prior_map is None:
        raise ConfigError("--localize-only needs a map to localise in (--map RUN_DIR)")
    if prior_map is None:
        return
    if poses is not None:
        raise ConfigError("--map cannot be combined with --poses (mapping with given poses has nothing to localise)")
    if tracker == "orb":
        raise ConfigError("--map is not supported with --tracker orb (its map is a keyframe cloud, not surfels); "
                          "use --tracker dense or hybrid")
