"""Reading and writing a saved map (``map.npz``): one uncompressed NumPy archive, written atomically.

The arrays and the manifest are :func:`surfelslam.slam.saved_map.to_arrays`'s; ``docs/outputs.md`` (Saved map)
documents them. Reading never unpickles (``allow_pickle=False``) and checks every array's structure and values
(finite, in range: :func:`~surfelslam.slam.saved_map.check_map_values`); a missing, truncated or corrupt file, a bad
value, or one of another format version, raises :class:`~surfelslam.errors.MapFileError` naming it.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from surfelslam.errors import MapFileError
from surfelslam.io.atomic import atomic_path
from surfelslam.slam.saved_map import MapFormatProblem, SavedMap, check_map_values, from_arrays, to_arrays

#: The saved map's file name in a run folder.
MAP_FILE = "map.npz"


def write_map_file(path: str | Path, saved: SavedMap) -> None:
    """Write ``saved`` to ``path`` (temp file, then rename: a reader never sees half a map).

    Raises:
        OutputError: the file cannot be written (it is left as it was).
    """
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **to_arrays(saved))


def map_file_of(path: str | Path) -> Path:
    """The map file ``path`` names: the file itself, or ``path/map.npz`` for a run folder."""
    path = Path(path)
    return path / MAP_FILE if path.is_dir() else path


def read_map_file(path: str | Path) -> SavedMap:
    """The map in ``path`` (a ``map.npz`` or a run folder holding one), fully read and checked.

    Raises:
        MapFileError: no such file, not a map archive, truncated or corrupt, or another format version.
    """
    file = map_file_of(path)
    if not file.is_file():
        where = f"{path} holds no {MAP_FILE}" if Path(path).is_dir() else "no such map file"
        hint = ("; runs of the orb tracker, and runs with --set map_reuse.save=false, save no map"
                if Path(path).is_dir() else "")
        raise MapFileError(file, f"{where}{hint}" if Path(path).is_dir() else where)
    try:
        with np.load(file, allow_pickle=False) as arrays:
            saved = from_arrays(arrays)
        check_map_values(saved)
        return saved
    except MapFormatProblem as exc:
        raise MapFileError(file, str(exc)) from None
    # NotImplementedError: zipfile's word for a member that needs a zip version or compression it does not have
    except (OSError, ValueError, EOFError, KeyError, NotImplementedError, zipfile.BadZipFile,
            zipfile.LargeZipFile) as exc:
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise MapFileError(file, f"not a readable map archive, truncated or corrupt ({text})") from None
