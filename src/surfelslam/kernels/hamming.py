"""Hamming nearest neighbours of binary descriptors, brute force or guided by predicted pixels (numba), with numpy
references.

ORB descriptors are 256 bits = 32 bytes, read as four 64-bit words; the distance of two descriptors is the
number of set bits of their XOR (a SWAR popcount, which LLVM turns into the CPU's popcount instruction).
:func:`nearest_two` gives, for every query descriptor, the smallest and second-smallest distance over the train
set and the index of the nearest one (the first one on ties), i.e. what a cross-check or a ratio test needs: the
same results as OpenCV's ``BFMatcher`` (tested), in less time (``benchmarks/bench_orb.py`` times both).
:func:`nearest_mutual_within` compares each query only with the train rows within a radius of its predicted pixel
(a grid of the train keypoints), not with all of them.
"""

from __future__ import annotations

import numpy as np
from numba import njit

NO_MATCH = np.iinfo(np.int64).max  # distance reported when the train set has fewer than 1 (2) descriptors

_M1 = np.uint64(0x5555555555555555)
_M2 = np.uint64(0x3333333333333333)
_M4 = np.uint64(0x0F0F0F0F0F0F0F0F)
_H01 = np.uint64(0x0101010101010101)
_ORB_WORDS = 4  # 64-bit words of an ORB descriptor (256 bits): the unrolled case of _distances


@njit(cache=True, nogil=True)
def _popcount64(x):
    x = x - ((x >> np.uint64(1)) & _M1)
    x = (x & _M2) + ((x >> np.uint64(2)) & _M2)
    x = (x + (x >> np.uint64(4))) & _M4
    return (x * _H01) >> np.uint64(56)


popcount64 = _popcount64  # set bits of a uint64 (njit), for the other descriptor kernels (hamming_hash)


@njit(cache=True, nogil=True)
def _distances(query, i, train, d):
    """``d[j]`` = Hamming distance of ``query[i]`` to every ``train[j]``: a branch-free loop of its own, which LLVM
    vectorises (unrolled for the words of an ORB descriptor: 2.2 ms for 1000 x 1000, against 3.0 ms generic)."""
    m = train.shape[0]
    if query.shape[1] == _ORB_WORDS:
        q0, q1, q2, q3 = query[i, 0], query[i, 1], query[i, 2], query[i, 3]
        for j in range(m):
            d[j] = (int(_popcount64(q0 ^ train[j, 0])) + int(_popcount64(q1 ^ train[j, 1]))
                    + int(_popcount64(q2 ^ train[j, 2])) + int(_popcount64(q3 ^ train[j, 3])))
        return
    for j in range(m):
        s = 0
        for w in range(query.shape[1]):
            s += int(_popcount64(query[i, w] ^ train[j, w]))
        d[j] = s


@njit(cache=True, nogil=True)
def _search(query, train, best_d, second_d, best_idx, col_idx, columns):
    """The brute-force pass of :func:`nearest_two` and :func:`nearest_two_mutual` (``columns``: also fill
    ``col_idx``; a literal at each call site). One loop for both, so the two cannot drift apart. Each query row's
    distances are computed first, then scanned: about twice as fast as one loop doing both."""
    m = train.shape[0]
    col_d = np.full(m if columns else 0, NO_MATCH, np.int64)
    d = np.empty(m, np.int64)
    if columns:
        for j in range(m):
            col_idx[j] = -1
    for i in range(query.shape[0]):
        _distances(query, i, train, d)
        best_d[i], second_d[i], best_idx[i] = _scan(d, m, i, columns, col_d, col_idx)


@njit(cache=True, nogil=True)
def _scan(d, m, i, columns, col_d, col_idx):
    """The two smallest of the distances ``d[:m]`` of query row ``i`` and the first index of the smallest; with
    ``columns``, each train row's nearest query row so far (``col_d``, ``col_idx``) takes row ``i`` where nearer."""
    b1 = NO_MATCH
    b2 = NO_MATCH
    bi = -1
    for j in range(m):
        dj = d[j]
        if dj < b2:  # rarely true: one well-predicted branch for most rows
            if dj < b1:
                b2 = b1
                b1 = dj
                bi = j
            else:
                b2 = dj
        if columns and dj < col_d[j]:
            col_d[j] = dj
            col_idx[j] = i
    return b1, b2, bi


@njit(cache=True, nogil=True)
def nearest_two(query, train, best_d, second_d, best_idx):
    """For each row of ``query`` the two smallest Hamming distances to ``train`` rows and the nearest index.

    Args:
        query: ``(N, W)`` uint64 descriptors (W words each); train: ``(M, W)`` uint64.
        best_d, second_d: ``(N,)`` int64 outputs (``NO_MATCH`` where ``M`` < 1 / < 2).
        best_idx: ``(N,)`` int64 output, index into ``train`` of the first nearest row (-1 when ``M`` = 0).
    """
    _search(query, train, best_d, second_d, best_idx, np.empty(0, np.int64), False)


@njit(cache=True, nogil=True)
def _search_columns(query, train_columns, m, best_d, second_d, best_idx, col_idx, columns):
    """:func:`_search` of ORB descriptors (4 words) against a train set stored word-major: ``train_columns``
    ``(4, >= m)`` uint64, column ``j < m`` holding train row ``j``. Each word's loop then reads contiguous memory,
    which LLVM vectorises: about half the time of the row-major search, with the same results."""
    col_d = np.full(m if columns else 0, NO_MATCH, np.int64)
    d = np.empty(m, np.int64)
    if columns:
        for j in range(m):
            col_idx[j] = -1
    t0, t1, t2, t3 = train_columns[0], train_columns[1], train_columns[2], train_columns[3]
    for i in range(query.shape[0]):
        q0, q1, q2, q3 = query[i, 0], query[i, 1], query[i, 2], query[i, 3]
        for j in range(m):
            d[j] = (int(_popcount64(q0 ^ t0[j])) + int(_popcount64(q1 ^ t1[j])) + int(_popcount64(q2 ^ t2[j]))
                    + int(_popcount64(q3 ^ t3[j])))
        best_d[i], second_d[i], best_idx[i] = _scan(d, m, i, columns, col_d, col_idx)


@njit(cache=True, nogil=True)
def nearest_two_columns(query, train_columns, m, best_d, second_d, best_idx):
    """:func:`nearest_two` of ORB descriptors (``query`` ``(N, 4)`` uint64) against the first ``m`` columns of a
    word-major train set ``(4, >= m)`` (see :func:`_search_columns`): what a growing database keeps."""
    _search_columns(query, train_columns, m, best_d, second_d, best_idx, np.empty(0, np.int64), False)


@njit(cache=True, nogil=True)
def nearest_two_mutual(query, train, best_d, second_d, best_idx, col_idx):
    """:func:`nearest_two` plus, in the same pass, each train row's nearest query row (for a cross-check).

    Every distance is computed once instead of once per direction. ``col_idx``: ``(M,)`` int64 output, the first
    query row at the smallest distance to each train row (-1 when ``N`` = 0): exactly ``best_idx`` of
    ``nearest_two(train, query)``.
    """
    _search(query, train, best_d, second_d, best_idx, col_idx, True)


@njit(cache=True, nogil=True)
def nearest_mutual_within(query, pred_uv, train, train_uv, cell_start, cell_order, cell_px, n_cols, n_rows,
                          radius_px, best_d, best_idx, col_idx):
    """Guided matching: for each query row, its nearest train row among those within ``radius_px`` of its predicted
    pixel, and for each train row its nearest query row among the queries predicted within that radius of it (a
    cross-check restricted to the same discs).

    Args:
        query: ``(N, W)`` uint64; pred_uv: ``(N, 2)`` float64 predicted pixels (non-finite: no candidates).
        train: ``(M, W)`` uint64; train_uv: ``(M, 2)`` float64 keypoint pixels.
        cell_start: ``(n_rows * n_cols + 1,)`` int64 and cell_order: ``(M,)`` int64: train rows grouped by grid
            cell of ``cell_px`` pixels (row-major), see :func:`grid_cells`.
        best_d, best_idx: ``(N,)`` int64 outputs (``NO_MATCH`` / -1 without candidates); col_idx: ``(M,)`` int64
            output (-1 when no query has the train row as a candidate). Ties go to the lowest index, as in
            :func:`nearest_two_mutual`.
    """
    n_words = query.shape[1]
    col_d = np.full(train.shape[0], NO_MATCH, np.int64)
    col_idx[:] = -1
    r2 = radius_px * radius_px
    for i in range(query.shape[0]):
        best_d[i] = NO_MATCH
        best_idx[i] = -1
        pu, pv = pred_uv[i, 0], pred_uv[i, 1]
        if not (np.isfinite(pu) and np.isfinite(pv)):
            continue
        # cells the disc overlaps; points outside the image sit in the border cells, so the range is clamped
        # to the grid (before the int conversion, which could overflow) and the exact distance test decides
        cx0 = int(np.floor(min(max((pu - radius_px) / cell_px, 0.0), n_cols - 1.0)))
        cx1 = int(np.floor(min(max((pu + radius_px) / cell_px, 0.0), n_cols - 1.0)))
        cy0 = int(np.floor(min(max((pv - radius_px) / cell_px, 0.0), n_rows - 1.0)))
        cy1 = int(np.floor(min(max((pv + radius_px) / cell_px, 0.0), n_rows - 1.0)))
        for cy in range(cy0, cy1 + 1):
            for cx in range(cx0, cx1 + 1):
                c = cy * n_cols + cx
                for t in range(cell_start[c], cell_start[c + 1]):
                    j = cell_order[t]
                    du = train_uv[j, 0] - pu
                    dv = train_uv[j, 1] - pv
                    if du * du + dv * dv > r2:
                        continue
                    d = 0
                    for w in range(n_words):
                        d += int(_popcount64(query[i, w] ^ train[j, w]))
                    if d < best_d[i] or (d == best_d[i] and j < best_idx[i]):
                        best_d[i] = d
                        best_idx[i] = j
                    if d < col_d[j]:  # queries come in increasing order: the first one wins ties
                        col_d[j] = d
                        col_idx[j] = i


def grid_cells(uv: np.ndarray, cell_px: float, width: int, height: int):
    """Rows of ``uv (M, 2)`` grouped by square grid cell: ``(cell_start (C + 1,), cell_order (M,), n_cols, n_rows)``
    for :func:`nearest_mutual_within` (points outside the image go to the nearest border cell)."""
    n_cols, n_rows = max(int(np.ceil(width / cell_px)), 1), max(int(np.ceil(height / cell_px)), 1)
    cu = np.clip((uv[:, 0] // cell_px).astype(np.int64), 0, n_cols - 1)
    cv = np.clip((uv[:, 1] // cell_px).astype(np.int64), 0, n_rows - 1)
    cell = cv * n_cols + cu
    order = np.argsort(cell, kind="stable").astype(np.int64)
    start = np.zeros(n_cols * n_rows + 1, np.int64)
    np.cumsum(np.bincount(cell, minlength=n_cols * n_rows), out=start[1:])
    return start, order, n_cols, n_rows


def nearest_mutual_within_words(query_words: np.ndarray, pred_uv: np.ndarray, train_words: np.ndarray,
                                train_uv: np.ndarray, radius_px: float, width: int, height: int):
    """:func:`nearest_mutual_within` on word arrays (see :func:`as_words`) -> ``(best_d, best_idx, col_idx)``;
    the grid's cells are ``radius_px`` wide."""
    n, m = len(query_words), len(train_words)
    best_d, best_idx, col_idx = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(m, np.int64)
    train_uv = np.ascontiguousarray(train_uv, np.float64)
    start, order, n_cols, n_rows = grid_cells(train_uv, float(radius_px), width, height)
    nearest_mutual_within(query_words, np.ascontiguousarray(pred_uv, np.float64), train_words, train_uv, start,
                          order, float(radius_px), n_cols, n_rows, float(radius_px), best_d, best_idx, col_idx)
    return best_d, best_idx, col_idx


def nearest_mutual_within_ref(query: np.ndarray, pred_uv: np.ndarray, train: np.ndarray, train_uv: np.ndarray,
                              radius_px: float):
    """Numpy reference of :func:`nearest_mutual_within_words` on uint8 descriptors (full distance matrix, masked)."""
    n, m = len(query), len(train)
    D = np.unpackbits(np.bitwise_xor(query[:, None, :], train[None, :, :]), axis=2).sum(axis=2).astype(np.int64)
    with np.errstate(invalid="ignore"):
        near = ((pred_uv[:, None, :] - train_uv[None, :, :]) ** 2).sum(axis=2) <= radius_px ** 2  # NaN: False
    D = np.where(near, D, NO_MATCH)
    best_idx = np.where(near.any(axis=1), np.argmin(D, axis=1), -1) if m else np.full(n, -1)
    best_d = np.where(best_idx >= 0, D[np.arange(n), np.maximum(best_idx, 0)], NO_MATCH) if m else np.full(n, NO_MATCH)
    col_idx = np.where(near.any(axis=0), np.argmin(D, axis=0), -1) if n else np.full(m, -1)
    return best_d, best_idx, col_idx


def as_words(descriptors: np.ndarray) -> np.ndarray:
    """``(N, B)`` uint8 descriptors (B a multiple of 8) -> ``(N, B / 8)`` uint64 words (a view when possible)."""
    d = np.ascontiguousarray(descriptors, dtype=np.uint8)
    if d.ndim != 2 or d.shape[1] % 8:
        raise ValueError(f"descriptors must be (N, B) uint8 with B a multiple of 8, got shape {d.shape}")
    return d.view(np.uint64)


def nearest_two_words(query_words: np.ndarray, train_words: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`nearest_two` on word arrays (see :func:`as_words`) -> ``(best_d, second_d, best_idx)``, each ``(N,)``."""
    n = len(query_words)
    best_d = np.empty(n, np.int64)
    second_d = np.empty(n, np.int64)
    best_idx = np.empty(n, np.int64)
    nearest_two(query_words, train_words, best_d, second_d, best_idx)
    return best_d, second_d, best_idx


def nearest_two_columns_words(query_words: np.ndarray, train_columns: np.ndarray, m: int):
    """:func:`nearest_two_columns` on ``(N, 4)`` query words and ``(4, >= m)`` train columns ->
    ``(best_d, second_d, best_idx)``, each ``(N,)``."""
    if query_words.shape[1] != _ORB_WORDS or train_columns.shape[0] != _ORB_WORDS or train_columns.shape[1] < m:
        raise ValueError(f"need (N, {_ORB_WORDS}) query words and ({_ORB_WORDS}, >= {m}) train columns, got "
                         f"{query_words.shape} and {train_columns.shape}")
    n = len(query_words)
    best_d, second_d, best_idx = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.int64)
    nearest_two_columns(query_words, train_columns, int(m), best_d, second_d, best_idx)
    return best_d, second_d, best_idx


def nearest_two_mutual_words(query_words: np.ndarray, train_words: np.ndarray):
    """:func:`nearest_two_mutual` on word arrays -> ``(best_d, second_d, best_idx, col_idx)``."""
    n, m = len(query_words), len(train_words)
    best_d = np.empty(n, np.int64)
    second_d = np.empty(n, np.int64)
    best_idx = np.empty(n, np.int64)
    col_idx = np.empty(m, np.int64)
    if query_words.shape[1] == _ORB_WORDS and train_words.shape[1] == _ORB_WORDS:
        _search_columns(query_words, np.ascontiguousarray(train_words.T), m, best_d, second_d, best_idx, col_idx, True)
    else:
        nearest_two_mutual(query_words, train_words, best_d, second_d, best_idx, col_idx)
    return best_d, second_d, best_idx, col_idx


def nearest_two_ref(query: np.ndarray, train: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Numpy reference on ``(N, B)`` / ``(M, B)`` uint8 descriptors: the full distance matrix by bit unpacking."""
    n = len(query)
    if len(train) == 0:
        return np.full(n, NO_MATCH), np.full(n, NO_MATCH), np.full(n, -1)
    x = np.bitwise_xor(query[:, None, :], train[None, :, :])
    D = np.unpackbits(x, axis=2).sum(axis=2).astype(np.int64)  # (N, M)
    idx = np.argmin(D, axis=1)  # first minimum on ties
    best = D[np.arange(n), idx]
    if train.shape[0] < 2:
        return best, np.full(n, NO_MATCH), idx
    D2 = D.copy()
    D2[np.arange(n), idx] = np.iinfo(np.int64).max
    return best, D2.min(axis=1), idx
