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
  Repeated or backward header stamps are counted in the sequence's warnings (a repeat is left out); stamps a driver
  did not set (mostly repeated, e.g. all zero) are replaced by the bag's record times, with a warning
  (:mod:`surfelslam.datasets.rosbag.stamps`).
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

from surfelslam.datasets.rosbag.decode import (
    COLOUR_ENCODINGS,
    DEPTH_ENCODINGS,
    METRE_DEPTH_SCALE,
    MM_DEPTH_SCALE,
    decode_colour,
    decode_depth,
    depth_kind,
)
from surfelslam.datasets.rosbag.index import BagFrameEntry, MessageRef, TopicIndex, message_path
from surfelslam.datasets.rosbag.sequence import RosbagSequence
from surfelslam.datasets.rosbag.topics import (
    BAG_SUFFIXES,
    CAMERA_INFO,
    COMPRESSED,
    HEADER_TYPES,
    IMAGE,
    IMAGE_TYPES,
    POSE_TYPES,
    ROS2_METADATA,
    choose_topics,
    is_bag,
    looks_like_bag,
    seconds_to_stamp,
    stamp_seconds,
)

__all__ = [
    "BAG_SUFFIXES", "CAMERA_INFO", "COLOUR_ENCODINGS", "COMPRESSED", "DEPTH_ENCODINGS", "HEADER_TYPES", "IMAGE",
    "IMAGE_TYPES", "METRE_DEPTH_SCALE", "MM_DEPTH_SCALE", "POSE_TYPES", "ROS2_METADATA", "BagFrameEntry", "MessageRef",
    "RosbagSequence", "TopicIndex", "choose_topics", "decode_colour", "decode_depth", "depth_kind", "is_bag",
    "looks_like_bag", "message_path", "seconds_to_stamp", "stamp_seconds",
]
