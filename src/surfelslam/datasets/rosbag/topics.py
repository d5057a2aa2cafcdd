"""Bag topics: the message types read, bag paths, header stamps, and choosing the colour, depth, camera-info and
ground-truth topics (see :mod:`surfelslam.datasets.rosbag`)."""

from __future__ import annotations

import re
import struct
from decimal import ROUND_HALF_EVEN, Decimal
from pathlib import Path

from surfelslam.datasets.base import DatasetOptions
from surfelslam.errors import DatasetError

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


def header_stamp(raw: bytes | memoryview, ros2: bool) -> tuple[int, int]:
    """``(sec, nanosec)`` of the ``std_msgs/Header`` every read message starts with, from its serialised bytes
    (ROS 1: ``seq``, then the time; ROS 2 CDR: a 4-byte encapsulation header, then the time)."""
    if ros2:
        endian = "<" if raw[1] == 1 else ">"  # CDR_LE (0x0001) or CDR_BE (0x0000)
        sec, nsec = struct.unpack_from(endian + "iI", raw, 4)
    else:
        sec, nsec = struct.unpack_from("<II", raw, 4)
    return sec, nsec


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


def choose_ground_truth(root: Path, types: dict[str, str], options: DatasetOptions
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
