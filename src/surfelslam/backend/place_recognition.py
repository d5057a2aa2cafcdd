"""Appearance-based keyframe retrieval by descriptor voting.

Every keyframe's ORB descriptors are appended to one database (grown by doubling). A query frame
matches each of its descriptors to its two nearest database descriptors (exact Hamming kNN,
numba brute force, :mod:`surfelslam.kernels.hamming`); a match passing the ratio test and a distance
bound casts one vote for the keyframe that owns the nearest descriptor. Keyframes are ranked by votes
(ties: lower id first).

Keyframes are stored in id order, so restricting a query to "keyframes older than k" is a prefix
of the database: recent keyframes (which trivially look alike) are excluded without copying.
Brute-force search is exact and deterministic; no vocabulary needs training.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surfelslam.config import Config, setting
from surfelslam.kernels import hamming

_DESCRIPTOR_BYTES = 32
_INITIAL_CAPACITY = 4096


@dataclass(frozen=True)
class RetrievalConfig(Config):
    """Keyframe retrieval by descriptor voting."""

    max_hamming_bits: float = setting(50.0, unit="bits", gt=0, le=256,
                                      doc="a vote needs a nearest-neighbour distance below this (of 256 bits)")
    ratio: float = setting(0.8, gt=0, le=1, doc="nearest / second-nearest distance bound (Lowe ratio test)")
    min_votes: int = setting(8, unit="votes", ge=0, le=1_000_000, doc="keyframes with fewer votes are not returned")
    max_descriptors_per_keyframe: int = setting(300, unit="descriptors", ge=1, le=100_000,
                                                doc="only the strongest keypoints with depth are stored and queried "
                                                    "(bounds the brute-force cost)")


def select_descriptors(descriptors: np.ndarray, response: np.ndarray, valid: np.ndarray, n_max: int) -> np.ndarray:
    """The ``n_max`` strongest valid-depth descriptors ``(<= n_max, 32)``, in their original order."""
    idx = np.flatnonzero(valid)
    if len(idx) > n_max:
        strongest = np.lexsort((idx, -response[idx]))[:n_max]
        idx = np.sort(idx[strongest])
    return descriptors[idx]


class DescriptorIndex:
    """Database of keyframe descriptors with voting queries."""

    def __init__(self, cfg: RetrievalConfig | None = None) -> None:
        self.cfg = cfg or RetrievalConfig()
        self._desc = np.zeros((_INITIAL_CAPACITY, _DESCRIPTOR_BYTES), np.uint8)
        self._owner = np.zeros(_INITIAL_CAPACITY, np.int64)
        self._n = 0
        self._kf_end: list[int] = []  # database rows [0, _kf_end[k]) belong to keyframes 0..k

    @property
    def n_keyframes(self) -> int:
        return len(self._kf_end)

    def add(self, descriptors: np.ndarray) -> int:
        """Append the next keyframe's ``(N, 32)`` uint8 descriptors; returns its keyframe id."""
        d = np.asarray(descriptors, np.uint8).reshape(-1, _DESCRIPTOR_BYTES)
        need = self._n + len(d)
        if need > len(self._desc):
            cap = len(self._desc)
            while cap < need:
                cap *= 2
            desc = np.zeros((cap, _DESCRIPTOR_BYTES), np.uint8)
            owner = np.zeros(cap, np.int64)
            desc[: self._n] = self._desc[: self._n]
            owner[: self._n] = self._owner[: self._n]
            self._desc, self._owner = desc, owner
        kf = len(self._kf_end)
        self._desc[self._n : need] = d
        self._owner[self._n : need] = kf
        self._n = need
        self._kf_end.append(need)
        return kf

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
        db = self._desc[:end]
        d1, d2, idx = hamming.nearest_two_words(hamming.as_words(descriptors), hamming.as_words(db))
        good = (d1 < self.cfg.max_hamming_bits) & (d1 < self.cfg.ratio * d2)
        owners = self._owner[idx[good]]
        votes = np.bincount(owners, minlength=k_max)
        order = np.lexsort((np.arange(k_max), -votes))
        return [(int(k), int(votes[k])) for k in order[:n_results] if votes[k] >= self.cfg.min_votes]
