"""Core data types: camera intrinsics, RGB-D frames and trajectories.

Conventions
-----------
* Images are indexed ``[v, u]`` (row, column); pixel centres sit at integer coordinates,
  so pixel ``(u, v)`` covers ``[u - 0.5, u + 0.5) x [v - 0.5, v + 0.5)``.
* Camera frame: x right, y down, z forward (optical axis). ``u = fx * x / z + cx``.
* Poses are 4x4 homogeneous matrices named ``T_a_b``: they map points from frame b to frame a,
  so ``T_world_cam`` is the camera-to-world pose.
* Depth is metric (``depth_m``, float32); 0 marks an invalid pixel.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from surfelslam.errors import ConfigError


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of an image of ``width`` x ``height`` pixels.

    ``fy`` may be negative (the ICL-NUIM convention); projection and back-projection use it as is.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        if self.fx == 0 or self.fy == 0:
            raise ConfigError(f"intrinsics: focal lengths must be non-zero (fx={self.fx}, fy={self.fy})")
        if self.width <= 0 or self.height <= 0:
            raise ConfigError(f"intrinsics: image size must be positive ({self.width}x{self.height})")

    def scaled(self, factor: int) -> Intrinsics:
        """Intrinsics of the image sampled ``[::factor, ::factor]``.

        With pixel centres at integer coordinates, new pixel ``u'`` is old pixel ``factor * u'``,
        so focal lengths and the principal point are divided by ``factor`` exactly (no half-pixel
        shift). The size is ``ceil(size / factor)``, which is what the slicing produces.
        """
        if factor < 1 or int(factor) != factor:
            raise ConfigError(f"downsample factor must be a positive integer, got {factor}")
        f = int(factor)
        if f == 1:
            return self
        return Intrinsics(
            self.fx / f, self.fy / f, self.cx / f, self.cy / f,
            -(-self.width // f), -(-self.height // f),
        )

    @property
    def K(self) -> np.ndarray:
        """3x3 camera matrix (float64)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape ``(height, width)``."""
        return (self.height, self.width)

    def as_tuple(self) -> tuple[float, float, float, float]:
        return (self.fx, self.fy, self.cx, self.cy)


@dataclass(frozen=True)
class ColourCamera:
    """A colour camera separate from the depth camera (colour and depth images not registered).

    A point ``X_depth`` (metres, depth camera frame) is seen by the colour camera at
    ``project(X_depth + t_colour_depth_m)`` with ``intrinsics`` (the colour image's own pixel grid); the two
    cameras' axes are taken as parallel (a Kinect-style rig, whose residual rotation is a few milliradians).

    Attributes:
        intrinsics: colour camera pinhole intrinsics; ``width`` x ``height`` is the colour image size.
        t_colour_depth_m: ``(3,)`` translation from the depth camera frame to the colour camera frame (m).
    """

    intrinsics: Intrinsics
    t_colour_depth_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def scaled(self, factor: int) -> ColourCamera:
        """The same camera for images sampled ``[::factor, ::factor]`` (see :meth:`Intrinsics.scaled`)."""
        return ColourCamera(self.intrinsics.scaled(factor), self.t_colour_depth_m)


@dataclass
class RGBDFrame:
    """One registered RGB-D frame.

    Attributes:
        index: position of the frame in its sequence (0-based, after start/stride selection).
        timestamp: the colour image's capture stamp, as the dataset gives it (written to the trajectory as is).
        rgb: ``(H, W, 3)`` uint8, RGB order.
        depth_m: ``(H, W)`` float32 metres, 0 = invalid.
        depth_timestamp: the depth image's capture stamp when the sensor records a separate one (TUM), else
            ``None`` (taken together with the colour).
        seconds_per_stamp: seconds per unit of the stamps: 1 for stamps in seconds (almost every dataset); ICL-NUIM
            stamps frames by their number, 1 apart, which is 1/30 s. Motion bounds and velocities use
            :attr:`time_s`, so they hold in real time whatever the dataset's unit.
    """

    index: int
    timestamp: float
    rgb: np.ndarray
    depth_m: np.ndarray
    depth_timestamp: float | None = None
    seconds_per_stamp: float = 1.0

    @property
    def time_s(self) -> float:
        """The frame's capture time (s): its stamp in seconds."""
        return float(self.timestamp) * self.seconds_per_stamp

    @property
    def colour_minus_depth_s(self) -> float:
        """Colour stamp minus depth stamp (s); 0 when they were taken together."""
        if self.depth_timestamp is None:
            return 0.0
        return float(self.timestamp - self.depth_timestamp) * self.seconds_per_stamp

    @property
    def depth_stamp_s(self) -> float:
        """The depth image's capture time (s)."""
        return float(self.timestamp if self.depth_timestamp is None else self.depth_timestamp) * self.seconds_per_stamp

    def __post_init__(self) -> None:
        if self.depth_m.ndim != 2:
            raise ValueError(f"depth_m must be (H, W), got shape {self.depth_m.shape}")
        if self.rgb.shape != (*self.depth_m.shape, 3):
            raise ValueError(f"rgb must be {(*self.depth_m.shape, 3)}, got {self.rgb.shape}")

    @property
    def shape(self) -> tuple[int, int]:
        return self.depth_m.shape  # type: ignore[return-value]


@dataclass
class Trajectory:
    """A timed sequence of camera poses.

    Attributes:
        timestamps: ``(N,)`` float64 seconds, ascending.
        T_world_cam: ``(N, 4, 4)`` float64 camera-to-world poses.
    """

    timestamps: np.ndarray
    T_world_cam: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        self.T_world_cam = np.asarray(self.T_world_cam, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.timestamps) != len(self.T_world_cam):
            raise ValueError(
                f"trajectory has {len(self.timestamps)} timestamps but {len(self.T_world_cam)} poses"
            )

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        """``(N, 3)`` camera centres in the world frame."""
        return self.T_world_cam[:, :3, 3]

    def lookup(self, stamps: np.ndarray, max_dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Pose with the nearest timestamp for each query stamp.

        Returns:
            ``(T_world_cam (M, 4, 4), valid (M,) bool)``; a stamp farther than ``max_dt_s`` from every pose is
            invalid and gets the identity.
        """
        stamps = np.asarray(stamps, dtype=np.float64).reshape(-1)
        T = np.tile(np.eye(4), (len(stamps), 1, 1))
        if len(self) == 0 or len(stamps) == 0:
            return T, np.zeros(len(stamps), dtype=bool)
        t = self.timestamps
        idx = np.clip(np.searchsorted(t, stamps), 1, max(len(t) - 1, 1))
        lo, hi = idx - 1, np.minimum(idx, len(t) - 1)
        best = np.where(np.abs(t[lo] - stamps) <= np.abs(t[hi] - stamps), lo, hi)
        valid = np.abs(t[best] - stamps) <= max_dt_s
        T[valid] = self.T_world_cam[best[valid]]
        return T, valid

    def subset(self, mask_or_index) -> Trajectory:
        return Trajectory(self.timestamps[mask_or_index], self.T_world_cam[mask_or_index])


class GrowingRows:
    """Rows of one shape and dtype appended one at a time ``(N, *row_shape)``: preallocated and grown by doubling, so
    an append copies the whole array only when the capacity doubles (never per call). Rows not yet appended hold
    ``fill``, so a kernel may be given the whole buffer (:attr:`buffer`) where unused rows must read as empty."""

    def __init__(self, row_shape: tuple[int, ...] = (), dtype=np.float64, fill=0, capacity: int = 16) -> None:
        self._fill = fill
        self._buf = np.full((max(int(capacity), 1), *row_shape), fill, dtype)
        self._n = 0

    def __len__(self) -> int:
        return self._n

    @property
    def rows(self) -> np.ndarray:
        """``(N, *row_shape)`` view of the appended rows (writes go to the array)."""
        return self._buf[: self._n]

    @property
    def buffer(self) -> np.ndarray:
        """``(capacity, *row_shape)`` view of the whole buffer, unused rows at ``fill`` (valid until the next
        append)."""
        return self._buf

    @property
    def capacity(self) -> int:
        return len(self._buf)

    def append(self, row) -> int:
        """Append one row (copied); returns its index."""
        if self._n == len(self._buf):
            buf = np.full((2 * len(self._buf), *self._buf.shape[1:]), self._fill, self._buf.dtype)
            buf[: self._n] = self._buf[: self._n]
            self._buf = buf
        self._buf[self._n] = row
        self._n += 1
        return self._n - 1


class PoseArray:
    """A growing stack of poses ``(K, 4, 4)`` float64 (:class:`GrowingRows` of 4x4 rows)."""

    def __init__(self, capacity: int = 16) -> None:
        self._rows = GrowingRows((4, 4), np.float64, 0.0, capacity)

    def __len__(self) -> int:
        return len(self._rows)

    @property
    def poses(self) -> np.ndarray:
        """``(K, 4, 4)`` view of the stored poses (writes go to the stack)."""
        return self._rows.rows

    @property
    def capacity(self) -> int:
        return self._rows.capacity

    def append(self, T: np.ndarray) -> None:
        """Append one ``(4, 4)`` pose (copied)."""
        self._rows.append(T)
