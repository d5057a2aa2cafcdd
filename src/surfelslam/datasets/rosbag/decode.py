"""Decoding bag messages: colour and depth ``Image`` / ``CompressedImage`` (incl. ``compressedDepth``) to arrays, and
pose messages to ``T_world_cam`` (see :mod:`surfelslam.datasets.rosbag`)."""

from __future__ import annotations

import struct

import numpy as np

from surfelslam.datasets.rosbag.topics import COMPRESSED

COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8")
DEPTH_ENCODINGS = ("16uc1", "mono16", "32fc1")
#: Raw depth units per metre of 16-bit depth (ROS: millimetres), and of 32-bit float depth (metres).
MM_DEPTH_SCALE = 1000.0
METRE_DEPTH_SCALE = 1.0


def pose_matrix(msg, msgtype: str) -> np.ndarray:
    """``T_world_cam`` (4x4) of a pose message (``PoseStamped``, ``PoseWithCovarianceStamped``,
    ``TransformStamped`` or ``Odometry``)."""
    from surfelslam.geometry.se3 import make_T

    if msgtype.endswith("TransformStamped"):
        p, q = msg.transform.translation, msg.transform.rotation
    elif msgtype.endswith("PoseStamped"):
        p, q = msg.pose.position, msg.pose.orientation
    else:  # PoseWithCovarianceStamped, Odometry: pose.pose
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
    qv = np.array([q.x, q.y, q.z, q.w], np.float64)
    big = np.abs(qv).max()
    if not (np.isfinite(big) and big > 0 and np.all(np.isfinite([p.x, p.y, p.z]))):
        return np.full((4, 4), np.nan)  # a zero or non-finite pose: left out (and counted) by the indexer
    qv = np.ldexp(qv, -np.frexp(big)[1])  # exact power-of-two scaling: components like 1e200 do not overflow
    qv /= np.linalg.norm(qv)
    x, y, z, w = qv
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    return make_T(R, np.array([p.x, p.y, p.z], np.float64))


def message_field(msg, *names):
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
