"""Colour re-timing: colour taken at another stamp than depth, moved to the depth stamp before photometric ICP."""

import json

import numpy as np
import pytest

from surfelslam.errors import ConfigError
from surfelslam.geometry import se3
from surfelslam.synth.render import render
from surfelslam.synth.scenes import make_scene
from surfelslam.synth.trajectories import make_trajectory
from surfelslam.synth.writer import (
    generate_sequence,
    make_frame,
    noise_config,
    poses_at,
)
from surfelslam.tracking.icp import pairwise_config
from surfelslam.tracking.photometric import intensity_from_rgb
from surfelslam.tracking.preprocess import PreprocessConfig, Preprocessor
from surfelslam.tracking.registration import colour_timing, register_pair
from surfelslam.tracking.retime import ColourTiming, RetimeConfig, retime_intensity, twist_from_pose
from surfelslam.types import RGBDFrame

from helpers import INTR


def test_twist_from_pose_inverts_the_constant_velocity_motion():
    twist = np.array([0.3, -0.2, 0.5, 0.4, 0.1, -0.25])  # rad/s, m/s
    dt = 0.05
    T_b_a = se3.invert(se3.exp(dt * twist))  # camera b = camera a after dt: T_world_b = T_world_a exp(dt twist)
    np.testing.assert_allclose(twist_from_pose(T_b_a, dt), twist, atol=1e-12)
    np.testing.assert_allclose(twist_from_pose(se3.invert(T_b_a), -dt), twist, atol=1e-12)  # b before a
    ct = ColourTiming(-0.01, twist)
    np.testing.assert_allclose(ct.T_colour_depth, se3.exp(0.01 * twist), atol=1e-15)
    with pytest.raises(ConfigError, match="different times"):
        twist_from_pose(T_b_a, 0.0)


def test_retime_config_bounds_and_validation():
    cfg = RetimeConfig()
    assert not cfg.applies(0.0) and not cfg.applies(0.0005)
    assert cfg.applies(0.015) and cfg.applies(-0.015)
    assert not cfg.applies(0.2)  # paired across a gap: no constant-velocity model
    assert not RetimeConfig(mode="off").applies(0.015)
    with pytest.raises(ConfigError, match="auto, off"):
        RetimeConfig(mode="yes")
    with pytest.raises(ConfigError):
        RetimeConfig(min_offset_s=0.1, max_offset_s=0.05)


def _office_frames(poses_depth, poses_colour, seed=1):
    scene = make_scene("office", seed)
    frames, synced = [], []
    for i, (Td, Tc) in enumerate(zip(poses_depth, poses_colour, strict=True)):
        d = render(scene, Td, INTR)
        c = render(scene, Tc, INTR)
        depth = make_frame(i, i / 30, d, INTR, noise_config("kinect"), seed).depth_m
        frames.append(RGBDFrame(i, i / 30, c.rgb.copy(), depth))
        synced.append(RGBDFrame(i, i / 30, d.rgb.copy(), depth))
    return frames, synced


def test_retime_intensity_recovers_the_image_at_the_depth_pose():
    """Colour rendered 12 mm / 0.6 deg away from the depth pose: re-timed with the exact colour-from-depth
    transform, it matches the colour rendered at the depth pose to the rendering's interpolation error."""
    scene = make_scene("office", 1)
    traj = make_trajectory("handheld", 10, scene, fps=30.0, seed=1)
    Td, Tc = traj.T_world_cam[5], traj.T_world_cam[4]
    d, c = render(scene, Td, INTR), render(scene, Tc, INTR)
    at_depth = intensity_from_rgb(d.rgb)
    taken = intensity_from_rgb(c.rgb)
    identity = retime_intensity(taken, d.depth_m, INTR, np.eye(4))
    np.testing.assert_allclose(identity, taken, atol=1e-6)  # integer pixel positions: no resampling
    out = retime_intensity(taken, d.depth_m, INTR, se3.invert(Tc) @ Td)
    ok = np.isfinite(out) & (d.depth_m > 0)
    assert ok.mean() > 0.9
    before = np.median(np.abs(taken - at_depth)[ok])
    after = np.median(np.abs(out - at_depth)[ok])
    assert after < 0.3 * before, (before, after)
    with pytest.raises(ConfigError, match="intensity is"):
        retime_intensity(taken[:10], d.depth_m, INTR, np.eye(4))


def test_registration_with_retimed_colour_is_as_accurate_as_with_simultaneous_colour():
    """Office hand-held, colour 10-14 ms before depth (jittered as on TUM): joint ICP with the colour as taken is
    pulled off the depth pose; re-timed with velocities from the neighbours' ICP it comes back to the error with
    simultaneous colour."""
    scene = make_scene("office", 1)
    traj = make_trajectory("handheld", 24, scene, fps=30.0, seed=1)
    offsets = np.array([-0.012, -0.010, -0.014, -0.011, -0.013, -0.010])
    idx = [2, 3, 4, 12, 13, 14]  # source 3 and target 13 with their neighbours
    stamps = traj.timestamps[idx]
    frames, synced = _office_frames(traj.T_world_cam[idx], poses_at(traj, stamps + offsets))
    pre = Preprocessor(INTR, PreprocessConfig())
    pyr = [pre.process(f.depth_m) for f in frames]
    cfg = pairwise_config()
    T_gt = se3.invert(traj.T_world_cam[13]) @ traj.T_world_cam[3]

    def timing(k):  # k: position in idx of the frame, with neighbours at k - 1 and k + 1
        pairs = [(frames[a], frames[b], pyr[a], pyr[b], stamps[a], stamps[b]) for a, b in ((k - 1, k), (k, k + 1))]
        return colour_timing(offsets[k], stamps[k], pairs, INTR, cfg, RetimeConfig())

    tm = (timing(1), timing(4))
    assert all(t is not None for t in tm)
    err = {}
    for name, fr, ct in (("synced", synced, (None, None)), ("as taken", frames, (None, None)),
                         ("retimed", frames, tm)):
        res = register_pair(fr[1], fr[4], pyr[1], pyr[4], INTR, cfg, "identity", photometric=True,
                            colour_timing=ct).icp
        err[name] = se3.pose_error(res.T_target_source, T_gt)
    assert err["as taken"][0] > 0.0008, err  # the offset costs about 1 mm here (0.08 deg)
    assert err["retimed"][0] < 0.5 * err["as taken"][0], err
    assert err["retimed"][0] < err["synced"][0] + 0.0005, err
    # below the threshold nothing is re-timed
    assert colour_timing(0.0002, 0.0, [], INTR, cfg, RetimeConfig()) is None
    # one neighbour pair alone: used only when the middle of its interval is near the colour capture
    before = [(frames[0], frames[1], pyr[0], pyr[1], stamps[0], stamps[1])]  # middle 16.7 ms before the depth
    after = [(frames[1], frames[2], pyr[1], pyr[2], stamps[1], stamps[2])]  # 16.7 ms after
    assert colour_timing(-0.012, stamps[1], before, INTR, cfg, RetimeConfig()) is not None  # 10.7 ms away
    assert colour_timing(-0.012, stamps[1], after, INTR, cfg, RetimeConfig()) is None  # 22.7 ms away
    assert colour_timing(0.012, stamps[1], after, INTR, cfg, RetimeConfig()) is not None


def test_synth_colour_offset_writes_colour_stamps_and_validates(tmp_path):
    from surfelslam.datasets import DatasetOptions, open_sequence

    seq_dir = generate_sequence(tmp_path / "s", "room", "slow", 6, "kinect", 0, 64, 48, colour_offset_s=-0.012,
                                colour_jitter_s=0.003)
    seq = open_sequence(seq_dir, DatasetOptions())
    d = seq.timestamps - seq.depth_timestamps
    assert len(seq) == 6 and np.all((d >= -0.015 - 1e-6) & (d <= -0.009 + 1e-6)) and np.ptp(d) > 0
    assert seq[2].colour_minus_depth_s == pytest.approx(d[2])
    assert seq[2].depth_stamp_s == pytest.approx(2 / 30, abs=1e-6)
    np.testing.assert_allclose(seq.depth_timestamps, np.arange(6) / 30.0, atol=1e-6)
    T, valid = seq.gt_poses(at_depth_time=True)
    assert valid.all()
    np.testing.assert_allclose(T, seq.ground_truth.T_world_cam, atol=1e-6)  # GT is the depth camera's
    assert "colour timing" in (seq_dir / "INFO.txt").read_text()
    # poses_at reproduces the samples and extrapolates the first interval
    traj = seq.ground_truth
    np.testing.assert_allclose(poses_at(traj, traj.timestamps), traj.T_world_cam, atol=1e-9)
    with pytest.raises(ConfigError, match="half|within"):
        generate_sequence(tmp_path / "bad", "room", "slow", 6, "kinect", 0, 64, 48, colour_offset_s=0.017)
    with pytest.raises(ConfigError):
        generate_sequence(tmp_path / "bad", "room", "slow", 6, "kinect", 0, 64, 48, colour_jitter_s=-0.001)


def test_register_command_retimes_offset_colour(tmp_path):
    """``register`` on a sequence whose colour is 8-16 ms before its depth: ``--retime-colour auto`` (default)
    re-times both frames and lands closer to the ground truth than ``off``; a bad mode exits 2."""
    from typer.testing import CliRunner

    from helpers import register_app

    seq = generate_sequence(tmp_path / "seq", "office", "handheld", 17, "kinect", 1, 320, 240,
                            colour_offset_s=-0.012, colour_jitter_s=0.004)
    out = {}
    for mode in ("auto", "off"):
        res = CliRunner().invoke(register_app(), ["register", str(seq), "--source", "5", "--target", "15",
                                                  "--retime-colour", mode, "--out", str(tmp_path / mode),
                                                  "--no-figures"])
        assert res.exit_code == 0, res.output
        out[mode] = json.loads((tmp_path / mode / "registration.json").read_text())
    ct = out["auto"]["colour_timing"]
    assert ct["source"]["retimed"] and ct["target"]["retimed"]
    assert -0.017 < ct["source"]["colour_minus_depth_s"] < -0.007
    assert not out["off"]["colour_timing"]["source"]["retimed"]
    assert out["off"]["colour_timing"]["config"]["mode"] == "off" and ct["config"]["max_velocity_lag_s"] == 0.015
    e_auto, e_off = out["auto"]["gt_error"]["trans_m"], out["off"]["gt_error"]["trans_m"]
    assert e_auto < 0.5 * e_off and e_auto < 0.0005, (e_auto, e_off)
    # frame 4 unreadable: frame 5's velocity is measured only after it (too far from its colour): neither frame is
    # re-timed (one alone would be worse than both as taken), and the run goes on
    (seq / "depth" / sorted((seq / "depth").iterdir())[4].name).write_bytes(b"not a png")
    res = CliRunner().invoke(register_app(), ["register", str(seq), "--source", "5", "--target", "15",
                                              "--out", str(tmp_path / "broken"), "--no-figures"])
    assert res.exit_code == 0, res.output
    ct = json.loads((tmp_path / "broken" / "registration.json").read_text())["colour_timing"]
    assert not ct["source"]["retimed"] and not ct["target"]["retimed"] and "neither" in ct["note"]
    assert "not re-timed" in res.output
    bad = CliRunner().invoke(register_app(), ["register", str(seq), "--source", "0", "--target", "1",
                                              "--retime-colour", "yes", "--out", str(tmp_path / "b")])
    assert bad.exit_code == 2 and "re-timing" in bad.output and "Traceback" not in bad.output
