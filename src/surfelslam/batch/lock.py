"""One batch at a time per batch folder: ``OUT/.batch.lock`` holds the PID of the process driving the batch.

Two batches into one ``--out`` would each see the other's run folders locked and record those jobs as failed, and
``results.csv`` would be whichever table was written last. The lock is created with ``O_CREAT | O_EXCL`` (as a run
folder's, :mod:`surfelslam.io.run_folder`); a second batch (or ``--report`` rebuild) stops with one line naming the
PID; a lock whose process is gone (a killed batch) is taken over.
"""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path

from surfelslam.errors import OutputError
from surfelslam.io.atomic import os_error_text
from surfelslam.io.run_folder import EMPTY_LOCK_STALE_S, pid_alive

BATCH_LOCK_NAME = ".batch.lock"
#: Tries to take over a stale lock before giving up (another batch keeps taking it in between).
TAKEOVER_ATTEMPTS = 3


def lock_holder(path: Path) -> int | None:
    """The PID in a batch lock file: ``None`` when empty, ``-1`` when unreadable garbage."""
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    try:
        return int(text.split()[0]) if text else None
    except ValueError:
        return -1


def _is_stale(path: Path, holder: int | None) -> bool:
    if holder is None:  # being written right now, or its writer died before writing
        try:
            return time.time() - path.stat().st_mtime > EMPTY_LOCK_STALE_S
        except FileNotFoundError:
            return True
    return not pid_alive(holder)


class BatchLock:
    """``with BatchLock(out):`` holds ``out/.batch.lock`` for this process; OutputError (one line) when a live batch
    holds it."""

    def __init__(self, out: str | Path):
        self.out = Path(out)
        self.path = self.out / BATCH_LOCK_NAME
        self._held = False

    def __enter__(self) -> BatchLock:
        path = self.path
        for _ in range(TAKEOVER_ATTEMPTS):
            try:
                fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                holder = lock_holder(path)
                if not _is_stale(path, holder):
                    who = "another batch" if holder is None else f"another batch (process {holder})"
                    raise OutputError(path, f"{who} is writing into {self.out}; wait for it to end, or choose "
                                            f"another --out (delete {path} only if no batch is going)") from None
                if lock_holder(path) == holder:  # still the same stale lock: take it over
                    with contextlib.suppress(FileNotFoundError):
                        path.unlink()
                continue
            except OSError as exc:
                raise OutputError(path, f"cannot create the batch lock file ({os_error_text(exc)})") from None
            try:
                os.write(fd, f"{os.getpid()}\n".encode())
            finally:
                os.close(fd)
            self._held = True
            return self
        raise OutputError(path, "cannot take over the stale batch lock (another batch keeps taking it)")

    def __exit__(self, *exc) -> None:
        if self._held and lock_holder(self.path) == os.getpid():
            with contextlib.suppress(OSError):
                self.path.unlink()
        self._held = False
