"""Tracker runs shared by the tracker test modules: cached synthetic room frames, a run through a tracker, the full
hybrid preset. Imported as ``from tracker_helpers import ...``; the caches are per test process, so modules whose
tests share an ``xdist_group`` share the rendered frames too.
"""

from __future__ import annotations

from dataclasses import replace
from functools import cache

import numpy as np

from surfelslam.geometry import se3
from surfelslam.slam import SlamConfig, build_slam
from surfelslam.slam.runner import load_config
from surfelslam.synth.scenes import make_scene
from surfelslam.synth.trajectories import make_trajectory
from surfelslam.synth.writer import iter_frames, noise_config

from helpers import INTR

N_SLOW = 40  # frames of the slow room sequence
N_LOOP = 60  # frames of the walking loop


@cache
def room_frames(style: str, n: int, seed: int = 0, keep: tuple[int, ...] | None = None):
    """``(frames, gt (n, 4, 4))``: ``n`` frames of the room along the ``style`` trajectory, Kinect-like noise; the
    ground truth starts at the identity (as every estimate does). ``keep``: render only these frames (each the same
    as in the whole sequence); the ground truth is still the whole sequence's."""
    scene = make_scene("room", seed)
    traj = make_trajectory(style, n, scene, seed=seed)
    gt = se3.invert(traj.T_world_cam[0]) @ traj.T_world_cam
    return list(iter_frames(scene, traj, INTR, noise_config("kinect"), seed, indices=keep)), gt


def run_tracker(tracker: str, frames, cfg: SlamConfig | None = None, intr=INTR, colour_registered: bool = True):
    """``(poses (N, 4, 4), result, tracker object)``: the final poses (the back end's when it overrides them)."""
    slam = build_slam(intr, cfg or SlamConfig(), tracker, colour_registered)
    live = np.stack([slam.process(f).T_world_cam for f in frames])
    res = slam.finish()
    est = live if res.trajectory_override is None else res.trajectory_override.T_world_cam
    return est, res, slam


def full_hybrid() -> SlamConfig:
    """The full hybrid (preset ``hybrid-full``): the per-frame PnP check and joint feature term, twice the keyframes,
    5 + 5 loop candidates. The tests of those mechanisms run it; the rest run the default hybrid."""
    return load_config("hybrid-full")


def few_loop_checks() -> SlamConfig:
    """The full hybrid (:func:`full_hybrid`) with fewer loop candidates per keyframe (2 nearby, 1 random): cheaper,
    still closing loops."""
    cfg = full_hybrid()
    return replace(cfg, sparse=replace(cfg.sparse, loop=replace(cfg.sparse.loop, n_nearby=2, n_random=1)))
