"""The ``rosbag`` layout's sequence: a bag indexed once at opening, each frame's two messages re-read by receive time
(see :mod:`surfelslam.datasets.rosbag`)."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from surfelslam.datasets.base import DatasetOptions, FrameEntry, RGBDSequence
from surfelslam.datasets.rosbag.decode import decode_colour, decode_depth
from surfelslam.datasets.rosbag.index import (
    BagFrameEntry,
    BagIndex,
    MessageRef,
    TopicIndex,
    index_bag,
    message_path,
    open_reader,
    reader_error_text,
)
from surfelslam.datasets.rosbag.topics import header_stamp, is_bag, stamp_seconds
from surfelslam.errors import FrameError


class RosbagSequence(RGBDSequence):
    """A ROS 1 / ROS 2 bag or MCAP file (module docstring)."""

    layout = "rosbag"
    expects = ("a ROS 1 .bag, a ROS 2 bag folder (metadata.yaml + .db3 / .mcap), or an .mcap / .db3 file, with "
               "colour, depth and CameraInfo topics")

    #: the opened ``rosbags`` reader (``None`` once closed)
    reader = None
    topics: dict[str, TopicIndex]
    rgb_topic: str
    depth_topic: str
    camera_info_topic: str | None = None
    ground_truth_topic: str | None = None
    ground_truth_source: str | None = None
    bag_format: str = ""

    def __init__(self, root: Path, options: DatasetOptions, reader, bag: BagIndex):
        """The sequence of the opened bag ``reader`` at ``root``, as :func:`~.index.index_bag` indexed it (it is
        closed by :meth:`close`)."""
        super().__init__(root, bag.entries, bag.intrinsics, bag.depth_scale, options, bag.ground_truth)
        self._lock = threading.Lock()
        self.reader = reader
        #: ROS 2 (CDR) serialisation, else ROS 1
        self.ros2 = bag.ros2
        self.topics = bag.topics
        #: message count per topic, as the bag declares them (for the topics not read)
        self.message_counts = bag.message_counts
        self.rgb_topic, self.depth_topic = bag.rgb_topic, bag.depth_topic
        self.camera_info_topic = bag.camera_info_topic
        self.ground_truth_topic = bag.ground_truth_topic
        self.ground_truth_source = bag.ground_truth_source
        self.bag_format = bag.bag_format
        self.unpaired = bag.unpaired
        self.warnings = list(bag.notes)
        self.intrinsics_source, self.intrinsics_kind = bag.intrinsics_source, bag.intrinsics_kind
        self.depth_scale_source = bag.depth_scale_source
        #: ``"mm"`` (16-bit millimetres) or ``"m"`` (float metres)
        self.depth_kind = bag.depth_kind

    @classmethod
    def detect(cls, root: Path, meta) -> bool:
        return is_bag(root)

    @classmethod
    def open(cls, root: Path, options: DatasetOptions, meta=None) -> RosbagSequence:
        root = Path(root)
        reader = open_reader(root)
        try:
            return cls(root, options, reader, index_bag(root, reader, options))
        except BaseException:
            reader.close()
            raise


    # -------------------------------------------------------------------------------------------- frames
    def _message(self, ref: MessageRef):
        """The deserialised message ``ref`` points at (re-read from the bag by receive time)."""
        ti = self.topics[ref.topic]
        with self._lock:
            if self.reader is None:
                raise FrameError(self.root, "the bag is closed")
            found = None
            try:
                for conn, _, raw in self.reader.messages(connections=ti.connections, start=ref.log_ns,
                                                         stop=ref.log_ns + 1):
                    if stamp_seconds(*header_stamp(raw, self.ros2)) == ref.own_stamp:
                        found = self.reader.deserialize(raw, conn.msgtype)
                        break
            except Exception as exc:  # noqa: BLE001 - storage errors of a damaged bag
                raise FrameError(message_path(self.root, ref.topic, ref.stamp),
                                 f"cannot read the message ({reader_error_text(exc)})") from None
        if found is None:
            raise FrameError(message_path(self.root, ref.topic, ref.stamp), "message not found again in the bag")
        return found

    def read_depth_raw(self, i: int) -> np.ndarray:
        e = self.entries[i]
        assert isinstance(e, BagFrameEntry) and e.depth_ref is not None
        msg = self._message(e.depth_ref)
        try:
            return decode_depth(msg, self.topics[e.depth_ref.topic].msgtype)
        except (ValueError, AttributeError) as exc:
            raise FrameError(e.depth_path, str(exc), index=i) from None

    def _read_images(self, i: int, e: FrameEntry) -> tuple[np.ndarray, np.ndarray]:
        assert isinstance(e, BagFrameEntry) and e.rgb_ref is not None
        raw = self.read_depth_raw(i)
        msg = self._message(e.rgb_ref)
        try:
            rgb = decode_colour(msg, self.topics[e.rgb_ref.topic].msgtype)
        except (ValueError, AttributeError) as exc:
            raise FrameError(e.rgb_path, str(exc), index=i) from None
        return raw, rgb

    def close(self) -> None:
        """Close the bag (frames can no longer be read)."""
        lock = getattr(self, "_lock", None)
        if lock is None:
            return
        with lock:
            if self.reader is not None:
                reader, self.reader = self.reader, None
                try:
                    reader.close()
                except Exception:  # noqa: BLE001, S110 - closing a damaged bag
                    pass

    def __del__(self):  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:  # noqa: BLE001, S110
            pass

    # -------------------------------------------------------------------------------------------- description
    def topic_table(self) -> list[dict]:
        """Every topic of the bag: name, type, message count, rate (Hz, from header stamps, for the topics read)
        and its role here (``colour``, ``depth``, ``camera_info``, ``ground_truth`` or ``None``)."""
        roles = {self.rgb_topic: "colour", self.depth_topic: "depth", self.camera_info_topic: "camera_info",
                 self.ground_truth_topic: "ground_truth"}
        out = []
        for name in sorted(self.topics):
            ti = self.topics[name]
            rate = ti.rate_hz()
            count = ti.count if ti.count else self.message_counts.get(name, 0)
            out.append({"topic": name, "type": ti.msgtype, "count": count,
                        "rate_hz": None if rate is None else round(rate, 3), "role": roles.get(name)})
        return out

    def info(self) -> dict:
        out = super().info()
        out.update(bag_format=self.bag_format, rgb_topic=self.rgb_topic, depth_topic=self.depth_topic,
                   camera_info_topic=self.camera_info_topic, ground_truth_source=self.ground_truth_source,
                   topics=self.topic_table())
        return out
