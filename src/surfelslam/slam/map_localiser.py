"""Where a frame is in a saved map: place recognition and PnP against its keyframes, then a verified dense ICP.

Per frame (:class:`MapLocaliser`):

1. ``retrieve``: the frame's ORB descriptors vote for the saved keyframes
   (:class:`~surfelslam.backend.place_recognition.DescriptorIndex`); the ``map_reuse.localise_candidates`` best are
   kept.
2. ``pnp``: each candidate is verified by PnP-RANSAC with the loop-closure rules
   (:func:`~surfelslam.backend.loops.verify_edge`, motion bound ``sparse.relocalise_max_norm``): a pose guess
   ``T_world_kf T_kf_cam`` in the map's frame per keyframe that passes, most inliers first.
3. ``verify`` (:func:`verify_icp`): the tracker renders the saved surfels at the guess and registers the frame by
   ICP from it; the pose is accepted only when ICP succeeds, keeps ``localise_min_inlier_fraction`` of the frame's
   points as inliers (the overlap) with an RMS residual of at most ``localise_max_rmse_m``, and moves the PnP pose
   by at most ``localise_max_shift_m`` / ``_deg``. A map of another place gives no PnP pose or fails these checks:
   it is refused, never forced.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from surfelslam.backend.loops import verify_edge
from surfelslam.backend.place_recognition import DescriptorIndex, select_descriptors
from surfelslam.backend.sparse_slam import SparseSlamConfig
from surfelslam.geometry.se3 import invert
from surfelslam.slam.config import MapReuseConfig
from surfelslam.slam.map_keyframes import MapKeyframes
from surfelslam.tracking.features import Features
from surfelslam.tracking.icp import ICPResult, icp_failure
from surfelslam.types import Intrinsics

#: reason of a frame not yet localised in a loaded map (lost, no pose written)
NOT_LOCALISED = "not_localised_in_map"


@dataclass
class PoseGuess:
    """A PnP pose of the frame against one saved keyframe: ``T_world_cam`` ``(4, 4)`` in the map's frame."""

    T_world_cam: np.ndarray
    kf_id: int
    n_inliers: int


class MapLocaliser:
    """Place recognition and PnP of frames against a saved map's keyframes.

    Args:
        keyframes: the saved keyframes (map frame).
        intr: the camera of the frames to localise.
        sparse_cfg: the sparse settings (ORB matching and PnP, retrieval, loop bounds), scaled for ``intr``'s width.
        cfg: the ``[map_reuse]`` settings.
    """

    def __init__(self, keyframes: MapKeyframes, intr: Intrinsics, sparse_cfg: SparseSlamConfig,
                 cfg: MapReuseConfig) -> None:
        self.keyframes = keyframes
        self.intr = intr
        self.cfg = cfg
        self._features_cfg = sparse_cfg.features
        self._loop_cfg = replace(sparse_cfg.loop, max_norm_loop=sparse_cfg.relocalise_max_norm)
        self._n_max = sparse_cfg.loop.retrieval.max_descriptors_per_keyframe
        self._index = DescriptorIndex(sparse_cfg.loop.retrieval)
        for f in keyframes.features:
            self._index.add(select_descriptors(f.descriptors, f.response, f.valid, self._n_max))

    def guesses(self, feats: Features) -> list[PoseGuess]:
        """PnP-verified poses of a frame with features ``feats`` against the best-voted keyframes, most inliers
        first (empty: no keyframe verified)."""
        query = select_descriptors(feats.descriptors, feats.response, feats.valid, self._n_max)
        out = []
        for k, _votes in self._index.query(query, self.cfg.localise_candidates):
            res = verify_edge(self.keyframes.features[k], feats, self.intr, self._features_cfg, self._loop_cfg)
            if res.ok:
                out.append(PoseGuess(self.keyframes.T_world_kf[k] @ invert(res.T_cur_ref), k, int(res.n_inliers)))
        out.sort(key=lambda g: (-g.n_inliers, g.kf_id))
        return out


def verify_icp(res: ICPResult, cfg: MapReuseConfig) -> str | None:
    """Why the ICP result ``res`` (from a PnP guess, against the rendered saved map) is not a trusted relocalisation,
    or ``None`` when it is."""
    failure = icp_failure(res)
    if failure is not None:
        return f"icp_{failure}"
    if res.inlier_fraction < cfg.localise_min_inlier_fraction:
        return "too_little_overlap"
    if res.rmse_m > cfg.localise_max_rmse_m:
        return "residual_too_large"
    if res.motion_m > cfg.localise_max_shift_m or res.motion_deg > cfg.localise_max_shift_deg:
        return "icp_moved_pnp_pose"
    return None
