"""One batch at a time per batch folder: ``OUT/.batch.lock`` holds the PID of the process driving the batch.

Two batches into one ``--out`` would each see the other's run folders locked and record those jobs as failed, and
``results.csv`` would be whichever table was written last. The lock is created with ``O_CREAT | O_EXCL`` (as a run
folder's, :mod:`surfelslam.io.run_folder`); a second batch (or ``--report`` rebuild) stops with one line naming the
PID; a lock whose process is gone (a killed batch) is taken over.
"""

from __future__ import annotations

from pathlib import Path

from surfelslam.io.run_folder import release_lock, take_lock

BATCH_LOCK_NAME = ".batch.lock"


class BatchLock:
    """``with BatchLock(out):`` holds ``out/.batch.lock`` for this process; OutputError (one line) when a live batch
    holds it."""

    def __init__(self, out: str | Path):
        self.out = Path(out)
        self.path = self.out / BATCH_LOCK_NAME
        self._held = False

    def __enter__(self) -> BatchLock:
        take_lock(self.path, "batch lock", "batch", self._held_message)
        self._held = True
        return self

    def _held_message(self, holder: int | None) -> str:
        who = "another batch" if holder is None else f"another batch (process {holder})"
        return (f"{who} is writing into {self.out}; wait for it to end, or choose another --out (delete {self.path} "
                "only if no batch is going)")

    def __exit__(self, *exc) -> None:
        if self._held:
            release_lock(self.path)
        self._held = False
