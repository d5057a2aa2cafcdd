"""The surfel map: preallocated, growable arrays of surfels plus a voxel-block index for view culling.

Storage
-------
Every attribute lives in a preallocated array of ``capacity`` rows; the first ``size`` rows are in use.
When an append does not fit, the capacity doubles (amortised O(1) per surfel; the map is never
concatenated as a whole per frame). The properties ``map.position`` etc. return views ``[:size]``.

Rows are appended in fusion order, so ``first_seen`` is non-decreasing along the rows as long as frames
are fused in increasing order; :meth:`SurfelMap.remove` and :meth:`SurfelMap.compact` keep the order
(stable compaction), which the dormant-surfel rule of :mod:`surfelslam.mapping.fusion` relies on.

Removal is two-step for speed: :meth:`mark_dead` flags rows (rendering and fusion skip them at once) and
:meth:`compact` moves the live rows down. ``size`` counts flagged rows until the next compaction;
``n_alive`` does not. :meth:`remove` does both.

Culling index
-------------
Each surfel belongs to the cubic block (edge ``block_size_m``) holding its position when it was added.
The index keeps, for the first ``n_grouped`` surfels, their indices grouped by block (a stable counting
sort, ``order`` + per-block ``start``/``count``); surfels appended since then form the *tail*. For a view,
the blocks' boxes (grown by ``block_margin_m`` to allow for surfels that drifted while being merged) are
tested against the frustum, and only the surfels of visible blocks plus the visible part of the tail are
handed to the renderers, so the per-frame cost follows what is in view, not the map size. The grouping is
rebuilt when the tail exceeds ``index_max_tail`` surfels or after a compaction (O(size), amortised).

Memory locality
---------------
The grouping is by index, so a block's surfels still lie wherever fusion appended them: after a few passes over a
scene every block is scattered over the whole array and the renderers' gathers miss the cache. :meth:`maybe_reorder`
therefore regroups the rows themselves by block, but only the rows the dormant rule has already checked (before
``dormant_cursor``): the rows after it keep their fusion order, which that rule relies on. This keeps the per-frame
cost of long runs from growing (``benchmarks/bench_pipeline.py``). Only the rows checked since the last regrouping are
regrouped (among themselves), except when they reach a quarter of the rows regrouped as a whole last time: then all of
them are, so each row moves O(1) times on average and a floor-sized map does not pay O(map) every few frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surfelslam.config import Config, setting
from surfelslam.geometry import se3
from surfelslam.kernels import render as kr
from surfelslam.kernels import surfels as ks
from surfelslam.types import Intrinsics

_KEY_BITS = 21
# all checked rows are regrouped together once those checked since the last whole regrouping reach this fraction of
# it (geometric: O(1) moves per row; below, only the new rows are regrouped, among themselves)
_FULL_REORDER_GROWTH = 0.25
_KEY_OFFSET = 1 << (_KEY_BITS - 1)
_LOD_MAX_STRIDE = 255  # a block's level-of-detail stride is kept in its uint8 visibility flag
# Culling tests cubes of this many blocks a side first (4 x 0.25 m by default): a floor's map holds some 10^4 blocks,
# most of them outside the view, and a cube rejects its 10-30 blocks in one test
_CULL_GROUP_BLOCKS = 4
# blocks added since the cubes were formed are tested one by one; this many of them and the cubes are formed again
# (O(blocks log blocks), about a millisecond at 10^4 blocks; a run adds a few blocks per frame)
_CULL_REGROUP_BLOCKS = 512


@dataclass(frozen=True)
class MapConfig(Config):
    """Storage and culling-index settings of a :class:`SurfelMap`."""

    initial_capacity: int = setting(65536, unit="surfels", ge=1, le=1 << 26,
                                    doc="surfels allocated up front (the arrays grow as needed)")
    block_size_m: float = setting(0.25, unit="m", ge=0.01, le=100, doc="edge of the cubic culling blocks")
    block_margin_m: float = setting(0.1, unit="m", ge=0, le=100, doc="blocks' boxes are grown by this much in the "
                                    "frustum test")
    index_max_tail: int = setting(131072, unit="surfels", ge=0, le=1 << 30,
                                  doc="rebuild the block grouping when this many surfels are ungrouped")
    reorder_every_rows: int = setting(32768, unit="surfels", ge=0, le=1 << 30,
                                      doc="regroup rows by block in memory once this many more are checked; 0 = off")


def _pack_keys(ijk: np.ndarray) -> np.ndarray:
    """Integer block coordinates ``(N, 3)`` -> int64 keys (21 bits per axis)."""
    o = (ijk.astype(np.int64) + _KEY_OFFSET) & ((1 << _KEY_BITS) - 1)
    return (o[:, 0] << (2 * _KEY_BITS)) | (o[:, 1] << _KEY_BITS) | o[:, 2]


class SurfelMap:
    """Growable surfel arrays (world frame) with a voxel-block culling index.

    Attributes (views of the first ``size`` rows):
        position: ``(N, 3)`` float32 metres, world frame.
        normal: ``(N, 3)`` float32 unit vectors, world frame.
        colour: ``(N, 3)`` float32 RGB in [0, 255] (averaged, so kept as float).
        confidence: ``(N,)`` float32 accumulated observation weight.
        radius: ``(N,)`` float32 metres.
        first_seen, last_seen: ``(N,)`` int32 frame indices of the first and the latest observation.
        hits: ``(N,)`` int32 number of frames the surfel was observed in (its creation counts as 1).
        block_id: ``(N,)`` int32 culling block of each surfel.
        dead: ``(N,)`` uint8, 1 for surfels flagged for removal but not yet compacted.
    """

    def __init__(self, cfg: MapConfig | None = None):
        self.cfg = cfg or MapConfig()
        self._size = 0
        self._n_dead = 0
        self.latest_frame = -1  # highest frame index fused so far (set by fusion)
        self.dormant_cursor = 0  # rows before this were already checked by the dormant rule (fusion)
        self._reordered_upto = 0  # dormant_cursor at the last regrouping of rows by block
        self._full_reordered_upto = 0  # ... at the last regrouping of all checked rows together
        self._alloc(self.cfg.initial_capacity)
        # block index
        self._inv_block = 1.0 / self.cfg.block_size_m
        self._key_to_block: dict[int, int] = {}
        self._block_ijk = np.zeros((64, 3), np.int32)
        self._n_blocks = 0
        self._order = np.zeros(self._cap, np.int32)
        self._block_start = np.zeros(64, np.int32)
        self._block_count = np.zeros(64, np.int32)
        self._n_grouped = 0
        self._n_blocks_grouped = 0
        self._cand = np.zeros(self._cap, np.int32)
        self._visible = np.zeros(64, np.uint8)
        # the blocks grouped in cubes for culling (:meth:`_cull_groups`): (cube ijk, start, blocks, blocks covered)
        self._groups: tuple[np.ndarray, np.ndarray, np.ndarray, int] | None = None
        self._scratch: dict[str, np.ndarray] = {}

    # ------------------------------------------------------------------ storage
    def _alloc(self, cap: int) -> None:
        self._cap = cap
        self._position = np.zeros((cap, 3), np.float32)
        self._normal = np.zeros((cap, 3), np.float32)
        self._colour = np.zeros((cap, 3), np.float32)
        self._confidence = np.zeros(cap, np.float32)
        self._radius = np.zeros(cap, np.float32)
        self._first_seen = np.zeros(cap, np.int32)
        self._last_seen = np.zeros(cap, np.int32)
        self._hits = np.zeros(cap, np.int32)
        self._block_id = np.zeros(cap, np.int32)
        self._dead = np.zeros(cap, np.uint8)

    _FIELDS = (
        "_position", "_normal", "_colour", "_confidence", "_radius",
        "_first_seen", "_last_seen", "_hits", "_block_id", "_dead",
    )

    def reserve(self, n_total: int) -> None:
        """Make room for ``n_total`` rows; capacity at least doubles when it has to grow."""
        if n_total <= self._cap:
            return
        new_cap = max(2 * self._cap, int(n_total))
        n = self._size
        for name in self._FIELDS:
            old = getattr(self, name)
            new = np.zeros((new_cap, *old.shape[1:]), old.dtype)
            new[:n] = old[:n]
            setattr(self, name, new)
        self._cap = new_cap
        order = np.zeros(new_cap, np.int32)
        order[: self._n_grouped] = self._order[: self._n_grouped]
        self._order = order
        self._cand = np.zeros(new_cap, np.int32)

    @property
    def size(self) -> int:
        """Rows in use (including rows flagged dead and not yet compacted)."""
        return self._size

    @property
    def capacity(self) -> int:
        return self._cap

    @property
    def n_dead(self) -> int:
        return self._n_dead

    @property
    def n_alive(self) -> int:
        return self._size - self._n_dead

    def __len__(self) -> int:
        return self._size

    position = property(lambda self: self._position[: self._size])
    normal = property(lambda self: self._normal[: self._size])
    colour = property(lambda self: self._colour[: self._size])
    confidence = property(lambda self: self._confidence[: self._size])
    radius = property(lambda self: self._radius[: self._size])
    first_seen = property(lambda self: self._first_seen[: self._size])
    last_seen = property(lambda self: self._last_seen[: self._size])
    hits = property(lambda self: self._hits[: self._size])
    block_id = property(lambda self: self._block_id[: self._size])
    dead = property(lambda self: self._dead[: self._size])

    def alive_mask(self) -> np.ndarray:
        """``(size,)`` bool, True for live surfels."""
        return self._dead[: self._size] == 0

    def append(
        self,
        position: np.ndarray,
        normal: np.ndarray,
        colour: np.ndarray,
        confidence: np.ndarray | float,
        radius: np.ndarray | float,
        frame_index: int,
    ) -> slice:
        """Append ``n`` surfels (world frame); returns the slice of their rows.

        ``position``/``normal`` ``(n, 3)``, ``colour`` ``(n, 3)`` in [0, 255], ``confidence``/``radius``
        scalars or ``(n,)``. ``first_seen = last_seen = frame_index``, ``hits = 1``.
        """
        position = np.asarray(position, np.float32).reshape(-1, 3)
        n = len(position)
        s0 = self._size
        self.reserve(s0 + n)
        rows = slice(s0, s0 + n)
        self._position[rows] = position
        self._normal[rows] = np.asarray(normal, np.float32).reshape(-1, 3)
        self._colour[rows] = np.clip(np.asarray(colour, np.float32).reshape(-1, 3), 0, 255)
        self._confidence[rows] = confidence
        self._radius[rows] = radius
        self._first_seen[rows] = frame_index
        self._last_seen[rows] = frame_index
        self._hits[rows] = 1
        self._dead[rows] = 0
        self._size = s0 + n
        self._assign_blocks(s0, s0 + n)
        return rows

    def load(self, surfels: dict[str, np.ndarray]) -> None:
        """Fill an empty map with saved surfels (a map to continue from): ``{name: (n, ...)}`` for ``position``,
        ``normal``, ``colour``, ``confidence``, ``radius``, ``first_seen``, ``last_seen``, ``hits`` (see the class
        attributes). The rows count as checked by the dormant rule and are grouped by block."""
        if self._size:
            raise ValueError(f"load: the map must be empty, it has {self._size} surfels")
        n = len(surfels["position"])
        self.reserve(n)
        for name in ("position", "normal", "colour", "confidence", "radius", "first_seen", "last_seen", "hits"):
            getattr(self, "_" + name)[:n] = surfels[name]
        self._dead[:n] = 0
        self._size = n
        self.latest_frame = int(self._last_seen[:n].max()) if n else -1
        self.dormant_cursor = n
        self._assign_blocks(0, n)
        self.reorder_by_block(n)

    def commit_appended(self, start: int, stop: int) -> None:
        """Register rows ``start..stop-1`` written directly into the arrays by a kernel (sets ``size``)."""
        self._size = stop
        self._assign_blocks(start, stop)

    # ------------------------------------------------------------------ removal
    def mark_dead(self, mask_or_index: np.ndarray) -> int:
        """Flag surfels for removal (rendering and fusion skip them); returns how many were newly flagged."""
        sel = np.zeros(self._size, bool)
        sel[mask_or_index] = True
        sel &= self._dead[: self._size] == 0
        k = int(sel.sum())
        self._dead[: self._size][sel] = 1
        self._n_dead += k
        return k

    def add_dead_count(self, k: int) -> None:
        """Account for ``k`` surfels a kernel flagged directly in ``dead``."""
        self._n_dead += int(k)

    def compact(self) -> int:
        """Remove all flagged surfels in place (stable order); returns how many were removed."""
        if self._n_dead == 0:
            return 0
        n_before_cursor = int(np.count_nonzero(self._dead[: self.dormant_cursor] == 0))
        n_before_full = int(np.count_nonzero(self._dead[: self._full_reordered_upto] == 0))
        new_size = ks.compact_rows(
            self._position, self._normal, self._colour, self._confidence, self._radius,
            self._first_seen, self._last_seen, self._hits, self._block_id, self._dead, self._size,
        )
        removed = self._size - new_size
        self._size = new_size
        self._n_dead = 0
        self._reordered_upto = min(self._reordered_upto, n_before_cursor)
        self._full_reordered_upto = min(n_before_full, self._reordered_upto)
        self.dormant_cursor = n_before_cursor
        self.rebuild_index()  # rows moved: regroup (O(size), like the compaction itself)
        return removed

    def remove(self, mask: np.ndarray) -> int:
        """Remove the surfels where ``mask`` (``(size,)`` bool) is True; compacts in place, stable order."""
        mask = np.asarray(mask, bool)
        if mask.shape != (self._size,):
            raise ValueError(f"remove: mask must have shape ({self._size},), got {mask.shape}")
        self.mark_dead(mask)
        return self.compact()

    def transform_surfels(self, R: np.ndarray, t: np.ndarray, rows: np.ndarray | None = None) -> None:
        """Move surfels by their own rigid transforms: every surfel (``rows`` ``None``; ``R`` ``(size, 3, 3)``, ``t``
        ``(size, 3)``) or the surfels ``rows`` ``(m,)`` (``R`` ``(m, 3, 3)``, ``t`` ``(m, 3)``), float32: positions
        ``R p + t``, normals ``R n``. The moved surfels' culling blocks and the grouping are rebuilt (a pose-graph
        correction of the map)."""
        n = self._size if rows is None else len(rows)
        if R.shape != (n, 3, 3) or t.shape != (n, 3):
            raise ValueError(f"transform_surfels: R must be ({n}, 3, 3) and t ({n}, 3), got {R.shape} and {t.shape}")
        rows = np.arange(n) if rows is None else rows
        self.transform_groups(np.ascontiguousarray(R, np.float32), np.ascontiguousarray(t, np.float32),
                              np.arange(n), rows)

    def transform_groups(self, R: np.ndarray, t: np.ndarray, group: np.ndarray, rows: np.ndarray | None = None) -> None:
        """Move each surfel (``rows`` ``None``) or each of ``rows`` ``(m,)`` by the rigid transform of its group
        ``group`` ``(size,)`` or ``(m,)``: ``R`` ``(G, 3, 3)``, ``t`` ``(G, 3)`` float32 (e.g. one per keyframe:
        positions ``R p + t``, normals ``R n``); the moved surfels' culling blocks and the grouping are rebuilt (a
        pose-graph correction of the map; moving only some rows keeps its cost with them, apart from the O(size)
        grouping)."""
        rows = np.arange(self._size) if rows is None else np.asarray(rows, np.int64)
        group = np.asarray(group, np.int64)
        if group.shape != rows.shape or R.shape[1:] != (3, 3) or t.shape != (len(R), 3):
            raise ValueError(f"transform_groups: group must be {rows.shape}, R (G, 3, 3) and t (G, 3), got "
                             f"{group.shape}, {R.shape} and {t.shape}")
        if len(rows) == 0:
            return
        if rows.min() < 0 or rows.max() >= self._size or group.min() < 0 or group.max() >= len(R):
            raise ValueError(f"transform_groups: rows must lie in [0, {self._size}) and groups in [0, {len(R)})")
        ks.transform_rows(self._position, self._normal, rows, group, np.ascontiguousarray(R, np.float32),
                          np.ascontiguousarray(t, np.float32))
        # only the surfels that left their block need a new one (a correction moves most by less than a block)
        left = rows[ks.rows_off_block(self._position, rows, self._block_id, self._block_ijk,
                                      np.float32(self._inv_block))]
        self._block_id[left] = self._block_ids(self._position[left])
        self.rebuild_index()

    # ------------------------------------------------------------------ block index
    def _assign_blocks(self, start: int, stop: int) -> None:
        if stop <= start:
            return
        self._block_id[start:stop] = self._block_ids(self._position[start:stop])

    def _block_ids(self, position: np.ndarray) -> np.ndarray:
        """``(n,)`` int32 block of each position ``(n, 3)``, blocks created as needed."""
        ijk = np.floor(position * self._inv_block).astype(np.int32)
        keys = _pack_keys(ijk)
        uniq, first, inv = np.unique(keys, return_index=True, return_inverse=True)
        ids = np.empty(len(uniq), np.int32)
        for j, key in enumerate(uniq.tolist()):  # one iteration per distinct block, not per surfel
            b = self._key_to_block.get(key)
            if b is None:
                b = self._new_block(ijk[first[j]])
                self._key_to_block[key] = b
            ids[j] = b
        return ids[inv.reshape(-1)]

    def _new_block(self, ijk: np.ndarray) -> int:
        b = self._n_blocks
        if b >= len(self._block_ijk):
            n2 = 2 * len(self._block_ijk)
            for name, dtype, shape in (
                ("_block_ijk", np.int32, (n2, 3)), ("_block_start", np.int32, (n2,)),
                ("_block_count", np.int32, (n2,)), ("_visible", np.uint8, (n2,)),
            ):
                new = np.zeros(shape, dtype)
                old = getattr(self, name)
                new[: len(old)] = old
                setattr(self, name, new)
        self._block_ijk[b] = ijk
        self._n_blocks = b + 1
        return b

    @property
    def n_blocks(self) -> int:
        return self._n_blocks

    @property
    def n_grouped(self) -> int:
        """Surfels covered by the block grouping (the rest is the tail, scanned linearly)."""
        return self._n_grouped

    def rebuild_index(self) -> None:
        """Group all current surfels by block (O(size + n_blocks))."""
        ks.group_by_block(
            self._block_id, self._size, self._n_blocks, self._order, self._block_start, self._block_count
        )
        self._n_grouped = self._size
        self._n_blocks_grouped = self._n_blocks

    def maybe_reorder(self) -> bool:
        """Regroup the checked rows by block (:meth:`reorder_by_block`) when ``reorder_every_rows`` more rows
        have been checked by the dormant rule since the last time: all of them when the rows checked since the last
        whole regrouping reach ``_FULL_REORDER_GROWTH`` of it, else only the new ones; returns whether it did."""
        every = self.cfg.reorder_every_rows
        cursor = self.dormant_cursor
        if every <= 0 or cursor - self._reordered_upto < every:
            return False
        full = self._full_reordered_upto
        self.reorder_by_block(cursor, 0 if cursor - full >= _FULL_REORDER_GROWTH * full else self._reordered_upto)
        return True

    def reorder_by_block(self, n: int, start: int = 0) -> None:
        """Move rows ``start..n-1`` so that each block's surfels among them are contiguous (stable within a block);
        the other rows are untouched. O(n - start + n_blocks); the block index is rebuilt."""
        n = min(int(n), self._size)
        start = min(max(int(start), 0), n)
        if n <= start:
            return
        order = np.empty(n - start, np.int32)
        first = np.empty(max(self._n_blocks, 1), np.int32)
        count = np.empty(max(self._n_blocks, 1), np.int32)
        ks.group_by_block(self._block_id[start:], n - start, self._n_blocks, order, first, count)
        for name in self._FIELDS:
            a = getattr(self, name)
            a[start:n] = a[start:n][order]
        self._reordered_upto = n
        if start == 0:
            self._full_reordered_upto = n
        self.rebuild_index()

    def visible_candidates(
        self, T_world_cam: np.ndarray, intr: Intrinsics, min_depth_m: float, max_depth_m: float,
        margin_px: float = 0.0, lod_surfels_per_px: float = 0.0,
    ) -> np.ndarray:
        """Indices of live surfels whose block's box meets the view frustum (a superset of what is seen).

        Args:
            T_world_cam: ``(4, 4)`` camera-to-world pose.
            intr: intrinsics of the view.
            min_depth_m, max_depth_m: depth range of the frustum (camera z).
            margin_px: the image rectangle is grown by this many pixels (for splats crossing the border).
            lod_surfels_per_px: > 0: level of detail, a block whose surfels crowd more than this many onto each
                pixel of its face gives only one of each ``k`` of them (:func:`~surfelslam.kernels.render.lod_strides`,
                :func:`~surfelslam.kernels.surfels.gather_candidates`; no longer a superset of what is seen: for a
                z-buffer, not for fusion). 0: every surfel.

        Returns:
            ``(M,)`` int32 view into an internal buffer (valid until the next call).
        """
        if self._size - self._n_grouped > self.cfg.index_max_tail or self._n_grouped > self._size:
            self.rebuild_index()
        nb = self._n_blocks
        if self._size == 0 or nb == 0:
            return self._cand[:0]
        T_cam_world = se3.invert(np.asarray(T_world_cam, np.float64))
        image = (-0.5 - margin_px, intr.width - 0.5 + margin_px, -0.5 - margin_px, intr.height - 0.5 + margin_px)
        camera = (float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy))
        group_ijk, group_start, group_blocks, n_in_groups = self._cull_groups()
        kr.cull_blocks_grouped(
            group_ijk, group_start, group_blocks, _CULL_GROUP_BLOCKS * self.cfg.block_size_m, n_in_groups,
            self._block_ijk, nb, self.cfg.block_size_m, self.cfg.block_margin_m,
            np.ascontiguousarray(T_cam_world[:3, :3]), np.ascontiguousarray(T_cam_world[:3, 3]),
            *camera, *image, float(min_depth_m), float(max_depth_m),
            kr.frustum_reach(*camera, *image, float(max_depth_m)), self._visible,
        )
        if lod_surfels_per_px > 0:
            kr.lod_strides(self._visible, self._n_blocks_grouped, self._block_ijk, self._block_count,
                           self.cfg.block_size_m, np.ascontiguousarray(T_cam_world[:3, :3]),
                           np.ascontiguousarray(T_cam_world[:3, 3]), camera[0], camera[1], float(lod_surfels_per_px),
                           _LOD_MAX_STRIDE)
        m = ks.gather_candidates(
            self._visible, self._order, self._block_start, self._block_count, self._n_blocks_grouped,
            self._block_id, self._n_grouped, self._size, self._dead, self._cand,
        )
        return self._cand[:m]

    def _cull_groups(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """The blocks grouped in cubes of :data:`_CULL_GROUP_BLOCKS` blocks a side (:func:`cull_blocks_grouped`):
        ``(cube ijk (G, 3) int32, start (G + 1,) int64, blocks (n,) int32, n)``, over the first ``n`` blocks; regrouped
        once :data:`_CULL_REGROUP_BLOCKS` blocks were added since (blocks are only ever appended)."""
        nb = self._n_blocks
        if self._groups is None or nb - self._groups[3] >= _CULL_REGROUP_BLOCKS:
            cube = np.floor_divide(self._block_ijk[:nb], _CULL_GROUP_BLOCKS)
            group_ijk, cube_of_block = np.unique(cube, axis=0, return_inverse=True)
            cube_of_block = cube_of_block.reshape(-1)
            blocks = np.argsort(cube_of_block, kind="stable").astype(np.int32)
            start = np.concatenate([[0], np.cumsum(np.bincount(cube_of_block, minlength=len(group_ijk)))])
            self._groups = (np.ascontiguousarray(group_ijk, np.int32), start.astype(np.int64), blocks, nb)
        return self._groups

    def scratch(self, name: str, n: int, dtype) -> np.ndarray:
        """A reusable 1-D work buffer of at least ``n`` elements (grown by doubling), for per-frame kernels."""
        buf = self._scratch.get(name)
        if buf is None or len(buf) < n or buf.dtype != np.dtype(dtype):
            buf = np.empty(max(int(n), 2 * (len(buf) if buf is not None else 0)), dtype)
            self._scratch[name] = buf
        return buf[:n]

    # raw arrays for the kernels (full capacity; callers use [:size])
    def raw(self) -> dict[str, np.ndarray]:
        return {name[1:]: getattr(self, name) for name in self._FIELDS}
