"""Frame sources: anything that yields RGB-D frames with a camera, so that :class:`surfelslam.Slam` (``track``) and the
run loop can be fed from a folder, a bag, a camera or numpy arrays alike.

A :class:`FrameSource` is iterable (``RGBDFrame`` objects in time order) and has ``intrinsics`` (the frames'
camera) and ``ground_truth`` (a :class:`~surfelslam.types.Trajectory` or ``None``). Implemented by

* every opened sequence (:func:`surfelslam.datasets.open_sequence`: folders, and ROS bags / MCAP files through
  :class:`~surfelslam.datasets.rosbag.RosbagSequence`);
* :class:`ArraySource`: frames already in memory (numpy arrays), e.g. from another program or a camera SDK;
* :class:`DeviceSource`: a live camera behind the small :class:`Device` interface (frames as they come, no length).

A source that also has ``__len__`` and ``__getitem__`` (sequences, :class:`ArraySource`) can go through the whole
run loop (:func:`surfelslam.api.run_sequence`); any source can be fed to a :class:`~surfelslam.Slam` with
:func:`track_source`::

    src = ArraySource(rgb_frames, depth_frames_m, stamps, intrinsics)
    run = track_source(ss.Slam(src.intrinsics), src)
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from surfelslam.datasets.base import DatasetOptions, UnpairedFrame
from surfelslam.errors import ConfigError, FrameError
from surfelslam.types import Intrinsics, RGBDFrame, Trajectory


@runtime_checkable
class FrameSource(Protocol):
    """Frames in time order with their camera (module docstring)."""

    intrinsics: Intrinsics
    ground_truth: Trajectory | None

    def __iter__(self) -> Iterator[RGBDFrame]: ...


def clean_depth(depth_m: np.ndarray) -> np.ndarray:
    """``(H, W)`` float32 metres with NaN, inf and non-positive values set to 0 (invalid)."""
    d = np.asarray(depth_m, dtype=np.float32)
    return np.where(np.isfinite(d) & (d > 0), d, np.float32(0.0)).astype(np.float32, copy=False)


class ArraySource:
    """In-memory frames: ``rgb[i]`` ``(H, W, 3)`` uint8, ``depth_m[i]`` ``(H, W)`` metres (0 / NaN invalid),
    ``timestamps[i]`` seconds, increasing.

    Indexable and iterable like a sequence (``src[i]`` is an :class:`RGBDFrame` whose ``index`` is ``i``), with the
    attributes the run loop reads (``root``, ``layout``, ``options``, ``unpaired``, ``warnings``), so
    :func:`~surfelslam.api.run_sequence` takes it too. Shapes and types are checked up front (ConfigError
    naming the frame).
    """

    layout = "arrays"
    colour_camera = None

    def __init__(self, rgb: Sequence[np.ndarray] | np.ndarray, depth_m: Sequence[np.ndarray] | np.ndarray,
                 timestamps: Sequence[float] | np.ndarray, intrinsics: Intrinsics,
                 ground_truth: Trajectory | None = None, *, colour_registered: bool = True,
                 name: str = "<arrays>"):
        n = len(rgb)
        if len(depth_m) != n or len(timestamps) != n:
            raise ConfigError(f"ArraySource: {n} colour images, {len(depth_m)} depth images and {len(timestamps)} "
                              "timestamps: give one of each per frame")
        if n == 0:
            raise ConfigError("ArraySource: no frames")
        t = np.asarray(timestamps, np.float64)
        if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
            raise ConfigError("ArraySource: timestamps must be finite and strictly increasing")
        h, w = intrinsics.height, intrinsics.width
        for i in range(n):
            c, d = np.asarray(rgb[i]), np.asarray(depth_m[i])
            if c.shape != (h, w, 3) or c.dtype != np.uint8:
                raise ConfigError(f"ArraySource: frame {i}: rgb must be ({h}, {w}, 3) uint8, got {c.shape} {c.dtype}")
            if d.shape != (h, w):
                raise ConfigError(f"ArraySource: frame {i}: depth_m must be ({h}, {w}), got {d.shape}")
        self._rgb, self._depth, self._t = rgb, depth_m, t
        self.intrinsics = intrinsics
        self.full_intrinsics = intrinsics
        self.ground_truth = ground_truth
        self.colour_registered = colour_registered
        self.root = Path(name)
        self.options = DatasetOptions()
        self.unpaired: list[UnpairedFrame] = []
        self.warnings: list[str] = []

    def __len__(self) -> int:
        return len(self._t)

    @property
    def timestamps(self) -> np.ndarray:
        return self._t.copy()

    def __getitem__(self, i: int) -> RGBDFrame:
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {i} out of range for {len(self)} frames")
        i = i % len(self)
        return RGBDFrame(i, float(self._t[i]), np.ascontiguousarray(self._rgb[i]), clean_depth(self._depth[i]))

    def __iter__(self) -> Iterator[RGBDFrame]:
        for i in range(len(self)):
            yield self[i]


class Device(Protocol):
    """A live RGB-D camera as :class:`DeviceSource` drives it (a fake one in the tests, pyrealsense2 in use).

    ``intrinsics``: the colour camera, with depth aligned to it; ``depth_scale``: raw depth units per metre;
    ``read()``: the next ``(rgb (H, W, 3) uint8, raw depth (H, W), timestamp s)``, or ``None`` when the stream
    ended; ``close()``: stop it.
    """

    intrinsics: Intrinsics
    depth_scale: float

    def read(self) -> tuple[np.ndarray, np.ndarray, float] | None: ...

    def close(self) -> None: ...


class DeviceSource:
    """Frames from a :class:`Device` as they arrive (no length, no random access): for :func:`track_source`.

    ``max_frames``: stop after this many (``None``: until the device ends). ``record``: called with every frame
    (e.g. a bag writer). A frame of the wrong size is a FrameError naming its position. The device is closed when
    the iteration ends (or is abandoned).
    """

    ground_truth = None

    def __init__(self, device: Device, max_frames: int | None = None,
                 record: Callable[[RGBDFrame], None] | None = None):
        if max_frames is not None and max_frames < 1:
            raise ConfigError(f"max_frames must be >= 1, got {max_frames}")
        self.device = device
        self.intrinsics = device.intrinsics
        self.max_frames = max_frames
        self.record = record

    def __iter__(self) -> Iterator[RGBDFrame]:
        intr, scale = self.intrinsics, float(self.device.depth_scale)
        k = 0
        last_t = -np.inf
        try:
            while self.max_frames is None or k < self.max_frames:
                got = self.device.read()
                if got is None:
                    return
                rgb, raw, t = got
                if float(t) <= last_t:
                    continue  # a repeated frame
                if rgb.shape != (intr.height, intr.width, 3) or raw.shape != (intr.height, intr.width):
                    raise FrameError(None, f"device frame {k}: {rgb.shape} colour / {raw.shape} depth, expected "
                                           f"{intr.width}x{intr.height}", index=k)
                depth = raw.astype(np.float32) / np.float32(scale)
                depth[raw == 0] = 0.0
                frame = RGBDFrame(k, float(t), np.ascontiguousarray(rgb, np.uint8), clean_depth(depth))
                if self.record is not None:
                    self.record(frame)
                last_t = float(t)
                k += 1
                yield frame
        finally:
            self.device.close()


def track_source(slam, source: FrameSource, on_frame: Callable[[RGBDFrame, object], None] | None = None):
    """Feed every frame of ``source`` to ``slam`` (a :class:`surfelslam.Slam`) with ``slam.track`` and return
    ``slam.finish()``; ``on_frame(frame, result)`` is called after each frame."""
    for frame in source:
        res = slam.track(frame)
        if on_frame is not None:
            on_frame(frame, res)
    return slam.finish()


class DeviceSequence:
    """A live :class:`Device` as a sequence of known length for the run loop (``surfelslam run realsense``).

    Device frames are read in order as ``seq[0]``, ``seq[1]`` ... are asked for (the run loop's reader thread does);
    the selection options apply to the device's frames: the first ``start`` are dropped (auto-exposure settling),
    then every ``stride``-th is kept until ``end`` device frames were read (``end`` is required: a live stream has no
    end of its own); ``downsample`` samples the images. ``record(rgb, depth_m, timestamp)`` gets each kept frame at
    the device's resolution (e.g. a :class:`~surfelslam.datasets.rosbag.write.BagRecorder`); ``on_close`` is called
    once, after the last frame or by :meth:`close`. Random access and going back raise FrameError.
    """

    layout = "live"
    colour_registered = True
    colour_camera = None
    intrinsics_kind = "device"

    def __init__(self, device: Device, options: DatasetOptions, name: str = "device",
                 record: Callable[[np.ndarray, np.ndarray, float], None] | None = None,
                 on_close: Callable[[], None] | None = None, ground_truth: Trajectory | None = None):
        if options.end is None:
            raise ConfigError(f"{name}: a live camera needs --end N (how many of its frames to read)")
        self.device = device
        self.options = options
        self.root = Path(name)
        self.full_intrinsics = device.intrinsics
        self.intrinsics = device.intrinsics.scaled(options.downsample)
        self.depth_scale = float(device.depth_scale)
        self.intrinsics_source = self.depth_scale_source = f"the {name} device"
        self.ground_truth = ground_truth
        self.unpaired: list[UnpairedFrame] = []
        self.warnings: list[str] = []
        self._keep = range(options.start, options.end, options.stride)
        self._read = 0  # device frames read so far
        self._next = 0  # next position to hand out
        self._record, self._on_close = record, on_close
        self._closed = False
        self._stamps: list[float] = []

    def __len__(self) -> int:
        return len(self._keep)

    @property
    def timestamps(self) -> np.ndarray:
        """Stamps of the frames handed out so far."""
        return np.array(self._stamps, np.float64)

    def __getitem__(self, i: int) -> RGBDFrame:
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} out of range for {len(self)} frames")
        if i != self._next:
            raise FrameError(self.root, f"frame {i}: a live camera's frames are read once, in order "
                                        f"(the next is {self._next})", index=i)
        want = self._keep[i]
        got = None
        while self._read <= want:
            got = None if self._closed else self.device.read()
            if got is None:
                self.close()
                raise FrameError(self.root, f"the device stream ended after {self._read} frames", index=i)
            self._read += 1
        assert got is not None
        rgb, raw, t = got
        intr = self.full_intrinsics
        if rgb.shape != (intr.height, intr.width, 3) or raw.shape != (intr.height, intr.width):
            raise FrameError(self.root, f"device frame {want}: {rgb.shape} colour / {raw.shape} depth, expected "
                                        f"{intr.width}x{intr.height}", index=i)
        depth = np.asarray(raw).astype(np.float32) / np.float32(self.depth_scale)
        depth[np.asarray(raw) == 0] = 0.0
        depth = clean_depth(depth)
        rgb = np.ascontiguousarray(rgb, np.uint8)
        if self._record is not None:
            self._record(rgb, depth, float(t))
        self._next += 1
        self._stamps.append(float(t))
        if self._next == len(self):
            self.close()
        f = self.options.downsample
        if f > 1:
            rgb, depth = np.ascontiguousarray(rgb[::f, ::f]), np.ascontiguousarray(depth[::f, ::f])
        return RGBDFrame(i, float(t), rgb, depth)

    def __iter__(self) -> Iterator[RGBDFrame]:
        for i in range(self._next, len(self)):
            yield self[i]

    def close(self) -> None:
        """Stop the device and finish the recording (once)."""
        if self._closed:
            return
        self._closed = True
        try:
            self.device.close()
        finally:
            if self._on_close is not None:
                self._on_close()

    def info(self) -> dict:
        intr = self.intrinsics
        return {"layout": self.layout, "root": str(self.root), "frames": len(self), "frames_total": len(self),
                "images_unpaired": 0, "unpaired": [], "warnings": list(self.warnings),
                "resolution": [intr.width, intr.height],
                "intrinsics": {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy},
                "depth_scale": self.depth_scale, "downsample": self.options.downsample,
                "ground_truth_poses": 0 if self.ground_truth is None else len(self.ground_truth),
                "frames_with_ground_truth": 0, "colour_registered": True, "colour_camera": None}
