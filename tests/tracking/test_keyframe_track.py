"""A keyframe's keypoints tracked into a later frame without its features (tracking/features/keyframe_track.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from surfelslam.geometry.camera import project
from surfelslam.geometry.se3 import invert, make_T, pose_error, so3_exp
from surfelslam.synth.render import render
from surfelslam.synth.scenes import make_scene
from surfelslam.synth.trajectories import make_trajectory
from surfelslam.synth.writer import default_intrinsics, make_frame, noise_config
from surfelslam.tracking.features import FeatureConfig, extract, keyframe_track, to_grey
from surfelslam.tracking.features.keyframe_track import MAX_TRACKED_POINTS, KeyframePoints, track_keyframe

INTR = default_intrinsics(320, 240)


@pytest.fixture(scope="module")
def pair():
    """A keyframe and a frame 6 hand-held steps later (Kinect-like noise, 320x240), with the true relative pose."""
    scene = make_scene("room", 1)
    traj = make_trajectory("handheld", 40, scene, seed=1)
    frames = [make_frame(i, 0.0, render(scene, traj.T_world_cam[i], INTR), INTR, noise_config("kinect"), 1)
              for i in (30, 36)]
    T_cur_ref = invert(traj.T_world_cam[36]) @ traj.T_world_cam[30]
    return extract(frames[0].rgb, frames[0].depth_m, INTR, FeatureConfig()), frames[1], T_cur_ref


def _predicted(T_true: np.ndarray, rot_deg: float, shift_m: float) -> np.ndarray:
    """The true pose off by a rotation and a translation, as a constant-velocity prediction is on a hand-held jerk."""
    return make_T(so3_exp(np.radians([rot_deg, -rot_deg, 0.5 * rot_deg])), [shift_m, -shift_m, shift_m]) @ T_true


@pytest.mark.parametrize("rot_deg, shift_m", [(0.0, 0.0), (1.5, 0.02), (3.0, 0.04)])
def test_pose_and_pixels_are_recovered_from_a_wrong_prediction(pair, rot_deg, shift_m) -> None:
    """From predictions up to 3 deg and 4 cm off (15 to 20 px at 320x240), the points land on their true pixels
    (median under a quarter of a pixel) and the pose from their pixels alone is within 6 mm and 0.15 deg of the truth
    (the keyframe points carry its depth noise)."""
    ref, cur, T_true = pair
    found = track_keyframe(ref, to_grey(cur.rgb), _predicted(T_true, rot_deg, shift_m), INTR, FeatureConfig())
    assert found is not None
    assert 100 <= len(found.uv_cur) <= MAX_TRACKED_POINTS
    u, v, _ = project(found.points_ref @ T_true[:3, :3].T + T_true[:3, 3], INTR)
    assert np.median(np.hypot(u - found.uv_cur[:, 0], v - found.uv_cur[:, 1])) < 0.25
    dt, dr = pose_error(found.T_cur_ref, T_true)
    assert dt < 0.006 and dr < 0.15, (dt, dr)


def test_nothing_is_found_in_a_blank_frame_or_a_frame_of_another_size(pair) -> None:
    ref, cur, T_true = pair
    assert track_keyframe(ref, np.full((240, 320), 90, np.uint8), T_true, INTR, FeatureConfig()) is None
    assert track_keyframe(ref, np.zeros((120, 160), np.uint8), T_true, INTR, FeatureConfig()) is None


def test_a_prediction_looking_away_finds_nothing(pair) -> None:
    """A predicted pose turned 180 deg puts every keyframe point behind the camera: no points, no pose."""
    ref, cur, T_true = pair
    away = make_T(so3_exp([0.0, np.pi, 0.0]), [0.0, 0.0, 0.0]) @ T_true
    assert track_keyframe(ref, to_grey(cur.rgb), away, INTR, FeatureConfig()) is None


def test_the_keyframe_points_are_selected_once_and_follow_the_keyframe(pair, monkeypatch):
    """Kept between frames (:class:`KeyframePoints`), the keyframe's points are selected once and track exactly as
    points selected afresh; another keyframe gets its own selection."""
    ref, cur, T_true = pair
    cfg, grey = FeatureConfig(), to_grey(cur.rgb)
    fresh = track_keyframe(ref, grey, T_true, INTR, cfg)
    calls = []
    select = keyframe_track._selected
    monkeypatch.setattr(keyframe_track, "_selected", lambda *a: calls.append(1) or select(*a))
    kept = KeyframePoints()
    for _ in range(3):
        again = track_keyframe(ref, grey, T_true, INTR, cfg, kept)
        assert np.array_equal(again.T_cur_ref, fresh.T_cur_ref) and np.array_equal(again.uv_cur, fresh.uv_cur)
    assert len(calls) == 1
    other = replace(ref, valid=ref.valid & (np.arange(len(ref)) % 2 == 0))  # another keyframe: half the points
    P, uv = kept.of(other, grey.shape, cfg)
    assert len(calls) == 2 and len(P) == len(uv) <= other.valid.sum() < ref.valid.sum()
    assert np.all(np.isin(uv, other.keypoints_uv[other.valid]).all(axis=1))


@pytest.mark.parametrize("n_outliers", [0, 10])
def test_the_pose_refinement_stops_once_a_round_drops_no_point(monkeypatch, n_outliers) -> None:
    """Without outliers the first Levenberg-Marquardt round keeps every point: a second round on the same points
    would start from its own optimum, so it is not run (the pose is the one it would return). With 10 points 20 px off,
    they are dropped and a second round refines on the rest; the pose is the true one either way."""
    import cv2

    rng = np.random.default_rng(3)
    P = np.column_stack([rng.uniform(-1, 1, 200), rng.uniform(-0.8, 0.8, 200), rng.uniform(1.5, 3.0, 200)])
    T_true = make_T(so3_exp(np.radians([1.0, -2.0, 0.5])), [0.03, -0.01, 0.02])
    u, v, _ = project(P @ T_true[:3, :3].T + T_true[:3, 3], INTR)
    uv = np.column_stack([u, v]) + rng.normal(0.0, 0.2, (200, 2))
    uv[:n_outliers] += 20.0
    calls = []
    real = cv2.solvePnPRefineLM
    monkeypatch.setattr(keyframe_track.cv2, "solvePnPRefineLM", lambda *a, **k: calls.append(1) or real(*a, **k))
    T, kept = keyframe_track._refined(P, uv, _predicted(T_true, 1.0, 0.01), INTR, 2.0)
    assert len(calls) == (1 if n_outliers == 0 else 2)
    assert kept.sum() == 200 - n_outliers and not kept[:n_outliers].any()
    dt, dr = pose_error(T, T_true)
    assert dt < 0.002 and dr < 0.05, (dt, dr)
    if n_outliers == 0:  # the round left out returns the same pose
        K = INTR.K.copy()
        img = uv.copy()
        if INTR.fy < 0:
            K[1, 1] = -INTR.fy
            img[:, 1] = 2.0 * INTR.cy - img[:, 1]
        rvec, tvec = real(P, img, K, None, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3].reshape(3, 1).copy())
        assert pose_error(make_T(cv2.Rodrigues(rvec)[0], tvec.reshape(3)), T)[0] < 1e-6  # a micrometre
