"""The keyframe retrieval index: hashed nearest neighbours against brute force, and the votes they give."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from surfelslam.backend import place_recognition
from surfelslam.backend.place_recognition import DescriptorIndex, RetrievalConfig, hash_bit_positions
from surfelslam.kernels import hamming, hamming_hash

HASHED = replace(RetrievalConfig(), exact_below_descriptors=0)  # hashed from the first keyframe on


def _noisy(desc: np.ndarray, n_bits: int, rng: np.random.Generator) -> np.ndarray:
    """``desc`` ``(N, 32)`` with ``n_bits`` distinct random bits of every row flipped."""
    bits = np.unpackbits(desc, axis=1)
    for row in bits:
        row[rng.choice(256, n_bits, replace=False)] ^= 1
    return np.packbits(bits, axis=1)


def _planted(n_kf: int = 60, kf: int = 17, seed: int = 0):
    """``n_kf`` keyframes of 200 random descriptors, and a query made of keyframe ``kf``'s with 12 of 256 bits
    flipped."""
    rng = np.random.default_rng(seed)
    kfs = [rng.integers(0, 256, (200, 32), dtype=np.uint8) for _ in range(n_kf)]
    return kfs, _noisy(kfs[kf], 12, rng)


def test_hashed_search_equals_brute_force_where_it_finds_the_nearest() -> None:
    kfs, q = _planted()
    idx = DescriptorIndex(HASHED)
    for d in kfs:
        idx.add(d)
    assert idx.hashed
    db = np.concatenate(kfs)
    e1, e2, ei = hamming.nearest_two_ref(q, db)
    h1, h2, hi = idx._nearest_two(q, len(db))
    # 12 flipped bits: the planted neighbour shares a 20-bit key (grown from 16 over 6 doublings) in one of 16 tables
    # with probability > 0.999
    found = hi == ei
    assert found.mean() > 0.98
    np.testing.assert_array_equal(h1[found], e1[found])
    assert np.all(h1 >= e1) and np.all(h2 >= e2)  # never nearer than the truth: only fewer rows are seen
    np.testing.assert_array_equal(ei[:5], 17 * 200 + np.arange(5))


def test_hashed_votes_give_the_brute_force_top_candidates() -> None:
    kfs, q = _planted()
    exact, hashed = DescriptorIndex(), DescriptorIndex(HASHED)
    for d in kfs:
        exact.add(d)
        hashed.add(d)
    assert not exact.hashed
    top_e, top_h = exact.query(q, 3), hashed.query(q, 3)
    assert top_e[0] == (17, 200)  # every planted descriptor votes for its keyframe
    assert top_h[0][0] == 17 and top_h[0][1] >= 196
    assert [k for k, _ in top_h] == [k for k, _ in top_e]
    # the prefix: keyframe 17 and later do not vote
    assert all(k < 17 for k, _ in hashed.query(q, 3, before_kf=17))


def test_switch_to_hashing_at_the_threshold_keeps_exact_results_below_it() -> None:
    kfs, q = _planted(n_kf=10, kf=2)
    idx = DescriptorIndex(replace(RetrievalConfig(), exact_below_descriptors=1000))
    ref = DescriptorIndex(replace(RetrievalConfig(), exact_below_descriptors=10**9))
    for k, d in enumerate(kfs):
        idx.add(d)
        ref.add(d)
        assert idx.hashed == (200 * (k + 1) >= 1000)
    below = idx.query(q, 3, before_kf=4)
    assert below == ref.query(q, 3, before_kf=4) and below[0] == (2, 200)  # 800 rows: brute force
    assert idx.query(q, 3)[0][0] == ref.query(q, 3)[0][0] == 2  # 2000 rows: hashed


def test_hash_tables_hold_every_row_once_per_table() -> None:
    rng = np.random.default_rng(3)
    desc = rng.integers(0, 256, (500, 32), dtype=np.uint8)
    bits = hash_bit_positions(desc, 4, 10)
    assert bits.shape == (4, 10) and all(len(set(b)) == 10 for b in bits)
    keys = np.empty((500, 4), np.int64)
    hamming_hash.hash_keys(hamming.as_words(desc), bits, keys)
    # the key's bits are the descriptor's bits at those positions (little-endian within a byte)
    unpacked = np.unpackbits(desc, axis=1, bitorder="little")
    np.testing.assert_array_equal(keys[:, 0], unpacked[:, bits[0]] @ (1 << np.arange(9, -1, -1)))
    head = np.full((4, 1 << 10), hamming_hash.NO_ROW, np.int32)
    start = np.zeros((4, (1 << 10) + 1), np.int32)
    sealed = np.zeros((4, 500), np.int32)
    nxt = np.zeros((4, 300), np.int32)  # the longest tail: the first 300 rows
    count = np.zeros(head.shape, np.uint16)
    hamming_hash.insert_rows(keys[:300], 0, head, nxt, count, 0)  # a tail of 300 rows, sealed
    hamming_hash.seal_rows(keys[:300], 0, start, sealed, head)
    assert np.all(head == hamming_hash.NO_ROW)  # the tail lists are empty after a seal
    hamming_hash.insert_rows(keys[300:400], 300, head, nxt, count, 300)  # 100 more, sealed behind them
    hamming_hash.seal_rows(keys[300:400], 300, start, sealed, head)
    hamming_hash.insert_rows(keys[400:], 400, head, nxt, count, 400)  # the last 100: the tail
    for t in range(4):
        rows = []
        for k in range(1 << 10):
            run = sealed[t, start[t, k] : start[t, k + 1]]
            np.testing.assert_array_equal(run, np.flatnonzero(keys[:400, t] == k))  # the bucket's rows, ascending
            r = head[t, k]
            tail = []
            while r != hamming_hash.NO_ROW:
                assert keys[r, t] == k
                tail.append(r)
                r = nxt[t, r - 400]
            assert tail == sorted(tail, reverse=True) and all(r >= 400 for r in tail)  # newest first
            assert count[t, k] == len(run) + len(tail)
            rows += list(run) + tail
        assert sorted(rows) == list(range(500))
        assert start[t, -1] == 400


def test_the_hashed_search_is_the_two_nearest_among_the_rows_sharing_a_key(monkeypatch) -> None:
    # a small seal size, so that the tables hold sealed rows and a tail between their rebuilds
    monkeypatch.setattr(place_recognition, "SEAL_ROWS", 500)
    kfs, q = _planted(n_kf=30)
    idx = DescriptorIndex(HASHED)
    seals = set()
    for d in kfs:
        idx.add(d)
        seals.add((idx.key_bits, idx._n_sealed))
    db = np.concatenate(kfs)
    assert 0 < len(db) - idx._n_sealed < 500 and len(seals) > idx.key_bits - HASHED.hash_key_bits + 2
    keys, q_keys = idx._keys(db), idx._keys(q)
    ones = np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1).sum(axis=1)  # set bits of each byte value
    dist = ones[q[:, None, :] ^ db[None, :, :]].sum(axis=2)  # (queries, rows) Hamming distances
    sharing = (keys[None] == q_keys[:, None]).any(axis=2)  # (queries, rows): the row shares a key with the query
    for end in (len(db), 4100, 900):  # every row; a prefix ending in the sealed rows
        best, second, nearest = idx._nearest_two(q, end)
        for i in range(len(q)):
            shared = np.flatnonzero(sharing[i, :end])
            d = dist[i, shared]
            if len(d) == 0:
                assert (best[i], nearest[i]) == (hamming.NO_MATCH, -1)
                continue
            assert best[i] == d.min() and nearest[i] == shared[d == d.min()].min()
            assert second[i] == (np.sort(d)[1] if len(d) > 1 else hamming.NO_MATCH)


def test_balanced_bits_are_preferred() -> None:
    rng = np.random.default_rng(4)
    desc = rng.integers(0, 256, (2000, 32), dtype=np.uint8)
    desc[:, :16] = 0  # bits 0..127 constant: they carry nothing
    bits = hash_bit_positions(desc, 8, 16)
    assert bits.min() >= 128


def test_keys_gain_a_bit_per_doubling_and_still_find_the_planted_keyframe() -> None:
    kfs, q = _planted(n_kf=40, kf=30)
    idx = DescriptorIndex(replace(RetrievalConfig(), exact_below_descriptors=1000, hash_key_bits=8))
    bits = []
    for d in kfs:
        idx.add(d)
        bits.append(idx.key_bits)
    # keyframe k ends at row 200 (k + 1): tables from 1000 rows with 8 bits, rebuilt with 9 at 2000, 10 at 4000, 11
    # at 8000
    assert bits[:4] == [0] * 4
    assert [bits[k] for k in (4, 8, 9, 18, 19, 38, 39)] == [8, 8, 9, 9, 10, 10, 11]
    assert idx.query(q, 1)[0][0] == 30


def _crowded_walk(n_kf: int, seed: int = 6) -> tuple[list[np.ndarray], np.ndarray]:
    """``n_kf`` keyframes of 100 distinctive descriptors and 100 look-alikes of one common set (3 bits from it, in
    every keyframe), and a query: keyframe 5's distinctive ones (5 bits off) with the common set."""
    rng = np.random.default_rng(seed)
    common = rng.integers(0, 256, (100, 32), dtype=np.uint8)
    kfs = [np.concatenate([rng.integers(0, 256, (100, 32), dtype=np.uint8), _noisy(common, 3, rng)])
           for _ in range(n_kf)]
    return kfs, np.concatenate([_noisy(kfs[5][:100], 5, rng), common])


def test_common_appearances_are_stop_words_and_bound_the_work() -> None:
    work = {}
    for bound in (0, 8):
        for n_kf in (20, 80):
            kfs, q = _crowded_walk(n_kf)
            idx = DescriptorIndex(replace(HASHED, hash_bucket_rows=bound))
            for d in kfs:
                idx.add(d)
            before = idx.rows_compared
            top = idx.query(q, 2)
            work[bound, n_kf] = idx.rows_compared - before
            # keyframe 5's distinctive descriptors vote for it either way (the look-alikes fail the ratio test)
            assert top[0][0] == 5 and top[0][1] >= 95
    # without the bound the look-alikes of the common set are compared in most of the tables they share a key in (3 to
    # 6 bits apart): the work grows with the map
    assert work[0, 80] > 3 * work[0, 20] > 3 * 8 * 20 * 100
    # with it the buckets of the common set (16 rows and more each) are left out before any row is
    # compared: the work is that of the 100 distinctive ones (about their own look-alike each, compared once),
    # whatever the map size
    assert work[8, 20] <= 200 and work[8, 80] <= 200


def test_stop_word_rows_are_counted_per_bucket() -> None:
    kfs, q = _crowded_walk(30)
    idx = DescriptorIndex(HASHED)
    for d in kfs:
        idx.add(d)
    keys = idx._keys(np.concatenate(kfs))
    for t in range(keys.shape[1]):
        np.testing.assert_array_equal(idx._count[t], np.bincount(keys[:, t], minlength=idx._count.shape[1]))


def test_the_exact_search_over_the_word_major_copy_equals_the_reference() -> None:
    """Below the hashing threshold the index searches its word-major copy of the rows (grown over two doublings
    here): the reference's nearest, second-nearest and first-nearest index, ties and prefixes included; 0 or 1
    rows give the no-match values."""
    rng = np.random.default_rng(3)
    kfs = [rng.integers(0, 256, (1500, 32), dtype=np.uint8) for _ in range(8)]  # 12000 rows: capacity 4096 -> 16384
    kfs[5][7] = kfs[2][40]  # a tie: the first row wins
    q = np.concatenate([rng.integers(0, 256, (50, 32), dtype=np.uint8), kfs[2][40:41], _noisy(kfs[6][:20], 5, rng)])
    idx = DescriptorIndex()
    for d in kfs:
        idx.add(d)
    assert not idx.hashed
    db = np.concatenate(kfs)
    for end in (len(db), 4500, 1, 0):
        got = idx._nearest_two(q, end)
        want = hamming.nearest_two_ref(q, db[:end])
        for g, w in zip(got, want, strict=True):
            np.testing.assert_array_equal(g, w)
    assert idx._nearest_two(q, len(db))[2][50] == 2 * 1500 + 40  # not 5 * 1500 + 7
    np.testing.assert_array_equal(idx._nearest_two(q, len(db))[2][51:], 6 * 1500 + np.arange(20))
