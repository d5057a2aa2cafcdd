"""Hashed Hamming nearest neighbours of binary descriptors (numba): locality-sensitive hashing by bit sampling.

Each of ``T`` tables keys a descriptor by ``B`` of its bits (fixed positions, drawn once). Descriptors within a small
Hamming distance agree on all ``B`` sampled bits with a high probability (``(1 - d / 256) ** B`` per table for ORB's
256 bits), so a query compares itself only with the rows that share its key in at least one table, not with the
whole database. A query costs ``T x`` the bucket sizes, about ``T N / 2 ** B`` rows for ``N`` rows, against ``N`` for
brute force.

Each table keeps its rows in two parts. The *sealed* rows are stored bucket after bucket (compressed rows: a start
offset per key, then each bucket's row numbers ascending), so a query reads a bucket as one contiguous run; the rows
added since the last seal (the *tail*) are a linked list per bucket (a head per key, a "next row" link per tail row,
newest first), so appending a row is O(T). :func:`seal_rows` moves the tail into the sealed part. The linked walk
costs a cache miss per link besides the row's descriptor: on a floor-sized database whose common appearances crowd
buckets with thousands of rows, a query walked them at about 7x the cost of the contiguous runs.

:func:`nearest_two_hashed` returns what :func:`surfelslam.kernels.hamming.nearest_two` returns, over the rows it
reaches: the nearest one is found with that probability, and the second-nearest distance is an upper bound of the
exact one. Each bucket also counts its rows (saturating at :data:`COUNT_MAX`), so a crowded bucket (a common
appearance, whose rows are a large share of the database) can be left out before any of its rows is walked.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from surfelslam.kernels.hamming import NO_MATCH, popcount64

NO_ROW = -1  # end of a bucket's list
COUNT_MAX = np.iinfo(np.uint16).max  # a bucket's row count saturates here (uint16 counts: half the heads' memory)
_WORD_BITS = 64


@njit(cache=True, nogil=True)
def hash_keys(words, bit_pos, keys_out):
    """Keys of descriptors: ``keys_out[i, t]`` packs the bits ``bit_pos[t, :]`` of ``words[i]``.

    Args:
        words: ``(N, W)`` uint64 descriptors; bit_pos: ``(T, B)`` int64 bit positions in ``[0, 64 W)``.
        keys_out: ``(N, T)`` int64 output, each in ``[0, 2 ** B)``.
    """
    for i in range(words.shape[0]):
        for t in range(bit_pos.shape[0]):
            key = 0
            for b in range(bit_pos.shape[1]):
                p = bit_pos[t, b]
                bit = (words[i, p // _WORD_BITS] >> np.uint64(p % _WORD_BITS)) & np.uint64(1)
                key = (key << 1) | int(bit)
            keys_out[i, t] = key


@njit(cache=True, nogil=True)
def insert_rows(keys, row0, head, next_row, count, base):
    """Append rows ``row0 .. row0 + len(keys) - 1`` (keys ``(n, T)`` int64) to the tail: each becomes the head of
    its bucket in every table. ``head``: ``(T, 2 ** B)`` int32; ``next_row``: ``(T, >= row0 + n - base)`` int32, the
    link of tail row ``r`` at ``r - base`` (``base``: the first tail row; rows below ``2 ** 31``); ``count``:
    ``(T, 2 ** B)`` uint16 rows per bucket (sealed and tail), saturating at :data:`COUNT_MAX`."""
    for i in range(keys.shape[0]):
        r = row0 + i
        for t in range(keys.shape[1]):
            k = keys[i, t]
            next_row[t, r - base] = head[t, k]
            head[t, k] = r
            if count[t, k] < COUNT_MAX:
                count[t, k] += 1


@njit(cache=True, nogil=True)
def seal_rows(keys, row0, start, rows, head):
    """Move the tail rows ``row0 .. row0 + len(keys) - 1`` (keys ``(n, T)`` int64, the rows after the sealed ones)
    into the sealed part, in place, and empty their buckets' tail lists.

    Args:
        keys: ``(n, T)`` int64 the tail rows' keys.
        row0: the number of sealed rows (the first tail row).
        start: ``(T, 2 ** B + 1)`` int32; bucket ``k`` of table ``t`` holds ``rows[t, start[t, k]:start[t, k + 1]]``
            (``start[t, 2 ** B]`` = ``row0`` before, ``row0 + n`` after).
        rows: ``(T, >= row0 + n)`` int32 sealed row numbers, ascending within each bucket.
        head: ``(T, 2 ** B)`` int32 the tail lists' heads: those of the tail rows' buckets are reset to :data:`NO_ROW`.

    O(T (2 ** B + row0 + n)): each table's buckets are shifted right (from the last one down, so that no row is
    overwritten before it is read) to make room for their tail rows, which are appended in ascending order.
    """
    n = keys.shape[0]
    n_keys = start.shape[1] - 1
    added = np.zeros(n_keys, np.int32)
    for t in range(keys.shape[1]):
        added[:] = 0
        for i in range(n):
            added[keys[i, t]] += 1
        shift = n  # tail rows of the buckets below k, counted down from all of them
        old_next = start[t, n_keys]
        start[t, n_keys] = old_next + n
        for k in range(n_keys - 1, -1, -1):
            shift -= added[k]
            old_k = start[t, k]
            if shift > 0:
                for p in range(old_next - 1, old_k - 1, -1):
                    rows[t, p + shift] = rows[t, p]
            start[t, k] = old_k + shift
            old_next = old_k
        for i in range(n):  # the tail rows after each bucket's sealed ones, ascending
            k = keys[i, t]
            rows[t, start[t, k + 1] - added[k]] = row0 + i
            added[k] -= 1
            head[t, k] = NO_ROW


@njit(cache=True, nogil=True)
def nearest_two_hashed(query, query_keys, train, start, rows, head, next_row, base, count, end, max_bucket_rows,
                       best_d, second_d, best_idx, compared):
    """For each query row, the two smallest Hamming distances to the train rows ``< end`` that share one of its keys,
    and the nearest such row (the lowest index on ties, as in brute force); ``NO_MATCH`` / -1 where none. The result
    does not depend on the order in which the rows are met.

    Args:
        query: ``(N, W)`` uint64; query_keys: ``(N, T)`` int64 (:func:`hash_keys`).
        train: ``(M, W)`` uint64; the tables over ``train``'s rows: ``start``, ``rows`` the sealed part
            (:func:`seal_rows`), ``head``, ``next_row`` the tail (:func:`insert_rows`, first tail row ``base``) and
            ``count``.
        end: only rows ``< end`` are candidates (a prefix of the database).
        max_bucket_rows: a bucket of more rows than this (its count: every row of the database) is a common appearance
            (a stop word) and is not walked; the query row's other buckets are. Bounds the cost of a query row to
            ``T x max_bucket_rows`` compared rows whatever the database size (0: no bound).
        best_d, second_d, best_idx: ``(N,)`` int64 outputs.
        compared: ``(1,)`` int64, incremented by the number of rows compared (the query's work).

    A row reached through several tables is compared each time; only its repeat as the nearest row needs a guard
    (its equal distance would otherwise also become the second-nearest).
    """
    for i in range(query.shape[0]):
        b1 = NO_MATCH
        b2 = NO_MATCH
        bi = -1
        for t in range(query_keys.shape[1]):
            k = query_keys[i, t]
            if max_bucket_rows > 0 and count[t, k] > max_bucket_rows:
                continue
            for p in range(start[t, k], start[t, k + 1]):
                r = rows[t, p]
                if r >= end:
                    break  # ascending: the rest are beyond the prefix too
                if r != bi:
                    b1, b2, bi = _compared(query, i, train, r, b1, b2, bi, compared)
            r = head[t, k]
            while r != NO_ROW:
                if r < end and r != bi:
                    b1, b2, bi = _compared(query, i, train, r, b1, b2, bi, compared)
                r = next_row[t, r - base]
        best_d[i] = b1
        second_d[i] = b2
        best_idx[i] = bi


@njit(cache=True, nogil=True, inline="always")
def _compared(query, i, train, r, b1, b2, bi, compared):
    """``(b1, b2, bi)`` after comparing query row ``i`` with train row ``r`` (counted in ``compared``)."""
    compared[0] += 1
    d = 0
    for w in range(query.shape[1]):
        d += int(popcount64(query[i, w] ^ train[r, w]))
    if d < b1 or (d == b1 and r < bi):
        return d, b1, r
    if d < b2:
        return b1, d, bi
    return b1, b2, bi
