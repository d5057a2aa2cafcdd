"""ICL-NUIM (Handa et al. 2014), in either of two forms.

* Native "TUM RGB-D compatible" release: ``rgb/<n>.png``, ``depth/<n>.png`` numbered from 0, plus one
  ``*.gt.freiburg`` trajectory whose first column is a frame id starting at 1. ICL uses frame ids as
  timestamps; the i-th ground-truth line belongs to the i-th image, so image ``n`` gets timestamp
  ``n + (first GT id - first image number)`` (``n + 1`` for the official release) and matches its GT line
  exactly. Timestamps are therefore in *frames*, not seconds (1 frame apart): the trajectory keeps them, so it
  matches the ``*.gt.freiburg`` file, while motion checks take them at 30 Hz (``seconds_per_stamp``).
* The TUM layout (rgb.txt / depth.txt) in a folder whose name (or parent's) says ``icl``,
  ``living_room`` / ``livingRoom`` or ``office`` (but not ``redwood``, ``aug``, ``freiburg``, ``frN``,
  ``tum`` or ``rgbd_dataset``, which are Augmented ICL-NUIM / TUM). Ground truth: ``groundtruth.txt`` or
  ``*.gt.freiburg``.

Camera: fx=481.2, fy=-480 (NEGATIVE, kept: our projection handles it, and the GT poses assume it),
cx=319.5, cy=239.5; depth scale 5000.
"""

from __future__ import annotations

import re
from pathlib import Path

from surfelslam.datasets.base import DatasetOptions, FrameEntry, RGBDSequence
from surfelslam.datasets.folder import has_numbered_folders, paired_numbered_images
from surfelslam.datasets.metadata import FolderMetadata, build_sequence, read_metadata
from surfelslam.datasets.tum import GT_FILE, has_tum_index, read_ground_truth_file, read_tum_entries
from surfelslam.errors import DatasetError
from surfelslam.types import Trajectory

ICL_INTRINSICS = (481.2, -480.0, 319.5, 239.5)
ICL_DEPTH_SCALE = 5000.0
GT_SUFFIX = ".gt.freiburg"
_ICL_NAME = re.compile(r"icl|living_?room|office")
# Augmented ICL-NUIM (Redwood) and TUM names (freiburgN, frN, tum) are not ICL-NUIM.
_NOT_ICL_NAME = re.compile(r"redwood|aug|freiburg|rgbd_dataset|(?<![a-z])(?:fr[123]|tum)(?![a-z0-9])")
_DEFAULT_DESC = "ICL-NUIM default 481.2/-480/319.5/239.5, scale 5000"


def _gt_files(root: Path) -> list[Path]:
    return sorted(root.glob(f"*{GT_SUFFIX}"))


def name_says_icl(root: Path) -> bool:
    """True when the folder's or its parent's name marks ICL-NUIM (and not Augmented ICL / TUM)."""
    names = [root.name.lower(), root.parent.name.lower()]
    return any(_ICL_NAME.search(n) for n in names) and not any(_NOT_ICL_NAME.search(n) for n in names)


def _read_gt_freiburg(root: Path) -> Trajectory | None:
    files = _gt_files(root)
    if len(files) > 1:
        raise DatasetError(root, f"several ground-truth files: {', '.join(f.name for f in files)}; keep one")
    return read_ground_truth_file(files[0]) if files else None


class IclSequence(RGBDSequence):
    """ICL-NUIM living room / office (synthetic, negative fy)."""

    layout = "icl"
    stamps_may_be_frame_numbers = True  # frame ids: motion checks take them at 30 Hz
    expects = (
        "numbered rgb/ + depth/ with a *.gt.freiburg file, or the TUM layout in a folder named "
        "icl / living_room / office; fy=-480, depth scale 5000"
    )

    @classmethod
    def detect(cls, root: Path, meta: FolderMetadata) -> bool:
        native = has_numbered_folders(root) and bool(_gt_files(root))
        return native or (has_tum_index(root) and name_says_icl(root))

    @classmethod
    def open(cls, root: Path, options: DatasetOptions, meta: FolderMetadata | None = None) -> RGBDSequence:
        meta = read_metadata(root) if meta is None else meta
        if has_tum_index(root):
            entries, unpaired = read_tum_entries(root)
            gt = read_ground_truth_file(root / GT_FILE) if (root / GT_FILE).is_file() else _read_gt_freiburg(root)
        else:
            pairs, unpaired = paired_numbered_images(root)
            gt = _read_gt_freiburg(root)
            offset = 0.0 if gt is None else float(gt.timestamps[0]) - pairs[0][0]
            entries = [FrameEntry(n + offset, r, d) for n, r, d in pairs]
            unpaired = [u._replace(timestamp=None) for u in unpaired]  # image numbers, not seconds
        return build_sequence(
            cls, root, entries, options, meta, ICL_INTRINSICS, ICL_DEPTH_SCALE, _DEFAULT_DESC, gt, unpaired=unpaired
        )
