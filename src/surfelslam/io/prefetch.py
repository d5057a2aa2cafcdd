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
from surfelslam.kernels.threads import lower_thread_priority
from surfelslam.types import RGBDFrame

#: nice levels below the tracking thread for the reader: its frames are queued ahead, so it can take the core the
#: tracking thread leaves idle rather than compete with the work on that thread's path
READER_NICE = 5
#: the reader thread's name prefix (a thread pool numbers its threads after it)
READER_THREAD = "surfelslam-read"


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
    return LoadedFrame(i, frame, err, read_ms, _prepared(frame, prepare))


def _prepared(frame: RGBDFrame | None, prepare: Callable[[RGBDFrame], object] | None) -> object | None:
    """``prepare(frame)``, or ``None`` without either or when it fails (the pipeline redoes the work in order and
    raises or reports the failure there)."""
    if prepare is None or frame is None:
        return None
    try:
        return prepare(frame)
    except Exception:  # noqa: BLE001 - see the docstring
        return None


def _prepare_loaded(read: Future, prepare: Callable[[RGBDFrame], object] | None) -> LoadedFrame:
    """``prepare`` a slot read before ``prepare`` was known (queued behind its read on the one reader thread)."""
    item = read.result()
    item.prepared = _prepared(item.frame, prepare)
    return item


class FrameReader:
    """The reader thread of :func:`prefetch_frames`, started before the frames are wanted.

    ``FrameReader(seq, ahead)`` starts decoding the first ``ahead`` frames at once (e.g. while the tracker's kernels
    compile); :meth:`frames` then yields every slot in order, running ``prepare`` (known only now) on those first
    frames in the same thread, before any later frame is read: the slots are those of ``prefetch_frames``. Use as a
    context manager (or :meth:`close`): the thread stops with it.
    """

    def __init__(self, seq, ahead: int = 3):
        self.seq = seq
        self.ahead = max(int(ahead), 0)
        self._pool: ThreadPoolExecutor | None = None
        self._early: dict[int, Future] = {}
        if self.ahead > 0:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=READER_THREAD,
                                            initializer=lower_thread_priority, initargs=(READER_NICE,))
            for i in range(min(self.ahead, len(seq))):
                self._early[i] = self._pool.submit(_load, seq, i, None)

    def frames(self, prepare: Callable[[RGBDFrame], object] | None = None) -> Iterator[LoadedFrame]:
        """Every slot of the sequence in order (see :func:`prefetch_frames` for ``prepare``); once only."""
        seq, n, ahead = self.seq, len(self.seq), self.ahead
        if self._pool is None:
            for i in range(n):
                yield _load(seq, i)
            return
        try:
            pending = {i: self._pool.submit(_prepare_loaded, read, prepare) for i, read in self._early.items()}
            self._early = {}
            for i in range(n):
                nxt = i + ahead
                if nxt < n:
                    pending[nxt] = self._pool.submit(_load, seq, nxt, prepare)
                yield pending.pop(i).result()
        finally:
            self.close()

    def close(self) -> None:
        """Stop the thread: wait for the frame being read, drop the queued ones."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> FrameReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def prefetch_frames(seq, ahead: int = 3, prepare: Callable[[RGBDFrame], object] | None = None
                    ) -> Iterator[LoadedFrame]:
    """Yield every position of ``seq`` in order; ``ahead`` frames are decoded in advance.

    ``prepare``: optional frame-only work run on each frame in the reader thread (its result is the slot's
    ``prepared``); it must be safe to run beside the consumer's processing. ``ahead = 0`` reads
    synchronously (no thread, and ``prepare`` is not called: the consumer does that work itself).
    A consumer that stops early (error, Ctrl-C) waits for the frame being read, not for the queued ones.
    """
    yield from FrameReader(seq, ahead).frames(prepare)
