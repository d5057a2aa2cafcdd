"""Near-degenerate views: frames registered along the constrained directions are kept and fused, relocalisations
that would move the camera impossibly fast are refused, and a run that ends lost says so."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

import surfelslam as ss
from surfelslam.geometry import se3
from surfelslam.slam import SlamConfig
from surfelslam.slam.motion import MotionModel, TrackingState
from surfelslam.synth.scenes import make_scene
from surfelslam.synth.textures import TextureConfig
from surfelslam.synth.trajectories import make_trajectory
from surfelslam.synth.writer import default_intrinsics, iter_frames, noise_config

from helpers import ate_m

pytestmark = pytest.mark.slow

INTR_SMALL = default_intrinsics(160, 120)


@cache
def _plane_frames():
    """A plain wall filling the view, the camera swaying along it: every registration is degenerate."""
    scene = make_scene("plane", 1, TextureConfig(style="plain"))
    traj = make_trajectory("slow", 60, scene, seed=1)
    gt = se3.invert(traj.T_world_cam[0]) @ traj.T_world_cam
    return list(iter_frames(scene, traj, INTR_SMALL, noise_config("kinect"), 1)), gt


def _run(frames, intr=INTR_SMALL, tracker=None, **tracking):
    slam = ss.Slam(intr, tracker, config={"tracking": tracking})
    for f in frames:
        slam.track(f)
    return slam.finish()


def test_degenerate_frames_are_registered_weakly_and_fused_instead_of_refused():
    frames, gt = _plane_frames()
    weak = _run(frames, tracker="dense")  # the dense tracker's own handling (the hybrid would relocalise)
    # relocalisation off: a plain wall gives the shape guess nothing to match (measured: the same poses, and 47
    # vain attempts that took 5 of the test's 8 s)
    refused = _run(frames, tracker="dense", fuse_weak_frames=False, relocalise_after_failures=0)
    assert refused.metrics["tracking_failure_reasons"].get("degenerate", 0) > 20
    assert weak.metrics["tracking_failures"] == 0 and weak.metrics["weak_frames"] > 30
    assert weak.metrics["frames_fused"] == len(frames) > refused.metrics["frames_fused"]
    # the texture (photometric term) holds what the plane leaves free once the frames are fused (measured 5 vs 48 mm)
    assert ate_m(weak.trajectory.T_world_cam, gt) < 0.5 * ate_m(refused.trajectory.T_world_cam, gt)
    assert weak.metrics["weak_segments"] >= 1 and weak.metrics["lost_segments"] == 0


def _motion(cfg: SlamConfig) -> MotionModel:
    """The dense front end's motion model with ``cfg``'s settings, on a fresh state."""
    return MotionModel(cfg.tracking, cfg.icp, TrackingState())


def test_a_relocalisation_faster_than_a_camera_moves_is_refused():
    slam = _motion(SlamConfig())
    slam.state.T_world_last_tracked, slam.state.t_last_tracked_s = np.eye(4), 10.0
    tc = slam.cfg
    near = se3.make_T(np.eye(3), [0.5, 0.0, 0.0])  # 0.5 m in 1 s: a walk
    far = se3.make_T(np.eye(3), [2.3, 0.0, 0.0])  # 2.3 m in 1 s: a wrong match
    assert slam.plausible_jump(near, 11.0) and not slam.plausible_jump(far, 11.0)
    assert slam.plausible_jump(far, 10.0 + (2.3 - tc.relocalise_slack_m) / tc.relocalise_max_speed_m_s + 0.1)
    turn = se3.make_T(se3.so3_exp([0.0, np.radians(170.0), 0.0]), [0.0, 0.0, 0.0])
    assert not slam.plausible_jump(turn, 10.5) and slam.plausible_jump(turn, 12.0)
    assert slam.state.relocalisations["refused_implausible"] == 2


def test_a_run_that_ends_lost_says_so(tmp_path):
    frames, _ = _plane_frames()
    blank = [ss.RGBDFrame(f.index, f.timestamp, f.rgb, np.zeros_like(f.depth_m)) for f in frames[40:]]
    run = _run(frames[:40] + blank)
    assert run.metrics["lost_at_end"] is True
    last = run.metrics["tracking_segments"][-1]
    assert last["kind"] == "lost" and last["first_frame"] == 40 and last["recovery"] == "not recovered"


def test_weak_frames_predict_the_last_tracked_velocity_fading_or_holding_still():
    """Through weak frames the prediction is the last fully tracked step, fading with weak_velocity_decay_s (0: held
    still); a weak frame's own step never feeds the prediction, so ICP sliding along a free direction cannot build up
    speed (carrying weak steps on ran a plain-wall run 2.8 m away)."""
    from surfelslam.slam.config import TrackingConfig
    from surfelslam.slam.frame import FrameStatus

    v = se3.make_T(se3.so3_exp([0.0, 0.01, 0.0]), [0.02, 0.0, 0.0])  # 2 cm and 0.57 deg per frame
    slide = se3.make_T(np.eye(3), [0.0, 0.5, 0.0])  # a weak step that slid 0.5 m
    fading = _motion(SlamConfig(tracking=TrackingConfig(weak_velocity_decay_s=2.0)))
    assert np.array_equal(fading.velocity_after(v, FrameStatus.TRACKED, 10.0), v)
    for t, keep in ((10.5, np.exp(-0.25)), (14.0, np.exp(-2.0))):
        got = fading.velocity_after(slide, FrameStatus.WEAK, t)
        np.testing.assert_allclose(se3.log(got), keep * se3.log(v), atol=1e-12)
    assert np.array_equal(fading.velocity_after(v, FrameStatus.RELOCALISED, 15.0), np.eye(4))
    held = _motion(SlamConfig())  # the default holds still
    held.velocity_after(v, FrameStatus.TRACKED, 10.0)
    assert np.array_equal(held.velocity_after(slide, FrameStatus.WEAK, 10.1), np.eye(4))
    # a step that is no measurement of the motion (dense: a correction beyond any change of velocity, as after a
    # gap) gives no velocity, and no last tracked step to fade from either
    assert np.array_equal(fading.velocity_after(v, FrameStatus.TRACKED, 20.0), v)
    assert np.array_equal(fading.velocity_after(slide, FrameStatus.TRACKED, 20.1, measured=False), np.eye(4))
    assert np.array_equal(fading.velocity_after(slide, FrameStatus.WEAK, 20.2), np.eye(4))


def test_frozen_directions_move_the_velocity_only_by_the_gain():
    """Where the finest ICP level left a direction at the prediction (solution remapping), the frame's step along it
    is the prediction plus what the coarse levels did: the velocity moves only ``frozen_velocity_gain`` of the way
    there; along the measured directions it is the step. (A plain corridor: one wrong photometric pull fed back in
    full kept the prediction lagging for ten frames, and the keyframes made meanwhile held the lag: 7.3 cm.)"""
    from surfelslam.slam.config import TrackingConfig
    from surfelslam.slam.frame import FrameStatus
    from surfelslam.tracking.icp import ICPResult, LevelInfo, depth_scaling, weak_projector

    d = 2.0  # mean depth (m): rotations are compared with the translations that move points as far
    H = np.diag([1e4 * d**2, 1e4 * d**2, 1e4 * d**2, 1e4, 1e4, 2.0])  # along z, 5000x weaker: frozen
    P = weak_projector(H, d, 1e3)
    np.testing.assert_allclose(P, np.diag([0, 0, 0, 0, 0, 1.0]), atol=1e-12)
    assert weak_projector(H, d, 1e4) is None  # under the ratio nothing is weak
    # a weak direction mixing rotation and translation: eigenvectors of the depth-scaled matrix, mapped back to twists
    Q = np.linalg.qr(np.random.default_rng(0).normal(size=(6, 6)))[0]
    S = np.diag(depth_scaling(d))
    Sinv = np.linalg.inv(S)
    P_mixed = weak_projector(Sinv @ Q @ np.diag([1e-4, 1, 2, 3, 4, 5]) @ Q.T @ Sinv, d, 1e3)
    np.testing.assert_allclose(P_mixed @ S @ Q[:, 0], S @ Q[:, 0], atol=1e-9)  # the weak twist is kept ...
    np.testing.assert_allclose(P_mixed @ S @ Q[:, 1:], 0.0, atol=1e-9)  # ... the others are removed
    res = ICPResult(np.eye(4), 1000, 0.9, 0.001, 10, True, False, 5e3, normal_matrix=H, mean_depth_m=d,
                    levels=[LevelInfo(0, 5, 1000, 0.9, 0.001, 1e-5, "update", frozen_directions=1)])
    v_old = se3.make_T(np.eye(3), [0.01, 0.0, 0.02])
    step = se3.make_T(se3.so3_exp([0.0, 0.002, 0.0]), [0.012, 0.001, 0.036])  # z pulled 16 mm beyond the prediction
    for gain in (0.5, 0.0, 1.0):
        slam = _motion(SlamConfig(tracking=TrackingConfig(frozen_velocity_gain=gain)))
        slam.state.velocity = v_old
        got = slam.velocity_after(step, FrameStatus.TRACKED, 1.0, res)
        # first order in the 16 mm difference; the rotation and x, y are the step's
        np.testing.assert_allclose(got[:3, :3], step[:3, :3], atol=1e-12)
        np.testing.assert_allclose(got[:3, 3], [0.012, 0.001, 0.02 + gain * 0.016], atol=5e-5)
        if gain == 1.0:
            assert np.array_equal(got, step)
    no_freeze = ICPResult(np.eye(4), 1000, 0.9, 0.001, 10, True, False, 1.0, normal_matrix=H, mean_depth_m=d,
                          levels=[LevelInfo(0, 5, 1000, 0.9, 0.001, 1e-5, "update")])
    slam = _motion(SlamConfig())
    slam.state.velocity = v_old
    assert np.array_equal(slam.velocity_after(step, FrameStatus.TRACKED, 1.0, no_freeze), step)


@pytest.mark.heavy  # make test-all: the orb tracker's own prediction (the default hybrid's: the tests above)
def test_orb_does_not_feed_depth_only_steps_back_into_its_prediction():
    """Plain ceiling and wall, no features to match: orb registers every frame by depth alone, and ICP keeps the
    prediction along the direction the two planes leave free. Fed back as the velocity, that step made the pose run
    away (a 1500-frame office tour: 20 m; here 1.06 m over 90 frames); predicting the frame where the last one is
    halves it (0.52 m). Loop closure is off so that only the odometry is compared."""
    scene = make_scene("office", 0, TextureConfig(style="plain"))
    traj = make_trajectory("upward", 90, scene, seed=0)
    gt = se3.invert(traj.T_world_cam[0]) @ traj.T_world_cam
    frames = list(iter_frames(scene, traj, INTR_SMALL, noise_config("kinect"), 0))
    ate = {}
    for hold in (False, True):
        slam = ss.Slam(INTR_SMALL, tracker="orb", config={
            "sparse": {"loop": {"n_random": 0, "n_retrieved": 0}},
            "orb": {"depth_odometry": {"hold_after_depth_only": hold}}})
        for f in frames:
            slam.track(f)
        run = slam.finish()
        assert run.metrics["depth_odometry"]["from_prediction"] > 80  # depth alone, nearly every frame
        ate[hold] = ate_m(run.trajectory.T_world_cam, gt)
    assert ate[True] < 0.7 * ate[False], ate


def test_a_correction_beyond_a_change_of_velocity_is_a_jump_and_holds_are_capped():
    """ICP's correction of the prediction is bounded by max_velocity_change_m_s (max_rate_change_deg_s) times the
    time since the last posed frame, plus the slack: 0.02 + 1.0 / 30 m after one frame at 30 Hz."""
    from types import SimpleNamespace

    from surfelslam.slam.frame import FrameStatus
    from surfelslam.slam.motion import CORRECTION_SLACK_M

    motion = _motion(SlamConfig())
    motion.mark_tracked(np.eye(4), 10.0, FrameStatus.TRACKED)
    one = 10.0 + 1 / 30
    bound_m = CORRECTION_SLACK_M + 1.0 / 30

    def res(m, deg=0.0):
        return SimpleNamespace(motion_m=m, motion_deg=deg)

    assert not motion.jumped(res(0.5), one)  # an identity velocity (none measured yet) bounds nothing
    motion.state.velocity = se3.make_T(np.eye(3), [0.0, 0.0, 0.04])  # walking, 4 cm per frame

    assert not motion.jumped(res(bound_m - 1e-3), one) and motion.jumped(res(bound_m + 1e-3), one)
    assert motion.jumped(res(0.0, 2.0 + 180.0 / 30 + 0.1), one) and not motion.jumped(res(0.0, 7.9), one)
    assert not motion.jumped(res(0.17), 10.0 + 5 / 30)  # 17 cm over 5 frames is a walk's change of pace
    for k in range(motion.cfg.max_held_frames):
        assert motion.may_hold()
        motion.mark_held(one + k / 30)
    assert not motion.may_hold() and motion.state.held_frames == motion.cfg.max_held_frames
    assert not motion.jumped(res(bound_m - 1e-3), one + motion.cfg.max_held_frames / 30)  # from the last held frame
    motion.count_failure("implausible_correction")
    assert motion.may_hold()


@cache
def _featureless_room():
    """A slow pass in a room with grey colour (no features, no photometric term): ICP has the depth alone."""
    scene = make_scene("room", 1, TextureConfig(style="plain"))
    traj = make_trajectory("slow", 45, scene, seed=1)
    gt = se3.invert(traj.T_world_cam[0]) @ traj.T_world_cam
    frames = [ss.RGBDFrame(f.index, f.timestamp, np.full_like(f.rgb, 128), f.depth_m)
              for f in iter_frames(scene, traj, INTR_SMALL, noise_config("kinect"), 1)]
    return frames, gt


def test_a_registration_that_jumps_off_the_prediction_is_held_not_fused():
    """Frame 30 shows the view of frame 42 (15 cm, 8 deg ahead): ICP registers it there, a jump no camera makes in
    one frame; with no features to confirm it the frame is held at the prediction (a weak stretch), not fused, and
    tracking goes on. With the gate off it is tracked 15 cm off (measured: 3 mm held, 148 mm tracked)."""
    frames, gt = _featureless_room()
    planted = list(frames)
    planted[30] = ss.RGBDFrame(30, frames[30].timestamp, frames[42].rgb, frames[42].depth_m)
    held = _run(planted, tracker="hybrid")
    jumped = _run(planted, tracker="hybrid", max_velocity_change_m_s=float("inf"), max_rate_change_deg_s=float("inf"))
    assert held.metrics["held_frames"] == 1 and jumped.metrics["held_frames"] == 0
    assert held.metrics["frames_fused"] == len(frames) - 1 and held.metrics["lost_segments"] == 0
    seg = held.metrics["tracking_segments"]
    assert [(s["kind"], s["first_frame"], s["reason"], s["recovery"]) for s in seg] == [
        ("weak", 30, "implausible_correction", "tracking resumed")]
    assert se3.pose_error(held.trajectory.T_world_cam[30], gt[30])[0] < 0.01
    assert se3.pose_error(jumped.trajectory.T_world_cam[30], gt[30])[0] > 0.1
    assert ate_m(held.trajectory.T_world_cam, gt) < 0.01


def test_a_features_pose_near_the_prediction_bridges_without_a_relocalisation():
    """A frame the map refuses is bridged at a PnP pose within the jump bound of the prediction (no failure counted,
    capped by max_held_frames); a PnP pose 30 cm off, or any with no measured velocity, is not."""
    from surfelslam.slam.frame import FrameStatus

    motion = _motion(SlamConfig())
    motion.mark_tracked(np.eye(4), 10.0, FrameStatus.TRACKED)
    T_pred = se3.make_T(np.eye(3), [0.0, 0.0, 0.04])
    near = se3.make_T(np.eye(3), [0.01, 0.0, 0.05])
    far = se3.make_T(np.eye(3), [0.3, 0.0, 0.04])
    one = 10.0 + 1 / 30
    assert not motion.bridge_holds(T_pred, near, one)  # identity velocity: nothing to hold to
    motion.state.velocity = T_pred
    assert motion.bridge_holds(T_pred, near, one) and not motion.bridge_holds(T_pred, far, one)
    for k in range(motion.cfg.max_held_frames):
        motion.mark_held(one + k / 30)
    assert not motion.bridge_holds(T_pred, near, one + motion.cfg.max_held_frames / 30)


def test_an_unconverged_registration_that_moved_the_prediction_beyond_the_slack_is_a_slide():
    """A finest level out of iterations after correcting a good prediction (one tracked step old) by more than
    CORRECTION_SLACK_M is still sliding: not a measurement, even within the jump bound; converged, or small, or after
    a held frame (a worse prediction), it is not."""
    from types import SimpleNamespace

    from surfelslam.slam.frame import FrameStatus
    from surfelslam.slam.motion import CORRECTION_SLACK_DEG, CORRECTION_SLACK_M
    from surfelslam.tracking.icp import ICPStatus

    motion = _motion(SlamConfig())
    motion.mark_tracked(np.eye(4), 10.0, FrameStatus.TRACKED)

    def res(status, m, deg=0.0):
        return SimpleNamespace(status=status, motion_m=m, motion_deg=deg)

    slide = res(ICPStatus.MAX_ITERATIONS, CORRECTION_SLACK_M + 0.025)  # 4.5 cm: within the jump bound of 5.3 cm
    assert not motion.slid_unconverged(slide)  # an identity velocity (none measured yet): no prediction to judge
    motion.state.velocity = se3.make_T(np.eye(3), [0.0, 0.0, 0.04])
    assert motion.slid_unconverged(slide) and not motion.jumped(slide, 10.0 + 1 / 30)
    assert motion.slid_unconverged(res(ICPStatus.MAX_ITERATIONS, 0.0, CORRECTION_SLACK_DEG + 0.5))
    assert not motion.slid_unconverged(res(ICPStatus.MAX_ITERATIONS, CORRECTION_SLACK_M - 1e-3))
    assert not motion.slid_unconverged(res(ICPStatus.CONVERGED, CORRECTION_SLACK_M + 0.025))
    motion.mark_held(10.0 + 1 / 30)
    assert not motion.slid_unconverged(slide)


@cache
def _textured_room():
    """A slow pass in a textured room: PnP against the keyframe has its inliers (a trusted pose)."""
    scene = make_scene("room", 1)
    traj = make_trajectory("slow", 25, scene, seed=1)
    gt = se3.invert(traj.T_world_cam[0]) @ traj.T_world_cam
    return list(iter_frames(scene, traj, INTR_SMALL, noise_config("kinect"), 1)), gt


def _hybrid_after_20_frames():
    """The hybrid after the textured room's first 20 frames: (frames, truth, the tracker, its 20 results)."""
    from surfelslam.slam import HybridSlam

    frames, gt = _textured_room()
    slam = HybridSlam(INTR_SMALL, SlamConfig())
    return frames, gt, slam, [slam.process(f) for f in frames[:20]]


def _pnp_retry_run(monkeypatch, pred_off_m: float, retry_off_m: float):
    """Hybrid on the textured room; at frame 20 the prediction is planted ``pred_off_m`` off (sideways), ICP from it
    fails (too few inliers) and ICP from the PnP pose is planted ``retry_off_m`` off its own result with a converged
    status. Returns (frame 20's result, its truth, the tracker's counts)."""
    frames, gt, slam, results = _hybrid_after_20_frames()
    icp_from, predict = slam.localiser.icp_from, slam.front.predict
    calls = []

    def planted_icp(T_render, T_init_rel, match=None, match_of=None):
        res, failure, T = icp_from(T_render, T_init_rel, match, match_of)
        calls.append(failure)
        if len(calls) == 1:
            return res, "too_few_inliers", T
        return res, failure, T @ se3.make_T(np.eye(3), [retry_off_m, 0.0, 0.0])

    monkeypatch.setattr(slam.localiser, "icp_from", planted_icp)
    monkeypatch.setattr(slam.front, "predict", lambda: predict() @ se3.make_T(np.eye(3), [pred_off_m, 0.0, 0.0]))
    r = slam.process(frames[20])
    T0 = results[0].T_world_cam
    counts = dict(slam.counts)
    slam.finish()  # its background threads stop with the test
    return r, se3.invert(T0) @ r.T_world_cam, gt[20], counts, len(calls)


def test_icp_from_a_pnp_pose_far_from_the_prediction_needs_the_pnp_pose_as_evidence(monkeypatch):
    """ICP from the PnP pose that lands 12 cm from its own start (and from a good prediction), disagreeing with the
    trusted PnP pose, is no tracked frame: held at the prediction (before: fused 12 cm off). A PnP pose far from a
    bad prediction (planted 12 cm off) whose ICP converges on it is a well-supported correction: tracked there."""
    from surfelslam.slam.frame import FrameStatus

    r, T, truth, counts, n = _pnp_retry_run(monkeypatch, pred_off_m=0.0, retry_off_m=0.12)
    assert n == 2 and r.status == FrameStatus.HELD and counts["pnp_unsupported"] == 1
    assert se3.pose_error(T, truth)[0] < 0.01
    r, T, truth, counts, n = _pnp_retry_run(monkeypatch, pred_off_m=0.12, retry_off_m=0.0)
    assert n == 2 and r.status == FrameStatus.TRACKED and counts["pnp_unsupported"] == 0
    assert counts["pnp_guesses_tracked"] == 1 and se3.pose_error(T, truth)[0] < 0.01


def test_a_registration_that_slid_off_a_good_prediction_is_retried_at_the_fine_levels(monkeypatch):
    """The first registration of frame 20 is planted 35 cm sideways of its own result (as the coarse levels carried
    ICP along plain walls on a floor): a jump. ICP again from the prediction at the two finest levels alone (their
    correspondence gates cannot reach that far) registers the frame within a centimetre of the truth: tracked and
    fused, not held."""
    import dataclasses

    from surfelslam.slam.frame import FrameStatus

    frames, gt, slam, results = _hybrid_after_20_frames()
    icp_from, register = slam.localiser.icp_from, slam.front.register
    levels = []

    def slid_icp(T_render, T_init_rel, match=None, match_of=None):
        res, failure, T = icp_from(T_render, T_init_rel, match, match_of)
        return dataclasses.replace(res, motion_m=0.35), failure, T @ se3.make_T(np.eye(3), [0.35, 0.0, 0.0])

    def counted_register(target, T_init, reprojection=None, **kw):
        levels.append(kw.get("levels"))
        return register(target, T_init, reprojection, **kw)

    monkeypatch.setattr(slam.localiser, "icp_from", slid_icp)
    monkeypatch.setattr(slam.front, "register", counted_register)
    r = slam.process(frames[20])
    T = se3.invert(results[0].T_world_cam) @ r.T_world_cam
    assert levels == [None, 2]  # the planted registration, then one retry at the two finest levels
    assert r.status == FrameStatus.TRACKED and r.fused
    assert slam.counts["fine_retries_tried"] == slam.counts["fine_retries_tracked"] == 1
    assert se3.pose_error(T, gt[20])[0] < 0.01
    slam.finish()  # its background threads stop with the test
