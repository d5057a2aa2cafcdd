"""Where numba caches the compiled kernels: beside their sources, else the user-wide cache, else a temp folder.

numba raises a RuntimeError at the first cached kernel when neither its in-tree nor its user-wide cache folder is
writable (a read-only install without a writable HOME). :func:`configure_numba_cache` points ``NUMBA_CACHE_DIR`` at
a temp folder then; the command line calls it before numba is imported, and a batch hands the folder it chose to
its workers. This module does not import numba.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping
from pathlib import Path

NUMBA_CACHE_ENV = "NUMBA_CACHE_DIR"
#: numba's in-tree cache of our kernels (it falls back to the user-wide cache when this is not writable)
KERNEL_CACHE_DIR = Path(__file__).resolve().parent / "kernels" / "__pycache__"


def _writable_dir(path: Path) -> bool:
    """True when ``path`` exists or can be created and a file can be created in it (numba's own test)."""
    try:
        os.makedirs(path, exist_ok=True)
        tempfile.TemporaryFile(dir=path).close()
        return True
    except OSError:
        return False


def numba_cache_fallback(environ: Mapping[str, str] | None = None, in_tree: Path | None = None,
                         temp_root: Path | None = None) -> str | None:
    """The ``NUMBA_CACHE_DIR`` to set, or ``None`` when numba's defaults work (or the user chose one).

    numba tries the kernels' ``__pycache__`` (``in_tree``), then ``$XDG_CACHE_HOME/numba`` or
    ``~/.cache/numba``, and raises a RuntimeError at the first cached kernel when neither is writable. Then this
    gives ``<temp>/surfelslam-numba-<uid>`` (a fresh temp folder when that one is not usable either).
    """
    environ = os.environ if environ is None else environ
    if environ.get(NUMBA_CACHE_ENV):
        return None
    if _writable_dir(KERNEL_CACHE_DIR if in_tree is None else in_tree):
        return None
    home = environ.get("HOME") or os.path.expanduser("~")
    user = Path(environ.get("XDG_CACHE_HOME", os.path.join(home, ".cache"))) / "numba"
    if _writable_dir(user):
        return None
    root = Path(tempfile.gettempdir()) if temp_root is None else temp_root
    uid = os.getuid() if hasattr(os, "getuid") else 0
    shared = root / f"surfelslam-numba-{uid}"
    if _writable_dir(shared):
        return str(shared)
    try:
        return tempfile.mkdtemp(prefix="surfelslam-numba-", dir=root)
    except OSError:
        return None  # nowhere to write: numba reports it when a kernel is compiled


def configure_numba_cache() -> None:
    """Set ``NUMBA_CACHE_DIR`` from :func:`numba_cache_fallback` (before numba is imported)."""
    fallback = numba_cache_fallback()
    if fallback is not None:
        os.environ[NUMBA_CACHE_ENV] = fallback
