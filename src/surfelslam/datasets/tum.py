"""TUM RGB-D layout: ``rgb.txt`` and ``depth.txt`` (``timestamp filename`` lines, ``#`` comments),
optional ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``, camera-to-world).

Colour and depth are paired by nearest timestamp within :data:`MAX_RGB_DEPTH_DT_S` (each depth image used
at most once, the closest pair wins); the frame takes the colour timestamp. Images left without a partner are
listed in the sequence's ``unpaired`` (with the reason); when fewer than half of the listed images pair, the
sequence is refused (the index files disagree: another clock, milliseconds instead of seconds, ...).
Unsorted index lines are sorted; a duplicated timestamp (in an index or the ground truth) is an error naming
both lines. ``associations.txt`` is only
used when ``rgb.txt`` or ``depth.txt`` is absent (its lines may list the depth pair first, as ICL-NUIM's do).

This module also holds the ``synthetic`` layout: the TUM layout written by ``surfelslam synth``
(recognised by ``generator : surfelslam synth`` in its ``INFO.txt``).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from surfelslam.datasets.base import (
    MIN_PAIRED_FRACTION,
    DatasetOptions,
    FrameEntry,
    RGBDSequence,
    UnpairedFrame,
    unpaired_examples,
)
from surfelslam.datasets.metadata import FolderMetadata, build_sequence, read_metadata
from surfelslam.errors import DatasetError, GroundTruthError, InputError
from surfelslam.io.trajectory import MAX_ABS_STAMP_S, data_lines, read_tum
from surfelslam.types import Trajectory

#: Largest colour/depth timestamp difference accepted as one frame (seconds).
MAX_RGB_DEPTH_DT_S = 0.02
#: Raw depth units per metre of the TUM benchmark.
TUM_DEPTH_SCALE = 5000.0
#: Per-camera calibration of the TUM benchmark (fx, fy, cx, cy), chosen by ``freiburgN`` / ``frN``.
TUM_INTRINSICS = {
    "1": (517.3, 516.5, 318.6, 255.3),
    "2": (520.9, 521.0, 325.1, 249.7),
    "3": (535.4, 539.2, 320.1, 247.6),
}
#: ROS default Kinect intrinsics, used when the name does not say which TUM camera it is.
ROS_DEFAULT_INTRINSICS = (525.0, 525.0, 319.5, 239.5)

RGB_INDEX, DEPTH_INDEX, ASSOC_INDEX, GT_FILE = "rgb.txt", "depth.txt", "associations.txt", "groundtruth.txt"
_FREIBURG = re.compile(r"(?:freiburg|fr)([123])(?![0-9])")


def has_tum_index(root: Path) -> bool:
    """True when the folder has any TUM index file (rgb.txt, depth.txt or associations.txt)."""
    return any((root / f).is_file() for f in (RGB_INDEX, DEPTH_INDEX, ASSOC_INDEX))


def read_index(path: Path, min_columns: int = 2) -> list[tuple[int, list[str]]]:
    """Non-comment lines of an index file as ``(line number, fields)``; DatasetError when absent or empty."""
    if path.exists() and not path.is_file():
        raise DatasetError(path, f"{path.name} is not a file (the TUM layout needs rgb.txt and depth.txt files)")
    if not path.is_file():
        raise DatasetError(path, f"{path.name} not found (the TUM layout needs rgb.txt and depth.txt)")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(path, f"cannot read index file ({exc})") from None
    rows = []
    for lineno, line in data_lines(text):
        parts = line.split()
        if len(parts) < min_columns:
            raise DatasetError(path, f"line {lineno}: expected 'timestamp filename', got {line!r}")
        rows.append((lineno, parts))
    if not rows:
        raise DatasetError(path, "index file lists no frames (empty)")
    return rows


def _timestamp(path: Path, lineno: int, text: str) -> float:
    try:
        t = float(text)
    except ValueError:
        raise DatasetError(path, f"line {lineno}: timestamp {text!r} is not a number") from None
    if not np.isfinite(t):
        raise DatasetError(path, f"line {lineno}: timestamp {text!r} is not finite")
    if abs(t) > MAX_ABS_STAMP_S:
        raise DatasetError(path, f"line {lineno}: timestamp {text!r} is out of range (|t| > {MAX_ABS_STAMP_S:g} s)")
    return t


def _sorted_unique(path: Path, t: np.ndarray, linenos: np.ndarray) -> np.ndarray:
    """Order sorting the timestamps; DatasetError naming both lines when one is duplicated."""
    order = np.argsort(t, kind="stable")
    dup = np.nonzero(np.diff(t[order]) == 0)[0]
    if len(dup):
        a, b = linenos[order[dup[0]]], linenos[order[dup[0] + 1]]
        raise DatasetError(path, f"duplicate timestamp {t[order[dup[0]]]:.6f} (lines {a} and {b})")
    return order


def read_timed_files(path: Path, root: Path) -> tuple[np.ndarray, list[Path]]:
    """``rgb.txt`` / ``depth.txt`` -> ``(timestamps (N,) ascending, absolute paths)``.

    Unsorted lines are sorted; a duplicated timestamp is an error (naming both line numbers).
    """
    rows = read_index(path)
    for lineno, parts in rows:
        if len(parts) != 2:
            raise DatasetError(path, f"line {lineno}: expected 'timestamp filename', got {' '.join(parts)!r}")
    t = np.array([_timestamp(path, n, p[0]) for n, p in rows], dtype=np.float64)
    order = _sorted_unique(path, t, np.array([n for n, _ in rows]))
    return t[order], [root / rows[k][1][1] for k in order]


def associate(t_a: np.ndarray, t_b: np.ndarray, max_dt_s: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Pair each ``t_a`` with its nearest ``t_b`` within ``max_dt_s``, each ``t_b`` used at most once.

    Args:
        t_a: ``(N,)`` ascending timestamps (s). t_b: ``(M,)`` ascending timestamps (s).
    Returns:
        ``(ia (K,), ib (K,), nearest_gap_s)``: indices of the pairs in ascending ``ia``; when a ``t_b`` is
        nearest to several ``t_a``, the closest one keeps it. ``nearest_gap_s`` is the smallest
        ``|t_a - t_b|`` over all of ``t_a`` (to report when nothing pairs).
    """
    j = np.searchsorted(t_b, t_a)
    left = np.clip(j - 1, 0, len(t_b) - 1)
    right = np.clip(j, 0, len(t_b) - 1)
    d_left = np.abs(t_a - t_b[left])
    d_right = np.abs(t_b[right] - t_a)
    nearest = np.where(d_right < d_left, right, left)
    dt = np.minimum(d_left, d_right)
    ok = np.nonzero(dt <= max_dt_s * (1 + 1e-9))[0]
    order = ok[np.lexsort((ok, dt[ok]))]  # by gap, then by position
    _, first = np.unique(nearest[order], return_index=True)
    ia = np.sort(order[first])
    return ia, nearest[ia], float(dt.min())


def unpaired_reasons(t_a: np.ndarray, t_b: np.ndarray, used_b: np.ndarray, max_dt_s: float,
                     b_index: str, b_what: str) -> list[str]:
    """Why each of ``t_a`` (all unpaired) has no partner among ``t_b``: too far, or its nearest is taken."""
    if len(t_b) == 0:
        return [f"{b_index} lists no {b_what}"] * len(t_a)
    k = np.searchsorted(t_b, t_a)
    left = np.clip(k - 1, 0, len(t_b) - 1)
    right = np.clip(k, 0, len(t_b) - 1)
    j = np.where(np.abs(t_b[right] - t_a) < np.abs(t_a - t_b[left]), right, left)
    gap = np.abs(t_b[j] - t_a)
    out = []
    for g, jb in zip(gap, j, strict=True):
        if g <= max_dt_s * (1 + 1e-9) and used_b[jb]:
            out.append(f"its nearest {b_what} in {b_index} ({g:.4f} s away) is paired with a closer one")
        else:
            out.append(f"no {b_what} within {max_dt_s} s in {b_index} (the nearest is {g:.4g} s away)")
    return out


def read_tum_entries(root: Path, max_dt_s: float = MAX_RGB_DEPTH_DT_S) -> tuple[list[FrameEntry], list[UnpairedFrame]]:
    """Frames of a TUM-layout folder (rgb.txt + depth.txt, else associations.txt), and the listed images that
    found no partner.

    Raises:
        DatasetError: nothing pairs, or fewer than :data:`MIN_PAIRED_FRACTION` of the listed images do (the
            message names both index files and example stamps).
    """
    rgb_idx, depth_idx, assoc = root / RGB_INDEX, root / DEPTH_INDEX, root / ASSOC_INDEX
    if not (rgb_idx.is_file() and depth_idx.is_file()) and assoc.is_file():
        return _read_associations(assoc, root), []
    t_rgb, rgb_paths = read_timed_files(rgb_idx, root)
    t_depth, depth_paths = read_timed_files(depth_idx, root)
    ia, ib, gap = associate(t_rgb, t_depth, max_dt_s)
    if len(ia) == 0:
        raise DatasetError(
            root,
            f"no rgb/depth pair within {max_dt_s} s between {RGB_INDEX} ({len(t_rgb)} lines) and "
            f"{DEPTH_INDEX} ({len(t_depth)} lines); the nearest gap found is {gap:.6g} s",
        )
    used_rgb = np.zeros(len(t_rgb), bool)
    used_rgb[ia] = True
    used_depth = np.zeros(len(t_depth), bool)
    used_depth[ib] = True
    lone_rgb, lone_depth = np.nonzero(~used_rgb)[0], np.nonzero(~used_depth)[0]
    unpaired = [UnpairedFrame(rgb_paths[k], float(t_rgb[k]), why) for k, why in zip(
        lone_rgb, unpaired_reasons(t_rgb[lone_rgb], t_depth, used_depth, max_dt_s, DEPTH_INDEX, "depth image"),
        strict=True)]
    unpaired += [UnpairedFrame(depth_paths[k], float(t_depth[k]), why) for k, why in zip(
        lone_depth, unpaired_reasons(t_depth[lone_depth], t_rgb, used_rgb, max_dt_s, RGB_INDEX, "colour image"),
        strict=True)]
    listed = max(len(t_rgb), len(t_depth))
    if len(ia) < MIN_PAIRED_FRACTION * listed:
        raise DatasetError(
            root,
            f"only {len(ia)} rgb/depth pair{'' if len(ia) == 1 else 's'} within {max_dt_s} s between {RGB_INDEX} "
            f"({len(t_rgb)} lines) and "
            f"{DEPTH_INDEX} ({len(t_depth)} lines), fewer than {MIN_PAIRED_FRACTION:.0%}; unpaired: "
            f"{unpaired_examples(unpaired)}; check that both files use the same clock and units (seconds)",
        )
    entries = [FrameEntry(float(t_rgb[a]), rgb_paths[a], depth_paths[b], float(t_depth[b]))
               for a, b in zip(ia, ib, strict=True)]
    return entries, unpaired


def _read_associations(path: Path, root: Path) -> list[FrameEntry]:
    """``associations.txt``: ``t_rgb rgb_file t_depth depth_file`` per line (TUM associate.py order)."""
    rows = read_index(path, min_columns=4)
    t = np.array([_timestamp(path, n, p[0]) for n, p in rows], dtype=np.float64)
    t_depth = np.array([_timestamp(path, n, p[2]) for n, p in rows], dtype=np.float64)
    order = _sorted_unique(path, t, np.array([n for n, _ in rows]))
    entries = []
    for k in order:
        _, p = rows[k]
        rgb, depth = p[1], p[3]
        t_d = float(t_depth[k])
        if "depth" in Path(rgb).parts[0] and "rgb" in Path(depth).parts[0]:
            rgb, depth = depth, rgb  # some tools write the depth pair first
            t_d = float(t[k])
        entries.append(FrameEntry(float(t[k]), root / rgb, root / depth, t_d))
    return entries


def read_ground_truth_file(path: Path) -> Trajectory:
    """A TUM ground-truth file; its problems (malformed line, duplicated stamp) are GroundTruthErrors."""
    try:
        return read_tum(path)
    except InputError as exc:
        raise GroundTruthError(path, exc.problem) from None


def read_ground_truth(root: Path, names: tuple[str, ...] = (GT_FILE,)) -> Trajectory | None:
    """The first existing ground-truth file among ``names`` (TUM format), or ``None``."""
    for name in names:
        path = root / name
        if path.is_file():
            return read_ground_truth_file(path)
    return None


def tum_default_intrinsics(root: Path) -> tuple[tuple[float, float, float, float], str]:
    """TUM calibration chosen by ``freiburgN`` / ``frN`` in the folder (or parent) name, else ROS default."""
    for name in (root.name.lower(), root.parent.name.lower()):
        m = _FREIBURG.search(name)
        if m:
            return TUM_INTRINSICS[m.group(1)], f"TUM freiburg{m.group(1)} default (from the folder name)"
    return ROS_DEFAULT_INTRINSICS, "ROS default 525/525/319.5/239.5 (no freiburgN in the folder name)"


class TumSequence(RGBDSequence):
    """TUM RGB-D benchmark layout."""

    layout = "tum"
    stamps_may_be_frame_numbers = True  # TUM-layout copies of ICL-NUIM keep its frame ids
    expects = "rgb.txt + depth.txt ('timestamp filename' lines), optional groundtruth.txt; depth scale 5000"

    @classmethod
    def detect(cls, root: Path, meta: FolderMetadata) -> bool:
        return has_tum_index(root)

    @classmethod
    def open(cls, root: Path, options: DatasetOptions, meta: FolderMetadata | None = None) -> RGBDSequence:
        meta = read_metadata(root) if meta is None else meta
        entries, unpaired = read_tum_entries(root)
        intr, desc = tum_default_intrinsics(root)
        return build_sequence(
            cls, root, entries, options, meta, intr, TUM_DEPTH_SCALE, desc, read_ground_truth(root),
            unpaired=unpaired,
        )


class SyntheticSequence(TumSequence):
    """Written by ``surfelslam synth``: TUM layout whose INFO.txt says ``generator : surfelslam synth``."""

    layout = "synthetic"
    expects = "TUM layout whose INFO.txt has 'generator : surfelslam synth' (written by surfelslam synth)"

    @classmethod
    def detect(cls, root: Path, meta: FolderMetadata) -> bool:
        return meta.is_synthetic and has_tum_index(root)
