"""Microsoft 7-Scenes (Shotton et al. 2013), in either of two forms.

* Native: ``seq-XX/frame-XXXXXX.color.png`` (or ``.jpg``), ``frame-XXXXXX.depth.png`` and
  ``frame-XXXXXX.pose.txt`` (4x4 camera-to-world). Give the ``seq-XX`` folder, or a scene folder holding
  exactly one ``seq-XX``. Timestamps are ``frame number / 30`` s.
* The TUM layout (rgb.txt / depth.txt / groundtruth.txt) in a folder whose name (or parent's) contains
  ``7scenes``, ``7-scenes``, ``7_scenes`` or ``sevenscenes``, or whose ``INFO.txt`` names 7-Scenes in a value.

Camera: fx=fy=585, cx=320, cy=240 (the depth camera; colour is not registered to it); depth in
millimetres (scale 1000), raw 0 and 65535 are invalid.

Colour camera (``SEVENSCENES_COLOUR_CAMERA``): the dataset gives no colour calibration, and its colour images are
the raw Kinect RGB camera's, whose field of view is wider than the depth camera's (a depth pixel 300 px from the
centre sees the colour pixel about 30 px closer to it). The model here was measured on redkitchen frames 0-499
(every 5th) by aligning colour edges (Canny) with depth discontinuities (relative jump > 5 %), minimising their
mean chamfer distance over the colour camera's fx, fy, cx, cy and the horizontal offset between the cameras:
fx 524, fy 530, cx 322, cy 238 and the colour camera 3.2 cm along the depth camera's +x axis (the Kinect v1 RGB
focal length is nominally 525 and its baseline to the IR camera 2.5 cm). Mean edge distance 4.7 px unregistered,
2.5 px with the model; per 50-frame window the fitted scale varies by 1 % and the offsets by 2-3 px.
"""

from __future__ import annotations

import re
import warnings
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
from surfelslam.datasets.tum import has_tum_index, read_ground_truth, read_tum_entries
from surfelslam.errors import DatasetError
from surfelslam.types import ColourCamera, Intrinsics, Trajectory

SEVENSCENES_INTRINSICS = (585.0, 585.0, 320.0, 240.0)
#: The Kinect RGB camera of the 7-Scenes recordings relative to the depth camera (see the module docstring).
SEVENSCENES_COLOUR_CAMERA = ColourCamera(Intrinsics(524.0, 530.0, 322.0, 238.0, 640, 480), (-0.032, 0.0, 0.0))
SEVENSCENES_DEPTH_SCALE = 1000.0
SEVENSCENES_INVALID_RAW = (0, 65535)
#: Frame rate of the Kinect v1 recordings (Hz); timestamps are frame number / this.
SEVENSCENES_FPS_HZ = 30.0
#: Largest deviation of a pose.txt rotation from orthonormal accepted (|R R^T - I| max).
POSE_ORTHONORMAL_TOL = 1e-2
#: Deviation below which an accepted rotation is kept as written; above it, it is replaced by the nearest rotation
#: (the printed matrices carry a few digits only; downstream code assumes exact rotations).
POSE_EXACT_TOL = 1e-9
_NAME = re.compile(r"7[-_ ]?scenes|sevenscenes|seven[-_]scenes")
_FRAME = re.compile(r"^frame-(\d+)\.depth\.png$")
_COLOUR = re.compile(r"^frame-(\d+)\.color\.(?:png|jpg)$")
_DEFAULT_DESC = "7-Scenes default 585/585/320/240, scale 1000 (mm)"


def _seq_dirs(root: Path) -> list[Path]:
    return sorted(p for p in root.glob("seq-*") if p.is_dir())


def _has_frames(folder: Path) -> bool:
    return any(_FRAME.match(p.name) for p in folder.glob("frame-*.depth.png"))


def name_says_7scenes(root: Path) -> bool:
    return any(_NAME.search(n.lower()) for n in (root.name, root.parent.name))


def info_says_7scenes(meta: FolderMetadata) -> bool:
    """Whether the folder's INFO.txt names 7-Scenes in any value (a copy renamed on disk is still 7-Scenes: its
    colour is not registered to depth); never for generated sequences."""
    return not meta.is_synthetic and any(_NAME.search(v.lower()) for v in meta.fields.values())


def _native_folder(root: Path) -> Path | None:
    """The folder holding ``frame-*`` files: ``root`` itself or its single ``seq-XX``; None if neither."""
    if _has_frames(root):
        return root
    seqs = [s for s in _seq_dirs(root) if _has_frames(s)]
    if len(seqs) > 1:
        raise DatasetError(
            root,
            f"holds {len(seqs)} 7-Scenes sequences ({', '.join(s.name for s in seqs)}); give one of them",
        )
    return seqs[0] if seqs else None


def _read_pose(path: Path) -> np.ndarray:
    try:
        with warnings.catch_warnings():  # an empty file: numpy warns, the shape check below says it in one line
            warnings.simplefilter("ignore", UserWarning)
            T = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as exc:
        raise DatasetError(path, f"cannot read a 4x4 pose ({exc})") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        shape = f"{T.shape[0]}x{T.shape[1]}"
        raise DatasetError(path, f"expected a 4x4 camera-to-world matrix, got shape {shape}")
    R = T[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # entries like 1e200: inf / NaN, refused just below
        deviation = np.abs(R @ R.T - np.eye(3)).max()
    if not deviation <= POSE_ORTHONORMAL_TOL or not np.allclose(T[3], [0, 0, 0, 1]):
        raise DatasetError(path, "not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)")
    if np.linalg.det(R) <= 0:  # orthonormal within the tolerance, but a reflection: no rotation
        raise DatasetError(path, "not a rigid transform (the rotation part is a reflection)")
    if deviation > POSE_EXACT_TOL:
        U, _, Vt = np.linalg.svd(R)
        T = T.copy()
        T[:3, :3] = U @ Vt  # the nearest rotation (det > 0 above)
    return T


def _read_native(folder: Path) -> tuple[list[FrameEntry], Trajectory | None, list[UnpairedFrame]]:
    """Frames of a ``seq-XX`` folder, its ground truth, and the colour / depth images without a partner."""
    entries, gt_t, gt_T, unpaired = [], [], [], []
    numbered = sorted(
        (int(m.group(1)), p) for p in folder.glob("frame-*.depth.png") if (m := _FRAME.match(p.name))
    )
    depth_numbers = {n for n, _ in numbered}
    for n, depth in numbered:
        stem = depth.name[: -len(".depth.png")]
        candidates = (folder / f"{stem}.color.png", folder / f"{stem}.color.jpg")
        color = next((c for c in candidates if c.is_file()), None)
        t = n / SEVENSCENES_FPS_HZ
        if color is None:
            unpaired.append(UnpairedFrame(depth, t, f"no colour image {stem}.color.png or .color.jpg"))
            continue
        entries.append(FrameEntry(t, color, depth))
        pose = folder / f"{stem}.pose.txt"
        if pose.is_file():
            gt_t.append(t)
            gt_T.append(_read_pose(pose))
    for p in sorted(folder.glob("frame-*.color.*")):
        m = _COLOUR.match(p.name)
        if m is not None and int(m.group(1)) not in depth_numbers:
            unpaired.append(UnpairedFrame(p, int(m.group(1)) / SEVENSCENES_FPS_HZ,
                                          f"no depth image frame-{m.group(1)}.depth.png"))
    if len(entries) < MIN_PAIRED_FRACTION * (len(entries) + len(unpaired)):
        raise DatasetError(folder, f"only {len(entries)} of the frame-*.depth.png / .color.* images pair up, "
                                   f"fewer than {MIN_PAIRED_FRACTION:.0%}; unpaired: {unpaired_examples(unpaired)}")
    gt = Trajectory(np.array(gt_t), np.array(gt_T)) if gt_t else None
    return entries, gt, unpaired


class SevenScenesSequence(RGBDSequence):
    """Microsoft 7-Scenes (Kinect v1, millimetre depth)."""

    layout = "7scenes"
    colour_registered = False  # 7-Scenes colour and depth come from separate, uncalibrated Kinect cameras
    expects = (
        "seq-XX/frame-XXXXXX.{color.png|color.jpg,depth.png,pose.txt}, or the TUM layout in a folder named "
        "7scenes / 7-scenes (or whose INFO.txt names 7-Scenes); depth in mm"
    )

    @classmethod
    def detect(cls, root: Path, meta: FolderMetadata) -> bool:
        return _native_folder(root) is not None or (
            has_tum_index(root) and (name_says_7scenes(root) or info_says_7scenes(meta)))

    @classmethod
    def open(cls, root: Path, options: DatasetOptions, meta: FolderMetadata | None = None) -> RGBDSequence:
        native = _native_folder(root)
        if native is not None:
            meta = read_metadata(native)
            entries, gt, unpaired = _read_native(native)
            root = native
        else:
            meta = read_metadata(root) if meta is None else meta
            (entries, unpaired), gt = read_tum_entries(root), read_ground_truth(root)
        seq = build_sequence(
            cls, root, entries, options, meta, SEVENSCENES_INTRINSICS, SEVENSCENES_DEPTH_SCALE, _DEFAULT_DESC,
            gt, depth_invalid_raw=SEVENSCENES_INVALID_RAW, unpaired=unpaired,
        )
        # the Kinect colour model holds for the recorded 640x480 images (INFO.txt 'colour intrinsics' overrides it)
        if seq.full_colour_camera is None and seq.full_intrinsics.shape == SEVENSCENES_COLOUR_CAMERA.intrinsics.shape:
            seq.full_colour_camera = SEVENSCENES_COLOUR_CAMERA
        return seq
