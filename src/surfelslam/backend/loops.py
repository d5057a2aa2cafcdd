"""Loop-closure candidates (nearby, random, appearance-retrieved keyframes) and their verification."""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import numpy as np

from surfelslam.backend.loop_consistency import LoopConsistencyConfig
from surfelslam.backend.place_recognition import DescriptorIndex, RetrievalConfig
from surfelslam.config import Config, setting
from surfelslam.tracking.features import FeatureConfig, Features, MotionResult, estimate_motion
from surfelslam.types import Intrinsics


@dataclass(frozen=True)
class LoopConfig(Config):
    """Loop-closure candidates (nearby, random and retrieved keyframes) and their verification."""

    n_nearby: int | None = setting(
        None, unit="keyframes", ge=0, le=1000, user=True,
        doc="the keyframes just before the previous one that are checked (local edges); none: the running tracker's "
            "own (orb 5, hybrid 3)")
    n_random: int | None = setting(
        None, unit="keyframes", ge=0, le=1000, user=True,
        doc="keyframes drawn uniformly (seeded) among the older ones; none: the running tracker's own (orb 5, "
            "hybrid 0)")
    seed: int = setting(0, ge=0, le=2**63 - 1, doc="seed of the random draws")
    n_retrieved: int | None = setting(
        None, unit="keyframes", ge=0, le=1000,
        doc="older keyframes proposed by descriptor voting (also the candidates of a relocalisation); none: the "
            "running tracker's own (orb 3, hybrid 2)")
    max_norm_loop: float = setting(2.0, unit="m + rad", gt=0, le=100, doc="loop edges may span up to this motion "
                                   "norm")
    min_loop_inliers: int = setting(30, unit="inliers", ge=0, le=1_000_000,
                                    doc="PnP inliers needed to accept an edge (nearby or loop)")
    min_loop_inlier_ratio: float = setting(0.25, unit="fraction", ge=0, le=1, doc="... and this fraction of the "
                                           "good matches")
    min_consistent_matches: int = setting(
        10, unit="matches", ge=0, le=1_000_000,
        doc="before PnP-RANSAC a candidate's good matches must hold a rigidly consistent 3D set this large "
            "(cheap rejection of non-overlapping candidates); 0 = off")
    pnp_nearby_edges: str = setting(
        "auto", choices=("auto", "on", "off"),
        doc="whether the PnP-verified edges to nearby keyframes enter the PnP edges' graph (refined ones enter the "
            "refined graph either way); auto: unless colour and depth are not registered, where keypoint depths "
            "come from another camera's view and bias these short edges by more than the odometry drifts")
    guided_older: bool = setting(
        True, doc="older candidates (retrieved, random) are matched near where the graph's current estimate of the "
                  "pair projects the keypoints, as nearby ones are (brute force when that finds too few): a loop the "
                  "graph already closed is verified at a fraction of the cost")
    closed_retrieved: int | None = setting(
        None, unit="candidates", ge=0, le=1000,
        doc="once this many retrieved candidates of a keyframe are verified where the graph already put them (the "
            "loop is closed there), its other retrieved ones are skipped; 0: all verified; none: the running "
            "tracker's own (orb 0, hybrid 2)")
    retrieval: RetrievalConfig = setting(default_factory=RetrievalConfig, doc="descriptor-voting parameters")
    consistency: LoopConsistencyConfig = setting(
        default_factory=LoopConsistencyConfig,
        doc="chi-square gate of verified edges against the odometry chain (false-loop-closure guard)")


@dataclass(frozen=True)
class Candidate:
    """A keyframe to verify against the new one; ``source`` is "nearby", "random" or "retrieved"."""

    kf_id: int
    source: str


def loop_candidates(
    new_kf: int,
    descriptors: np.ndarray,
    index: DescriptorIndex,
    rng: np.random.Generator,
    cfg: LoopConfig,
) -> list[Candidate]:
    """Candidates for keyframe ``new_kf`` (its predecessor ``new_kf - 1`` has the odometry edge).

    Nearby: ``new_kf - 2 ... new_kf - 1 - n_nearby``. Older keyframes ``[0, new_kf - 1 - n_nearby)``:
    ``n_retrieved`` by appearance, then ``n_random`` drawn without replacement. No duplicates.
    """
    out: list[Candidate] = []
    seen: set[int] = set()
    for k in range(new_kf - 2, max(new_kf - 2 - cfg.n_nearby, -1), -1):
        out.append(Candidate(k, "nearby"))
        seen.add(k)
    n_old = max(new_kf - 1 - cfg.n_nearby, 0)
    if n_old == 0:
        return out
    for k, _votes in index.query(descriptors, cfg.n_retrieved, before_kf=n_old):
        if k not in seen:
            out.append(Candidate(k, "retrieved"))
            seen.add(k)
    draws = rng.permutation(n_old)[: cfg.n_random + cfg.n_retrieved]  # fixed number of draws per call
    for k in draws:
        if len([c for c in out if c.source == "random"]) >= cfg.n_random:
            break
        if int(k) not in seen:
            out.append(Candidate(int(k), "random"))
            seen.add(int(k))
    return out


@functools.lru_cache(maxsize=16)
def _loop_features(feat_cfg: FeatureConfig, cfg: LoopConfig) -> FeatureConfig:
    """``feat_cfg`` with the loop bounds (made once per pair of configs: building a config validates every field)."""
    # too few good matches to ever reach min_loop_inliers: skip RANSAC (cheap rejection of non-overlap)
    return replace(
        feat_cfg,
        max_motion_norm=cfg.max_norm_loop,
        min_good_matches=max(feat_cfg.min_good_matches, cfg.min_loop_inliers),
        min_inliers=max(feat_cfg.min_inliers, cfg.min_loop_inliers),  # also lets the 3D consensus stop early
    )


def verify_edge(
    ref: Features, cur: Features, intr: Intrinsics, feat_cfg: FeatureConfig, cfg: LoopConfig,
    T_prior_cur_ref: np.ndarray | None = None, prior_min_inlier_fraction: float = 0.0,
) -> MotionResult:
    """PnP between two keyframes with the loop bounds; ``ok`` only if the inlier rules pass too.

    ``result.T_cur_ref`` maps points of the candidate (ref) keyframe into the new (cur) keyframe.
    ``T_prior_cur_ref``: ``(4, 4)`` the graph's estimate of that pose (for a nearby pair the odometry's, good to
    a few pixels; for an older one good where the graph already closed the loop): the matches are then searched near
    where it projects the keypoints (``guided_radius_px``; brute force when that finds too few, see
    :func:`estimate_motion`). ``prior_min_inlier_fraction`` > 0: that estimate is trusted (a nearby pair's
    odometry) and stands for PnP-RANSAC when it explains this fraction of the guided matches (see
    :func:`estimate_motion`).
    """
    res = estimate_motion(ref, cur, intr, _loop_features(feat_cfg, cfg), T_init_cur_ref=T_prior_cur_ref,
                          min_consistent=cfg.min_consistent_matches,
                          prior_min_inlier_fraction=prior_min_inlier_fraction)
    if res.ok and (
        res.n_inliers < cfg.min_loop_inliers or res.n_inliers < cfg.min_loop_inlier_ratio * res.n_good
    ):
        res.ok, res.reason = False, "too_few_inliers"
    return res
