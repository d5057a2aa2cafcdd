"""Triangle meshes of a run: a TSDF of the depth frames at the run's poses, then marching cubes; or Poisson.

:class:`TsdfVolume` is a sparse TSDF (blocks of 8^3 voxels allocated where depth is seen, found through a hash),
kernels in :mod:`surfelslam.kernels.tsdf`: :meth:`TsdfVolume.integrate` fuses one depth image (projective
distance; each depth weighted by the inverse variance of a Kinect-like noise model, its truncation widened with
that noise, so every valid depth can be fused without the far, noisy ones blurring what near ones saw; colour
averaged near the surface), and :meth:`TsdfVolume.extract_mesh` runs marching cubes over the observed voxels (a
welded mesh with vertex normals from the TSDF gradient and vertex colours), then removes what mesh tools refuse
(:func:`surfelslam.mapping.mesh_topology.clean_faces`: non-manifold vertices, degenerate triangles, floating pieces
of fewer than ``min_component`` triangles). Memory grows with the observed surface, not with the room's volume:
about ``BYTES_PER_VOXEL`` x 512 bytes per block; ``max_memory_mb`` stops a run that would exceed it with one line.

:func:`poisson_mesh` reconstructs from the surfels of ``map.ply`` with Open3D's screened Poisson (the optional
``bench`` extra, ``open3d-cpu``).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from surfelslam.config import Config, ordered, setting
from surfelslam.errors import ConfigError
from surfelslam.kernels import tsdf as kt
from surfelslam.mapping.mesh_topology import clean_faces
from surfelslam.types import Intrinsics

METHODS = ("tsdf", "poisson")
#: bytes per voxel: tsdf float32, weight float32, frame count uint16, colour 3 x uint16, colour weight uint16
BYTES_PER_VOXEL = 4 + 4 + 2 + 6 + 2
#: the extraction's bytes per vertex (position and normal 3 x float32, colour 3 x uint8, key in its block int16) and
#: per triangle (3 x int32), held beside the TSDF while a mesh is extracted
EXTRACT_BYTES_PER_VERTEX = 12 + 12 + 3 + 2
EXTRACT_BYTES_PER_FACE = 12
#: blocks allocated up front (the arrays double when full)
INITIAL_BLOCKS = 4096
#: the far end (m) of a Kinect-class sensor's valid range: `surfelslam mesh` fuses every depth up to it (the noise
#: weighting, not a range cut, keeps far depth from degrading the near surface); farther readings (TUM's Kinect
#: reports up to ~10 m) have a noise sigma over 4 cm and would multiply the TSDF's size for little surface
SENSOR_MAX_DEPTH_M = 5.0
#: axial depth noise of a Kinect-like sensor, sigma(z) = base + quad (z - offset)^2 (m; Nguyen, Izadi and Lovell,
#: 3DIMPVT 2012, the model `surfelslam synth --noise kinect` renders with)
DEPTH_SIGMA_BASE_M, DEPTH_SIGMA_QUAD_PER_M, DEPTH_SIGMA_OFFSET_M = 0.0012, 0.0019, 0.4
#: a depth measured here (m) has weight 1 (nearer ones more, farther ones less: 1 / sigma^2)
REFERENCE_DEPTH_M = 1.0
#: the truncation widens to this many noise sigmas where that exceeds trunc_m (a narrower band clips the noise,
#: biasing the average) ...
TRUNC_SIGMAS = 3.0
#: ... up to this many times trunc_m (3 sigma at 5 m; a wider band thickens thin objects and allocates more blocks)
TRUNC_MAX_FACTOR = 3.0
#: floating pieces of fewer triangles are removed by default (about 50 cm^2 at a 1 cm voxel: noise, not objects)
DEFAULT_MIN_COMPONENT = 100


@dataclass(frozen=True)
class MeshConfig(Config):
    """Mesh extraction: the TSDF's resolution and range (``surfelslam mesh``)."""

    method: str = setting("tsdf", choices=METHODS,
                          doc="tsdf: fuse the depth frames at the run's poses, then marching cubes; poisson: "
                              "screened Poisson on the surfels of map.ply (needs open3d)")
    voxel_m: float = setting(0.01, unit="m", ge=0.001, le=1.0, doc="TSDF voxel edge (the mesh's resolution)")
    trunc_m: float = setting(0.0, unit="m", ge=0, le=10,
                             doc="truncation distance of the TSDF; 0: 4 voxels")
    min_depth_m: float = setting(0.1, unit="m", gt=0, le=100, doc="nearer depths are not fused")
    max_depth_m: float = setting(SENSOR_MAX_DEPTH_M, unit="m", gt=0, le=100,
                                 doc="farther depths are not fused (default: a Kinect-class sensor's whole range; "
                                     "each depth is weighted by its noise, which grows with depth squared)")
    stride: int = setting(1, unit="frames", ge=1, le=100_000, doc="fuse every stride-th frame of the run")
    min_weight: float = setting(1.0, unit="frames", gt=0, le=1e6,
                                doc="marching cubes uses voxels observed in at least this many frames")
    max_weight: float = setting(1e4, unit="frames", ge=1, le=1e9,
                                doc="a voxel's weight (frames at 1 m; nearer count more, farther less) saturates "
                                    "here (newer frames then count more)")
    min_component: int = setting(DEFAULT_MIN_COMPONENT, unit="triangles", ge=0, le=10**9,
                                 doc="floating pieces of the mesh with fewer triangles are removed; 0: keep all")
    max_memory_mb: float = setting(4096.0, unit="MiB", gt=0, le=1e7,
                                   doc="the TSDF may not grow past this; a larger one stops with an error")
    poisson_depth: int = setting(9, ge=4, le=14, doc="octree depth of Poisson reconstruction")
    poisson_density_quantile: float = setting(0.02, unit="fraction", ge=0, lt=1,
                                              doc="Poisson vertices in this share of lowest support are removed")

    _depth_range = ordered("min_depth_m", "max_depth_m")

    @property
    def truncation_m(self) -> float:
        """``trunc_m``, or 4 voxels when it is 0."""
        return self.trunc_m if self.trunc_m > 0 else 4.0 * self.voxel_m


@dataclass
class Mesh:
    """A triangle mesh: ``vertices`` ``(V, 3)`` float32 m, ``normals`` ``(V, 3)`` float32 (unit or 0), ``colours``
    ``(V, 3)`` uint8, ``faces`` ``(F, 3)`` int32 (counter-clockwise seen from the side the normals point to)."""

    vertices: np.ndarray
    normals: np.ndarray
    colours: np.ndarray
    faces: np.ndarray

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    def transformed(self, T: np.ndarray) -> Mesh:
        """The mesh moved by the rigid transform ``T`` ``(4, 4)``."""
        R, t = T[:3, :3], T[:3, 3]
        return Mesh((self.vertices @ R.T + t).astype(np.float32), (self.normals @ R.T).astype(np.float32),
                    self.colours, self.faces)

    def face_areas(self) -> np.ndarray:
        v = self.vertices.astype(np.float64)
        a, b, c = v[self.faces[:, 0]], v[self.faces[:, 1]], v[self.faces[:, 2]]
        return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


class TsdfVolume:
    """A sparse TSDF of ``voxel_m`` voxels (module docstring). Poses are ``T_world_cam`` (camera to world)."""

    #: the per-block arrays (those :meth:`_grow` copies)
    _PER_BLOCK = ("coords", "tsdf", "weight", "count", "colour", "colour_weight", "stamps")

    def __init__(self, voxel_m: float, trunc_m: float, min_depth_m: float = 0.1,
                 max_depth_m: float = SENSOR_MAX_DEPTH_M, max_weight: float = 1e4, max_memory_mb: float = 4096.0,
                 initial_blocks: int = INITIAL_BLOCKS, min_weight: float = 1.0,
                 min_component: int = DEFAULT_MIN_COMPONENT):
        if not (voxel_m > 0 and trunc_m > 0):
            raise ConfigError(f"TSDF: voxel ({voxel_m} m) and truncation ({trunc_m} m) must be > 0")
        self.voxel_m = float(voxel_m)
        self.trunc_m = float(trunc_m)
        self.min_depth_m = float(min_depth_m)
        self.max_depth_m = float(max_depth_m)
        self.max_weight = float(max_weight)
        self.max_memory_mb = float(max_memory_mb)
        self.min_weight = float(min_weight)
        self.min_component = int(min_component)
        ref_sigma = DEPTH_SIGMA_BASE_M + DEPTH_SIGMA_QUAD_PER_M * (REFERENCE_DEPTH_M - DEPTH_SIGMA_OFFSET_M) ** 2
        self.noise = np.zeros(6, np.float64)  # the layout of kt.NOISE_*
        self.noise[[kt.NOISE_BASE, kt.NOISE_QUAD, kt.NOISE_OFFSET]] = (DEPTH_SIGMA_BASE_M, DEPTH_SIGMA_QUAD_PER_M,
                                                                       DEPTH_SIGMA_OFFSET_M)
        self.noise[kt.NOISE_TRUNC_SIGMAS] = TRUNC_SIGMAS
        self.noise[kt.NOISE_TRUNC_MAX] = TRUNC_MAX_FACTOR * self.trunc_m
        self.noise[kt.NOISE_REF_VAR] = ref_sigma**2
        self.n_blocks = 0
        self.frames = 0
        self._stamp = 0
        self._alloc(max(1, initial_blocks))

    @classmethod
    def from_config(cls, cfg: MeshConfig) -> TsdfVolume:
        return cls(cfg.voxel_m, cfg.truncation_m, cfg.min_depth_m, cfg.max_depth_m, cfg.max_weight,
                   cfg.max_memory_mb, min_weight=cfg.min_weight, min_component=cfg.min_component)

    # -------------------------------------------------------------------------------------------- storage
    @property
    def block_m(self) -> float:
        return self.voxel_m * kt.BLOCK

    def memory_mb(self, blocks: int | None = None) -> float:
        """MiB held by ``blocks`` blocks (default: the allocated capacity)."""
        n = self.coords.shape[0] if blocks is None else blocks
        return n * kt.BLOCK_VOXELS * BYTES_PER_VOXEL / 2**20

    def _alloc(self, capacity: int) -> None:
        self.coords = np.zeros((capacity, 3), np.int64)
        self.tsdf = np.zeros((capacity, kt.BLOCK_VOXELS), np.float32)
        self.weight = np.zeros((capacity, kt.BLOCK_VOXELS), np.float32)
        self.count = np.zeros((capacity, kt.BLOCK_VOXELS), np.uint16)
        self.colour = np.zeros((capacity, kt.BLOCK_VOXELS, 3), np.uint16)
        self.colour_weight = np.zeros((capacity, kt.BLOCK_VOXELS), np.uint16)
        self.stamps = np.zeros(capacity, np.int64)
        self.visible = np.zeros(capacity, np.int64)
        slots = _hash_slots(capacity)
        self.keys = np.full(slots, kt.EMPTY, np.int64)
        self.vals = np.zeros(slots, np.int64)

    def _grow(self) -> None:
        n = self.n_blocks
        new_cap = 2 * self.coords.shape[0]
        if self.memory_mb(new_cap) > self.max_memory_mb:
            new_cap = int(self.max_memory_mb * 2**20 / (kt.BLOCK_VOXELS * BYTES_PER_VOXEL))
            if new_cap <= n:
                raise ConfigError(
                    f"the TSDF needs more than max_memory_mb = {self.max_memory_mb:g} MiB ({n:,} blocks of 8^3 voxels "
                    f"of {self.voxel_m * 100:g} cm after {self.frames} frames): use a coarser --voxel, a smaller "
                    "--max-depth, or raise [mesh] max_memory_mb")
        # one array at a time, each old one freed once copied: the peak is the volume plus its largest array, not
        # twice the volume
        for name in self._PER_BLOCK:
            old = getattr(self, name)
            new = np.zeros((new_cap, *old.shape[1:]), old.dtype)
            new[:n] = old[:n]
            setattr(self, name, new)
            del old, new
        self.visible = np.zeros(new_cap, np.int64)
        slots = _hash_slots(new_cap)
        self.keys = np.full(slots, kt.EMPTY, np.int64)
        self.vals = np.zeros(slots, np.int64)
        kt.rehash(self.coords, n, self.keys, self.vals)

    # -------------------------------------------------------------------------------------------- fusion
    def integrate(self, depth_m: np.ndarray, rgb: np.ndarray, intr: Intrinsics, T_world_cam: np.ndarray) -> int:
        """Fuse one depth image (``(H, W)`` metres, 0 = none) with its colour (``(H, W, 3)`` uint8, the colour of
        each depth pixel) seen at ``T_world_cam``. Returns the number of blocks updated."""
        depth = np.ascontiguousarray(depth_m, np.float32)
        rgb = np.ascontiguousarray(rgb, np.uint8)
        if rgb.shape != (*depth.shape, 3):
            raise ValueError(f"TSDF: colour {rgb.shape} does not match depth {depth.shape}")
        T = np.ascontiguousarray(T_world_cam, np.float64)
        while True:
            self._stamp += 1
            n_blocks, n_vis, full = kt.allocate(
                depth, intr.fx, intr.fy, intr.cx, intr.cy, T, self.min_depth_m, self.max_depth_m, self.trunc_m,
                self.noise, self.voxel_m, self.keys, self.vals, self.coords, self.n_blocks, self._stamp, self.stamps,
                self.visible)
            self.n_blocks = n_blocks
            if not full:
                break
            self._grow()
        T_cw = np.linalg.inv(T)
        kt.integrate(depth, rgb, intr.fx, intr.fy, intr.cx, intr.cy, T_cw, self.min_depth_m, self.max_depth_m,
                     self.trunc_m, self.noise, self.voxel_m, self.visible[:n_vis], self.coords, self.tsdf,
                     self.weight, self.count, self.colour, self.colour_weight, self.max_weight)
        self.frames += 1
        return n_vis

    # -------------------------------------------------------------------------------------------- extraction
    def extract_mesh(self, min_weight: float | None = None, min_component: int | None = None,
                     release: bool = False) -> Mesh:
        """Marching cubes over the cubes whose 8 corners were observed in at least ``min_weight`` frames, then the
        clean-up of :func:`~surfelslam.mapping.mesh_topology.clean_faces` (pieces under ``min_component``
        triangles removed). ``None``: the volume's settings. ``release``: the volume's storage (up to
        ``max_memory_mb``) is freed before the clean-up, leaving it empty: the peak of meshing a large volume."""
        min_weight = self.min_weight if min_weight is None else float(min_weight)
        min_component = self.min_component if min_component is None else int(min_component)
        if release:  # fusion's own arrays (the weights, the visibility lists) are not read by the extraction
            self.weight, self.stamps, self.visible = (np.zeros((0, kt.BLOCK_VOXELS), np.float32), np.zeros(0, np.int64),
                                                      np.zeros(0, np.int64))
        try:
            raw = self.marching_cubes(min_weight)
        finally:
            if release:  # empty and whole again, whether the extraction ended or failed
                self.n_blocks = 0
                self._alloc(1)
        return compact(raw, clean_faces(raw.vertices, raw.faces, min_component))

    def marching_cubes(self, min_weight: float = 1.0) -> Mesh:
        """The raw marching cubes surface (welded, edge-manifold and oriented; no clean-up) over the cubes whose 8
        corners were observed in at least ``min_weight`` frames."""
        n = self.n_blocks
        if n == 0:
            return _empty_mesh()
        coords = self.coords[:n]
        tsdf, seen, colour, colour_weight = self.tsdf[:n], self.count[:n], self.colour[:n], self.colour_weight[:n]
        nbr = kt.neighbour_table(coords, n, self.keys, self.vals)
        counts = np.zeros(n, np.int64)
        kt.count_vertices(nbr, tsdf, seen, min_weight, counts)
        vstart = np.zeros(n + 1, np.int64)  # block b's vertices: vstart[b] to vstart[b + 1]
        np.cumsum(counts, out=vstart[1:])
        n_v = int(vstart[-1])
        kt.count_triangles(nbr, tsdf, seen, min_weight, kt.TRI_COUNT, counts)
        start = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        n_f = int(counts.sum())
        extra_mb = (n_v * EXTRACT_BYTES_PER_VERTEX + n_f * EXTRACT_BYTES_PER_FACE) / 2**20
        if self.memory_mb(n) + extra_mb > self.max_memory_mb * 1.5:
            raise ConfigError(f"extracting the mesh needs {extra_mb:,.0f} MiB more than the TSDF's "
                              f"{self.memory_mb(n):,.0f} MiB: use a coarser --voxel or raise [mesh] max_memory_mb")
        vkey = np.empty(n_v, np.int16)
        verts = np.empty((n_v, 3), np.float32)
        normals = np.empty((n_v, 3), np.float32)
        rgb = np.empty((n_v, 3), np.uint8)
        kt.fill_vertices(nbr, coords, tsdf, seen, colour, colour_weight, min_weight, self.voxel_m, vstart, vkey, verts,
                         normals, rgb)
        faces = np.empty((n_f, 3), np.int32)
        kt.fill_triangles(nbr, tsdf, seen, min_weight, kt.TRI_TABLE, kt.TRI_COUNT, kt.EDGE_CORNER, kt.EDGE_AXIS,
                          vkey, vstart, start, faces)
        return Mesh(verts, normals, rgb, faces)

    def dense_grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(tsdf (X, Y, Z), frames (X, Y, Z), origin voxel (3,))``: the allocated blocks in one dense array over
        their bounding box (unallocated voxels: tsdf 1, seen in 0 frames). For comparisons with dense marching
        cubes."""
        c = self.coords[: self.n_blocks]
        lo = c.min(axis=0)
        shape = (c.max(axis=0) - lo + 1) * kt.BLOCK
        t = np.ones(tuple(shape), np.float32)
        w = np.zeros(tuple(shape), np.float32)
        for b in range(self.n_blocks):  # per block (512 voxels each), not per voxel
            o = (c[b] - lo) * kt.BLOCK
            sl = (slice(o[0], o[0] + 8), slice(o[1], o[1] + 8), slice(o[2], o[2] + 8))
            t[sl] = self.tsdf[b].reshape(8, 8, 8).transpose(2, 1, 0)
            w[sl] = self.count[b].reshape(8, 8, 8).transpose(2, 1, 0)
        return t, w, lo * kt.BLOCK


def _hash_slots(capacity: int) -> int:
    """The block hash's size for ``capacity`` blocks: a power of two (the hash masks), at least twice as many."""
    return 1 << int(2 * capacity - 1).bit_length()


def _empty_mesh() -> Mesh:
    return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8),
                np.zeros((0, 3), np.int32))


def compact(mesh: Mesh, keep_faces: np.ndarray) -> Mesh:
    """``mesh`` with the faces of the mask ``keep_faces`` ``(F,)`` only, and only the vertices they use (in their
    order)."""
    faces = mesh.faces[keep_faces]
    used = np.zeros(mesh.n_vertices, bool)
    used[faces.reshape(-1)] = True
    new_index = np.cumsum(used, dtype=np.int64) - 1
    return Mesh(mesh.vertices[used], mesh.normals[used], mesh.colours[used],
                new_index[faces].astype(np.int32).reshape(-1, 3))


def fuse_frames(frames: Iterable, poses: Iterable[np.ndarray], intr: Intrinsics, cfg: MeshConfig,
                colour_of=None, progress=None) -> TsdfVolume:
    """A :class:`TsdfVolume` of ``frames`` (:class:`~surfelslam.types.RGBDFrame`) at ``poses`` (``T_world_cam``).
    ``colour_of(frame)``: the colour of each depth pixel (default ``frame.rgb``); ``progress()`` after each frame."""
    vol = TsdfVolume.from_config(cfg)
    for frame, T in zip(frames, poses, strict=True):
        rgb = frame.rgb if colour_of is None else colour_of(frame)
        vol.integrate(frame.depth_m, rgb, intr, T)
        if progress is not None:
            progress()
    return vol


# ------------------------------------------------------------------------------------------------ Poisson
OPEN3D_MISSING = "the poisson method needs Open3D: pip install 'surfelslam[bench]' (open3d-cpu)"


def require_open3d():
    """The ``open3d`` module, or a one-line ConfigError naming the extra."""
    try:
        import open3d as o3d
    except ImportError:
        raise ConfigError(OPEN3D_MISSING) from None
    return o3d


def poisson_mesh(points: np.ndarray, normals: np.ndarray, colours: np.ndarray, cfg: MeshConfig) -> Mesh:
    """Screened Poisson reconstruction (Open3D) of oriented points (a surfel map); the vertices of the lowest
    ``poisson_density_quantile`` support are removed (Poisson closes holes with surfaces far from any point)."""
    o3d = require_open3d()
    if len(points) < 10:
        raise ConfigError(f"poisson: the map has {len(points)} points, too few to reconstruct a surface")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64))
    pcd.colors = o3d.utility.Vector3dVector(np.asarray(colours, np.float64) / 255.0)
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=cfg.poisson_depth)
    density = np.asarray(density)
    if cfg.poisson_density_quantile > 0 and len(density):
        mesh.remove_vertices_by_mask(density < np.quantile(density, cfg.poisson_density_quantile))
    mesh.compute_vertex_normals()
    cols = np.asarray(mesh.vertex_colors)
    v = np.asarray(mesh.vertices)
    return Mesh(v.astype(np.float32), np.asarray(mesh.vertex_normals, np.float32),
                np.clip(np.floor(cols * 255 + 0.5), 0, 255).astype(np.uint8) if len(cols) == len(v)
                else np.full((len(v), 3), 200, np.uint8),
                np.asarray(mesh.triangles, np.int32))

