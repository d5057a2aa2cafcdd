"""Write an opened RGB-D sequence folder as a ROS bag or MCAP file, with ``rosbags``' own writers.

    from surfelslam.datasets import open_sequence
    from surfelslam.datasets.rosbag.write import write_bag
    seq = open_sequence("rgbd_dataset_freiburg1_xyz")
    write_bag(seq, "fr1_xyz.bag", "ros1")      # ROS 1 bag
    write_bag(seq, "fr1_xyz_db3", "ros2")      # ROS 2 bag folder, SQLite storage
    write_bag(seq, "fr1_xyz_mcap", "mcap")     # ROS 2 bag folder, MCAP storage

Topics (RealSense ROS driver names): colour ``sensor_msgs/Image`` (``rgb8``, or ``bgr8`` / JPEG / PNG), depth
registered to colour ``sensor_msgs/Image`` (``32FC1`` metres, or ``16UC1`` in the folder's raw depth units), a
``CameraInfo`` per colour image, and the ground truth as ``geometry_msgs/PoseStamped`` when the folder has one.
Header stamps are the folder's timestamps; receive times the same stamps.

Depth written as ``32FC1`` holds exactly the metres the folder reader computes (raw / depth scale, in float32), so
the bag gives the same frames, bit for bit: ``surfelslam run`` on the bag writes the folder run's trajectory. With
``16UC1`` the raw values are kept: read the bag with the folder's ``--depth-scale`` (or it is taken as millimetres).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from surfelslam.datasets.base import DatasetOptions, RGBDSequence
from surfelslam.datasets.rosbag import (
    CAMERA_INFO,
    COMPRESSED,
    IMAGE,
    MM_DEPTH_SCALE,
    seconds_to_stamp,
)
from surfelslam.errors import ConfigError, OutputError

FORMATS = ("ros1", "ros2", "mcap")
COLOUR_ENCODINGS = ("rgb8", "bgr8", "jpeg", "png")
DEPTH_ENCODINGS = ("auto", "32FC1", "16UC1", "compressedDepth")
POSE = "geometry_msgs/msg/PoseStamped"

RGB_TOPIC = "/camera/color/image_raw"
DEPTH_TOPIC = "/camera/aligned_depth_to_color/image_raw"
INFO_TOPIC = "/camera/color/camera_info"
GT_TOPIC = "/ground_truth/pose"
FRAME_ID = "camera_color_optical_frame"


def write_bag(seq: RGBDSequence, out_path: str | Path, format: str = "ros1", *,  # noqa: A002
              colour_encoding: str = "rgb8", depth_encoding: str = "auto",
              rgb_topic: str = RGB_TOPIC, depth_topic: str = DEPTH_TOPIC, info_topic: str | None = INFO_TOPIC,
              gt_topic: str | None = GT_TOPIC) -> Path:
    """Write ``seq``, a sequence folder opened by :func:`~surfelslam.datasets.open_sequence` (any folder layout, at
    the files' resolution; the options it was opened with select the frames), as a bag at ``out_path`` (which must
    not exist).

    Args:
        format: ``ros1`` (a ``.bag`` file), ``ros2`` (a ROS 2 bag folder with SQLite storage) or ``mcap`` (a ROS 2
            bag folder with MCAP storage; its ``.mcap`` file is also a plain MCAP file).
        colour_encoding: ``rgb8`` / ``bgr8`` (``Image``), ``jpeg`` / ``png`` (``CompressedImage``).
        depth_encoding: ``32FC1`` (metres), ``16UC1`` (the folder's raw units), ``compressedDepth`` (16UC1 in PNG
            behind the 12-byte header), or ``auto``: ``16UC1`` when the folder's depth is in millimetres, else
            ``32FC1``.
        info_topic / gt_topic: ``None`` leaves the camera info / the ground truth out.
    Returns the written path (the ``.bag`` file or the ROS 2 bag folder).
    """
    out = Path(out_path)
    _check_arguments(format, colour_encoding, depth_encoding, out, seq.options)
    if depth_encoding == "auto":
        depth_encoding = "16UC1" if seq.depth_scale == MM_DEPTH_SCALE else "32FC1"

    msgs = _Messages(format == "ros1")
    writer = _writer(out, format)
    colour_type = IMAGE if colour_encoding in ("rgb8", "bgr8") else COMPRESSED
    depth_type = COMPRESSED if depth_encoding == "compressedDepth" else IMAGE
    gt = seq.ground_truth if gt_topic is not None else None
    messages = _message_plan(seq, gt, rgb_topic, depth_topic, info_topic, gt_topic)
    with writer:
        ts = msgs.ts
        conns = {rgb_topic: writer.add_connection(rgb_topic, colour_type, typestore=ts),
                 depth_topic: writer.add_connection(depth_topic, depth_type, typestore=ts)}
        if info_topic is not None:
            conns[info_topic] = writer.add_connection(info_topic, CAMERA_INFO, typestore=ts)
        if gt is not None:
            conns[gt_topic] = writer.add_connection(gt_topic, POSE, typestore=ts)
        for log_ns, topic, t, what in messages:
            msgtype, msg = _build_message(msgs, seq, what, t, colour_encoding, depth_encoding)
            writer.write(conns[topic], log_ns, msgs.serialize(msg, msgtype))
    return out


def _check_arguments(format: str, colour_encoding: str, depth_encoding: str, out: Path,  # noqa: A002
                     opts: DatasetOptions) -> None:
    """ConfigError / OutputError for an unknown format or encoding, an existing output or a downsampled selection."""
    if format not in FORMATS:
        raise ConfigError(f"bag format must be one of {', '.join(FORMATS)}, got {format!r}")
    if colour_encoding not in COLOUR_ENCODINGS:
        raise ConfigError(f"colour encoding must be one of {', '.join(COLOUR_ENCODINGS)}, got {colour_encoding!r}")
    if depth_encoding not in DEPTH_ENCODINGS:
        raise ConfigError(f"depth encoding must be one of {', '.join(DEPTH_ENCODINGS)}, got {depth_encoding!r}")
    if out.exists():
        raise OutputError(out, "already exists (the bag writers only create new bags)")
    if opts.downsample != 1:
        raise ConfigError("write_bag writes the files' resolution: leave downsample at 1")


def _message_plan(seq, gt, rgb_topic: str, depth_topic: str, info_topic: str | None, gt_topic: str | None
                  ) -> list[tuple[int, str, float, tuple[str, object]]]:
    """``(receive ns, topic, stamp, (what, frame entry or pose))`` of every message to write, in receive order."""
    messages: list[tuple[int, str, float, tuple[str, object]]] = []
    for e in seq.entries:
        messages.append((_ns(e.timestamp), rgb_topic, e.timestamp, ("colour", e)))
        t_d = e.timestamp if e.depth_timestamp is None else e.depth_timestamp
        messages.append((_ns(t_d), depth_topic, t_d, ("depth", e)))
        if info_topic is not None:
            messages.append((_ns(e.timestamp), info_topic, e.timestamp, ("info", e)))
    if gt is not None:
        for t, M in zip(gt.timestamps, gt.T_world_cam, strict=True):
            messages.append((_ns(t), gt_topic, float(t), ("pose", M)))
    messages.sort(key=lambda m: m[0])  # stable: colour before depth before info at one time
    return messages


def _build_message(msgs: _Messages, seq, what: tuple[str, object], t: float, colour_encoding: str,
                   depth_encoding: str) -> tuple[str, object]:
    """``(message type, message)`` of one planned message (:func:`_message_plan`), its image read from the folder."""
    from surfelslam.io.images import read_depth_raw, read_rgb

    kind, obj = what
    if kind == "colour":
        return _colour_msg(msgs, t, read_rgb(obj.rgb_path), colour_encoding)
    if kind == "depth":
        return _depth_msg(msgs, t, read_depth_raw(obj.depth_path), depth_encoding, seq.depth_scale)
    if kind == "info":
        return CAMERA_INFO, msgs.camera_info(t, seq.full_intrinsics)
    return POSE, msgs.pose(t, obj)


def _colour_msg(msgs: _Messages, t: float, rgb: np.ndarray, colour_encoding: str) -> tuple[str, object]:
    import cv2

    if colour_encoding == "rgb8":
        return IMAGE, msgs.image(t, rgb, "rgb8")
    if colour_encoding == "bgr8":
        return IMAGE, msgs.image(t, rgb[:, :, ::-1], "bgr8")
    ok, buf = cv2.imencode(".jpg" if colour_encoding == "jpeg" else ".png", rgb[:, :, ::-1])
    assert ok
    return COMPRESSED, msgs.compressed(t, f"rgb8; {colour_encoding} compressed bgr8", buf.tobytes())


def _depth_msg(msgs: _Messages, t: float, raw: np.ndarray, depth_encoding: str, depth_scale: float
               ) -> tuple[str, object]:
    import cv2

    if depth_encoding == "32FC1":
        metres = raw.astype(np.float32) / np.float32(depth_scale)
        metres[~np.isfinite(metres) | (metres <= 0) | (raw == 0)] = 0.0
        return IMAGE, msgs.image(t, metres.astype("<f4"), "32FC1")
    raw16 = np.asarray(raw).astype("<u2")
    if depth_encoding == "16UC1":
        return IMAGE, msgs.image(t, raw16, "16UC1")
    ok, buf = cv2.imencode(".png", raw16)
    assert ok
    head = np.array([0], "<i4").tobytes() + np.array([0.0, 0.0], "<f4").tobytes()
    return COMPRESSED, msgs.compressed(t, "16UC1; compressedDepth png", head + buf.tobytes())


def _ns(t: float) -> int:
    sec, nsec = seconds_to_stamp(t)
    return sec * 1_000_000_000 + nsec


def _writer(out: Path, format: str):  # noqa: A002
    """rosbags' writer for ``format`` (not opened)."""
    if format == "ros1":
        from rosbags.rosbag1 import Writer as Writer1

        return Writer1(out)
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    return Writer2(out, version=9, storage_plugin=StoragePlugin.MCAP if format == "mcap" else StoragePlugin.SQLITE3)


class _Messages:
    """Builds the messages written (ROS 1 or ROS 2 types from rosbags' type stores) and serialises them."""

    def __init__(self, ros1: bool):
        from rosbags.typesys import Stores, get_typestore

        self.ros1 = ros1
        self.ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        self.T = self.ts.types
        self.serialize = self.ts.serialize_ros1 if ros1 else self.ts.serialize_cdr
        self._seq = 0

    def header(self, t: float):
        T = self.T
        sec, nsec = seconds_to_stamp(t)
        stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
        self._seq += 1
        if self.ros1:
            return T["std_msgs/msg/Header"](seq=self._seq, stamp=stamp, frame_id=FRAME_ID)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=FRAME_ID)

    def image(self, t: float, arr: np.ndarray, encoding: str):
        h, w = arr.shape[:2]
        data = np.ascontiguousarray(arr).view(np.uint8).reshape(-1)
        return self.T[IMAGE](header=self.header(t), height=h, width=w, encoding=encoding, is_bigendian=0,
                             step=data.size // h, data=data)

    def compressed(self, t: float, fmt: str, data: bytes):
        return self.T[COMPRESSED](header=self.header(t), format=fmt, data=np.frombuffer(data, np.uint8))

    def camera_info(self, t: float, intr):
        T = self.T
        K = np.array([intr.fx, 0, intr.cx, 0, intr.fy, intr.cy, 0, 0, 1], np.float64)
        P = np.array([intr.fx, 0, intr.cx, 0, 0, intr.fy, intr.cy, 0, 0, 0, 1, 0], np.float64)
        R = np.eye(3).reshape(-1)
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        names = ("D", "K", "R", "P") if self.ros1 else ("d", "k", "r", "p")
        kw = dict(zip(names, (np.zeros(5), K, R, P), strict=True))
        return T[CAMERA_INFO](header=self.header(t), height=intr.height, width=intr.width,
                              distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi, **kw)

    def pose(self, t: float, M: np.ndarray):
        from scipy.spatial.transform import Rotation

        T = self.T
        x, y, z, w = Rotation.from_matrix(M[:3, :3]).as_quat()
        P = T["geometry_msgs/msg/Point"](x=float(M[0, 3]), y=float(M[1, 3]), z=float(M[2, 3]))
        Q = T["geometry_msgs/msg/Quaternion"](x=float(x), y=float(y), z=float(z), w=float(w))
        return T[POSE](header=self.header(t), pose=T["geometry_msgs/msg/Pose"](position=P, orientation=Q))


class BagRecorder:
    """Records frames to a new bag as they come (``surfelslam run realsense --record out.bag``): colour ``rgb8``,
    depth ``32FC1`` (the metres tracked, exactly) and a ``CameraInfo`` per frame, on :func:`write_bag`'s topics.
    ``format``: ``ros1`` (``.bag``), ``ros2`` or ``mcap`` (a ROS 2 bag folder). Call :meth:`close` at the end (the
    ROS 1 index, the ROS 2 metadata and the MCAP summary are written then).
    """

    def __init__(self, out_path: str | Path, intrinsics, format: str | None = None):  # noqa: A002
        out = Path(out_path)
        format = format or ("ros1" if out.suffix.lower() == ".bag" else "mcap")
        if format not in FORMATS:
            raise ConfigError(f"bag format must be one of {', '.join(FORMATS)}, got {format!r}")
        if out.exists():
            raise OutputError(out, "already exists (the bag writers only create new bags)")
        self.path, self.intrinsics = out, intrinsics
        self._msgs = _Messages(format == "ros1")
        self._writer = _writer(out, format)
        try:
            self._writer.open()
        except Exception as exc:  # noqa: BLE001 - rosbags' writer errors, OS errors
            raise OutputError(out, f"cannot create the bag ({exc})") from None
        ts = self._msgs.ts
        self._conns = {t: self._writer.add_connection(t, ty, typestore=ts)
                       for t, ty in ((RGB_TOPIC, IMAGE), (DEPTH_TOPIC, IMAGE), (INFO_TOPIC, CAMERA_INFO))}
        self.frames = 0
        self._open = True

    def __call__(self, rgb: np.ndarray, depth_m: np.ndarray, timestamp: float) -> None:
        """Write one frame: ``(H, W, 3)`` uint8 colour, ``(H, W)`` depth in metres, its stamp (s)."""
        m = self._msgs
        ns = _ns(timestamp)
        for topic, msgtype, msg in ((RGB_TOPIC, IMAGE, m.image(timestamp, np.asarray(rgb, np.uint8), "rgb8")),
                                    (DEPTH_TOPIC, IMAGE, m.image(timestamp, np.asarray(depth_m, "<f4"), "32FC1")),
                                    (INFO_TOPIC, CAMERA_INFO, m.camera_info(timestamp, self.intrinsics))):
            self._writer.write(self._conns[topic], ns, m.serialize(msg, msgtype))
        self.frames += 1

    def close(self) -> None:
        if self._open:
            self._open = False
            self._writer.close()
