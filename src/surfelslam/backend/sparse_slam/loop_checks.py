"""Loop checks of the sparse SLAM: each new keyframe's loop candidates verified by PnP (and the dense check), inline
or in a background thread, and the descriptor index that retrieves candidates (also for relocalisation)."""

from __future__ import annotations

from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace

import numpy as np

from surfelslam.backend.dense_edges import DenseEdgeRefiner
from surfelslam.backend.keyframes import Keyframe
from surfelslam.backend.loops import LoopConfig, loop_candidates, verify_edge
from surfelslam.backend.place_recognition import DescriptorIndex, select_descriptors
from surfelslam.backend.sparse_slam.results import LoopCheck
from surfelslam.geometry.se3 import invert, pose_error
from surfelslam.kernels.threads import lower_thread_priority
from surfelslam.tracking.features import FeatureConfig, Features
from surfelslam.tracking.preprocess import FramePyramid
from surfelslam.types import Intrinsics

#: fraction: with ``DenseEdgeConfig.odometry_nearby``, a nearby pair's odometry stands for PnP-RANSAC when it
#: reprojects at least this share of the guided matches (a wrong pose explains few; RANSAC decides then)
ODOMETRY_MIN_INLIER_FRACTION = 0.5
#: m and deg: a refined edge to a retrieved keyframe this close to the graph's estimate of the pair is a loop the graph
#: has already closed (``LoopConfig.closed_retrieved``); well above a refined edge's error, well below a drift's
CLOSED_LOOP_SHIFT_M = 0.01
CLOSED_LOOP_SHIFT_DEG = 1.0
#: nice levels below the tracking thread for the loop checks: their results are collected keyframes later, so they
#: take the cores the tracking thread and the hybrid's feature worker (whose result it waits for) leave idle
LOOP_CHECK_NICE = 10
#: the loop-check thread's name prefix
LOOP_CHECK_THREAD = "loop-checks"


class LoopChecker:
    """Verifies the loop candidates of new keyframes and keeps the retrieval index.

    Args:
        intr: intrinsics of the keyframes.
        features_cfg: ORB / matching / PnP settings.
        loop_cfg: loop-candidate selection and verification.
        refiner: the dense check of keyframe edges, or ``None``.
        keyframes: the SLAM's keyframes (append-only; read here, never changed: a keyframe's features are fixed once
            it is added).
    """

    def __init__(self, intr: Intrinsics, features_cfg: FeatureConfig, loop_cfg: LoopConfig,
                 refiner: DenseEdgeRefiner | None, keyframes: list[Keyframe]) -> None:
        self._intr = intr
        self._features_cfg = features_cfg
        if refiner is not None and not refiner.cfg.pnp_refinement:  # the edge's ICP refines it instead
            self._features_cfg = replace(features_cfg, projection_search=False, rgbd_refine_iterations=0)
        self._loop_cfg = loop_cfg
        self._refiner = refiner
        self._kfs = keyframes
        self._index = DescriptorIndex(loop_cfg.retrieval)
        self._rng = np.random.default_rng(loop_cfg.seed)
        self._pool: ThreadPoolExecutor | None = None
        self._pending: deque[Future] = deque()  # loop checks of the last keyframes, oldest first, not applied yet

    def query_descriptors(self, feats: Features) -> np.ndarray:
        """The descriptors of ``feats`` that enter the retrieval index and its queries."""
        n_max = self._loop_cfg.retrieval.max_descriptors_per_keyframe
        return select_descriptors(feats.descriptors, feats.response, feats.valid, n_max)

    def add_to_index(self, feats: Features) -> None:
        """Add a keyframe without loop checks (the first one) to the retrieval index."""
        self._index.add(self.query_descriptors(feats))

    def retrieve(self, feats: Features, n: int) -> list[int]:
        """Ids of the (at most) ``n`` indexed keyframes that share the most descriptors with ``feats``. The index
        holds every keyframe only once the pending checks are collected (:meth:`collect`)."""
        return [k for k, _ in self._index.query(self.query_descriptors(feats), n)]

    @staticmethod
    def _candidate_poses(kf_id: int, poses_world_kf: np.ndarray) -> np.ndarray:
        """A copy of ``T_world_kf`` ``(kf_id + 1, 4, 4)`` of keyframe ``kf_id`` and those before it, its candidates:
        the priors of their matching."""
        return poses_world_kf[: kf_id + 1].copy()

    def check(self, kf_id: int, feats: Features, poses_world_kf: np.ndarray,
              pyramid: FramePyramid | None = None) -> tuple[int, list[LoopCheck]]:
        """Verify keyframe ``kf_id``'s loop candidates now; ``poses_world_kf``: the keyframe poses ``(K, 4, 4)``;
        ``pyramid``: the keyframe's :meth:`DenseEdgeRefiner.keyframe_pyramid`, if any (else built when needed)."""
        return self._check(kf_id, feats, self._candidate_poses(kf_id, poses_world_kf), pyramid)

    def submit(self, kf_id: int, feats: Features, poses_world_kf: np.ndarray,
               pyramid: FramePyramid | None = None) -> None:
        """:meth:`check` in the background thread, after the checks already submitted (one worker: the keyframes
        are checked and indexed in order); :meth:`collect` returns the results in that order. The candidates' poses
        are copied here, on the caller's thread."""
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=LOOP_CHECK_THREAD,
                                            initializer=lower_thread_priority, initargs=(LOOP_CHECK_NICE,))
        self._pending.append(self._pool.submit(self._check, kf_id, feats, self._candidate_poses(kf_id, poses_world_kf),
                                               pyramid))

    @property
    def n_pending(self) -> int:
        """Keyframes submitted whose checks were not collected yet."""
        return len(self._pending)

    def collect(self) -> tuple[int, list[LoopCheck]] | None:
        """Wait for the background loop checks of the oldest pending keyframe, if any: ``(kf_id, checks)``, or
        ``None``."""
        if not self._pending:
            return None
        return self._pending.popleft().result()

    def shutdown(self) -> None:
        """Stop the background thread (after :meth:`collect`)."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def _check(self, kf_id: int, feats: Features, poses: np.ndarray,
               pyramid: FramePyramid | None = None) -> tuple[int, list[LoopCheck]]:
        """Verify keyframe ``kf_id``'s loop candidates, then add it to the retrieval index.

        ``poses``: the :meth:`_candidate_poses` of ``kf_id`` when it was added (the priors of the candidates' matching
        and the start of depth-only nearby edges).

        Runs in the loop-check thread (or inline): it reads keyframe features (never changed once added) and is
        the only user of the index and the candidate generator between two :meth:`collect`.
        Returns ``(kf_id, checks)``.
        """
        q = self.query_descriptors(feats)
        checked = []
        if pyramid is not None and self._refiner is not None:
            self._refiner.adopt(kf_id, pyramid)
        n_closed = 0  # retrieved candidates verified where the graph already put them
        max_closed = self._loop_cfg.closed_retrieved or 0  # none (no tracker profile): all verified
        for cand in loop_candidates(kf_id, q, self._index, self._rng, self._loop_cfg):
            if cand.source == "retrieved" and 0 < max_closed <= n_closed:
                continue  # the loop is closed here: its other retrieved keyframes would add little
            nearby = cand.source == "nearby"
            prior = invert(poses[kf_id]) @ poses[cand.kf_id] if nearby or self._loop_cfg.guided_older else None
            from_odometry = nearby and self._refiner is not None and self._refiner.cfg.odometry_nearby
            res = verify_edge(self._kfs[cand.kf_id].features, feats, self._intr, self._features_cfg, self._loop_cfg,
                              prior, ODOMETRY_MIN_INLIER_FRACTION if from_odometry else 0.0)
            refined = None
            if res.ok and self._refiner is not None:
                inl = res.pairs[res.inlier_mask]
                uv = None if res.uv_cur is None else res.uv_cur[res.inlier_mask]
                refined = self._refiner.refine(cand.kf_id, kf_id, res.T_cur_ref,
                                               self._kfs[cand.kf_id].features.points_cam[inl[:, 0]], uv,
                                               finest_only=from_odometry)
            elif (not res.ok and nearby and self._refiner is not None and self._refiner.cfg.depth_only_nearby
                  and res.n_good < self._refiner.cfg.depth_only_max_matches):
                # texture too poor to verify: the depth alone, from the graph's estimate (the odometry's), over every
                # level (without feature terms the finest level alone converges worse on plain walls)
                refined = self._refiner.refine(cand.kf_id, kf_id, prior)
                if refined is not None:
                    checked.append(LoopCheck(cand, res, refined, depth_only=True))
                continue
            if cand.source == "retrieved" and refined is not None and prior is not None:
                n_closed += _agrees(refined.T_cur_ref, prior)
            checked.append(LoopCheck(cand, res, refined, res.ok and self._refiner is not None and refined is None))
        self._index.add(q)
        return kf_id, checked


def _agrees(T_edge_cur_ref: np.ndarray, T_graph_cur_ref: np.ndarray) -> bool:
    """Whether a refined edge ``(4, 4)`` is within :data:`CLOSED_LOOP_SHIFT_M` / :data:`CLOSED_LOOP_SHIFT_DEG` of the
    graph's estimate ``(4, 4)`` of the same pair."""
    dt_m, dr_deg = pose_error(T_edge_cur_ref, T_graph_cur_ref)
    return dt_m < CLOSED_LOOP_SHIFT_M and dr_deg < CLOSED_LOOP_SHIFT_DEG
