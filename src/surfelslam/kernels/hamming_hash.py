"""Hashed Hamming nearest neighbours of binary descriptors (numba): locality-sensitive hashing by bit sampling.

Each of ``T`` tables keys a descriptor by ``B`` of its bits (fixed positions, drawn once). Descriptors within a small
Hamming distance agree on all ``B`` sampled bits with a high probability (``(1 - d / 256) ** B`` per table for ORB's
256 bits), so a query compares itself only with the rows that share its key in at least one table, not with the
whole database. Each table is an array of bucket heads plus one "next row" link per database row (a linked list per
bucket, newest row first): appending a row is O(T), and a query costs ``T x`` the bucket sizes, about
``T N / 2 ** B`` rows for ``N`` rows, against ``N`` for brute force.

:func:`nearest_two_hashed` returns what :func:`surfelslam.kernels.hamming.nearest_two` returns, over the rows it
reaches: the nearest one is found with that probability, and the second-nearest distance is an upper bound of the
exact one.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from surfelslam.kernels.hamming import NO_MATCH, popcount64

NO_ROW = -1  # end of a bucket's list
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
def insert_rows(keys, row0, head, next_row):
    """Append rows ``row0 .. row0 + len(keys) - 1`` (keys ``(n, T)`` int64) to the buckets: each becomes the head of
    its bucket in every table. ``head``: ``(T, 2 ** B)`` int32; ``next_row``: ``(T, >= row0 + n)`` int32 (rows
    below ``2 ** 31``)."""
    for i in range(keys.shape[0]):
        r = row0 + i
        for t in range(keys.shape[1]):
            k = keys[i, t]
            next_row[t, r] = head[t, k]
            head[t, k] = r


@njit(cache=True, nogil=True)
def nearest_two_hashed(query, query_keys, train, head, next_row, end, max_bucket_rows, best_d, second_d, best_idx):
    """For each query row, the two smallest Hamming distances to the train rows ``< end`` that share one of its keys,
    and the nearest such row (the lowest index on ties, as in brute force); ``NO_MATCH`` / -1 where none.

    Args:
        query: ``(N, W)`` uint64; query_keys: ``(N, T)`` int64 (:func:`hash_keys`).
        train: ``(M, W)`` uint64; head, next_row: the tables (:func:`insert_rows`) over ``train``'s rows.
        end: only rows ``< end`` are candidates (a prefix of the database).
        max_bucket_rows: a query row one of whose buckets holds more candidate rows than this is a common
            appearance (a stop word): its second distance is set to its best, so no ratio test passes (0: no bound).
            Bounds the cost of a query row to ``T x max_bucket_rows`` whatever the database size.
        best_d, second_d, best_idx: ``(N,)`` int64 outputs.

    A row reached through several tables is compared each time; only its repeat as the nearest row needs a guard
    (its equal distance would otherwise also become the second-nearest).
    """
    n_words = query.shape[1]
    for i in range(query.shape[0]):
        b1 = NO_MATCH
        b2 = NO_MATCH
        bi = -1
        common = False
        for t in range(query_keys.shape[1]):
            r = head[t, query_keys[i, t]]
            seen = 0
            while r != NO_ROW:
                if r < end:
                    seen += 1
                    if max_bucket_rows > 0 and seen > max_bucket_rows:
                        common = True
                        break
                    if r != bi:
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
            if common:
                break
        best_d[i] = b1
        second_d[i] = b1 if common else b2
        best_idx[i] = bi
