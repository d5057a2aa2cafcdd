"""Write files so that a reader never sees a half-written one: temp file in the same folder, then rename.

The temp file gets the mode a plain ``open(path, "w")`` would give (``0o666`` minus the umask, e.g. 0644 under
umask 022), not ``mkstemp``'s private 0600. A failed write (disk full, read-only folder) raises
:class:`~surfelslam.errors.OutputError` naming the target file, and leaves no temp file behind.
"""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from surfelslam.errors import OutputError

#: Mode of a new file before the umask is applied (what ``open(path, "w")`` uses).
NEW_FILE_MODE = 0o666
_PROC_STATUS = Path("/proc/self/status")
_umask_lock = threading.Lock()


def current_umask() -> int:
    """The process umask, read without changing it where the OS allows (``/proc/self/status``)."""
    with contextlib.suppress(OSError, ValueError):
        for line in _PROC_STATUS.read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    with _umask_lock:  # fallback: set and restore (another thread could create a file in between)
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def default_file_mode() -> int:
    """``0o666 & ~umask``: the permissions a new output file gets."""
    return NEW_FILE_MODE & ~current_umask()


def os_error_text(exc: OSError) -> str:
    """``strerror`` of an OS error (``No space left on device``), without the file name."""
    return exc.strerror or str(exc)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temp file's path next to ``path``, for writers that take a file name; on success the temp file is
    renamed over ``path``, on failure deleted.

    Raises:
        OutputError: the folder or temp file cannot be created, or an OS error (disk full, permission) occurs
            while writing or renaming; the message names ``path``.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        if exc.errno in (errno.EEXIST, errno.ENOTDIR):
            raise OutputError(path, "cannot create the file: a part of its folder path is a file") from None
        raise OutputError(path, f"cannot create the file ({os_error_text(exc)})") from None
    try:
        os.fchmod(fd, default_file_mode())
    except OSError:
        pass  # e.g. a file system without permissions: keep mkstemp's mode
    finally:
        os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if exc.filename is not None and os.fspath(exc.filename) not in (tmp, os.fspath(path)):
            raise  # an error about another file (an input the writer read): keep its own message
        raise OutputError(path, f"cannot write the file ({os_error_text(exc)}); it is left as it was") from None
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "w") -> Iterator[IO]:
    """Open a temp file next to ``path``; on success it is fsynced and renamed over ``path``."""
    with atomic_path(path) as tmp, open(tmp, mode) as fh:
        yield fh
        fh.flush()
        os.fsync(fh.fileno())


def write_text_atomic(path: str | Path, text: str) -> None:
    with atomic_open(path, "w") as fh:
        fh.write(text)
