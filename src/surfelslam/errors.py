"""Typed exceptions. The CLI turns every ``SurfelSlamError`` into one line and exit code 2."""

from __future__ import annotations

from pathlib import Path


class SurfelSlamError(Exception):
    """Base of every error surfelslam raises on purpose (bad input, bad config, failed tracking)."""


class InputError(SurfelSlamError):
    """A file or folder given by the user is missing, unreadable or malformed.

    The message always names the offending path and the problem.
    """

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}" if path is not None else problem)


class DatasetError(InputError):
    """A sequence folder cannot be read as any known layout, or its index files disagree."""


class FrameError(InputError):
    """One frame of a sequence is corrupt (bad image, wrong size). Long runs skip and count it."""

    def __init__(self, path: str | Path | None, problem: str, index: int | None = None):
        self.index = index
        super().__init__(path, problem)


class GroundTruthError(InputError):
    """Ground truth is missing or cannot be associated with the frames."""


class MapFileError(InputError):
    """A saved map (``map.npz``, ``--map``) is missing, truncated, corrupt, or of another format version.

    The message names the file and the problem on one line."""


class ConfigError(SurfelSlamError):
    """A configuration value or file is invalid."""


class ConfigValueError(ConfigError, ValueError):
    """A setting outside its domain (:func:`surfelslam.config.validate`); also a ValueError, which some configs
    raised for these before."""


class TrackingError(SurfelSlamError):
    """Tracking could not produce a pose (too few inliers, degenerate geometry)."""


class OutputError(SurfelSlamError):
    """An output file cannot be written (disk full, read-only folder, permission denied).

    The message names the file; whatever was left on disk is valid (no torn line, no temp file).
    """

    def __init__(self, path: str | Path, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


class EvaluationError(SurfelSlamError, ValueError):
    """Trajectories that cannot be evaluated (degenerate motion, no pose pairs, bad options).

    Also a ValueError, which the metrics raised for these cases before.
    """


#: Every character :meth:`str.splitlines` breaks a line at (CR, LF, VT, FF, the file/group/record separators, NEL and
#: the Unicode line and paragraph separators): a message holding one of them would print as two lines.
LINE_BREAKS = "\r\n\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029"
_ESCAPED_BREAKS = str.maketrans({c: c.encode("unicode_escape").decode("ascii") for c in LINE_BREAKS})


def one_line(text: str) -> str:
    """``text`` with every line break character written as its escape (``\\n``, ``\\x1e`` ...): a message quoting user
    input stays one line."""
    return text.translate(_ESCAPED_BREAKS)
