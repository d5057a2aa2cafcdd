"""Keyframe edges from the old map (:mod:`surfelslam.slam.map_edges`): a camera back at a mapped place from another
direction, its pose drifted, is registered to the old surfels and the edge to their keyframe measures the truth."""

from __future__ import annotations

import numpy as np

from surfelslam.geometry.se3 import invert, pose_error
from surfelslam.slam import SlamConfig
from surfelslam.slam.frontend import DenseFrontEnd
from surfelslam.slam.hybrid_anchors import KeyframeAnchors
from surfelslam.slam.map_edges import INACTIVE_AFTER_S, MIN_DOMINANT_SHARE, MapEdges, dominant_visit
from surfelslam.types import RGBDFrame

from helpers import ROOM_INTR, look_pose, motion, render_room

T_OLD = look_pose(np.array([0.0, 0.1, 0.0]), 0.5)  # the keyframe that mapped the room's corner
T_BACK = look_pose(np.array([0.3, 0.0, 0.4]), 1.1, 0.1)  # the camera back there, 35 deg away from that view
DRIFT = motion([0.2, 1.0, 0.1], 2.0, [1.0, 0.2, 0.6], 0.2)  # its drifted estimate: 20 cm and 2 deg off


SIGMA = 0.003  # the edge sigma (m and rad): [hybrid.loop_icp] sigma_m


class _Keyframes:
    n_keyframes = 1  # the back end's keyframe count (the anchors read it)


def _setup(depth_scale: float = 1.0):
    """A map of one frame at :data:`T_OLD` (frame 0, keyframe 0), and the frame seen from :data:`T_BACK` (its depth
    times ``depth_scale``) as the front end's source."""
    cfg = SlamConfig()
    front = DenseFrontEnd(ROOM_INTR, cfg)
    anchors = KeyframeAnchors(_Keyframes())
    rgb, depth = render_room(T_OLD, ROOM_INTR, supersample=1)
    first = RGBDFrame(0, 0.0, rgb, depth)
    front.begin_frame(first)
    front.fuse(first, T_OLD)
    front.end_frame()
    anchors.add_keyframe(T_OLD)
    anchors.record(0, 0.0, T_OLD, fused=True)
    rgb, depth = render_room(T_BACK, ROOM_INTR, supersample=1)
    front.begin_frame(RGBDFrame(300, 2 * INACTIVE_AFTER_S, rgb, depth * np.float32(depth_scale)))
    edges = MapEdges(anchors, _Keyframes(), cfg.icp, front.render_cfg, cfg.preprocess)
    return front, edges


def test_map_edge_recovers_a_planted_drift_from_another_viewing_direction():
    front, edges = _setup()
    reg = edges.register(front.map, front.track_source, T_BACK @ DRIFT, 2 * INACTIVE_AFTER_S, 300, SIGMA)
    assert reg is not None and reg.kf_old == 0 and reg.share == 1.0
    dt_m, dr_deg = pose_error(reg.T_old_new, invert(T_OLD) @ T_BACK)
    assert dt_m < 0.004 and dr_deg < 0.2, (dt_m, dr_deg)
    assert edges.counts.tried == 1


def test_map_edge_refuses_a_place_that_does_not_fit():
    front, edges = _setup(depth_scale=0.8)  # a room a fifth smaller: no rigid motion fits it to the map
    assert edges.register(front.map, front.track_source, T_BACK @ DRIFT, 2 * INACTIVE_AFTER_S, 300, SIGMA) is None
    assert edges.counts.tried == 1  # the old map was in view: ICP ran and was refused


def test_recent_surfels_are_not_the_old_map():
    front, edges = _setup()
    # the map's only frame is younger than INACTIVE_AFTER_S: nothing inactive to register to
    assert edges.register(front.map, front.track_source, T_BACK, 0.5 * INACTIVE_AFTER_S, 300, SIGMA) is None
    assert edges.counts.tried == 0


def _stamps(ids):
    """Keyframe stamps (s): keyframes 0-19 every 0.3 s (one pass through a room), 20-29 a minute later."""
    ids = np.asarray(ids)
    return np.where(ids < 20, 0.3 * ids, 60.0 + 0.3 * (ids - 20))


def test_one_visit_spread_over_many_keyframes_dominates():
    # a room swept once: its inlier pixels spread over 15 keyframes, none with a tenth; a later pass holds a fifth
    anchors = np.concatenate([np.repeat(np.arange(2, 17), 8), [9] * 4, np.repeat([24, 25], 17)])
    k_old, share = dominant_visit(anchors, _stamps, INACTIVE_AFTER_S)
    assert k_old == 9  # the first pass's keyframe with most pixels (12), not the later pass's 17
    assert share == 124 / 158 and share >= MIN_DOMINANT_SHARE
    assert np.bincount(anchors).max() / len(anchors) < MIN_DOMINANT_SHARE / 4  # no single keyframe would pass


def test_two_visits_of_equal_weight_split_the_pixels():
    anchors = np.concatenate([np.repeat(np.arange(0, 5), 10), np.repeat(np.arange(21, 26), 10)])
    k_old, share = dominant_visit(anchors, _stamps, INACTIVE_AFTER_S)
    assert share == 0.5 and k_old == 0  # ties: the earlier visit, its earliest keyframe
    k_old, share = dominant_visit(anchors[:-1], _stamps, INACTIVE_AFTER_S)
    assert share == 50 / 99 and k_old == 0
    # within the inactive window the two passes are one visit
    assert dominant_visit(anchors, lambda ids: 0.3 * np.asarray(ids), INACTIVE_AFTER_S) == (0, 1.0)
