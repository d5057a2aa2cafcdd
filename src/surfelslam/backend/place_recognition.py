"""Appearance-based keyframe retrieval by descriptor voting.

Every keyframe's ORB descriptors are appended to one database (grown by doubling). A query frame
matches each of its descriptors to its two nearest database descriptors; a match passing the ratio test and a
distance bound casts one vote for the keyframe that owns the nearest descriptor. Keyframes are ranked by votes
(ties: lower id first).

The nearest descriptors are searched by brute force (exact, :mod:`surfelslam.kernels.hamming`, over a word-major copy
of the database: half the time of the row-major search) while the database is small (``exact_below_descriptors``),
beyond that in a locality-sensitive hash index that every descriptor enters when it is added (bit sampling,
:mod:`surfelslam.kernels.hamming_hash`): a query then compares each descriptor with the few rows that share one of its
hash keys instead of every keyframe's, and the keys gain a bit each time the database doubles (the tables are rebuilt,
O(1) per row on average), so its cost stays nearly flat as a floor-sized map gathers thousands of keyframes
(``benchmarks/bench_retrieval.py`` measures it); the rows are kept bucket after bucket, sealed every
:data:`SEAL_ROWS` new ones, so that a query reads each bucket as one contiguous run. That holds for descriptors spread
over the space; real ones crowd: on a floor walk with revisits a fifth of a query's descriptors share their buckets
with thousands of rows (common appearances, and their count grows with the map), and they were 3/4 of the rows
compared for 2 % of the votes; the rows compared per query descriptor grow from 250 to 2500 over a floor's 1662
keyframes. Each bucket counts its rows, and with ``hash_bucket_rows`` one of more rows is a stop word, left out before
any of its rows is compared (the descriptor's other buckets are searched): a query then compares at most
``hash_tables`` times that many rows per descriptor (:attr:`DescriptorIndex.rows_compared` counts them). It is off by
default: it changes which loop candidates a floor walk finds. The hashed search
finds a close nearest neighbour with a high probability and may miss the second-nearest (the ratio test is then
looser); the bit positions are drawn from a fixed seed, so results are deterministic. A library index was weighed:
OpenCV's FLANN LSH cannot append rows without rebuilding and draws its tables from the C library's global random
state, and no other binary-descriptor index is among the dependencies.

Keyframes are stored in id order, so restricting a query to "keyframes older than k" is a prefix
of the database: recent keyframes (which trivially look alike) are excluded without copying.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surfelslam.config import Config, setting
from surfelslam.kernels import hamming, hamming_hash

_DESCRIPTOR_BYTES = 32
_DESCRIPTOR_BITS = 8 * _DESCRIPTOR_BYTES
_INITIAL_CAPACITY = 4096
_HASH_SEED = 0  # seed of the hash tables' bit positions (fixed: retrieval is deterministic)
# the bits keys are drawn from: the half whose share of ones is nearest 1/2 (ORB bits are unbalanced; on a floor walk
# the balanced half gave 5x smaller buckets than all 256 bits, at 3% lower recall of the voting neighbours)
_BALANCED_BITS = 128
# the key grows by one bit per doubling of the database up to this: the bucket heads, starts and counts take tables x
# 2 ** bits x 10 bytes (160 MB for 16 tables at 20 bits)
_MAX_KEY_BITS = 20
# rows added to the hash tables since the last seal that make the next one (:func:`hamming_hash.seal_rows`): a seal
# moves every row (145 ms at 600k rows and 20-bit keys), the tail's linked walk costs a query about 7x the same rows
# sealed; at that size 16384 rows (55 keyframes of 300) minimises the estimated sum: 2.6 ms of seals per keyframe,
# 2 ms of tail per query on floor-like crowding (8192: 5.2 + 1)
SEAL_ROWS = 16384


@dataclass(frozen=True)
class RetrievalConfig(Config):
    """Keyframe retrieval by descriptor voting."""

    max_hamming_bits: float = setting(50.0, unit="bits", gt=0, le=256,
                                      doc="a vote needs a nearest-neighbour distance below this (of 256 bits)")
    ratio: float = setting(0.8, gt=0, le=1, doc="nearest / second-nearest distance bound (Lowe ratio test)")
    min_votes: int = setting(8, unit="votes", ge=0, le=1_000_000, doc="keyframes with fewer votes are not returned")
    max_descriptors_per_keyframe: int = setting(300, unit="descriptors", ge=1, le=100_000,
                                                doc="only the strongest keypoints with depth are stored and queried "
                                                    "(bounds the search cost)")
    exact_below_descriptors: int = setting(
        30_000, unit="descriptors", ge=0, le=1 << 40,
        doc="queries over a database smaller than this are brute force (exact); larger ones use the hash index")
    hash_tables: int = setting(16, unit="tables", ge=1, le=64,
                               doc="hash tables of the index (more: higher recall, slower queries)")
    # 256 on the 5000-frame floor walks: rows compared per query descriptor over the last 160 keyframes 2500 -> 430
    # (250 over the first 250), retrieval 13.8 -> 4.7 ms per frame over the last 500 frames, 97.5 % of the retrieved
    # keyframes kept; floor3 1.81 -> 1.83 cm, but floor0 1.79 cm -> 2.9 m with 7 lost segments: not the default
    hash_bucket_rows: int = setting(
        0, unit="rows", ge=0, le=hamming_hash.COUNT_MAX - 1,  # the buckets' counts saturate at COUNT_MAX
        doc="a hash bucket of more rows than this is a common appearance (a stop word): it is not searched, the query "
            "descriptor's other buckets are, so a query compares at most hash_tables x this rows per descriptor "
            "whatever the map size (0: no bound)")
    hash_key_bits: int = setting(
        16, unit="bits", ge=1, le=_MAX_KEY_BITS,
        doc="sampled bits per hash key when the index starts; one more each time the database doubles (up to 20), so "
            "the buckets keep their size as keyframes accumulate (more bits: faster queries, lower recall)")


def select_descriptors(descriptors: np.ndarray, response: np.ndarray, valid: np.ndarray, n_max: int) -> np.ndarray:
    """The ``n_max`` strongest valid-depth descriptors ``(<= n_max, 32)``, in their original order."""
    idx = np.flatnonzero(valid)
    if len(idx) > n_max:
        strongest = np.lexsort((idx, -response[idx]))[:n_max]
        idx = np.sort(idx[strongest])
    return descriptors[idx]


def hash_bit_positions(descriptors: np.ndarray, n_tables: int, key_bits: int, seed: int = _HASH_SEED) -> np.ndarray:
    """``(n_tables, key_bits)`` int64 distinct bit positions per table, drawn (from ``seed``) among the
    ``_BALANCED_BITS`` bits of ``descriptors`` ``(N, 32)`` uint8 whose share of ones is nearest one half."""
    ones = np.unpackbits(np.asarray(descriptors, np.uint8), axis=1, bitorder="little").mean(axis=0)
    pool = np.argsort(np.abs(ones - 0.5), kind="stable")[: max(_BALANCED_BITS, key_bits)]
    rng = np.random.default_rng(seed)
    return np.stack([rng.choice(pool, key_bits, replace=False) for _ in range(n_tables)]).astype(np.int64)


class DescriptorIndex:
    """Database of keyframe descriptors with voting queries (brute force while small, then hashed)."""

    def __init__(self, cfg: RetrievalConfig | None = None) -> None:
        self.cfg = cfg or RetrievalConfig()
        self._desc = np.zeros((_INITIAL_CAPACITY, _DESCRIPTOR_BYTES), np.uint8)
        self._owner = np.zeros(_INITIAL_CAPACITY, np.int64)
        # (4, capacity) uint64 the rows' words, word-major, for the brute-force search; dropped once hashed (then the
        # rare brute-force queries of a prefix below the threshold use the rows)
        self._columns: np.ndarray | None = np.zeros((_DESCRIPTOR_BYTES // 8, _INITIAL_CAPACITY), np.uint64)
        self._n = 0
        self._kf_end: list[int] = []  # database rows [0, _kf_end[k]) belong to keyframes 0..k
        # the hash tables, made once the database reaches exact_below_descriptors rows (:meth:`_build_tables`)
        self._bits: np.ndarray | None = None  # (tables, key bits) bit positions
        self._rebuild_at = 0  # rows at which the tables are rebuilt with one more key bit
        self._start = np.zeros((0, 0), np.int32)  # (tables, 2 ** key bits + 1) where each bucket's sealed rows start
        self._rows = np.zeros((0, 0), np.int32)  # (tables, capacity) the sealed rows, bucket after bucket
        self._n_sealed = 0  # rows [0, _n_sealed) are sealed, the rest are the tail
        self._head = np.zeros((0, 0), np.int32)  # (tables, 2 ** key bits) newest tail row of each bucket
        self._next = np.zeros((0, 0), np.int32)  # (tables, tail capacity) the older tail row after each in its bucket
        self._count = np.zeros((0, 0), np.uint16)  # (tables, 2 ** key bits) rows of each bucket (saturating)
        self._compared = np.zeros(1, np.int64)  # rows compared by the hashed queries so far

    @property
    def n_keyframes(self) -> int:
        return len(self._kf_end)

    @property
    def hashed(self) -> bool:
        """Whether the hash tables exist (the database has reached ``exact_below_descriptors`` rows)."""
        return self._bits is not None

    def add(self, descriptors: np.ndarray) -> int:
        """Append the next keyframe's ``(N, 32)`` uint8 descriptors; returns its keyframe id."""
        d = np.asarray(descriptors, np.uint8).reshape(-1, _DESCRIPTOR_BYTES)
        need = self._n + len(d)
        if need > len(self._desc):
            cap = len(self._desc)
            while cap < need:
                cap *= 2
            self._desc = _grown(self._desc, self._n, cap)
            self._owner = _grown(self._owner, self._n, cap)
            if self._columns is not None:
                self._columns = _grown(self._columns.T, self._n, cap).T.copy()
            if self.hashed:  # grown along rows: each table's sealed rows stay contiguous
                rows = np.zeros((len(self._rows), cap), np.int32)
                rows[:, : self._n_sealed] = self._rows[:, : self._n_sealed]
                self._rows = rows
        kf = len(self._kf_end)
        self._desc[self._n : need] = d
        self._owner[self._n : need] = kf
        if self._columns is not None:
            self._columns[:, self._n : need] = hamming.as_words(d).T
        if self.hashed:
            if need - self._n_sealed > self._next.shape[1]:
                nxt = np.zeros((len(self._next), 2 * (need - self._n_sealed)), np.int32)
                nxt[:, : self._n - self._n_sealed] = self._next[:, : self._n - self._n_sealed]
                self._next = nxt
            hamming_hash.insert_rows(self._keys(d), self._n, self._head, self._next, self._count, self._n_sealed)
        self._n = need
        self._kf_end.append(need)
        if not self.hashed and need >= self.cfg.exact_below_descriptors:
            self._build_tables(self.cfg.hash_key_bits)
        elif self.hashed and need >= self._rebuild_at:
            self._build_tables(self.key_bits + 1)
        elif self.hashed and need - self._n_sealed >= SEAL_ROWS:
            self._seal()
        return kf

    @property
    def rows_compared(self) -> int:
        """Rows the hashed queries have compared so far (their work; brute-force queries are not counted)."""
        return int(self._compared[0])

    @property
    def key_bits(self) -> int:
        """Bits of the hash keys now (0 before the tables exist)."""
        return 0 if self._bits is None else self._bits.shape[1]

    def _build_tables(self, key_bits: int) -> None:
        """(Re)make the tables with ``key_bits``-bit keys, their bit positions drawn from the rows so far, and seal
        every row in them; the next rebuild (one more bit) comes when the rows have doubled."""
        cfg = self.cfg
        self._columns = None
        self._bits = hash_bit_positions(self._desc[: self._n], cfg.hash_tables, key_bits)
        keys = self._keys(self._desc[: self._n])
        self._head = np.full((cfg.hash_tables, 1 << key_bits), hamming_hash.NO_ROW, np.int32)
        self._next = np.zeros((cfg.hash_tables, SEAL_ROWS), np.int32)
        self._start = np.zeros((cfg.hash_tables, (1 << key_bits) + 1), np.int32)
        self._rows = np.zeros((cfg.hash_tables, len(self._desc)), np.int32)
        self._n_sealed = 0
        self._seal(keys)
        self._count = np.empty((cfg.hash_tables, 1 << key_bits), np.uint16)
        for t in range(cfg.hash_tables):  # every row is sealed: a bucket's count is its run's length (saturated)
            self._count[t] = np.minimum(np.diff(self._start[t]), hamming_hash.COUNT_MAX)
        self._rebuild_at = 2 * max(self._n, 1) if key_bits < _MAX_KEY_BITS else np.iinfo(np.int64).max

    def _seal(self, keys: np.ndarray | None = None) -> None:
        """Move the tail rows into the sealed part of the tables (``keys``: theirs, ``(tail, tables)``, if known)."""
        if keys is None:
            keys = self._keys(self._desc[self._n_sealed : self._n])
        hamming_hash.seal_rows(keys, self._n_sealed, self._start, self._rows, self._head)
        self._n_sealed = self._n

    def query(self, descriptors: np.ndarray, n_results: int, before_kf: int | None = None) -> list[tuple[int, int]]:
        """Best keyframes for a query frame.

        Args:
            descriptors: ``(N, 32)`` uint8 query descriptors.
            n_results: at most this many keyframes are returned.
            before_kf: only keyframes with id ``< before_kf`` vote (``None``: all).

        Returns:
            ``[(kf_id, votes), ...]`` sorted by votes descending, then id ascending.
        """
        k_max = self.n_keyframes if before_kf is None else min(before_kf, self.n_keyframes)
        if k_max <= 0 or n_results <= 0 or len(descriptors) == 0:
            return []
        end = self._kf_end[k_max - 1]
        if end < 2:
            return []
        d1, d2, idx = self._nearest_two(np.asarray(descriptors, np.uint8), end)
        good = (d1 < self.cfg.max_hamming_bits) & (d1 < self.cfg.ratio * d2)
        owners = self._owner[idx[good]]
        votes = np.bincount(owners, minlength=k_max)
        order = np.lexsort((np.arange(k_max), -votes))
        return [(int(k), int(votes[k])) for k in order[:n_results] if votes[k] >= self.cfg.min_votes]

    def _keys(self, descriptors: np.ndarray) -> np.ndarray:
        """``(N, hash_tables)`` int64 hash keys of ``(N, 32)`` uint8 descriptors."""
        keys = np.empty((len(descriptors), len(self._bits)), np.int64)
        hamming_hash.hash_keys(hamming.as_words(descriptors), self._bits, keys)
        return keys

    def _nearest_two(self, descriptors: np.ndarray, end: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(best_d, second_d, best_idx)`` ``(N,)`` of the query over database rows ``[0, end)``: brute force below
        ``exact_below_descriptors`` rows, else through the hash tables."""
        words = hamming.as_words(descriptors)
        if self._columns is not None:
            return hamming.nearest_two_columns_words(words, self._columns, end)
        if not self.hashed or end < self.cfg.exact_below_descriptors:
            return hamming.nearest_two_words(words, hamming.as_words(self._desc[:end]))
        n = len(words)
        best_d, second_d, best_idx = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.int64)
        hamming_hash.nearest_two_hashed(words, self._keys(descriptors), hamming.as_words(self._desc), self._start,
                                        self._rows, self._head, self._next, self._n_sealed, self._count, end,
                                        self.cfg.hash_bucket_rows, best_d, second_d, best_idx, self._compared)
        return best_d, second_d, best_idx


def _grown(a: np.ndarray, n: int, cap: int) -> np.ndarray:
    """A copy of ``a`` with ``cap`` rows (zeros after the first ``n``, which are copied)."""
    out = np.zeros((cap,) + a.shape[1:], a.dtype)
    out[:n] = a[:n]
    return out
