"""Camera descriptions that sequence folders carry themselves, and how they combine with options.

Two sources are read, when present in the sequence folder:

* ``INFO.txt``: free text with ``key : value`` lines (a line starting with white space continues the
  previous value). Used keys: ``intrinsics`` (the first ``fx=``, ``fy=``, ``cx=``, ``cy=`` numbers in the
  value, or else the first four numbers of its first line), ``depth scale`` (the first number of the
  value), ``generator`` (``surfelslam synth`` marks our synthetic sequences) and, for a colour camera separate
  from the depth camera, ``colour intrinsics`` (as ``intrinsics``, on the colour image's pixel grid) with
  ``colour translation`` (``tx ty tz`` in metres, depth camera frame to colour camera frame; default 0): the
  maps' colours are then sampled through that camera (:func:`surfelslam.geometry.camera.colour_at_depth_pixels`)
  and the sequence counts as not registered (photometric terms off under ``auto``).
* ``camera-intrinsics.txt`` (7-Scenes / tsdf-fusion style): a 3x3 camera matrix, in the folder or its
  parent. Only used for what ``INFO.txt`` does not give.

Precedence, highest first: command-line options > metadata in the folder > the layout's defaults
(which may depend on the folder name, e.g. TUM freiburg1/2/3).
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from surfelslam.datasets.base import (
    FRAME_NUMBER_RATE_HZ,
    DatasetOptions,
    FrameEntry,
    RGBDSequence,
    UnpairedFrame,
    stamps_are_frame_numbers,
)
from surfelslam.errors import ConfigError, DatasetError, FrameError
from surfelslam.types import ColourCamera, Intrinsics, Trajectory

INFO_FILE = "INFO.txt"
CAMERA_INTRINSICS_FILE = "camera-intrinsics.txt"
SYNTH_GENERATOR = "surfelslam synth"

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_KEY_LINE = re.compile(r"^(?P<key>[A-Za-z][^:]*?)\s*:\s?(?P<value>.*)$")


@dataclass(frozen=True)
class FolderMetadata:
    """What a sequence folder says about its own camera.

    Attributes:
        intrinsics: ``(fx, fy, cx, cy)`` at full resolution, or ``None``.
        depth_scale: raw depth units per metre, or ``None``.
        generator: the ``generator`` value of ``INFO.txt`` (lower case), or ``None``.
        intrinsics_file / depth_scale_file: the file each value came from.
        fields: every ``key : value`` of ``INFO.txt`` (keys lower case, single-spaced).
        colour_intrinsics: ``(fx, fy, cx, cy)`` of a separate colour camera, or ``None``.
        colour_translation_m: ``(tx, ty, tz)`` from the depth camera frame to that colour camera's (m).
    """

    intrinsics: tuple[float, float, float, float] | None = None
    depth_scale: float | None = None
    generator: str | None = None
    intrinsics_file: Path | None = None
    depth_scale_file: Path | None = None
    fields: dict[str, str] = field(default_factory=dict)
    colour_intrinsics: tuple[float, float, float, float] | None = None
    colour_translation_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def is_synthetic(self) -> bool:
        return self.generator is not None and SYNTH_GENERATOR in self.generator


@dataclass(frozen=True)
class CameraSetup:
    """The camera a sequence ends up with, and where each value came from."""

    intrinsics: Intrinsics
    depth_scale: float
    intrinsics_source: str
    depth_scale_source: str
    #: where the intrinsics came from: "option" (--intrinsics), "file" (a metadata file) or "default" (layout)
    intrinsics_kind: str = "default"


def read_info_fields(path: Path) -> dict[str, str]:
    """``key : value`` lines of an INFO.txt-style file; continuation lines are appended to the value."""
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise DatasetError(path, f"cannot read metadata file ({exc.strerror or exc})") from None
    fields: dict[str, str] = {}
    key = None
    for line in text.splitlines():
        if not line.strip():
            key = None
            continue
        if line[0].isspace():
            if key is not None:
                fields[key] += "\n" + line.strip()
            continue
        m = _KEY_LINE.match(line)
        if m is None:
            key = None
            continue
        key = " ".join(m.group("key").lower().split())
        fields.setdefault(key, "")
        fields[key] = (fields[key] + "\n" + m.group("value").strip()).strip()
    return fields


def parse_intrinsics_text(text: str) -> tuple[float, float, float, float] | None:
    """``fx=.. fy=.. cx=.. cy=..`` (first match of each) or the first four numbers of the first line."""
    vals = []
    for name in ("fx", "fy", "cx", "cy"):
        m = re.search(rf"\b{name}\s*=\s*({_NUMBER})", text)
        if m is None:
            break
        vals.append(float(m.group(1)))
    if len(vals) != 4:
        first_line = text.splitlines()[0] if text else ""
        nums = re.findall(_NUMBER, first_line)
        if len(nums) < 4:
            return None
        vals = [float(x) for x in nums[:4]]
    if not all(np.isfinite(vals)) or vals[0] == 0 or vals[1] == 0:
        return None
    return (vals[0], vals[1], vals[2], vals[3])


def parse_depth_scale_text(text: str) -> float | None:
    """The first number of the value (``1000 (MILLIMETRES ...)`` -> 1000)."""
    m = re.search(_NUMBER, text)
    if m is None:
        return None
    val = float(m.group(0))
    return val if val > 0 and np.isfinite(val) else None


def read_camera_matrix(path: Path) -> tuple[float, float, float, float]:
    """A 3x3 camera matrix file (7-Scenes ``camera-intrinsics.txt``) -> ``(fx, fy, cx, cy)``."""
    try:
        with warnings.catch_warnings():  # an empty file: numpy warns, the shape check below says it in one line
            warnings.simplefilter("ignore", UserWarning)
            K = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as exc:
        raise DatasetError(path, f"cannot read a 3x3 camera matrix ({exc})") from None
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise DatasetError(path, f"expected a 3x3 camera matrix, got shape {K.shape[0]}x{K.shape[1]}")
    if K[0, 0] == 0 or K[1, 1] == 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise DatasetError(path, "not a camera matrix (zero focal length or last row is not 0 0 1)")
    return (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))


def read_metadata(root: Path) -> FolderMetadata:
    """Read ``INFO.txt`` and ``camera-intrinsics.txt`` of a sequence folder (each optional)."""
    root = Path(root)
    intr = scale = generator = None
    intr_file = scale_file = None
    fields: dict[str, str] = {}
    info = root / INFO_FILE
    if info.is_file():
        fields = read_info_fields(info)
        if "intrinsics" in fields:
            intr = parse_intrinsics_text(fields["intrinsics"])
            intr_file = info if intr is not None else None
        if "depth scale" in fields:
            scale = parse_depth_scale_text(fields["depth scale"])
            scale_file = info if scale is not None else None
        if "generator" in fields:
            generator = fields["generator"].strip().lower()
        colour_intr, colour_t = _colour_camera_fields(info, fields)
    else:
        colour_intr, colour_t = None, (0.0, 0.0, 0.0)
    if intr is None:
        for cand in (root / CAMERA_INTRINSICS_FILE, root.parent / CAMERA_INTRINSICS_FILE):
            if cand.is_file():
                intr, intr_file = read_camera_matrix(cand), cand
                break
    return FolderMetadata(intr, scale, generator, intr_file, scale_file, fields, colour_intr, colour_t)


def _colour_camera_fields(info: Path, fields: dict[str, str]
                          ) -> tuple[tuple[float, float, float, float] | None, tuple[float, float, float]]:
    """``colour intrinsics`` / ``colour translation`` of INFO.txt; a malformed value is a DatasetError."""
    t = (0.0, 0.0, 0.0)
    if "colour translation" in fields:
        first_line = (fields["colour translation"].splitlines() or [""])[0]
        nums = re.findall(_NUMBER, first_line)
        if len(nums) < 3 or not all(np.isfinite([float(x) for x in nums[:3]])):
            raise DatasetError(info, "'colour translation' needs three numbers 'tx ty tz' (metres)")
        t = (float(nums[0]), float(nums[1]), float(nums[2]))
    if "colour intrinsics" not in fields:
        if "colour translation" in fields:
            raise DatasetError(info, "'colour translation' is given without 'colour intrinsics'")
        return None, t
    intr = parse_intrinsics_text(fields["colour intrinsics"])
    if intr is None:
        raise DatasetError(info, "'colour intrinsics' needs fx=.. fy=.. cx=.. cy=.. (non-zero focal lengths)")
    return intr, t


#: Depth images tried for the image size, from the sequence's first frame on, when the first are unreadable.
SIZE_PROBE_MAX_FRAMES = 30


def first_depth_shape(path: Path) -> tuple[int, int]:
    """``(height, width)`` of a depth image (the sequence's resolution); FrameError if unreadable."""
    from surfelslam.io.images import read_depth_raw

    return read_depth_raw(path).shape  # type: ignore[return-value]


def probe_image_size(entries: list[FrameEntry], max_frames: int = SIZE_PROBE_MAX_FRAMES) -> tuple[int, int]:
    """``(height, width)`` of the sequence's first readable depth image (whatever the selection): a corrupt first
    frame is skipped here and reported when the frame is loaded.

    Raises:
        FrameError: the only frame tried is unreadable. DatasetError: none of the ``max_frames`` tried is.
    """
    first: FrameError | None = None
    tried = entries[:max_frames]
    for e in tried:
        try:
            return first_depth_shape(e.depth_path)
        except FrameError as exc:
            first = exc if first is None else first
    assert first is not None, "no frames to probe"
    if len(tried) == 1:
        raise first
    raise DatasetError(first.path, f"{first.problem}; none of the {len(tried)} depth images tried from here on is "
                                   "readable, so the image size is unknown")


def resolve_camera(
    options: DatasetOptions,
    meta: FolderMetadata,
    layout_intrinsics: tuple[float, float, float, float] | None,
    layout_depth_scale: float | None,
    layout_desc: str,
    entries: list[FrameEntry],
) -> CameraSetup | None:
    """Combine options > folder metadata > layout defaults; ``None`` when a value has no source at all.

    The resolution comes from the first readable depth image (:func:`probe_image_size`).
    """
    if options.intrinsics is not None:
        intr, intr_src, kind = options.intrinsics, "--intrinsics", "option"
    elif meta.intrinsics is not None:
        intr, intr_src, kind = meta.intrinsics, str(meta.intrinsics_file), "file"
    else:
        intr, intr_src, kind = layout_intrinsics, layout_desc, "default"
    if options.depth_scale is not None:
        scale, scale_src = options.depth_scale, "--depth-scale"
    elif meta.depth_scale is not None:
        scale, scale_src = meta.depth_scale, str(meta.depth_scale_file)
    else:
        scale, scale_src = layout_depth_scale, layout_desc
    if intr is None or scale is None:
        return None
    h, w = probe_image_size(entries)
    fx, fy, cx, cy = (float(x) for x in intr)
    return CameraSetup(Intrinsics(fx, fy, cx, cy, int(w), int(h)), float(scale), intr_src, scale_src, kind)


def build_sequence(
    cls: type[RGBDSequence],
    root: Path,
    entries: list[FrameEntry],
    options: DatasetOptions,
    meta: FolderMetadata,
    layout_intrinsics: tuple[float, float, float, float] | None,
    layout_depth_scale: float | None,
    layout_desc: str,
    ground_truth: Trajectory | None = None,
    depth_invalid_raw: tuple[int, ...] = (0,),
    unpaired: list[UnpairedFrame] | None = None,
) -> RGBDSequence:
    """Construct an adapter's sequence once its files are listed (shared by every adapter).

    ``unpaired``: the listed images that found no partner (kept as the sequence's ``unpaired``).

    Raises:
        DatasetError: no frames. ConfigError: intrinsics or depth scale known from nowhere.
    """
    if not entries:
        raise DatasetError(root, "no frames found")
    stamps = np.array([e.timestamp for e in entries])
    same = np.nonzero(np.diff(stamps) <= 0)[0]
    if len(same):  # frame numbers beyond 2**53 (or their offset) round to the same float
        a, b = entries[same[0]].rgb_path.name, entries[same[0] + 1].rgb_path.name
        raise DatasetError(root, f"frames {a} and {b} get the same timestamp {stamps[same[0]]:.6f}: their frame "
                                 "numbers or stamps are too large to tell apart")
    cam = resolve_camera(options, meta, layout_intrinsics, layout_depth_scale, layout_desc, entries)
    if cam is None:
        missing = []
        if options.intrinsics is None and meta.intrinsics is None and layout_intrinsics is None:
            missing.append("--intrinsics fx,fy,cx,cy")
        if options.depth_scale is None and meta.depth_scale is None and layout_depth_scale is None:
            missing.append("--depth-scale UNITS_PER_METRE")
        raise ConfigError(
            f"{root}: the {cls.layout!r} layout has no camera defaults; give {' and '.join(missing)} "
            f"(or write an {INFO_FILE} with 'intrinsics : fx=.. fy=.. cx=.. cy=..' and 'depth scale : N')"
        )
    seq = cls(root, entries, cam.intrinsics, cam.depth_scale, options, ground_truth, depth_invalid_raw)
    seq.unpaired = list(unpaired or [])
    if cls.stamps_may_be_frame_numbers and stamps_are_frame_numbers(np.array([e.timestamp for e in entries])):
        seq.seconds_per_stamp = 1.0 / FRAME_NUMBER_RATE_HZ
        seq.warnings.append(f"{root}: timestamps count frames (whole numbers, 1 or more apart), not seconds: taken "
                            f"as {FRAME_NUMBER_RATE_HZ:g} Hz for the motion checks; the trajectory keeps them")
    seq.intrinsics_kind = cam.intrinsics_kind
    if meta.colour_intrinsics is not None:  # colour images have the depth images' size (checked per frame)
        seq.full_colour_camera = ColourCamera(Intrinsics(*meta.colour_intrinsics, cam.intrinsics.width,
                                                         cam.intrinsics.height), meta.colour_translation_m)
        seq.colour_registered = False
    prefix = f"{root}/"  # show metadata files inside the sequence folder by their name
    seq.intrinsics_source = cam.intrinsics_source.removeprefix(prefix)
    seq.depth_scale_source = cam.depth_scale_source.removeprefix(prefix)
    return seq
