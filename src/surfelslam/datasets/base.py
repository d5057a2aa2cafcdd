"""The sequence interface every dataset adapter implements.

An adapter only has to list its files (``_entries``) and its native intrinsics / depth scale;
selection (start/end/stride), downsampling, image decoding and validation live here, once.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from surfelslam.errors import ConfigError, FrameError
from surfelslam.geometry.interpolation import interpolate_poses
from surfelslam.types import ColourCamera, Intrinsics, RGBDFrame, Trajectory

#: Largest gap (s) between two ground-truth poses that :meth:`RGBDSequence.gt_poses` interpolates across
#: (TUM motion capture runs at 100 Hz; a longer gap is a dropout, where the nearest pose is used instead).
GT_INTERPOLATION_MAX_GAP_S = 0.05
#: Frame rate (Hz) taken for sequences stamped by frame number (ICL-NUIM renders its trajectories at 30 Hz).
FRAME_NUMBER_RATE_HZ = 30.0


def stamps_are_frame_numbers(stamps: np.ndarray) -> bool:
    """Whether ``stamps`` ``(N,)`` count frames rather than seconds: all whole numbers, and consecutive frames
    at least 1 apart (ICL-NUIM's frame ids; no RGB-D camera records at 1 Hz or slower with whole-second stamps)."""
    t = np.asarray(stamps, np.float64)
    if len(t) < 2 or not np.all(np.isfinite(t)) or np.any(t != np.round(t)):
        return False
    steps = np.diff(t)
    return bool(np.all(steps > 0) and np.median(steps) >= 1.0)


@dataclass(frozen=True)
class DatasetOptions:
    """User overrides common to every adapter (the CLI's dataset options).

    Attributes:
        intrinsics: ``(fx, fy, cx, cy)`` at full resolution, overriding the layout's default.
        depth_scale: raw depth units per metre (5000 for TUM, 1000 for millimetres).
        start: first frame position (0-based, in the full sequence).
        end: one past the last frame position (``None``: to the end).
        stride: keep every ``stride``-th frame.
        downsample: image sampling factor ``[::n, ::n]`` (intrinsics divided by n).
        rgb_topic: the colour image topic of a ROS bag / MCAP file (``None``: found by message type and name).
        depth_topic: the depth image topic of a ROS bag / MCAP file (``None``: found by message type and name).
        camera_info_topic: the ``CameraInfo`` topic giving the intrinsics of a bag (``None``: found by type and name).
        gt: ground truth replacing the sequence's own: a TUM trajectory file, or a bag's pose topic.
    """

    intrinsics: tuple[float, float, float, float] | None = None
    depth_scale: float | None = None
    start: int = 0
    end: int | None = None
    stride: int = 1
    downsample: int = 1
    rgb_topic: str | None = None
    depth_topic: str | None = None
    camera_info_topic: str | None = None
    gt: str | None = None

    def __post_init__(self) -> None:
        if self.start < 0:
            raise ConfigError(f"--start must be >= 0, got {self.start}")
        if self.end is not None and self.end <= self.start:
            raise ConfigError(f"--end ({self.end}) must be greater than --start ({self.start})")
        if self.stride < 1:
            raise ConfigError(f"--stride must be >= 1, got {self.stride}")
        if self.downsample < 1:
            raise ConfigError(f"--downsample must be >= 1, got {self.downsample}")
        if self.depth_scale is not None and not (self.depth_scale > 0 and np.isfinite(self.depth_scale)):
            raise ConfigError(f"--depth-scale must be a positive number, got {self.depth_scale}")
        if self.intrinsics is not None:
            if len(self.intrinsics) != 4 or not all(np.isfinite(self.intrinsics)):
                raise ConfigError(f"--intrinsics must be four numbers fx,fy,cx,cy, got {self.intrinsics}")
            if self.intrinsics[0] == 0 or self.intrinsics[1] == 0:
                raise ConfigError("--intrinsics: focal lengths must be non-zero")


#: Smallest image side (px) after ``--downsample``: the default image pyramid (4 levels) halves a side three times;
#: below 16 px its coarsest level has under 2 pixels a side and cannot be tracked.
MIN_DOWNSAMPLED_SIDE_PX = 16


def check_selection(seq: RGBDSequence) -> None:
    """Check the options against the opened sequence (its image size and frame count) before anything runs:
    ConfigError naming the option for a selection that cannot work (``--downsample`` taking the images below
    :data:`MIN_DOWNSAMPLED_SIDE_PX`, files that small already excepted; ``--start`` past the last frame); an
    ``--end`` past the last frame is a warning (``seq.warnings``)."""
    o, full, n = seq.options, seq.full_intrinsics, len(seq.all_entries)
    w, h = seq.intrinsics.width, seq.intrinsics.height
    if o.downsample > 1 and min(w, h) < MIN_DOWNSAMPLED_SIDE_PX <= min(full.width, full.height):
        largest = max(1, min(full.width, full.height) // MIN_DOWNSAMPLED_SIDE_PX)
        raise ConfigError(f"{seq.root}: --downsample {o.downsample} turns the {full.width}x{full.height} images "
                          f"into {w}x{h}, below {MIN_DOWNSAMPLED_SIDE_PX} pixels a side; use --downsample "
                          f"{largest} or less")
    if o.start >= n:
        raise ConfigError(f"{seq.root}: --start {o.start} keeps no frame: the sequence has {n} frames "
                          f"(positions 0-{n - 1})")
    if o.end is not None and o.end > n:
        seq.warnings.append(f"{seq.root}: --end {o.end} is past the last frame ({n} frames): the selection ends "
                            "with the sequence")


class UnpairedFrame(NamedTuple):
    """A file an index or image folder lists that did not become a frame (it has no partner).

    ``file``: the colour or depth image; ``timestamp``: its stamp (s) when the layout has one, else ``None``;
    ``reason``: why it has no partner, naming the index file or folder it was looked for in.
    """

    file: Path
    timestamp: float | None
    reason: str


#: Below this fraction of listed images in pairs, a sequence is refused (the index files disagree).
MIN_PAIRED_FRACTION = 0.5
#: Unpaired images quoted in an error message.
UNPAIRED_EXAMPLES = 3


def unpaired_examples(unpaired: list[UnpairedFrame], n: int = UNPAIRED_EXAMPLES) -> str:
    """``'rgb/1.png (t=1.000000), ...'`` for the first ``n`` unpaired images (for one-line messages)."""
    parts = [f"{u.file.parent.name}/{u.file.name}" + ("" if u.timestamp is None else f" (t={u.timestamp:.6f})")
             for u in unpaired[:n]]
    return ", ".join(parts) + (f" and {len(unpaired) - n} more" if len(unpaired) > n else "")


@dataclass(frozen=True)
class FrameEntry:
    """One frame's files before loading: timestamps in seconds, absolute paths.

    ``timestamp`` is the frame's (the colour image's) stamp; ``depth_timestamp`` the depth image's when the
    layout records a separate one (TUM: colour and depth are captured up to 20 ms apart), else ``None``.
    """

    timestamp: float
    rgb_path: Path
    depth_path: Path
    depth_timestamp: float | None = None


class RGBDSequence:
    """A selected, possibly downsampled RGB-D sequence.

    Attributes:
        layout: adapter name (``"tum"``, ``"icl"``, ``"7scenes"``, ``"folder"``, ``"synthetic"``).
        root: the sequence folder.
        intrinsics: intrinsics *after* downsampling.
        full_intrinsics: intrinsics at the files' resolution.
        depth_scale: raw depth units per metre.
        entries: selected frames' files, in time order.
        ground_truth: the whole ground-truth trajectory, or ``None`` when the folder has none.
        unpaired: images the index files or folders list that found no partner (colour without depth or the
            reverse), as :class:`UnpairedFrame`, within the selection's stamp range (``all_unpaired``: all of
            them); they are not frames of the sequence. Filled at open time.
        warnings: doubts found at open time that do not stop a run (e.g. a layout's default intrinsics that do
            not fit the image size), one line each.

    ``seq[i]`` loads frame ``i`` of the selection as an :class:`RGBDFrame` whose ``index`` is ``i``;
    a corrupt file raises :class:`FrameError` naming it.
    """

    layout: str = "base"
    #: whether colour pixel (u, v) and depth pixel (u, v) see the same ray (one camera, or depth registered to
    #: colour); False for layouts whose colour and depth come from separate, uncalibrated cameras (7-Scenes)
    colour_registered: bool = True
    #: the separate colour camera at the files' resolution, when the layout knows it (``colour_camera`` has it
    #: at the selection's resolution); ``None``: colour registered, or no model known
    full_colour_camera: ColourCamera | None = None
    #: where the intrinsics / depth scale came from (an option, a metadata file, or the layout default)
    intrinsics_source: str = "unknown"
    depth_scale_source: str = "unknown"
    #: "option" (--intrinsics), "file" (a metadata file in the folder) or "default" (the layout's)
    intrinsics_kind: str = "default"
    #: whether the layout's stamps may count frames instead of seconds (:func:`stamps_are_frame_numbers`)
    stamps_may_be_frame_numbers: bool = False
    #: seconds per unit of the frame stamps (1/30 when they count frames); the frames carry it (``time_s``)
    seconds_per_stamp: float = 1.0

    def __init__(
        self,
        root: Path,
        entries: list[FrameEntry],
        full_intrinsics: Intrinsics,
        depth_scale: float,
        options: DatasetOptions,
        ground_truth: Trajectory | None = None,
        depth_invalid_raw: tuple[int, ...] = (0,),
    ):
        self.root = Path(root)
        self.options = options
        self.full_intrinsics = full_intrinsics
        self.intrinsics = full_intrinsics.scaled(options.downsample)
        self.depth_scale = float(depth_scale)
        self.all_entries = entries
        self.entries = entries[options.start : options.end : options.stride]
        self.ground_truth = ground_truth
        self.depth_invalid_raw = depth_invalid_raw
        #: every listed image without a partner, in or out of the selection (``unpaired``: those within it)
        self.all_unpaired: list[UnpairedFrame] = []
        self.warnings: list[str] = []

    @property
    def unpaired(self) -> list[UnpairedFrame]:
        """The unpaired images within the selection's stamp range (all of them without ``--start`` / ``--end``;
        images without a stamp always): an image outside the selection would not have been a frame anyway."""
        o = self.options
        if (o.start == 0 and o.end is None) or not self.entries:
            return list(self.all_unpaired)
        first, last = self.entries[0], self.entries[-1]
        lo = min(first.timestamp, first.timestamp if first.depth_timestamp is None else first.depth_timestamp)
        hi = max(last.timestamp, last.timestamp if last.depth_timestamp is None else last.depth_timestamp)
        return [u for u in self.all_unpaired if u.timestamp is None or lo <= u.timestamp <= hi]

    @unpaired.setter
    def unpaired(self, value: list[UnpairedFrame]) -> None:
        self.all_unpaired = list(value)

    @property
    def colour_camera(self) -> ColourCamera | None:
        """The separate colour camera for the loaded (downsampled) images, or ``None``."""
        cam = self.full_colour_camera
        return None if cam is None else cam.scaled(self.options.downsample)

    def __len__(self) -> int:
        return len(self.entries)

    @property
    def timestamps(self) -> np.ndarray:
        """``(N,)`` float64 timestamps of the selected frames."""
        return np.array([e.timestamp for e in self.entries], dtype=np.float64)

    @property
    def depth_timestamps(self) -> np.ndarray:
        """``(N,)`` float64 capture stamps of the selected frames' depth images (the frame stamp when the
        layout has no separate depth stamp)."""
        return np.array([e.timestamp if e.depth_timestamp is None else e.depth_timestamp for e in self.entries],
                        dtype=np.float64)

    def read_depth_raw(self, i: int) -> np.ndarray:
        """The raw depth image of selected frame ``i`` (the files' resolution and units); FrameError if unreadable."""
        from surfelslam.io.images import read_depth_raw

        return read_depth_raw(self.entries[i].depth_path)

    def _read_images(self, i: int, e: FrameEntry) -> tuple[np.ndarray, np.ndarray]:
        """``(raw depth, rgb)`` of selected frame ``i`` at the files' resolution (adapters that do not read image
        files override this); FrameError naming what is unreadable."""
        from surfelslam.io.images import read_rgb

        # depth first: without it there is no frame, and its message names the depth file
        return self.read_depth_raw(i), read_rgb(e.rgb_path)

    def __getitem__(self, i: int) -> RGBDFrame:
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {i} out of range for a sequence of {len(self)} frames")
        i = i % len(self)
        e = self.entries[i]
        full = self.full_intrinsics
        try:
            raw, rgb = self._read_images(i, e)
        except FrameError as exc:
            if exc.index is None:
                exc.index = i  # the position in the selection, for runs that skip and count bad frames
            raise
        for path, shape in ((e.depth_path, raw.shape), (e.rgb_path, rgb.shape[:2])):
            if shape != full.shape:
                raise FrameError(
                    path, f"image is {shape[1]}x{shape[0]}, expected {full.width}x{full.height}", index=i
                )
        f = self.options.downsample
        if f > 1:  # the kept pixels first: the conversion below is per pixel, so 1 / f^2 of it is done, same values
            rgb = rgb[::f, ::f]
            raw = raw[::f, ::f]
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):  # inf / NaN are made invalid just below
            depth_m = raw.astype(np.float32) / np.float32(self.depth_scale)
        invalid = ~np.isfinite(depth_m) | (depth_m <= 0)
        for bad in self.depth_invalid_raw:
            invalid |= raw == bad
        depth_m[invalid] = 0.0
        return RGBDFrame(i, e.timestamp, np.ascontiguousarray(rgb), np.ascontiguousarray(depth_m), e.depth_timestamp,
                         self.seconds_per_stamp)

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    def gt_poses(self, max_dt_s: float = 0.02, at_depth_time: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Ground-truth pose for each selected frame.

        Args:
            max_dt_s: a frame whose nearest ground-truth stamp is farther than this has no ground truth.
            at_depth_time: False (trajectory evaluation, the TUM tools' convention): the pose with the nearest
                stamp to the frame stamp. True (depth-only registration): the pose at the *depth* image's
                capture stamp, interpolated between the bracketing ground-truth poses when they are at most
                :data:`GT_INTERPOLATION_MAX_GAP_S` apart. On TUM, colour and depth stamps differ by up to 20 ms
                and ground truth is sampled at 100 Hz: at 0.5 m/s the frame-stamp pose is up to 1 cm from
                where the depth camera was.

        Returns:
            ``(T_world_cam (N, 4, 4), valid (N,) bool)``: frames without ground truth are marked invalid
            (their pose is identity).
        """
        if self.ground_truth is None:
            n = len(self)
            return np.tile(np.eye(4), (n, 1, 1)), np.zeros(n, dtype=bool)
        if at_depth_time:
            return interpolate_poses(self.ground_truth, self.depth_timestamps, GT_INTERPOLATION_MAX_GAP_S, max_dt_s)
        return self.ground_truth.lookup(self.timestamps, max_dt_s)

    def info(self) -> dict:
        """What was detected, for ``surfelslam info``."""
        _, gt_valid = self.gt_poses()
        intr = self.intrinsics
        return {
            "layout": self.layout,
            "root": str(self.root),
            "frames": len(self),
            "frames_total": len(self.all_entries),
            "images_unpaired": len(self.unpaired),
            "unpaired": [{"file": str(u.file), "timestamp": u.timestamp, "reason": u.reason}
                         for u in self.unpaired],
            "warnings": list(self.warnings),
            "resolution": [intr.width, intr.height],
            "intrinsics": {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy},
            "depth_scale": self.depth_scale,
            "seconds_per_stamp": self.seconds_per_stamp,
            "downsample": self.options.downsample,
            "ground_truth_poses": 0 if self.ground_truth is None else len(self.ground_truth),
            "frames_with_ground_truth": int(gt_valid.sum()),
            "colour_registered": self.colour_registered,
            "colour_camera": None if (cam := self.colour_camera) is None else {
                "fx": cam.intrinsics.fx, "fy": cam.intrinsics.fy, "cx": cam.intrinsics.cx, "cy": cam.intrinsics.cy,
                "t_colour_depth_m": list(cam.t_colour_depth_m)},
        }
