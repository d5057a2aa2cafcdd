"""Triangle meshes of a run: a TSDF of the depth frames at the run's poses, then marching cubes; or Poisson.

:class:`TsdfVolume` is a sparse TSDF (blocks of 8^3 voxels allocated where depth is seen, found through a hash),
kernels in :mod:`surfelslam.kernels.tsdf`: :meth:`TsdfVolume.integrate` fuses one depth image (projective
distance, truncated at ``trunc_m``, weight 1 per frame, colour averaged near the surface), and
:meth:`TsdfVolume.extract_mesh` runs marching cubes over the observed voxels (a welded mesh with vertex normals
from the TSDF gradient and vertex colours). Memory grows with the observed surface, not with the room's volume:
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
from surfelslam.types import Intrinsics

METHODS = ("tsdf", "poisson")
#: bytes per voxel: tsdf float32, weight float32, colour 3 x uint16, colour weight uint16 (+ the extraction's
#: vertex index table, 3 x int32, while a mesh is extracted)
BYTES_PER_VOXEL = 4 + 4 + 6 + 2
EXTRACT_BYTES_PER_VOXEL = 12
#: blocks allocated up front (the arrays double when full)
INITIAL_BLOCKS = 4096


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
    max_depth_m: float = setting(4.0, unit="m", gt=0, le=100,
                                 doc="farther depths are not fused (Kinect noise grows with depth squared)")
    stride: int = setting(1, unit="frames", ge=1, le=100_000, doc="fuse every stride-th frame of the run")
    min_weight: float = setting(1.0, unit="frames", gt=0, le=1e6,
                                doc="marching cubes uses voxels observed in at least this many frames")
    max_weight: float = setting(1e4, unit="frames", ge=1, le=1e9,
                                doc="a voxel's weight saturates here (newer frames then count more)")
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

    def __init__(self, voxel_m: float, trunc_m: float, min_depth_m: float = 0.1, max_depth_m: float = 4.0,
                 max_weight: float = 1e4, max_memory_mb: float = 4096.0, initial_blocks: int = INITIAL_BLOCKS):
        if not (voxel_m > 0 and trunc_m > 0):
            raise ConfigError(f"TSDF: voxel ({voxel_m} m) and truncation ({trunc_m} m) must be > 0")
        self.voxel_m = float(voxel_m)
        self.trunc_m = float(trunc_m)
        self.min_depth_m = float(min_depth_m)
        self.max_depth_m = float(max_depth_m)
        self.max_weight = float(max_weight)
        self.max_memory_mb = float(max_memory_mb)
        self.n_blocks = 0
        self.frames = 0
        self._stamp = 0
        self._alloc(max(1, initial_blocks))

    @classmethod
    def from_config(cls, cfg: MeshConfig) -> TsdfVolume:
        return cls(cfg.voxel_m, cfg.truncation_m, cfg.min_depth_m, cfg.max_depth_m, cfg.max_weight,
                   cfg.max_memory_mb)

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
        self.colour = np.zeros((capacity, kt.BLOCK_VOXELS, 3), np.uint16)
        self.colour_weight = np.zeros((capacity, kt.BLOCK_VOXELS), np.uint16)
        self.stamps = np.zeros(capacity, np.int64)
        self.visible = np.zeros(capacity, np.int64)
        slots = 1 << int(2 * capacity - 1).bit_length()  # a power of two (the hash masks), at least 2 x capacity
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
        old = (self.coords, self.tsdf, self.weight, self.colour, self.colour_weight, self.stamps)
        self._alloc(new_cap)
        for dst, src in zip((self.coords, self.tsdf, self.weight, self.colour, self.colour_weight, self.stamps), old,
                            strict=True):
            dst[:n] = src[:n]
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
                self.block_m, self.keys, self.vals, self.coords, self.n_blocks, self._stamp, self.stamps,
                self.visible)
            self.n_blocks = n_blocks
            if not full:
                break
            self._grow()
        T_cw = np.linalg.inv(T)
        kt.integrate(depth, rgb, intr.fx, intr.fy, intr.cx, intr.cy, T_cw, self.min_depth_m, self.max_depth_m,
                     self.trunc_m, self.voxel_m, self.visible[:n_vis], self.coords, self.tsdf, self.weight,
                     self.colour, self.colour_weight, self.max_weight)
        self.frames += 1
        return n_vis

    # -------------------------------------------------------------------------------------------- extraction
    def extract_mesh(self, min_weight: float = 1.0) -> Mesh:
        """Marching cubes over the cubes whose 8 corners were observed with at least ``min_weight``."""
        n = self.n_blocks
        if n == 0:
            return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8),
                        np.zeros((0, 3), np.int32))
        extra_mb = n * kt.BLOCK_VOXELS * EXTRACT_BYTES_PER_VOXEL / 2**20
        if self.memory_mb(n) + extra_mb > self.max_memory_mb * 1.5:
            raise ConfigError(f"extracting the mesh needs {extra_mb:,.0f} MiB more than the TSDF's "
                              f"{self.memory_mb(n):,.0f} MiB: use a coarser --voxel or raise [mesh] max_memory_mb")
        coords = self.coords[:n]
        tsdf, weight, colour, colour_weight = self.tsdf[:n], self.weight[:n], self.colour[:n], self.colour_weight[:n]
        nbr = kt.neighbour_table(coords, n, self.keys, self.vals)
        counts = np.zeros(n, np.int64)
        kt.count_vertices(nbr, tsdf, weight, min_weight, counts)
        start = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        n_v = int(counts.sum())
        vid = np.empty((n, kt.BLOCK_VOXELS, 3), np.int32)
        verts = np.empty((n_v, 3), np.float32)
        normals = np.empty((n_v, 3), np.float32)
        rgb = np.empty((n_v, 3), np.uint8)
        kt.fill_vertices(nbr, coords, tsdf, weight, colour, colour_weight, min_weight, self.voxel_m, start, vid, verts,
                         normals, rgb)
        kt.count_triangles(nbr, tsdf, weight, min_weight, kt.TRI_COUNT, counts)
        start = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        faces = np.empty((int(counts.sum()), 3), np.int32)
        kt.fill_triangles(nbr, tsdf, weight, min_weight, kt.TRI_TABLE, kt.TRI_COUNT, kt.EDGE_CORNER, kt.EDGE_AXIS,
                          vid, start, faces)
        return Mesh(verts, normals, rgb, faces)

    def dense_grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(tsdf (X, Y, Z), weight (X, Y, Z), origin voxel (3,))``: the allocated blocks in one dense array over
        their bounding box (unallocated voxels: tsdf 1, weight 0). For comparisons with dense marching cubes."""
        c = self.coords[: self.n_blocks]
        lo = c.min(axis=0)
        shape = (c.max(axis=0) - lo + 1) * kt.BLOCK
        t = np.ones(tuple(shape), np.float32)
        w = np.zeros(tuple(shape), np.float32)
        for b in range(self.n_blocks):  # per block (512 voxels each), not per voxel
            o = (c[b] - lo) * kt.BLOCK
            sl = (slice(o[0], o[0] + 8), slice(o[1], o[1] + 8), slice(o[2], o[2] + 8))
            t[sl] = self.tsdf[b].reshape(8, 8, 8).transpose(2, 1, 0)
            w[sl] = self.weight[b].reshape(8, 8, 8).transpose(2, 1, 0)
        return t, w, lo * kt.BLOCK


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

