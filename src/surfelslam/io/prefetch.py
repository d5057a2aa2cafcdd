"""Read frames ahead in a background thread so decoding overlaps tracking and fusion.

OpenCV releases the GIL while decoding, so one reader thread hides most of the read cost. The same thread
can also run the pipeline's frame-only work (``prepare``, e.g. ``DenseSlam.prepare``: the depth pyramid and
ORB features; numba kernels and OpenCV release the GIL too), which then overlaps the previous frame's map
stages. Order and content are those of the sequence: the result is deterministic.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

from surfelslam.errors import FrameError
from surfelslam.types import RGBDFrame


@dataclass
class LoadedFrame:
    """One slot of the stream: the frame, or the error that made it unreadable.

    ``prepared``: what ``prepare(frame)`` returned (``None`` without ``prepare``, or when it raised: the
    pipeline then does that work itself and reports the problem in its own context).
    """

    position: int
    frame: RGBDFrame | None
    error: FrameError | None
    read_ms: float
    prepared: object | None = None


def _load(seq, i: int, prepare: Callable[[RGBDFrame], object] | None = None) -> LoadedFrame:
    t0 = time.perf_counter()
    try:
        frame = seq[i]
        err = None
    except FrameError as exc:
        frame, err = None, exc
    read_ms = (time.perf_counter() - t0) * 1e3
    prepared = None
    if prepare is not None and frame is not None:
        try:
            prepared = prepare(frame)
        except Exception:  # noqa: BLE001 - redone (and raised or reported) by the pipeline in order
            prepared = None
    return LoadedFrame(i, frame, err, read_ms, prepared)


def prefetch_frames(seq, ahead: int = 3, prepare: Callable[[RGBDFrame], object] | None = None
                    ) -> Iterator[LoadedFrame]:
    """Yield every position of ``seq`` in order; ``ahead`` frames are decoded in advance.

    ``prepare``: optional frame-only work run on each frame in the reader thread (its result is the slot's
    ``prepared``); it must be safe to run beside the consumer's processing. ``ahead = 0`` reads
    synchronously (no thread, and ``prepare`` is not called: the consumer does that work itself).
    """
    n = len(seq)
    if ahead <= 0:
        for i in range(n):
            yield _load(seq, i)
        return
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="surfelslam-read")
    try:
        pending: dict[int, Future] = {}
        for i in range(min(ahead, n)):
            pending[i] = pool.submit(_load, seq, i, prepare)
        for i in range(n):
            nxt = i + ahead
            if nxt < n:
                pending[nxt] = pool.submit(_load, seq, nxt, prepare)
            yield pending.pop(i).result()
    finally:
        # a consumer that stops early (error, Ctrl-C) waits for the frame being read, not for the queued ones
        pool.shutdown(wait=True, cancel_futures=True)
