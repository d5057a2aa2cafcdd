"""Read frames ahead in a background thread so decoding overlaps tracking and fusion.

OpenCV releases the GIL while decoding, so one reader thread hides most of the read cost.
Order and content are those of the sequence: the result is deterministic.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

from surfelslam.errors import FrameError
from surfelslam.types import RGBDFrame


@dataclass
class LoadedFrame:
    """One slot of the stream: the frame, or the error that made it unreadable."""

    position: int
    frame: RGBDFrame | None
    error: FrameError | None
    read_ms: float


def _load(seq, i: int) -> LoadedFrame:
    t0 = time.perf_counter()
    try:
        frame = seq[i]
        err = None
    except FrameError as exc:
        frame, err = None, exc
    return LoadedFrame(i, frame, err, (time.perf_counter() - t0) * 1e3)


def prefetch_frames(seq, ahead: int = 3) -> Iterator[LoadedFrame]:
    """Yield every position of ``seq`` in order; ``ahead`` frames are decoded in advance.

    ``ahead = 0`` reads synchronously (no thread).
    """
    n = len(seq)
    if ahead <= 0:
        for i in range(n):
            yield _load(seq, i)
        return
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="surfelslam-read") as pool:
        pending: dict[int, Future] = {}
        for i in range(min(ahead, n)):
            pending[i] = pool.submit(_load, seq, i)
        for i in range(n):
            nxt = i + ahead
            if nxt < n:
                pending[nxt] = pool.submit(_load, seq, nxt)
            yield pending.pop(i).result()
