"""The keyframes a surfel tracker keeps for its saved map: poses, ORB features and subsampled depth.

A saved map (:mod:`surfelslam.slam.saved_map`) carries keyframes so that a later run can find where its first
frames are in the map (place recognition and PnP, :mod:`surfelslam.slam.map_localiser`). The surfel trackers
record them as they fuse (:class:`KeyframeRecorder`): a fused frame becomes a keyframe when its motion norm from the
last one reaches ``map_reuse.keyframe_motion``. Recording reads the frame and the tracked pose only; it never changes
tracking or the map.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field

import numpy as np

from surfelslam.geometry.se3 import invert, motion_norm
from surfelslam.tracking.features import Features
from surfelslam.types import RGBDFrame, Trajectory


@dataclass
class MapKeyframes:
    """Keyframes of a map, in the map's world frame.

    Attributes:
        T_world_kf: ``(K, 4, 4)`` float64 keyframe poses (camera to world).
        frame_index: ``(K,)`` int64 index of the frame each was made from (in its own session).
        timestamp: ``(K,)`` float64 its timestamp (s).
        session: ``(K,)`` int32 the session (run) that made it: 0 for the first, +1 for each run continuing the map.
        features: ``K`` :class:`Features` (keypoints, descriptors, camera-frame points; no image).
        depth_m: ``K`` ``(h, w)`` float32 depth images, subsampled by ``depth_step``.
        depth_step: the subsampling step of ``depth_m`` (pixels of the full image per saved pixel).
    """

    T_world_kf: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    frame_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    timestamp: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float64))
    session: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    features: list[Features] = field(default_factory=list)
    depth_m: list[np.ndarray] = field(default_factory=list)
    depth_step: int = 1

    def __len__(self) -> int:
        return len(self.features)


def slim_features(feats: Features) -> Features:
    """``feats`` without its images (what a saved keyframe keeps)."""
    return Features(feats.keypoints_uv, feats.descriptors, feats.points_cam, feats.valid, feats.response)


def depth_step_for_width(width_px: int, max_width_px: int) -> int:
    """The power-of-two subsampling step that brings ``width_px`` to at most ``max_width_px``."""
    step = 1
    while width_px // step > max_width_px:
        step *= 2
    return step


class KeyframeRecorder:
    """Keyframes for the saved map, recorded as frames are fused.

    Args:
        keyframe_motion: motion norm (m + rad) from the last keyframe that makes a new one.
        depth_step: subsampling step of the saved depth.
        features_of: the frame's ORB features (the tracker's own when it has them, else extracted), or a future of
            them (extracted on another thread; awaited when the keyframes are read), or ``None``: the frame has none at
            hand and is not recorded (a later frame far enough from the last keyframe is).
        prior: keyframes of a loaded map, kept first (a run that continues a map); this run's are session
            ``prior.session.max() + 1``.
    """

    def __init__(self, keyframe_motion: float, depth_step: int,
                 features_of: Callable[[RGBDFrame], Features | Future],
                 prior: MapKeyframes | None = None) -> None:
        self.keyframe_motion = keyframe_motion
        self.depth_step = depth_step
        self._features_of = features_of
        self._prior = prior if prior is not None and len(prior) else None
        self.session = 0 if self._prior is None else int(self._prior.session.max()) + 1
        self._poses: list[np.ndarray] = []
        self._frames: list[int] = []
        self._stamps: list[float] = []
        self._features: list[Features | Future] = []
        self._depth: list[np.ndarray] = []

    @property
    def n_recorded(self) -> int:
        """Keyframes recorded in this session."""
        return len(self._poses)

    def observe(self, frame: RGBDFrame, T_world_cam: np.ndarray) -> bool:
        """A fused frame at ``T_world_cam`` ``(4, 4)``: record it when it is far enough from the last keyframe of
        this session and its features are given (not ``None``); returns whether it did."""
        if self._poses and motion_norm(invert(self._poses[-1]) @ T_world_cam) < self.keyframe_motion:
            return False
        feats = self._features_of(frame)
        if feats is None:
            return False
        s = self.depth_step
        self._poses.append(np.asarray(T_world_cam, np.float64).copy())
        self._frames.append(int(frame.index))
        self._stamps.append(float(frame.timestamp))
        self._features.append(feats if isinstance(feats, Future) else slim_features(feats))
        self._depth.append(np.ascontiguousarray(frame.depth_m[::s, ::s], np.float32))
        return True

    def repose(self, trajectory: Trajectory) -> None:
        """Give this session's keyframes their poses in ``trajectory`` (the final, loop-corrected one), matched by
        timestamp; keyframes it does not hold keep theirs."""
        stamps = np.asarray(trajectory.timestamps, np.float64)
        for k, t in enumerate(self._stamps):
            i = int(np.searchsorted(stamps, t))
            if i < len(stamps) and stamps[i] == t:
                self._poses[k] = np.asarray(trajectory.T_world_cam[i], np.float64).copy()

    def keyframes(self) -> MapKeyframes:
        """The prior map's keyframes followed by this session's."""
        n = len(self._poses)
        self._features = [slim_features(f.result()) if isinstance(f, Future) else f for f in self._features]
        mine = MapKeyframes(np.asarray(self._poses, np.float64).reshape(n, 4, 4),
                            np.asarray(self._frames, np.int64), np.asarray(self._stamps, np.float64),
                            np.full(n, self.session, np.int32), list(self._features), list(self._depth),
                            self.depth_step)
        p = self._prior
        if p is None:
            return mine
        return MapKeyframes(np.concatenate([p.T_world_kf, mine.T_world_kf]),
                            np.concatenate([p.frame_index, mine.frame_index]),
                            np.concatenate([p.timestamp, mine.timestamp]),
                            np.concatenate([p.session, mine.session]), p.features + mine.features,
                            p.depth_m + mine.depth_m, p.depth_step)
