"""A live Intel RealSense camera as a sequence: ``surfelslam run realsense --end 900 [--record out.bag]``.

Needs the optional ``pyrealsense2`` (``pip install 'surfelslam[realsense]'``). The colour and depth streams are
started at the same size and rate, depth is aligned to colour by the SDK (``rs.align``), the intrinsics are the
colour stream's (``fx, fy, ppx, ppy``) and the depth scale the depth sensor's (``1 / get_depth_scale()`` units per
metre). Frames go through :class:`~surfelslam.datasets.stream.DeviceSequence` (the run loop reads them in order as
they arrive; ``--start`` drops the first frames while auto-exposure settles, ``--end`` is required), and
``--record`` writes each frame to a bag (:class:`~surfelslam.datasets.rosbag.write.BagRecorder`), so the run can be
repeated offline: ``surfelslam run out.bag`` sees the very same frames.

Not exercised here (no camera): :class:`RealSenseDevice` itself. The sequence, the selection, the recording and the
run over them are tested with a fake device that replays a synthetic sequence.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from surfelslam.datasets.base import DatasetOptions
from surfelslam.datasets.stream import Device, DeviceSequence
from surfelslam.errors import ConfigError, InputError
from surfelslam.types import Intrinsics

#: The sequence argument that opens the first RealSense camera.
NAME = "realsense"
MISSING = "the RealSense camera needs pyrealsense2: pip install 'surfelslam[realsense]'"
#: Milliseconds to wait for a frame before the device is taken as gone.
FRAME_TIMEOUT_MS = 5000


def is_realsense(path: str | Path) -> bool:
    """True for the ``realsense`` argument (when no file or folder of that name exists)."""
    return str(path) == NAME and not Path(path).exists()


class RealSenseDevice:
    """A RealSense camera through pyrealsense2 (a :class:`~surfelslam.datasets.stream.Device`): colour ``rgb8`` and
    depth ``z16`` at ``width`` x ``height`` and ``fps``, depth aligned to colour; ``serial`` picks a camera."""

    def __init__(self, width: int = 640, height: int = 480, fps: int = 30, serial: str | None = None):
        try:
            import pyrealsense2 as rs
        except ImportError:
            raise ConfigError(MISSING) from None
        self._rs = rs
        cfg = rs.config()
        if serial:
            cfg.enable_device(serial)
        cfg.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
        cfg.enable_stream(rs.stream.depth, width, height, rs.format.z16, fps)
        self._pipe = rs.pipeline()
        try:
            profile = self._pipe.start(cfg)
        except RuntimeError as exc:  # no camera, busy, unsupported mode
            raise InputError(NAME, f"cannot start the camera ({exc})") from None
        self._align = rs.align(rs.stream.color)
        sensor = profile.get_device().first_depth_sensor()
        self.depth_scale = 1.0 / float(sensor.get_depth_scale())  # the SDK gives metres per unit
        ci = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
        self.intrinsics = Intrinsics(float(ci.fx), float(ci.fy), float(ci.ppx), float(ci.ppy), int(ci.width),
                                     int(ci.height))
        self._running = True

    def read(self) -> tuple[np.ndarray, np.ndarray, float] | None:
        if not self._running:
            return None
        try:
            frames = self._pipe.wait_for_frames(FRAME_TIMEOUT_MS)
        except RuntimeError:
            return None  # the camera stopped sending (unplugged)
        aligned = self._align.process(frames)
        colour, depth = aligned.get_color_frame(), aligned.get_depth_frame()
        if not colour or not depth:
            return self.read()
        rgb = np.asanyarray(colour.get_data()).copy()
        raw = np.asanyarray(depth.get_data()).copy()
        return rgb, raw, float(frames.get_timestamp()) / 1000.0  # the SDK's stamp is in milliseconds

    def close(self) -> None:
        if self._running:
            self._running = False
            self._pipe.stop()


def open_realsense(options: DatasetOptions, record: str | Path | None = None, device: Device | None = None,
                   path: str | Path = NAME) -> DeviceSequence:
    """The camera (or ``device``, e.g. a fake one in tests) as a :class:`DeviceSequence` under ``options``, with
    every kept frame written to the bag ``record`` when given. ``--intrinsics`` / ``--depth-scale`` override the
    device's. ``--gt FILE`` gives ground truth (a TUM file).

    Raises:
        ConfigError: ``path`` is not ``realsense``, no ``--end``, or pyrealsense2 missing (one line saying how to
            install it). InputError: the camera cannot be started. OutputError: ``record`` exists.
    """
    if str(path) != NAME:
        raise ConfigError(f"--record needs the live camera as the sequence ('{NAME}'), got {path}")
    if options.end is None:
        raise ConfigError(f"{NAME}: a live camera needs --end N (how many of its frames to read)")
    dev = RealSenseDevice() if device is None else device
    if options.intrinsics is not None or options.depth_scale is not None:
        dev = _Overridden(dev, options)
    gt = None
    if options.gt is not None:
        from surfelslam.datasets.tum import read_ground_truth_file

        gt = read_ground_truth_file(Path(options.gt))
    recorder = None
    if record is not None:
        from surfelslam.datasets.rosbag.write import BagRecorder

        try:
            recorder = BagRecorder(record, dev.intrinsics)
        except BaseException:
            dev.close()
            raise
    return DeviceSequence(dev, options, NAME, record=recorder, on_close=None if recorder is None else recorder.close,
                          ground_truth=gt)


class _Overridden:
    """A device whose intrinsics / depth scale are replaced by the options'."""

    def __init__(self, dev: Device, options: DatasetOptions):
        self._dev = dev
        i = dev.intrinsics
        self.intrinsics = i if options.intrinsics is None else Intrinsics(*options.intrinsics, i.width, i.height)
        self.depth_scale = dev.depth_scale if options.depth_scale is None else options.depth_scale

    def read(self):
        return self._dev.read()

    def close(self) -> None:
        self._dev.close()
