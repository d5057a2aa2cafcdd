"""The reader thread: started before the frames are wanted (the warm-up meanwhile), the first frames are decoded
early and prepared, in order and in the reader thread, once ``prepare`` is known; the slots are prefetch_frames'."""

from __future__ import annotations

import threading

import pytest

from surfelslam.errors import FrameError
from surfelslam.io.prefetch import FrameReader, prefetch_frames

#: a guard against a hung reader thread, not a timing measurement
WAIT_S = 30.0


class _Frames:
    """A sequence of ints (position * 10) that logs each read and fails at position ``bad``."""

    def __init__(self, n: int, bad: int | None = None):
        self.n, self.bad = n, bad
        self.log: list[tuple[str, int, str]] = []
        self.third_read = threading.Event()

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> int:
        self.log.append(("read", i, threading.current_thread().name))
        if i == 2:
            self.third_read.set()
        if i == self.bad:
            raise FrameError(f"f{i}.png", "unreadable", i)
        return i * 10


def _prepare(seq: _Frames):
    def prepare(frame: int) -> int:
        seq.log.append(("prepare", frame // 10, threading.current_thread().name))
        return frame + 1
    return prepare


def _slots(items) -> list[tuple]:
    return [(it.position, it.frame, None if it.error is None else str(it.error), it.prepared) for it in items]


def test_first_frames_are_read_before_prepare_is_known_then_prepared_in_order():
    seq = _Frames(7, bad=4)
    with FrameReader(seq, ahead=3) as reader:
        assert seq.third_read.wait(WAIT_S)  # frames 0-2 are decoded before anyone asks for them
        assert [e[:2] for e in seq.log] == [("read", 0), ("read", 1), ("read", 2)]
        slots = _slots(reader.frames(_prepare(seq)))
    assert slots == [(0, 0, None, 1), (1, 10, None, 11), (2, 20, None, 21), (3, 30, None, 31),
                     (4, None, "f4.png: unreadable", None), (5, 50, None, 51), (6, 60, None, 61)]
    prepares = [e for e in seq.log if e[0] == "prepare"]
    assert [e[1] for e in prepares] == [0, 1, 2, 3, 5, 6]
    assert all(name.startswith("surfelslam-read") for _, _, name in seq.log)


@pytest.mark.parametrize("ahead", [0, 1, 3, 10])
def test_same_slots_as_prefetch_frames(ahead):
    a, b = _Frames(5, bad=1), _Frames(5, bad=1)
    with FrameReader(a, ahead=ahead) as reader:
        early = _slots(reader.frames(_prepare(a)))
    assert early == _slots(prefetch_frames(b, ahead=ahead, prepare=_prepare(b)))
    # ahead = 0: read in the caller's thread and never prepared (the consumer does that work)
    assert [s[3] for s in early] == ([None] * 5 if ahead == 0 else [1, None, 21, 31, 41])


def test_closing_before_the_frames_stops_the_thread():
    seq = _Frames(50)
    reader = FrameReader(seq, ahead=3)
    reader.close()
    assert len([e for e in seq.log if e[0] == "read"]) <= 3
    assert not any(t.name.startswith("surfelslam-read") for t in threading.enumerate())
