"""Plain folder layout: numbered images in ``rgb/`` and ``depth/`` (e.g. ``rgb/12.png``, ``depth/12.png``).

Files pair by the last number in their name and are ordered numerically; an image whose number the other
folder lacks is listed in the sequence's ``unpaired`` (fewer than half paired: refused). There are no timestamps: frame
number ``n`` gets ``n / FOLDER_FPS_HZ`` seconds. Intrinsics and depth scale must come from the options
(``--intrinsics``, ``--depth-scale``) or from an ``INFO.txt`` in the folder. An optional
``groundtruth.txt`` (TUM format, same timestamps) is read.
"""

from __future__ import annotations

import re
from pathlib import Path

from surfelslam.datasets.base import (
    MIN_PAIRED_FRACTION,
    DatasetOptions,
    FrameEntry,
    RGBDSequence,
    UnpairedFrame,
    unpaired_examples,
)
from surfelslam.datasets.metadata import FolderMetadata, build_sequence, read_metadata
from surfelslam.datasets.tum import read_ground_truth
from surfelslam.errors import DatasetError

#: Frame rate assumed for timestamps of numbered images (Hz).
FOLDER_FPS_HZ = 30.0
RGB_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".ppm")
DEPTH_SUFFIXES = (".png", ".tif", ".tiff", ".pgm")
_LAST_NUMBER = re.compile(r"(\d+)(?!.*\d)")


def numbered_images(folder: Path, suffixes: tuple[str, ...]) -> dict[int, Path]:
    """``{number: path}`` of the images in ``folder`` whose name holds a number (the last one counts).

    Raises:
        DatasetError: two files carry the same number.
    """
    out: dict[int, Path] = {}
    if not folder.is_dir():
        return out
    for p in folder.iterdir():
        if p.suffix.lower() not in suffixes or not p.is_file():
            continue
        m = _LAST_NUMBER.search(p.stem)
        if m is None:
            continue
        n = int(m.group(1))
        if n in out:
            raise DatasetError(folder, f"two images carry number {n}: {out[n].name} and {p.name}")
        out[n] = p
    return out


def paired_numbered_images(
    root: Path, rgb_dir: str = "rgb", depth_dir: str = "depth"
) -> tuple[list[tuple[int, Path, Path]], list[UnpairedFrame]]:
    """``(number, rgb path, depth path)`` for numbers present in both folders, ascending, and the images whose
    number the other folder lacks (timestamps ``number / FOLDER_FPS_HZ``).

    Raises:
        DatasetError: no images, no number common to both folders, or fewer than
            :data:`MIN_PAIRED_FRACTION` of the images pair.
    """
    rgb = numbered_images(root / rgb_dir, RGB_SUFFIXES)
    depth = numbered_images(root / depth_dir, DEPTH_SUFFIXES)
    for name, found, suf in ((rgb_dir, rgb, RGB_SUFFIXES), (depth_dir, depth, DEPTH_SUFFIXES)):
        if not found:
            raise DatasetError(root / name, f"no numbered images ({', '.join(suf)}) in this folder")
    common = sorted(set(rgb) & set(depth))
    if not common:
        raise DatasetError(
            root,
            f"{rgb_dir}/ ({min(rgb)}..{max(rgb)}) and {depth_dir}/ ({min(depth)}..{max(depth)}) "
            "share no image number",
        )
    unpaired = [UnpairedFrame(rgb[n], n / FOLDER_FPS_HZ, f"no image numbered {n} in {depth_dir}/")
                for n in sorted(set(rgb) - set(depth))]
    unpaired += [UnpairedFrame(depth[n], n / FOLDER_FPS_HZ, f"no image numbered {n} in {rgb_dir}/")
                 for n in sorted(set(depth) - set(rgb))]
    listed = max(len(rgb), len(depth))
    if len(common) < MIN_PAIRED_FRACTION * listed:
        raise DatasetError(
            root,
            f"only {len(common)} image numbers are in both {rgb_dir}/ ({len(rgb)} images) and {depth_dir}/ "
            f"({len(depth)} images), fewer than {MIN_PAIRED_FRACTION:.0%}; unpaired: {unpaired_examples(unpaired)}",
        )
    return [(n, rgb[n], depth[n]) for n in common], unpaired


def has_numbered_folders(root: Path) -> bool:
    return (root / "rgb").is_dir() and (root / "depth").is_dir()


class FolderSequence(RGBDSequence):
    """Numbered ``rgb/`` + ``depth/`` images with user-given camera."""

    layout = "folder"
    expects = (
        "rgb/ and depth/ with numbered images (rgb/0.png, depth/0.png, ...); "
        "needs --intrinsics and --depth-scale (or an INFO.txt)"
    )

    @classmethod
    def detect(cls, root: Path, meta: FolderMetadata) -> bool:
        return has_numbered_folders(root)

    @classmethod
    def open(cls, root: Path, options: DatasetOptions, meta: FolderMetadata | None = None) -> RGBDSequence:
        meta = read_metadata(root) if meta is None else meta
        pairs, unpaired = paired_numbered_images(root)
        entries = [FrameEntry(n / FOLDER_FPS_HZ, r, d) for n, r, d in pairs]
        return build_sequence(cls, root, entries, options, meta, None, None, "none", read_ground_truth(root),
                              unpaired=unpaired)
