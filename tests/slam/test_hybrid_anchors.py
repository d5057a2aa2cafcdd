"""Keyframe anchors: a partial live correction moves exactly the surfels of the keyframes it moves, and the final
(full) correction leaves every surfel at its keyframe's final correction, whatever was moved before."""

from __future__ import annotations

import numpy as np
import pytest

from surfelslam.geometry import se3
from surfelslam.mapping.surfel_map import SurfelMap
from surfelslam.slam.hybrid_anchors import SURFEL_REACH_M, KeyframeAnchors


class _Graph:
    """The back end as the anchors see it: a keyframe count and the graph poses."""

    def __init__(self) -> None:
        self.poses: list[np.ndarray] = []

    @property
    def n_keyframes(self) -> int:
        return len(self.poses)

    def keyframe_poses(self) -> np.ndarray:
        return np.array(self.poses)


N_KF, FRAMES_PER_KF, SURFELS_PER_FRAME = 6, 3, 40


def _anchored_map() -> tuple[KeyframeAnchors, _Graph, SurfelMap]:
    """Six keyframes 1 m apart along x, three fused frames each, 40 surfels per frame within 2 m of its camera."""
    rng = np.random.default_rng(4)
    graph = _Graph()
    anchors = KeyframeAnchors(graph)
    smap = SurfelMap()
    frame = 0
    for k in range(N_KF):
        T_kf = se3.make_T(se3.so3_exp([0.0, 0.1 * k, 0.0]), [float(k), 0.0, 0.0])
        graph.poses.append(T_kf)
        anchors.add_keyframe(T_kf)
        for _ in range(FRAMES_PER_KF):
            T_cam = T_kf @ se3.exp(rng.normal(0, 0.02, 6))
            anchors.record(frame, 0.1 * frame, T_cam, fused=True)
            pts = T_cam[:3, 3] + rng.uniform(-2.0, 2.0, (SURFELS_PER_FRAME, 3))
            normals = rng.normal(size=(SURFELS_PER_FRAME, 3))
            smap.append(pts, normals / np.linalg.norm(normals, axis=1, keepdims=True), np.full((40, 3), 128.0),
                        1.0, 0.01, frame)
            frame += 1
    return anchors, graph, smap


def _moved(points: np.ndarray, C: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    return np.einsum("nij,nj->ni", C[anchor, :3, :3], points) + C[anchor, :3, 3]


def test_partial_correction_moves_only_the_keyframes_that_move_and_the_final_one_all() -> None:
    anchors, graph, smap = _anchored_map()
    p0 = smap.position.astype(np.float64).copy()
    anchor = np.repeat(np.arange(N_KF), FRAMES_PER_KF * SURFELS_PER_FRAME)
    np.testing.assert_array_equal(anchors.surfel_anchors(smap), anchor)
    # keyframes 0-2 barely move (2 mm), 3-5 move 5 cm and turn 0.5 deg
    kf1 = np.array(graph.poses)
    small = se3.make_T(np.eye(3), [0.002, 0.0, 0.0])
    large = se3.make_T(se3.so3_exp([0.0, 0.0, np.radians(0.5)]), [0.0, 0.05, 0.0])
    kf1[:3] = small @ kf1[:3]
    kf1[3:] = large @ kf1[3:]
    moves = anchors.keyframe_moves_m(kf1)
    np.testing.assert_allclose(moves[:3], 0.002, atol=1e-9)
    assert np.all(moves[3:] > 0.05 + np.radians(0.5) * SURFEL_REACH_M * 0.99)
    C1 = anchors.corrections(kf1)
    T_cam = anchors.correct(kf1, smap, min_move_m=0.01)
    moved_rows = anchor >= 3
    np.testing.assert_allclose(smap.position[moved_rows], _moved(p0, C1, anchor)[moved_rows], atol=2e-5)
    np.testing.assert_array_equal(smap.position[~moved_rows], p0[~moved_rows].astype(np.float32))
    # the unmoved keyframes keep their dense poses (their correction pending), the moved ones take the graph's
    np.testing.assert_allclose(anchors.kf_dense.poses[:3], np.array(graph.poses)[:3], atol=0)
    np.testing.assert_allclose(anchors.kf_dense.poses[3:], kf1[3:], atol=1e-12)
    np.testing.assert_allclose(T_cam, kf1[5] @ anchors.T_kf_cam[-1], atol=1e-9)
    # the final correction (full) puts every surfel at its keyframe's final pose, moved before or not
    kf2 = se3.make_T(se3.so3_exp([0.01, 0.0, 0.0]), [0.0, 0.0, 0.03])[None] @ kf1
    C_total = kf2 @ se3.invert(np.array(graph.poses))
    anchors.correct(kf2, smap)
    np.testing.assert_allclose(smap.position, _moved(p0, C_total, anchor), atol=5e-5)
    np.testing.assert_allclose(anchors.kf_dense.poses, kf2, atol=1e-12)
    assert anchors.map_corrections == 2



def test_trajectory_spreads_the_change_between_keyframes_over_the_frames_between_them() -> None:
    """Keyframes 0, 1, 2 at frames 0, 4, 8 (0.1 s apart) on a straight dense path; the graph moves keyframe 1 by 4 mm
    and turns it 0.4 deg beyond its dense step from keyframe 0 and leaves keyframe 2's step from 1 as it was: the frame
    a quarter of the way to keyframe 1 takes a quarter of that change, keyframe 1's own frame all of it, and the frames
    after keyframe 1 (and the last keyframe) move rigidly with their anchor."""
    graph = _Graph()
    anchors = KeyframeAnchors(graph)
    step = se3.make_T(se3.so3_exp([0.0, 0.02, 0.0]), [0.01, 0.0, 0.0])  # dense motion per frame
    T = np.eye(4)
    for i in range(11):
        if i % 4 == 0:
            graph.poses.append(T.copy())
            anchors.add_keyframe(T)
        anchors.record(i, 0.1 * i, T, fused=True)
        T = T @ step
    kf = np.array(graph.poses)
    change = se3.make_T(se3.so3_exp([0.0, 0.0, np.radians(0.4)]), [0.004, 0.0, 0.0])
    kf_new = kf.copy()
    kf_new[1] = kf[1] @ change
    kf_new[2] = kf_new[1] @ se3.invert(kf[1]) @ kf[2]  # keyframe 2's dense step from 1 kept
    traj = anchors.trajectory(kf_new).T_world_cam
    W = se3.invert(kf[0]) @ kf_new[1] @ se3.invert(kf[1])  # the change, in keyframe 0's frame
    W_quarter = se3.make_T(se3.so3_exp(0.25 * se3.so3_log(W[:3, :3])), 0.25 * W[:3, 3])
    np.testing.assert_allclose(traj[0], kf_new[0], atol=1e-12)
    np.testing.assert_allclose(traj[1], kf_new[0] @ W_quarter @ step, atol=1e-12)
    np.testing.assert_allclose(traj[4], kf_new[1], atol=1e-12)
    # a quarter of the 0.4 deg turn, as the frame is a quarter of the time to keyframe 1
    assert se3.rotation_angle_deg((se3.invert(kf_new[0]) @ traj[1] @ se3.invert(step))[:3, :3]) \
        == pytest.approx(0.1, abs=1e-9)
    for i in (5, 6, 7, 8, 9, 10):  # keyframe 1 -> 2 unchanged, and after the last keyframe: rigid
        anchor = 1 if i < 8 else 2
        np.testing.assert_allclose(traj[i], kf_new[anchor] @ anchors.T_kf_cam[i], atol=1e-12)
    # the dense keyframe poses themselves: every frame where it was tracked
    np.testing.assert_allclose(anchors.trajectory(kf).T_world_cam, np.array([
        kf[a] @ anchors.T_kf_cam[i] for i, a in enumerate(anchors.anchor)]), atol=1e-12)


def test_the_last_frame_promoted_to_keyframe_anchors_itself_and_takes_the_change_before_it() -> None:
    """The last frame promoted to a keyframe at the end: it anchors itself at its dense pose, the trajectory at the
    dense poses is unchanged, and a graph change of it reaches the frames before it in proportion to their time."""
    graph = _Graph()
    anchors = KeyframeAnchors(graph)
    step = se3.make_T(np.eye(3), [0.02, 0.0, 0.0])
    T = np.eye(4)
    for i in range(5):
        if i == 0:
            graph.poses.append(T.copy())
            anchors.add_keyframe(T)
        anchors.record(i, 0.1 * i, T, fused=True)
        T = T @ step
    before = anchors.trajectory().T_world_cam
    anchors.promote_last()
    graph.poses.append(anchors.kf_dense.poses[-1].copy())
    assert list(anchors.anchor) == [0, 0, 0, 0, 1] and len(anchors) == 2
    np.testing.assert_allclose(anchors.kf_dense.poses[1], before[4], atol=1e-12)
    np.testing.assert_allclose(anchors.trajectory().T_world_cam, before, atol=1e-12)
    kf_new = np.array(graph.poses)
    kf_new[1] = se3.make_T(np.eye(3), [0.0, 0.004, 0.0]) @ kf_new[1]  # the graph moves the last frame 4 mm along y
    moved = anchors.trajectory(kf_new).T_world_cam[:, 1, 3] - before[:, 1, 3]
    np.testing.assert_allclose(moved, [0.0, 0.001, 0.002, 0.003, 0.004], atol=1e-12)
