"""The hybrid tracker's frames anchored to keyframes, and the loop corrections that move them and the map.

Each frame is anchored to the last keyframe when it was processed: its pose is kept as ``T_kf_cam`` relative to that
keyframe's pose in the dense frame (``T_kf_dense``, the ICP pose it was created with); each surfel is anchored to the
anchor of the frame that created it (``first_seen`` -> anchor, a sorted frame-index table). A keyframe's correction
is ``C_k = T_kf_graph inv(T_kf_dense)`` (see :mod:`surfelslam.slam.hybrid` for when corrections are applied).

The written trajectory does not move a frame rigidly with its anchor: the graph also changes each keyframe's pose
relative to the next one (the dense odometry between them drifts), so a frame between keyframes ``k`` and ``k + 1``
takes the fraction of that change its time spent since ``k`` (:meth:`KeyframeAnchors.trajectory`); else the frames
just before ``k + 1`` would keep the whole drift that the graph removed from ``k + 1``.
"""

from __future__ import annotations

import numpy as np

from surfelslam.backend.sparse_slam import SparseSlam
from surfelslam.geometry import se3
from surfelslam.mapping.surfel_map import SurfelMap
from surfelslam.types import GrowingRows, PoseArray, Trajectory

# surfels lie within the sensor's depth range of the keyframe that anchors them: a correction's rotation moves them by
# at most its angle times this
SURFEL_REACH_M = 5.0


class KeyframeAnchors:
    """Keyframe poses in the dense frame, every frame's anchor and relative pose, the fused frames' anchors.

    ``sparse``: the back end whose pose graph holds the keyframes' graph poses.
    """

    def __init__(self, sparse: SparseSlam):
        self.sparse = sparse
        self.kf_dense = PoseArray()  # keyframe poses in the dense (tracking and map) frame
        # per keyframe: its pose relative to the previous keyframe's in the dense frame when it was added (the
        # odometry edge the graph got; identity for the first), and the slot of its own frame in the records
        self._kf_step = PoseArray()
        self._kf_slot = GrowingRows((), np.int64)
        # per record (a processed frame): its timestamp, frame index, anchor keyframe and pose relative to it; growing
        # arrays, so that the per-keyframe lookups (:meth:`last_frame_before`, :meth:`keyframe_stamps`) convert nothing
        self._stamps = GrowingRows((), np.float64)
        self._frame_index = GrowingRows((), np.int64)
        self._anchor = GrowingRows((), np.int64)
        self._T_kf_cam = PoseArray()
        self._fused_frames = GrowingRows((), np.int64)  # frame index of each fused frame (increasing)
        self._fused_anchor = GrowingRows((), np.int64)
        self.map_corrections = 0  # corrections applied to the map and the current pose

    def __len__(self) -> int:
        """Keyframes known in the dense frame."""
        return len(self.kf_dense)

    @property
    def anchor(self) -> np.ndarray:
        """``(N,)`` int64 each recorded frame's anchor keyframe (a view: valid until the next record)."""
        return self._anchor.rows

    @property
    def T_kf_cam(self) -> np.ndarray:
        """``(N, 4, 4)`` each recorded frame's pose relative to its anchor (a view: valid until the next record)."""
        return self._T_kf_cam.poses

    def add_keyframe(self, T_world_kf: np.ndarray) -> None:
        """A new keyframe at ``T_world_kf`` ``(4, 4)`` in the dense frame (its own frame is recorded next)."""
        prev = self.kf_dense.poses[-1] if len(self.kf_dense) else np.asarray(T_world_kf)
        self._kf_step.append(se3.invert(prev) @ T_world_kf)
        self._kf_slot.append(len(self._stamps))
        self.kf_dense.append(T_world_kf)

    def promote_last(self) -> None:
        """The last recorded frame became a keyframe (:meth:`SparseSlam.promote_last_frame`): it anchors itself."""
        T_world_kf = self.kf_dense.poses[self.anchor[-1]] @ self.T_kf_cam[-1]
        self._kf_step.append(self.T_kf_cam[-1])
        self._kf_slot.append(len(self._stamps) - 1)
        self.kf_dense.append(T_world_kf)
        self.anchor[-1] = len(self.kf_dense) - 1
        self.T_kf_cam[-1] = np.eye(4)

    def record(self, frame_index: int, timestamp: float, T_world_cam: np.ndarray, fused: bool) -> None:
        """A processed frame at ``T_world_cam`` (dense frame), anchored to the back end's last keyframe."""
        anchor = self.sparse.n_keyframes - 1
        if fused:
            self._fused_frames.append(frame_index)
            self._fused_anchor.append(anchor)
        self._stamps.append(timestamp)
        self._frame_index.append(int(frame_index))
        self._anchor.append(anchor)
        self._T_kf_cam.append(se3.invert(self.kf_dense.poses[anchor]) @ T_world_cam)

    def correction(self, k: int) -> np.ndarray:
        """``C_k = T_kf_graph inv(T_kf_dense)``: maps dense-frame poses near keyframe ``k`` into the graph frame."""
        return self.sparse.keyframe_pose(k) @ se3.invert(self.kf_dense.poses[k])

    def corrections(self, kf_new: np.ndarray) -> np.ndarray:
        """``(K, 4, 4)`` each keyframe's correction ``T_new inv(T_dense)`` for the graph poses ``kf_new``."""
        return kf_new @ se3.invert(self.kf_dense.poses)

    def keyframe_moves_m(self, kf_new: np.ndarray) -> np.ndarray:
        """``(K,)`` bound (m) on how far the graph poses ``kf_new`` ``(K, 4, 4)`` would move each keyframe's surfels:
        the keyframe's own displacement plus its correction's rotation angle over :data:`SURFEL_REACH_M`."""
        dense = self.kf_dense.poses
        shift_m = np.linalg.norm(kf_new[:, :3, 3] - dense[:, :3, 3], axis=1)
        R_corr = kf_new[:, :3, :3] @ np.transpose(dense[:, :3, :3], (0, 2, 1))
        cos = np.clip((np.trace(R_corr, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
        return shift_m + np.arccos(cos) * SURFEL_REACH_M

    def correct(self, kf_new: np.ndarray, smap: SurfelMap | None, C: np.ndarray | None = None,
                min_move_m: float = 0.0) -> np.ndarray:
        """Move the surfels of ``smap`` (``None``: the map stays) by their anchors' corrections ``C``
        (:meth:`corrections` of ``kf_new`` by default); the keyframes take the poses ``kf_new``. With ``min_move_m``
        > 0 only the keyframes that :meth:`keyframe_moves_m` moves farther, and their surfels, do (the others keep
        their pending correction for a later call: the cost follows what moves). Returns the last frame's corrected
        pose ``(4, 4)``."""
        C = self.corrections(kf_new) if C is None else C
        self.map_corrections += 1
        moved = self.keyframe_moves_m(kf_new) > min_move_m if min_move_m > 0 else np.ones(len(kf_new), bool)
        if smap is not None and smap.size and moved.any():
            a = self.surfel_anchors(smap)
            R, t = C[:, :3, :3].astype(np.float32), C[:, :3, 3].astype(np.float32)
            if moved.all():
                smap.transform_groups(R, t, a)
            else:
                rows = np.flatnonzero(moved[a])
                smap.transform_groups(R, t, a[rows], rows)
        self.kf_dense.poses[moved] = kf_new[moved]
        return se3.orthonormalize(self.kf_dense.poses[self.anchor[-1]] @ self.T_kf_cam[-1])

    def surfel_anchors(self, smap: SurfelMap) -> np.ndarray:
        """``(size,)`` int64 anchor keyframe of each surfel of ``smap`` (that of the fused frame that created it)."""
        return self.anchors_of(smap.first_seen)

    def anchors_of(self, first_seen: np.ndarray) -> np.ndarray:
        """``(n,)`` int64 anchor keyframe of surfels first seen in the frames ``first_seen`` ``(n,)`` (fused frames)."""
        frames = self._fused_frames.rows
        if len(first_seen) == 0:
            return np.zeros(0, np.int64)
        # a table per frame index up to the newest surfel's (the frame count): one gather per surfel, no search
        row = np.clip(np.searchsorted(frames, np.arange(int(first_seen.max()) + 1)), 0, len(frames) - 1)
        return self._fused_anchor.rows[row][first_seen]

    def keyframe_stamps(self, keyframes: np.ndarray) -> np.ndarray:
        """``(n,)`` timestamps of the frames of ``keyframes`` ``(n,)`` (ids)."""
        return self._stamps.rows[self._kf_slot.rows[keyframes]]

    def last_frame_before(self, time_s: float) -> int:
        """Index of the last recorded frame whose timestamp is at most ``time_s`` (s); -1 when there is none."""
        slot = int(np.searchsorted(self._stamps.rows, time_s, side="right")) - 1
        return int(self._frame_index.rows[slot]) if slot >= 0 else -1

    def trajectory(self, kf_poses: np.ndarray | None = None) -> Trajectory:
        """Every frame's pose with the keyframe poses ``kf_poses`` ``(K, 4, 4)`` (default: the graph's):
        ``T_world_kf W_k(a) T_kf_cam`` for a frame anchored to keyframe ``k``, where ``W_k = inv(T_world_kf)
        T_world_kf+1 inv(step_k+1)`` is how the poses change keyframe ``k + 1`` relative to ``k`` beyond the dense
        step between them, and ``W_k(a)`` its fraction ``a`` (rotation angle and translation scaled by ``a``), ``a``
        the frame's time from keyframe ``k``'s over the time to ``k + 1``'s (0 after the last keyframe)."""
        kf = self.sparse.keyframe_poses() if kf_poses is None else kf_poses
        anchor = self.anchor
        T_kf_cam = self.T_kf_cam
        stamps = self._stamps.rows
        W = self._next_keyframe_changes(kf)
        frac = self._fractions(stamps, anchor, len(W))
        Wa = np.tile(np.eye(4), (len(anchor), 1, 1))
        part = np.flatnonzero(frac > 0)
        if len(part):
            a, k = frac[part], anchor[part]
            Wa[part, :3, :3] = se3.so3_exp_many(a[:, None] * se3.so3_log(W[k, :3, :3]))
            Wa[part, :3, 3] = a[:, None] * W[k, :3, 3]
        return Trajectory(stamps, kf[anchor] @ Wa @ T_kf_cam)

    def _next_keyframe_changes(self, kf: np.ndarray) -> np.ndarray:
        """``(K - 1, 4, 4)`` ``W_k = inv(kf_k) kf_k+1 inv(step_k+1)`` for the keyframe poses ``kf`` ``(K, 4, 4)``
        (identity where ``kf`` keeps the dense step)."""
        if len(kf) < 2:
            return np.zeros((0, 4, 4))
        steps = self._kf_step.poses[1:len(kf)]
        return se3.invert(kf[:-1]) @ kf[1:] @ se3.invert(steps)

    def _fractions(self, stamps: np.ndarray, anchor: np.ndarray, n_changes: int) -> np.ndarray:
        """``(N,)`` each record's fraction of the way (in time) from its anchor keyframe's frame to the next
        keyframe's (0 without a recorded next keyframe, or when their times do not increase)."""
        frac = np.zeros(len(anchor))
        slots = self._kf_slot.rows
        has_next = anchor < min(n_changes, int(np.count_nonzero(slots < len(stamps))) - 1)
        if not has_next.any():
            return frac
        k = anchor[has_next]
        t0, t1 = stamps[slots[k]], stamps[slots[k + 1]]
        span = t1 - t0
        ok = span > 0
        frac[np.flatnonzero(has_next)[ok]] = np.clip((stamps[has_next][ok] - t0[ok]) / span[ok], 0.0, 1.0)
        return frac

    def correction_m(self, kf_new: np.ndarray) -> float:
        """How far (m) the final graph poses ``kf_new`` move the farthest keyframe from its current pose, the first
        keyframe's rigid move taken out."""
        C0 = kf_new[0] @ se3.invert(self.kf_dense.poses[0])
        rel = se3.invert(C0) @ kf_new
        return float(np.linalg.norm(rel[:, :3, 3] - self.kf_dense.poses[:, :3, 3], axis=1).max())
