"""Layout detection: which adapter reads a folder, and helpers every command shares.

Detection order (first match wins), so that name- or metadata-based special cases of the TUM layout
come before plain TUM:

1. ``7scenes``   native ``frame-XXXXXX.*`` files (or one ``seq-XX``), or TUM layout named 7scenes/7-scenes
2. ``synthetic`` TUM layout whose ``INFO.txt`` says ``generator : surfelslam synth``
3. ``icl``       numbered ``rgb/`` + ``depth/`` with ``*.gt.freiburg``, or TUM layout named
                 icl / living_room / office
4. ``tum``       any of ``rgb.txt``, ``depth.txt``, ``associations.txt``
5. ``folder``    ``rgb/`` and ``depth/`` with numbered images (camera from options or INFO.txt)
6. ``rosbag``    a ROS 1 ``.bag``, a ROS 2 bag folder (``metadata.yaml``), or an ``.mcap`` / ``.db3`` file
                 (a file path is only ever a bag: :mod:`surfelslam.datasets.rosbag`)

``realsense`` (when no file or folder has that name) is the live camera (:mod:`surfelslam.datasets.realsense`).

``DatasetOptions.gt`` (``--gt FILE``) replaces any layout's ground truth by a TUM trajectory file (for a bag it may
also name a pose topic).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from surfelslam.datasets.base import DatasetOptions, RGBDSequence, check_selection
from surfelslam.datasets.folder import FolderSequence
from surfelslam.datasets.icl import IclSequence
from surfelslam.datasets.metadata import read_metadata
from surfelslam.datasets.plausibility import check_plausibility
from surfelslam.datasets.realsense import is_realsense
from surfelslam.datasets.rosbag import RosbagSequence, is_bag, looks_like_bag
from surfelslam.datasets.sevenscenes import SevenScenesSequence
from surfelslam.datasets.tum import SyntheticSequence, TumSequence
from surfelslam.errors import ConfigError, DatasetError, GroundTruthError
from surfelslam.types import RGBDFrame, Trajectory

#: Adapter name -> adapter class, in detection order.
LAYOUTS: dict[str, type[RGBDSequence]] = {
    cls.layout: cls
    for cls in (SevenScenesSequence, SyntheticSequence, IclSequence, TumSequence, FolderSequence, RosbagSequence)
}

#: Median valid depth of one frame outside this range (metres) suggests a wrong depth scale.
PLAUSIBLE_MEDIAN_DEPTH_M = (0.2, 10.0)


def known_layouts_text() -> str:
    return "; ".join(f"{name}: {cls.expects}" for name, cls in LAYOUTS.items())  # type: ignore[attr-defined]


def detect_layout(path: str | Path) -> str:
    """Name of the first adapter (in :data:`LAYOUTS` order) that recognises the folder.

    Raises:
        DatasetError: missing folder, empty folder, or no layout matches (the message lists the layouts).
    """
    root = Path(path)
    if not root.exists():
        raise DatasetError(root, "bag not found" if looks_like_bag(root) else "sequence folder not found")
    if is_bag(root):
        return RosbagSequence.layout
    if not root.is_dir():
        raise DatasetError(root, "not a folder (give the sequence folder)")
    if not any(root.iterdir()):
        raise DatasetError(root, "sequence folder is empty")
    meta = read_metadata(root)
    for name, cls in LAYOUTS.items():
        if cls.detect(root, meta):  # type: ignore[attr-defined]
            return name
    raise DatasetError(root, f"not a known RGB-D sequence layout. Known layouts: {known_layouts_text()}")


def open_sequence(
    path: str | Path, options: DatasetOptions | None = None, layout: str | None = None,
    plausibility: str = "refuse",
) -> RGBDSequence:
    """Open a sequence folder with the adapter its layout calls for.

    Args:
        path: the sequence folder.
        options: user overrides and frame selection (default: none).
        layout: force an adapter by name (a key of :data:`LAYOUTS`) instead of detecting it.
        plausibility: ``"refuse"``: implausible intrinsics or depth scale raise DatasetError naming the option
            (:mod:`surfelslam.datasets.plausibility`); ``"warn"``: they are only listed in ``seq.warnings``
            (for diagnosis, ``surfelslam info``).
    Raises:
        DatasetError / FrameError: unreadable folder or index files, too few images pairing, implausible camera.
        ConfigError: bad options, unknown ``layout``, missing camera for the plain folder layout, or a
        selection with no frames.

    The returned sequence lists the images that found no partner in ``seq.unpaired`` and open-time doubts in
    ``seq.warnings``.
    """
    options = DatasetOptions() if options is None else options
    root = Path(path)
    if layout is None and is_realsense(root):
        from surfelslam.datasets.realsense import open_realsense

        return open_realsense(options)  # type: ignore[return-value]  # frames are read once: no sampling here
    if layout is None:
        layout = detect_layout(root)
    elif layout not in LAYOUTS:
        raise ConfigError(f"unknown layout {layout!r}; known: {', '.join(LAYOUTS)}")
    elif not (root.is_dir() or (layout == RosbagSequence.layout and root.is_file())):
        raise DatasetError(root, "sequence folder not found")
    seq = LAYOUTS[layout].open(root, options)  # type: ignore[attr-defined]
    check_selection(seq)
    if options.gt is not None and layout != RosbagSequence.layout:  # the bag reader takes a file or a topic
        from surfelslam.datasets.tum import read_ground_truth_file

        if not Path(options.gt).is_file():
            raise DatasetError(Path(options.gt), "--gt: ground-truth file not found")
        seq.ground_truth = read_ground_truth_file(Path(options.gt))
    if len(seq) == 0:
        raise ConfigError(
            f"{root}: the selection (--start {options.start} --end {options.end} --stride {options.stride}) "
            f"keeps no frame of the {len(seq.all_entries)}"
        )
    check_plausibility(seq, plausibility)
    return seq


def require_ground_truth(seq: RGBDSequence, max_dt_s: float = 0.02) -> Trajectory:
    """The sequence's ground truth, or GroundTruthError when it has none or none of its frames match it."""
    if seq.ground_truth is None:
        raise GroundTruthError(seq.root, "this sequence has no ground truth (e.g. groundtruth.txt)")
    _, valid = seq.gt_poses(max_dt_s)
    if not valid.any():
        raise GroundTruthError(
            seq.root, f"no frame has a ground-truth pose within {max_dt_s} s of its timestamp"
        )
    return seq.ground_truth


def median_valid_depth_m(frame: RGBDFrame) -> float | None:
    """Median of the frame's valid depth (metres), ``None`` when no pixel is valid."""
    d = frame.depth_m[frame.depth_m > 0]
    return float(np.median(d)) if d.size else None


def check_depth_scale(
    frame: RGBDFrame,
    depth_scale: float | None = None,
    plausible_m: tuple[float, float] = PLAUSIBLE_MEDIAN_DEPTH_M,
) -> str | None:
    """A warning when the frame's median depth is implausible for an indoor RGB-D sensor, else ``None``."""
    med = median_valid_depth_m(frame)
    scale = "" if depth_scale is None else f" (now {depth_scale:g} units per metre)"
    if med is None:
        return f"frame {frame.index} has no valid depth pixel; check --depth-scale{scale} and the depth files"
    if not plausible_m[0] <= med <= plausible_m[1]:
        return (
            f"median depth of frame {frame.index} is {med:.3g} m, "
            f"outside {plausible_m[0]}-{plausible_m[1]} m; "
            f"is the depth scale right{scale}?"
        )
    return None


def describe(seq: RGBDSequence) -> dict:
    """``seq.info()`` plus where the camera came from and the first frame's median depth (loads frame 0)."""
    out = seq.info()
    out["full_resolution"] = [seq.full_intrinsics.width, seq.full_intrinsics.height]
    out["intrinsics_source"] = seq.intrinsics_source
    out["depth_scale_source"] = seq.depth_scale_source
    first = seq[0]
    med = median_valid_depth_m(first)
    out["first_frame_median_depth_m"] = None if med is None else round(med, 4)
    out["first_frame_valid_depth_fraction"] = round(float((first.depth_m > 0).mean()), 4)
    out["depth_scale_warning"] = check_depth_scale(first, seq.depth_scale)
    return out
