"""ROS bags and MCAP files as RGB-D sequences (layout ``rosbag``), read with the pure-Python ``rosbags`` library.

Accepted: a ROS 1 ``.bag``; a ROS 2 bag folder (``metadata.yaml`` with ``.db3`` or ``.mcap`` storage); a plain
``.mcap`` (ROS 2 messages) or ``.db3`` file.

* **Topics.** Colour and depth are ``sensor_msgs/Image`` or ``CompressedImage`` topics, the intrinsics come from a
  ``sensor_msgs/CameraInfo`` topic (its ``K``). Found by type and name (depth: the name holds ``depth``, preferring
  depth aligned / registered to colour; colour: ``color``, ``colour``, ``rgb`` or ``image`` without ``depth``,
  ``ir`` or ``infra``; camera info: the one beside the depth, else beside the colour topic); the dataset options
  ``rgb_topic``, ``depth_topic`` and ``camera_info_topic`` (``--rgb-topic`` ...) override the choice.
* **Encodings.** Colour: ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``, ``mono8``, or JPEG / PNG ``CompressedImage``.
  Depth: ``16UC1`` / ``mono16`` (millimetres: depth scale 1000 unless ``--depth-scale``), ``32FC1`` (metres),
  PNG ``CompressedImage`` (16-bit, millimetres) and ``compressedDepth`` (its 12-byte header, then PNG: 16UC1 in
  millimetres, or 32FC1 quantised inverse depth).
* **Frames.** Colour and depth are paired by their header stamps with the folder readers' rule (nearest within
  0.02 s, each depth image used once: :func:`surfelslam.datasets.tum.associate`); the frame takes the colour stamp.
* **Streaming.** Opening reads the bag once, keeping each message's topic, receive time and header stamp only;
  ``seq[i]`` re-reads the two messages of frame ``i`` by receive time (the storage's own index: ROS 1 chunk index,
  SQLite timestamp index, MCAP chunk index) and decodes them. Nothing else stays in memory.
* **Ground truth.** ``--gt FILE`` (TUM format), ``--gt TOPIC``, or else a ``geometry_msgs/PoseStamped``,
  ``PoseWithCovarianceStamped``, ``TransformStamped`` or ``nav_msgs/Odometry`` topic named like ground truth
  (``ground_truth``, ``groundtruth``, ``gt``, ``mocap``, ``vicon``, ``optitrack``): its poses are taken as the
  camera's ``T_world_cam`` (as TUM's ``groundtruth.txt``).

A bag that cannot be read (truncated, not indexed, unknown storage), a missing topic or an unsupported encoding is a
one-line :class:`DatasetError` naming the file and topic; a message that cannot be decoded later is a
:class:`FrameError` naming the file, topic and stamp (the run skips and counts it).
"""

from __future__ import annotations

import re
import struct
import threading
from dataclasses import dataclass, field
from decimal import ROUND_HALF_EVEN, Decimal
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
from surfelslam.datasets.tum import MAX_RGB_DEPTH_DT_S, _unpaired_reasons, associate
from surfelslam.errors import ConfigError, DatasetError, FrameError, InputError
from surfelslam.types import Intrinsics, Trajectory

#: File suffixes read as bags (a folder is a ROS 2 bag when it holds ``metadata.yaml``).
BAG_SUFFIXES = (".bag", ".mcap", ".db3")
ROS2_METADATA = "metadata.yaml"

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
IMAGE_TYPES = (IMAGE, COMPRESSED)
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped",
              "geometry_msgs/msg/TransformStamped", "nav_msgs/msg/Odometry")
#: Every message type the adapter reads starts with a ``std_msgs/Header`` (its stamp is read from the raw bytes).
HEADER_TYPES = (*IMAGE_TYPES, CAMERA_INFO, *POSE_TYPES)

COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8")
DEPTH_ENCODINGS = ("16uc1", "mono16", "32fc1")
#: Raw depth units per metre of 16-bit depth (ROS: millimetres), and of 32-bit float depth (metres).
MM_DEPTH_SCALE = 1000.0
METRE_DEPTH_SCALE = 1.0

_DEPTH_NAME = re.compile(r"depth", re.I)
_COLOUR_NAME = re.compile(r"colou?r|rgb|image", re.I)
_NOT_COLOUR = re.compile(r"depth|(^|[/_])ir($|[/_\d])|infra|confidence|disparity|mask|label|segment", re.I)
_GT_NAME = re.compile(r"ground_?truth|(^|[/_])gt($|[/_])|mocap|vicon|optitrack", re.I)


def is_bag(path: str | Path) -> bool:
    """True for a ``.bag`` / ``.mcap`` / ``.db3`` file or a ROS 2 bag folder (``metadata.yaml``)."""
    p = Path(path)
    if p.is_file():
        return p.suffix.lower() in BAG_SUFFIXES
    return p.is_dir() and (p / ROS2_METADATA).is_file()


def looks_like_bag(path: str | Path) -> bool:
    """True when the name says bag (``.bag`` / ``.mcap`` / ``.db3``), whether or not it exists."""
    return Path(path).suffix.lower() in BAG_SUFFIXES


def stamp_seconds(sec: int, nanosec: int) -> float:
    """A ROS time as seconds: the double nearest to the decimal ``sec.nanosec`` (so that a stamp written from a
    float with :func:`seconds_to_stamp` reads back as the very same float)."""
    return float(f"{int(sec)}.{int(nanosec):09d}")


def seconds_to_stamp(t: float) -> tuple[int, int]:
    """``(sec, nanosec)`` of ``t`` seconds (``t >= 0``), rounded to the nanosecond."""
    ns = int(Decimal(float(t)).quantize(Decimal("1e-9"), rounding=ROUND_HALF_EVEN).scaleb(9))
    return ns // 1_000_000_000, ns % 1_000_000_000


def _header_stamp(raw: bytes | memoryview, ros2: bool) -> tuple[int, int]:
    """``(sec, nanosec)`` of the ``std_msgs/Header`` every read message starts with, from its serialised bytes
    (ROS 1: ``seq``, then the time; ROS 2 CDR: a 4-byte encapsulation header, then the time)."""
    if ros2:
        endian = "<" if raw[1] == 1 else ">"  # CDR_LE (0x0001) or CDR_BE (0x0000)
        sec, nsec = struct.unpack_from(endian + "iI", raw, 4)
    else:
        sec, nsec = struct.unpack_from("<II", raw, 4)
    return sec, nsec


# ------------------------------------------------------------------------------------------------ opening a bag
def _reader_error_text(exc: BaseException) -> str:
    def flat(args) -> list[str]:
        return [x for a in args for x in (flat(a) if isinstance(a, tuple) else [str(a)])]

    text = " ".join(flat(exc.args)) if exc.args else type(exc).__name__
    text = re.sub(r"\(\s*'([^']*)',\s*\)", r"\1", text)  # rosbags quotes a cause's args tuple: ('why',)
    return re.sub(r"\s+", " ", text).strip() or type(exc).__name__


def _open_reader(path: Path):
    """An opened ``rosbags`` AnyReader on ``path``; DatasetError naming the file when it cannot be read."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:  # pragma: no cover - rosbags comes with evo
        raise ConfigError("reading ROS bags needs the rosbags package: pip install rosbags") from None
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except FileNotFoundError:
        raise DatasetError(path, "bag not found") from None
    except Exception as exc:  # noqa: BLE001 - rosbags, apsw, struct, OS errors: all mean an unreadable bag
        raise DatasetError(path, f"cannot read the bag ({_reader_error_text(exc)}); is it truncated or still "
                                 "being recorded?") from None
    return reader


@dataclass
class TopicIndex:
    """What opening learnt of one topic: its messages' receive times (ns) and header stamps (s), in stamp order."""

    name: str
    msgtype: str
    connections: list = field(default_factory=list)
    log_ns: list[int] = field(default_factory=list)
    stamps: list[float] = field(default_factory=list)

    @property
    def count(self) -> int:
        return len(self.stamps)

    def rate_hz(self) -> float | None:
        if self.count < 2:
            return None
        span = max(self.stamps) - min(self.stamps)
        return (self.count - 1) / span if span > 0 else None


@dataclass(frozen=True)
class MessageRef:
    """Where one message is: its topic, receive time (ns) and header stamp (s)."""

    topic: str
    log_ns: int
    stamp: float


@dataclass(frozen=True)
class BagFrameEntry(FrameEntry):
    """A frame of a bag: the colour and depth messages (``rgb_path`` / ``depth_path`` name them for messages:
    ``<bag>/<topic>@<stamp>``)."""

    rgb_ref: MessageRef | None = None
    depth_ref: MessageRef | None = None


def message_path(root: Path, topic: str, stamp: float) -> Path:
    """``<bag>/<topic>@<stamp>``: how errors and unpaired lists name one message."""
    return Path(f"{root}/{topic.strip('/')}@{stamp:.6f}")


def _rank_depth(name: str, msgtype: str) -> tuple:
    n = name.lower()
    aligned = "aligned" in n or "registered" in n or "align" in n
    return (not aligned, msgtype != IMAGE, "compressed" in n, "raw" not in n and "rect" not in n, name)


def _rank_colour(name: str, msgtype: str) -> tuple:
    n = name.lower()
    named = bool(re.search(r"colou?r|rgb", n))
    return (not named, msgtype != IMAGE, "compressed" in n, "rect" in n, name)


def _namespace(topic: str) -> str:
    parts = topic.rstrip("/").split("/")
    # /camera/color/image_raw -> /camera/color; /camera/image_raw/compressed -> /camera
    if parts and parts[-1] in ("compressed", "compressedDepth", "theora"):
        parts = parts[:-1]
    return "/".join(parts[:-1])


def choose_topics(types: dict[str, str], options: DatasetOptions, path: Path) -> tuple[str, str, str | None, list[str]]:
    """``(colour topic, depth topic, camera-info topic or None, notes)`` from ``{topic: message type}``.

    Raises:
        DatasetError: a topic given in the options is absent or of the wrong type, or no colour / depth topic is
            found (the message lists the image topics and names the option to give).
    """
    images = sorted(t for t, ty in types.items() if ty in IMAGE_TYPES)
    listed = ", ".join(f"{t} ({types[t].rsplit('/', 1)[-1]})" for t in images) or "none"
    notes: list[str] = []

    def given(topic: str, option: str, allowed: tuple[str, ...]) -> str:
        if topic not in types:
            raise DatasetError(path, f"{option} {topic}: no such topic in the bag (image topics: {listed})")
        if types[topic] not in allowed:
            raise DatasetError(path, f"{option} {topic}: the topic holds {types[topic]}, not "
                                     f"{' or '.join(allowed)}")
        return topic

    if options.depth_topic is not None:
        depth = given(options.depth_topic, "--depth-topic", IMAGE_TYPES)
    else:
        cands = sorted((t for t in images if _DEPTH_NAME.search(t)), key=lambda t: _rank_depth(t, types[t]))
        if not cands:
            raise DatasetError(path, f"no depth image topic found (none of the image topics has 'depth' in its "
                                     f"name; image topics: {listed}); give --depth-topic")
        depth = cands[0]
        if len(cands) > 1:
            notes.append(f"depth topic {depth} chosen among {', '.join(cands)} (--depth-topic to choose)")
    if options.rgb_topic is not None:
        rgb = given(options.rgb_topic, "--rgb-topic", IMAGE_TYPES)
    else:
        cands = sorted((t for t in images if t != depth and _COLOUR_NAME.search(t) and not _NOT_COLOUR.search(t)),
                       key=lambda t: _rank_colour(t, types[t]))
        if not cands:
            raise DatasetError(path, f"no colour image topic found (image topics: {listed}); give --rgb-topic")
        rgb = cands[0]
        if len(cands) > 1:
            notes.append(f"colour topic {rgb} chosen among {', '.join(cands)} (--rgb-topic to choose)")
    if options.camera_info_topic is not None:
        info: str | None = given(options.camera_info_topic, "--camera-info-topic", (CAMERA_INFO,))
    else:
        infos = sorted(t for t, ty in types.items() if ty == CAMERA_INFO)
        info = None
        for ns in (_namespace(depth), _namespace(rgb)):
            match = [t for t in infos if _namespace(t) == ns]
            if match:
                info = match[0]
                break
        if info is None and len(infos) == 1:
            info = infos[0]
        if info is None and infos:
            notes.append(f"no camera info topic beside {depth} or {rgb} among {', '.join(infos)} "
                         "(--camera-info-topic to choose)")
    return rgb, depth, info, notes


def _pose_matrix(msg, msgtype: str) -> np.ndarray:
    from surfelslam.geometry.se3 import make_T

    if msgtype.endswith("TransformStamped"):
        p, q = msg.transform.translation, msg.transform.rotation
    elif msgtype.endswith("PoseStamped"):
        p, q = msg.pose.position, msg.pose.orientation
    else:  # PoseWithCovarianceStamped, Odometry: pose.pose
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
    qv = np.array([q.x, q.y, q.z, q.w], np.float64)
    qv /= np.linalg.norm(qv)
    x, y, z, w = qv
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    return make_T(R, np.array([p.x, p.y, p.z], np.float64))


# ------------------------------------------------------------------------------------------------ decoding
def _field(msg, *names):
    for n in names:
        if hasattr(msg, n):
            return getattr(msg, n)
    raise AttributeError(names[0])


def _raw_image(msg, channels: int, dtype) -> np.ndarray:
    """The pixel array of a ``sensor_msgs/Image`` (row padding ``step`` and big-endian data handled)."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    itemsize = np.dtype(dtype).itemsize
    data = np.asarray(msg.data, np.uint8)
    if h * step > data.size or step < w * channels * itemsize:
        raise ValueError(f"{w}x{h} image with step {step} does not fit its {data.size} bytes")
    rows = data[: h * step].reshape(h, step)[:, : w * channels * itemsize]
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<") if itemsize > 1 else np.dtype(dtype)
    arr = np.ascontiguousarray(rows).view(dt).reshape(h, w, channels) if channels > 1 else \
        np.ascontiguousarray(rows).view(dt).reshape(h, w)
    return arr.astype(np.dtype(dtype).newbyteorder("="), copy=False)


def decode_colour(msg, msgtype: str) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB of a colour ``Image`` / ``CompressedImage``; ValueError when unsupported."""
    if msgtype == COMPRESSED:
        import cv2

        fmt = str(msg.format).lower()
        if "compresseddepth" in fmt:
            raise ValueError(f"CompressedImage format {msg.format!r} is depth, not colour")
        img = cv2.imdecode(np.asarray(msg.data, np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            raise ValueError(f"CompressedImage ({msg.format or 'no format'}) cannot be decoded")
        return np.ascontiguousarray(img[:, :, ::-1])
    enc = str(msg.encoding).lower()
    if enc in ("rgb8", "bgr8"):
        img = _raw_image(msg, 3, np.uint8)
        return np.ascontiguousarray(img if enc == "rgb8" else img[:, :, ::-1])
    if enc in ("rgba8", "bgra8"):
        img = _raw_image(msg, 4, np.uint8)[:, :, :3]
        return np.ascontiguousarray(img if enc == "rgba8" else img[:, :, ::-1])
    if enc == "mono8":
        g = _raw_image(msg, 1, np.uint8)
        return np.ascontiguousarray(np.repeat(g[:, :, None], 3, axis=2))
    raise ValueError(f"unsupported colour encoding {msg.encoding!r} (supported: {', '.join(COLOUR_ENCODINGS)}, "
                     "or a JPEG / PNG CompressedImage)")


#: ``compressedDepth`` header: int32 format, float32 depthQuantA, float32 depthQuantB (image_transport plugins).
_COMPRESSED_DEPTH_HEADER = struct.Struct("<iff")


def depth_kind(msg, msgtype: str) -> str:
    """``"mm"`` (16-bit millimetres) or ``"m"`` (float metres) for a depth message; ValueError when unsupported."""
    if msgtype == COMPRESSED:
        fmt = str(msg.format).lower()
        if "compresseddepth" in fmt:
            return "m" if "32fc1" in fmt else "mm"
        if "png" in fmt or fmt.strip() in ("16uc1", "mono16"):
            return "mm"
        raise ValueError(f"unsupported depth CompressedImage format {msg.format!r} (supported: PNG, compressedDepth)")
    enc = str(msg.encoding).lower()
    if enc in ("16uc1", "mono16"):
        return "mm"
    if enc == "32fc1":
        return "m"
    raise ValueError(f"unsupported depth encoding {msg.encoding!r} (supported: 16UC1 / mono16 in millimetres, "
                     "32FC1 in metres, PNG or compressedDepth CompressedImage)")


def decode_depth(msg, msgtype: str) -> np.ndarray:
    """The raw depth of a depth message: ``(H, W)`` uint16 (millimetres) or float32 (metres); ValueError when
    unsupported or undecodable."""
    kind = depth_kind(msg, msgtype)
    if msgtype == COMPRESSED:
        import cv2

        data = np.asarray(msg.data, np.uint8)
        compressed_depth = "compresseddepth" in str(msg.format).lower()
        qa = qb = 0.0
        if compressed_depth:
            if data.size <= _COMPRESSED_DEPTH_HEADER.size:
                raise ValueError("compressedDepth message shorter than its 12-byte header")
            _, qa, qb = _COMPRESSED_DEPTH_HEADER.unpack_from(data.tobytes()[:_COMPRESSED_DEPTH_HEADER.size])
            data = data[_COMPRESSED_DEPTH_HEADER.size:]
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        if img is None or img.ndim != 2:
            raise ValueError(f"depth CompressedImage ({msg.format or 'no format'}) cannot be decoded as one-channel")
        if kind == "m":  # quantised inverse depth: d = A / (v - B), v = 0 invalid
            v = img.astype(np.float32)
            with np.errstate(divide="ignore", invalid="ignore"):
                d = np.float32(qa) / (v - np.float32(qb))
            return np.where(img > 0, d, np.float32(0.0)).astype(np.float32)
        return img.astype(np.uint16, copy=False)
    if kind == "mm":
        return _raw_image(msg, 1, np.uint16)
    return _raw_image(msg, 1, np.float32)


# ------------------------------------------------------------------------------------------------ the adapter
class RosbagSequence(RGBDSequence):
    """A ROS 1 / ROS 2 bag or MCAP file (module docstring)."""

    layout = "rosbag"
    expects = ("a ROS 1 .bag, a ROS 2 bag folder (metadata.yaml + .db3 / .mcap), or an .mcap / .db3 file, with "
               "colour, depth and CameraInfo topics")

    #: set by :meth:`open`
    reader = None
    topics: dict[str, TopicIndex]
    rgb_topic: str
    depth_topic: str
    camera_info_topic: str | None = None
    ground_truth_topic: str | None = None
    ground_truth_source: str | None = None
    bag_format: str = ""

    @classmethod
    def detect(cls, root: Path, meta) -> bool:
        return is_bag(root)

    @classmethod
    def open(cls, root: Path, options: DatasetOptions, meta=None) -> RosbagSequence:
        root = Path(root)
        reader = _open_reader(root)
        try:
            return cls._index(root, reader, options)
        except BaseException:
            reader.close()
            raise

    @classmethod
    def _index(cls, root: Path, reader, options: DatasetOptions) -> RosbagSequence:
        ros2 = bool(reader.is2)
        types: dict[str, str] = {}
        conns: dict[str, list] = {}
        for c in reader.connections:
            types.setdefault(c.topic, c.msgtype)
            conns.setdefault(c.topic, []).append(c)
        rgb, depth, info, notes = choose_topics(types, options, root)
        gt_topic, gt_file = cls._ground_truth_choice(root, types, options)
        wanted = [t for t in dict.fromkeys((rgb, depth, info, gt_topic)) if t is not None]
        index = {t: TopicIndex(t, types[t], conns[t]) for t in wanted}
        first: dict[str, object] = {}
        gt_stamps: list[float] = []
        gt_poses: list[np.ndarray] = []
        where = root
        try:
            for conn, log_ns, raw in reader.messages(connections=[c for t in wanted for c in conns[t]]):
                ti = index[conn.topic]
                where = message_path(root, conn.topic, log_ns * 1e-9)
                sec, nsec = _header_stamp(raw, ros2)
                stamp = stamp_seconds(sec, nsec)
                ti.log_ns.append(int(log_ns))
                ti.stamps.append(stamp)
                if conn.topic not in first or conn.topic == gt_topic:
                    msg = reader.deserialize(raw, conn.msgtype)
                    first.setdefault(conn.topic, msg)
                    if conn.topic == gt_topic:
                        gt_stamps.append(stamp)
                        gt_poses.append(_pose_matrix(msg, conn.msgtype))
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001 - a truncated or corrupt bag, whatever the storage says
            raise DatasetError(where, f"cannot read the bag past this message ({_reader_error_text(exc)}); is it "
                                      "truncated?") from None
        for t in (rgb, depth):
            if index[t].count == 0:
                raise DatasetError(root, f"topic {t} has no messages")
        # what the first messages say: encodings, sizes, the camera
        try:
            colour0 = decode_colour(first[rgb], types[rgb])
        except ValueError as exc:
            raise DatasetError(root, f"colour topic {rgb}: {exc}") from None
        try:
            kind = depth_kind(first[depth], types[depth])
            depth0 = decode_depth(first[depth], types[depth])
        except ValueError as exc:
            raise DatasetError(root, f"depth topic {depth}: {exc}") from None
        h, w = depth0.shape
        if colour0.shape[:2] != (h, w):
            raise DatasetError(root, f"colour topic {rgb} has {colour0.shape[1]}x{colour0.shape[0]} images and depth "
                                     f"topic {depth} {w}x{h}: give a depth topic registered to the colour camera "
                                     "(e.g. aligned_depth_to_color) with --depth-topic")
        intr_src, kind_src = None, "default"
        if options.intrinsics is not None:
            fx, fy, cx, cy = (float(x) for x in options.intrinsics)
            intr_src, kind_src = "--intrinsics", "option"
        elif info is not None and info in first:
            msg = first[info]
            K = np.asarray(_field(msg, "k", "K"), np.float64).reshape(-1)
            if K.size != 9 or K[0] == 0 or K[4] == 0:
                raise DatasetError(root, f"camera info topic {info}: K = {K.tolist()} is not a camera matrix; give "
                                         "--intrinsics")
            iw, ih = int(msg.width), int(msg.height)
            if (iw, ih) != (0, 0) and (iw, ih) != (w, h):
                raise DatasetError(root, f"camera info topic {info} describes {iw}x{ih} images but the depth topic "
                                         f"{depth} has {w}x{h}; give --camera-info-topic or --intrinsics")
            fx, fy, cx, cy = float(K[0]), float(K[4]), float(K[2]), float(K[5])
            intr_src, kind_src = f"camera info topic {info}", "topic"
        else:
            why = f"camera info topic {info} has no messages" if info is not None else "no camera info topic found"
            raise ConfigError(f"{root}: {why}; give --intrinsics fx,fy,cx,cy (or --camera-info-topic)")
        if options.depth_scale is not None:
            scale, scale_src = float(options.depth_scale), "--depth-scale"
        elif kind == "mm":
            scale, scale_src = MM_DEPTH_SCALE, f"depth topic {depth} (16-bit: millimetres)"
        else:
            scale, scale_src = METRE_DEPTH_SCALE, f"depth topic {depth} (32-bit float: metres)"

        entries, unpaired = _pair(root, index[rgb], index[depth])
        gt = None
        if gt_file is not None:
            from surfelslam.datasets.tum import read_ground_truth_file

            gt = read_ground_truth_file(gt_file)
        elif gt_topic is not None and gt_poses:
            order = np.argsort(np.asarray(gt_stamps), kind="stable")
            st = np.asarray(gt_stamps)[order]
            keep = np.r_[True, np.diff(st) > 0]
            gt = Trajectory(st[keep], np.asarray(gt_poses)[order][keep])

        seq = cls(root, entries, Intrinsics(fx, fy, cx, cy, int(w), int(h)), scale, options, gt)
        seq.reader = reader
        seq._lock = threading.Lock()
        seq._ros2 = ros2
        seq.topics = {t: TopicIndex(t, types[t]) for t in types}
        for t, ti in index.items():
            seq.topics[t] = ti
        seq._counts = {c.topic: 0 for c in reader.connections}
        for c in reader.connections:
            seq._counts[c.topic] += int(getattr(c, "msgcount", 0) or 0)
        seq.rgb_topic, seq.depth_topic, seq.camera_info_topic = rgb, depth, info
        seq.ground_truth_topic = gt_topic if gt_file is None else None
        seq.ground_truth_source = str(gt_file) if gt_file is not None else gt_topic
        seq.bag_format = _bag_format(root, ros2)
        seq.unpaired = unpaired
        seq.warnings = list(notes)
        seq.intrinsics_source, seq.intrinsics_kind = intr_src, kind_src
        seq.depth_scale_source = scale_src
        seq._depth_kind = kind
        return seq

    @staticmethod
    def _ground_truth_choice(root: Path, types: dict[str, str], options: DatasetOptions
                             ) -> tuple[str | None, Path | None]:
        """``(pose topic, TUM file)``: ``--gt`` (a file, else a topic), else a pose topic named like ground truth."""
        if options.gt is not None:
            if Path(options.gt).is_file():
                return None, Path(options.gt)
            if options.gt in types:
                if types[options.gt] not in POSE_TYPES:
                    raise DatasetError(root, f"--gt {options.gt}: the topic holds {types[options.gt]}, not a pose "
                                             f"({', '.join(POSE_TYPES)})")
                return options.gt, None
            raise DatasetError(Path(options.gt), "--gt: neither a TUM trajectory file nor a pose topic of the bag")
        named = sorted(t for t, ty in types.items() if ty in POSE_TYPES and _GT_NAME.search(t))
        return (named[0] if named else None), None

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
                    if stamp_seconds(*_header_stamp(raw, self._ros2)) == ref.stamp:
                        found = self.reader.deserialize(raw, conn.msgtype)
                        break
            except Exception as exc:  # noqa: BLE001 - storage errors of a damaged bag
                raise FrameError(message_path(self.root, ref.topic, ref.stamp),
                                 f"cannot read the message ({_reader_error_text(exc)})") from None
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
            out.append({"topic": name, "type": ti.msgtype, "count": ti.count if ti.count else self._counts.get(name, 0),
                        "rate_hz": None if rate is None else round(rate, 3), "role": roles.get(name)})
        return out

    def info(self) -> dict:
        out = super().info()
        out.update(bag_format=self.bag_format, rgb_topic=self.rgb_topic, depth_topic=self.depth_topic,
                   camera_info_topic=self.camera_info_topic, ground_truth_source=self.ground_truth_source,
                   topics=self.topic_table())
        return out


def _bag_format(root: Path, ros2: bool) -> str:
    if not ros2:
        return "ROS 1 bag"
    if root.is_file():
        return "MCAP" if root.suffix.lower() == ".mcap" else "ROS 2 SQLite (.db3)"
    storage = "mcap" if any(root.glob("*.mcap")) else "sqlite3"
    return f"ROS 2 bag ({storage})"


def _sorted_unique(ti: TopicIndex) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """``(stamps, log_ns, dropped positions)`` of a topic in stamp order, a repeated stamp kept once."""
    st = np.asarray(ti.stamps, np.float64)
    order = np.argsort(st, kind="stable")
    keep = np.r_[True, np.diff(st[order]) > 0] if len(order) else np.zeros(0, bool)
    return st[order][keep], np.asarray(ti.log_ns, np.int64)[order][keep], [int(k) for k in order[~keep]]


def _pair(root: Path, rgb: TopicIndex, depth: TopicIndex) -> tuple[list[FrameEntry], list[UnpairedFrame]]:
    """Frames from the colour and depth messages paired by header stamp (:func:`~surfelslam.datasets.tum.associate`,
    the folder readers' rule); DatasetError when nothing or too little pairs."""
    t_rgb, log_rgb, _ = _sorted_unique(rgb)
    t_depth, log_depth, _ = _sorted_unique(depth)
    ia, ib, gap = associate(t_rgb, t_depth, MAX_RGB_DEPTH_DT_S)
    if len(ia) == 0:
        raise DatasetError(root, f"no colour/depth pair within {MAX_RGB_DEPTH_DT_S} s between {rgb.name} "
                                 f"({len(t_rgb)} messages) and {depth.name} ({len(t_depth)} messages); the nearest "
                                 f"header stamps are {gap:.6g} s apart")
    used_rgb = np.zeros(len(t_rgb), bool)
    used_rgb[ia] = True
    used_depth = np.zeros(len(t_depth), bool)
    used_depth[ib] = True
    lone_rgb, lone_depth = np.nonzero(~used_rgb)[0], np.nonzero(~used_depth)[0]
    unpaired = [UnpairedFrame(message_path(root, rgb.name, float(t_rgb[k])), float(t_rgb[k]), why)
                for k, why in zip(lone_rgb, _unpaired_reasons(t_rgb[lone_rgb], t_depth, used_depth,
                                                              MAX_RGB_DEPTH_DT_S, depth.name, "depth image"),
                                  strict=True)]
    unpaired += [UnpairedFrame(message_path(root, depth.name, float(t_depth[k])), float(t_depth[k]), why)
                 for k, why in zip(lone_depth, _unpaired_reasons(t_depth[lone_depth], t_rgb, used_rgb,
                                                                 MAX_RGB_DEPTH_DT_S, rgb.name, "colour image"),
                                   strict=True)]
    listed = max(len(t_rgb), len(t_depth))
    if len(ia) < MIN_PAIRED_FRACTION * listed:
        raise DatasetError(root, f"only {len(ia)} colour/depth pairs within {MAX_RGB_DEPTH_DT_S} s between "
                                 f"{rgb.name} ({len(t_rgb)} messages) and {depth.name} ({len(t_depth)} messages), "
                                 f"fewer than {MIN_PAIRED_FRACTION:.0%}; unpaired: {unpaired_examples(unpaired)}")
    entries: list[FrameEntry] = []
    for a, b in zip(ia, ib, strict=True):
        ta, tb = float(t_rgb[a]), float(t_depth[b])
        entries.append(BagFrameEntry(ta, message_path(root, rgb.name, ta), message_path(root, depth.name, tb), tb,
                                     MessageRef(rgb.name, int(log_rgb[a]), ta),
                                     MessageRef(depth.name, int(log_depth[b]), tb)))
    return entries, unpaired
