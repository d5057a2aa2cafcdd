"""Hashed Hamming nearest neighbours of binary descriptors (numba): locality-sensitive hashing by bit sampling.

Each of ``T`` tables keys a descriptor by ``B`` of its bits (fixed positions, drawn once). Descriptors within a small
Hamming distance agree on all ``B`` sampled bits with a high probability (``(1 - d / 256) ** B`` per table for ORB's
256 bits), so a query compares itself only with the rows that share its key in at least one table, not with the
whole database. Each table is an array of bucket heads plus one "next row" link per database row (a linked list per
bucket, newest row first): appending a row is O(T), and a query costs ``T x`` the bucket sizes, about
``T N / 2 ** B`` rows for ``N`` rows, against ``N`` for brute force.

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
def insert_rows(keys, row0, head, next_row, count):
    """Append rows ``row0 .. row0 + len(keys) - 1`` (keys ``(n, T)`` int64) to the buckets: each becomes the head of
    its bucket in every table. ``head``: ``(T, 2 ** B)`` int32; ``next_row``: ``(T, >= row0 + n)`` int32 (rows
    below ``2 ** 31``); ``count``: ``(T, 2 ** B)`` uint16 rows per bucket, saturating at :data:`COUNT_MAX`."""
    for i in range(keys.shape[0]):
        r = row0 + i
        for t in range(keys.shape[1]):
            k = keys[i, t]
            next_row[t, r] = head[t, k]
            head[t, k] = r
            if count[t, k] < COUNT_MAX:
                count[t, k] += 1


@njit(cache=True, nogil=True)
def nearest_two_hashed(query, query_keys, train, head, next_row, count, end, max_bucket_rows, best_d, second_d,
                       best_idx, compared):
    """For each query row, the two smallest Hamming distances to the train rows ``< end`` that share one of its keys,
    and the nearest such row (the lowest index on ties, as in brute force); ``NO_MATCH`` / -1 where none.

    Args:
        query: ``(N, W)`` uint64; query_keys: ``(N, T)`` int64 (:func:`hash_keys`).
        train: ``(M, W)`` uint64; head, next_row, count: the tables (:func:`insert_rows`) over ``train``'s rows.
        end: only rows ``< end`` are candidates (a prefix of the database).
        max_bucket_rows: a bucket of more rows than this (its count: every row of the database) is a common appearance
            (a stop word) and is not walked; the query row's other buckets are. Bounds the cost of a query row to
            ``T x max_bucket_rows`` compared rows whatever the database size (0: no bound).
        best_d, second_d, best_idx: ``(N,)`` int64 outputs.
        compared: ``(1,)`` int64, incremented by the number of rows compared (the query's work).

    A row reached through several tables is compared each time; only its repeat as the nearest row needs a guard
    (its equal distance would otherwise also become the second-nearest).
    """
    n_words = query.shape[1]
    for i in range(query.shape[0]):
        b1 = NO_MATCH
        b2 = NO_MATCH
        bi = -1
        for t in range(query_keys.shape[1]):
            k = query_keys[i, t]
            if max_bucket_rows > 0 and count[t, k] > max_bucket_rows:
                continue
            r = head[t, k]
            while r != NO_ROW:
                if r < end and r != bi:
                    compared[0] += 1
                    d = 0
                    for w in range(n_words):
                        d += int(popcount64(query[i, w] ^ train[r, w]))
                    if d < b1 or (d == b1 and r < bi):
                        b2 = b1
                        b1 = d
                        bi = r
                    elif d < b2:
                        b2 = d
                r = next_row[t, r]
        best_d[i] = b1
        second_d[i] = b2
        best_idx[i] = bi
