"""Indexing a bag: opening it with ``rosbags``, one pass over the chosen topics' messages (receive times and header
stamps), the camera and depth units from the first messages, and colour/depth pairing by header stamp (see
:mod:`surfelslam.datasets.rosbag`)."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from surfelslam.datasets.base import (
    MIN_PAIRED_FRACTION,
    DatasetOptions,
    FrameEntry,
    UnpairedFrame,
    unpaired_examples,
)
from surfelslam.datasets.rosbag.decode import (
    METRE_DEPTH_SCALE,
    MM_DEPTH_SCALE,
    decode_colour,
    decode_depth,
    depth_kind,
    message_field,
    pose_matrix,
)
from surfelslam.datasets.rosbag.stamps import check_camera_stamps, usable_mask
from surfelslam.datasets.rosbag.topics import (
    choose_ground_truth,
    choose_topics,
    header_stamp,
    stamp_seconds,
)
from surfelslam.datasets.tum import MAX_RGB_DEPTH_DT_S, associate, unpaired_reasons
from surfelslam.errors import ConfigError, DatasetError, InputError
from surfelslam.types import Intrinsics, Trajectory


def reader_error_text(exc: BaseException) -> str:
    def flat(args) -> list[str]:
        return [x for a in args for x in (flat(a) if isinstance(a, tuple) else [str(a)])]

    text = " ".join(flat(exc.args)) if exc.args else type(exc).__name__
    text = re.sub(r"\(\s*'([^']*)',\s*\)", r"\1", text)  # rosbags quotes a cause's args tuple: ('why',)
    return re.sub(r"\s+", " ", text).strip() or type(exc).__name__


def open_reader(path: Path):
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
        raise DatasetError(path, f"cannot read the bag ({reader_error_text(exc)}); is it truncated or still "
                                 "being recorded?") from None
    return reader


@dataclass
class TopicIndex:
    """What opening learnt of one topic: its messages' receive times (ns) and header stamps (s), in receive order."""

    name: str
    msgtype: str
    connections: list = field(default_factory=list)
    log_ns: list[int] = field(default_factory=list)
    stamps: list[float] = field(default_factory=list)
    #: the messages' own header stamps when ``stamps`` were repaired (:mod:`.stamps`); empty: ``stamps`` are them
    header_stamps: list[float] = field(default_factory=list)

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
    """Where one message is: its topic, receive time (ns) and frame stamp (s); ``header_stamp``: its header's stamp
    when the frame stamp is a repaired one (:mod:`.stamps`), else ``None`` (the same)."""

    topic: str
    log_ns: int
    stamp: float
    header_stamp: float | None = None

    @property
    def own_stamp(self) -> float:
        """The stamp in the message's header (which finds it again)."""
        return self.stamp if self.header_stamp is None else self.header_stamp


@dataclass(frozen=True)
class BagFrameEntry(FrameEntry):
    """A frame of a bag: the colour and depth messages (``rgb_path`` / ``depth_path`` name them for messages:
    ``<bag>/<topic>@<stamp>``)."""

    rgb_ref: MessageRef | None = None
    depth_ref: MessageRef | None = None


def message_path(root: Path, topic: str, stamp: float) -> Path:
    """``<bag>/<topic>@<stamp>``: how errors and unpaired lists name one message."""
    return Path(f"{root}/{topic.strip('/')}@{stamp:.6f}")


@dataclass
class BagIndex:
    """Everything opening a bag learnt: the frames, the camera, the chosen topics and every topic's index."""

    ros2: bool
    entries: list[FrameEntry]
    unpaired: list[UnpairedFrame]
    intrinsics: Intrinsics
    depth_scale: float
    ground_truth: Trajectory | None
    #: every topic of the bag (message times only for the topics read)
    topics: dict[str, TopicIndex]
    #: message count per topic, as the bag's connections declare them
    message_counts: dict[str, int]
    rgb_topic: str
    depth_topic: str
    camera_info_topic: str | None
    ground_truth_topic: str | None
    ground_truth_source: str | None
    bag_format: str
    notes: list[str]
    intrinsics_source: str | None
    intrinsics_kind: str
    depth_scale_source: str
    #: ``"mm"`` (16-bit millimetres) or ``"m"`` (float metres)
    depth_kind: str


def index_bag(root: Path, reader, options: DatasetOptions) -> BagIndex:
    """Read the opened bag ``reader`` once: choose the topics, index their messages, learn the camera and the depth
    units from the first messages, pair colour and depth. DatasetError / ConfigError naming the file and topic."""
    ros2 = bool(reader.is2)
    types: dict[str, str] = {}
    conns: dict[str, list] = {}
    for c in reader.connections:
        if not (isinstance(c.topic, str) and isinstance(c.msgtype, str)):  # a corrupt ROS 2 metadata.yaml
            raise DatasetError(root, f"the bag names a topic {c.topic!r} of type {c.msgtype!r}: not names; is its "
                                     "metadata corrupt?")
        types.setdefault(c.topic, c.msgtype)
        conns.setdefault(c.topic, []).append(c)
    rgb, depth, info, notes = choose_topics(types, options, root)
    gt_topic, gt_file = choose_ground_truth(root, types, options)
    wanted = [t for t in dict.fromkeys((rgb, depth, info, gt_topic)) if t is not None]
    index = {t: TopicIndex(t, types[t], conns[t]) for t in wanted}
    first, gt_stamps, gt_poses = _scan(root, reader, index, gt_topic, ros2)
    for t in (rgb, depth):
        if index[t].count == 0:
            raise DatasetError(root, f"topic {t} has no messages")
    notes = [*notes, *check_camera_stamps(root, [index[rgb], index[depth]])]
    (w, h), kind = _image_size_and_depth_kind(root, first, types, rgb, depth)
    intrinsics, intr_src, kind_src = _intrinsics(root, options, first, info, depth, w, h)
    scale, scale_src = _depth_scale(options, kind, depth)
    entries, unpaired = _pair(root, index[rgb], index[depth])
    gt_stamps, gt_poses = _usable_poses(root, gt_topic, gt_stamps, gt_poses, notes)
    gt = _ground_truth(gt_file, gt_topic, gt_stamps, gt_poses)
    topics = {t: TopicIndex(t, types[t]) for t in types}
    for t, ti in index.items():
        topics[t] = ti
    counts = {c.topic: 0 for c in reader.connections}
    for c in reader.connections:
        counts[c.topic] += int(getattr(c, "msgcount", 0) or 0)
    return BagIndex(
        ros2=ros2, entries=entries, unpaired=unpaired, intrinsics=intrinsics, depth_scale=scale, ground_truth=gt,
        topics=topics, message_counts=counts, rgb_topic=rgb, depth_topic=depth, camera_info_topic=info,
        ground_truth_topic=gt_topic if gt_file is None else None,
        ground_truth_source=str(gt_file) if gt_file is not None else gt_topic,
        bag_format=_bag_format(root, ros2), notes=list(notes), intrinsics_source=intr_src, intrinsics_kind=kind_src,
        depth_scale_source=scale_src, depth_kind=kind)


def _scan(root: Path, reader, index: dict[str, TopicIndex], gt_topic: str | None, ros2: bool
          ) -> tuple[dict[str, object], list[float], list[np.ndarray]]:
    """One pass over the messages of the ``index`` topics, filling their receive times and header stamps; returns
    ``(first message per topic, ground-truth stamps, ground-truth poses)``."""
    first: dict[str, object] = {}
    gt_stamps: list[float] = []
    gt_poses: list[np.ndarray] = []
    where = root
    try:
        for conn, log_ns, raw in reader.messages(connections=[c for ti in index.values() for c in ti.connections]):
            ti = index[conn.topic]
            where = message_path(root, conn.topic, log_ns * 1e-9)
            sec, nsec = header_stamp(raw, ros2)
            stamp = stamp_seconds(sec, nsec)
            ti.log_ns.append(int(log_ns))
            ti.stamps.append(stamp)
            if conn.topic not in first or conn.topic == gt_topic:
                msg = reader.deserialize(raw, conn.msgtype)
                first.setdefault(conn.topic, msg)
                if conn.topic == gt_topic:
                    gt_stamps.append(stamp)
                    gt_poses.append(pose_matrix(msg, conn.msgtype))
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - a truncated or corrupt bag, whatever the storage says
        raise DatasetError(where, f"cannot read the bag past this message ({reader_error_text(exc)}); is it "
                                  "truncated?") from None
    return first, gt_stamps, gt_poses


def _image_size_and_depth_kind(root: Path, first: dict[str, object], types: dict[str, str], rgb: str, depth: str
                               ) -> tuple[tuple[int, int], str]:
    """``((width, height), depth kind)`` from the first colour and depth messages (which must decode, at one size)."""
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
    return (w, h), kind


def _intrinsics(root: Path, options: DatasetOptions, first: dict[str, object], info: str | None, depth: str,
                w: int, h: int) -> tuple[Intrinsics, str | None, str]:
    """``(intrinsics, source, kind)``: ``--intrinsics``, else the camera info topic's ``K``; ConfigError without
    either."""
    if options.intrinsics is not None:
        fx, fy, cx, cy = (float(x) for x in options.intrinsics)
        intr_src, kind_src = "--intrinsics", "option"
    elif info is not None and info in first:
        msg = first[info]
        K = np.asarray(message_field(msg, "k", "K"), np.float64).reshape(-1)
        if K.size != 9 or not np.all(np.isfinite(K)) or not (K[0] > 0 and K[4] > 0):
            raise DatasetError(root, f"camera info topic {info}: K = {K.tolist()} is not a camera matrix (finite, "
                                     "positive focal lengths); give --intrinsics")
        iw, ih = int(msg.width), int(msg.height)
        if (iw, ih) != (0, 0) and (iw, ih) != (w, h):
            raise DatasetError(root, f"camera info topic {info} describes {iw}x{ih} images but the depth topic "
                                     f"{depth} has {w}x{h}; give --camera-info-topic or --intrinsics")
        fx, fy, cx, cy = float(K[0]), float(K[4]), float(K[2]), float(K[5])
        intr_src, kind_src = f"camera info topic {info}", "topic"
    else:
        why = f"camera info topic {info} has no messages" if info is not None else "no camera info topic found"
        raise ConfigError(f"{root}: {why}; give --intrinsics fx,fy,cx,cy (or --camera-info-topic)")
    return Intrinsics(fx, fy, cx, cy, int(w), int(h)), intr_src, kind_src


def _depth_scale(options: DatasetOptions, kind: str, depth: str) -> tuple[float, str]:
    """``(raw depth units per metre, source)``: ``--depth-scale``, else by the depth encoding."""
    if options.depth_scale is not None:
        return float(options.depth_scale), "--depth-scale"
    if kind == "mm":
        return MM_DEPTH_SCALE, f"depth topic {depth} (16-bit: millimetres)"
    return METRE_DEPTH_SCALE, f"depth topic {depth} (32-bit float: metres)"


def _usable_poses(root: Path, gt_topic: str | None, stamps: list[float], poses: list[np.ndarray], notes: list[str]
                  ) -> tuple[list[float], list[np.ndarray]]:
    """The ground-truth topic's finite poses; poses not finite (or with a zero quaternion) and repeated stamps are
    counted in ``notes`` (the repeats are left out by :func:`_ground_truth`)."""
    finite = [bool(np.all(np.isfinite(T))) for T in poses]
    if not all(finite):
        notes.append(f"{root}: ground-truth topic {gt_topic}: {finite.count(False)} of {len(finite)} poses are not "
                     "finite (or have a zero quaternion) and are left out")
        stamps = [t for t, ok in zip(stamps, finite, strict=True) if ok]
        poses = [T for T, ok in zip(poses, finite, strict=True) if ok]
    repeated = len(stamps) - len(set(stamps))
    if repeated:
        notes.append(f"{root}: ground-truth topic {gt_topic}: {repeated} of {len(stamps)} poses repeat an earlier "
                     "header stamp and are left out")
    return stamps, poses


def _ground_truth(gt_file: Path | None, gt_topic: str | None, gt_stamps: list[float], gt_poses: list[np.ndarray]
                  ) -> Trajectory | None:
    """The ``--gt`` TUM file's trajectory, else the pose topic's (stamp order, a repeated stamp kept once)."""
    if gt_file is not None:
        from surfelslam.datasets.tum import read_ground_truth_file

        return read_ground_truth_file(gt_file)
    if gt_topic is not None and gt_poses:
        order = np.argsort(np.asarray(gt_stamps), kind="stable")
        st = np.asarray(gt_stamps)[order]
        keep = np.r_[True, np.diff(st) > 0]
        return Trajectory(st[keep], np.asarray(gt_poses)[order][keep])
    return None


def _bag_format(root: Path, ros2: bool) -> str:
    if not ros2:
        return "ROS 1 bag"
    if root.is_file():
        return "MCAP" if root.suffix.lower() == ".mcap" else "ROS 2 SQLite (.db3)"
    storage = "mcap" if any(root.glob("*.mcap")) else "sqlite3"
    return f"ROS 2 bag ({storage})"


def _sorted_unique(ti: TopicIndex) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(stamps, log_ns, header stamps)`` of a topic's messages in stamp order, a repeated stamp kept once (the
    first received: :func:`~.stamps.usable_mask`; :func:`~.stamps.check_camera_stamps` reported the others)."""
    keep = usable_mask(ti.stamps)
    st = np.asarray(ti.stamps, np.float64)[keep]
    own = np.asarray(ti.header_stamps if ti.header_stamps else ti.stamps, np.float64)[keep]
    order = np.argsort(st, kind="stable")
    return st[order], np.asarray(ti.log_ns, np.int64)[keep][order], own[order]


def _pair(root: Path, rgb: TopicIndex, depth: TopicIndex) -> tuple[list[FrameEntry], list[UnpairedFrame]]:
    """Frames from the colour and depth messages paired by header stamp (:func:`~surfelslam.datasets.tum.associate`,
    the folder readers' rule); DatasetError when nothing or too little pairs."""
    t_rgb, log_rgb, own_rgb = _sorted_unique(rgb)
    t_depth, log_depth, own_depth = _sorted_unique(depth)
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
                for k, why in zip(lone_rgb, unpaired_reasons(t_rgb[lone_rgb], t_depth, used_depth,
                                                             MAX_RGB_DEPTH_DT_S, depth.name, "depth image"),
                                  strict=True)]
    unpaired += [UnpairedFrame(message_path(root, depth.name, float(t_depth[k])), float(t_depth[k]), why)
                 for k, why in zip(lone_depth, unpaired_reasons(t_depth[lone_depth], t_rgb, used_rgb,
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
                                     _ref(rgb.name, int(log_rgb[a]), ta, float(own_rgb[a])),
                                     _ref(depth.name, int(log_depth[b]), tb, float(own_depth[b]))))
    return entries, unpaired


def _ref(topic: str, log_ns: int, stamp: float, own_stamp: float) -> MessageRef:
    return MessageRef(topic, log_ns, stamp, None if own_stamp == stamp else own_stamp)
