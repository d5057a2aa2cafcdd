"""Colour of each depth pixel through a separate colour camera (``colour_at_depth_pixels``, 7-Scenes model)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from surfelslam.datasets import DatasetOptions, open_sequence
from surfelslam.errors import ConfigError
from surfelslam.geometry.camera import colour_at_depth_pixels, pixel_grid
from surfelslam.types import ColourCamera, Intrinsics

from helpers import shared_sequence

DEPTH = Intrinsics(300.0, 300.0, 79.5, 59.5, 160, 120)
#: a wider colour camera (smaller focal), its own principal point, 3 cm to the depth camera's +x and 1 cm behind
COLOUR = ColourCamera(Intrinsics(250.0, 260.0, 82.0, 57.0, 160, 120), (-0.03, 0.0, 0.01))


def _texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth RGB pattern on the plane (metres -> uint8, no aliasing at these scales)."""
    r = 127.5 + 120 * np.sin(9.0 * x) * np.cos(7.0 * y)
    g = 127.5 + 120 * np.cos(11.0 * x + 5.0 * y)
    b = 127.5 + 120 * np.sin(6.0 * y - 4.0 * x)
    return np.clip(np.stack([r, g, b], -1), 0, 255)


def _plane_scene(z_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth of a fronto-parallel plane at ``z_m`` (depth camera), the colour camera's image of its texture and
    the texture at each depth pixel (the exact registered colour)."""
    depth = np.full(DEPTH.shape, z_m, np.float32)
    u, v = pixel_grid(DEPTH)
    truth = _texture((u - DEPTH.cx) / DEPTH.fx * z_m, (v - DEPTH.cy) / DEPTH.fy * z_m)
    ci = COLOUR.intrinsics
    uc, vc = pixel_grid(ci)
    tx, ty, tz = COLOUR.t_colour_depth_m
    zc = z_m + tz  # the plane's depth in the colour camera; X_depth = X_colour - t
    rgb = _texture((uc - ci.cx) / ci.fx * zc - tx, (vc - ci.cy) / ci.fy * zc - ty)
    return depth, rgb.round().astype(np.uint8), truth


@pytest.mark.parametrize("z_m", [0.8, 2.5])
def test_registered_colour_is_the_texture_at_each_depth_pixel(z_m):
    depth, rgb, truth = _plane_scene(z_m)
    reg = colour_at_depth_pixels(rgb, depth, DEPTH, COLOUR, fallback_depth_m=2.0).astype(np.float64)
    inner = (slice(10, -10), slice(10, -10))  # the colour camera sees the whole depth view away from the border
    err = np.abs(reg - truth)[inner]
    assert err.mean() < 1.0 and np.percentile(err, 99) < 3.0
    naive = np.abs(rgb.astype(np.float64) - truth)[inner]  # the colour pixel at the same (u, v)
    assert naive.mean() > 20 * err.mean()


def test_invalid_depth_uses_the_fallback_depth():
    depth, rgb, _ = _plane_scene(1.5)
    holes = depth.copy()
    holes[40:80, 60:100] = 0.0
    holes[0:10, :] = np.nan
    at_fallback = colour_at_depth_pixels(rgb, np.full_like(depth, 3.0), DEPTH, COLOUR, fallback_depth_m=3.0)
    reg = colour_at_depth_pixels(rgb, holes, DEPTH, COLOUR, fallback_depth_m=3.0)
    bad = ~(holes > 0)  # NaN compares False
    assert np.array_equal(reg[bad], at_fallback[bad])
    assert np.array_equal(reg[~bad], colour_at_depth_pixels(rgb, depth, DEPTH, COLOUR, 3.0)[~bad])


def test_same_camera_returns_the_image():
    rgb = np.random.default_rng(0).integers(0, 256, (*DEPTH.shape, 3), dtype=np.uint8)
    depth = np.full(DEPTH.shape, 1.2, np.float32)
    assert np.array_equal(colour_at_depth_pixels(rgb, depth, DEPTH, ColourCamera(DEPTH), 2.0), rgb)


def test_wrong_colour_image_size_is_a_clear_error():
    depth = np.full(DEPTH.shape, 1.2, np.float32)
    with pytest.raises(ConfigError, match="colour image is 80x60"):
        colour_at_depth_pixels(np.zeros((60, 80, 3), np.uint8), depth, DEPTH, COLOUR, 2.0)


def test_colour_camera_scales_with_downsampling():
    cam = COLOUR.scaled(2)
    assert cam.intrinsics == COLOUR.intrinsics.scaled(2) and cam.t_colour_depth_m == COLOUR.t_colour_depth_m


def _edge_distance_px(rgb: np.ndarray, depth_m: np.ndarray) -> float:
    """Mean distance (px, capped at 8) from depth discontinuities (> 5 % jump) to the nearest colour edge."""
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    edges = cv2.Canny(cv2.GaussianBlur(grey, (5, 5), 1.2), 30, 80) > 0
    dist = cv2.distanceTransform((~edges).astype(np.uint8), cv2.DIST_L2, 5)
    d = np.where(depth_m > 0, depth_m, np.nan)
    jump = np.zeros(d.shape, bool)
    jump[:, 1:] |= np.nan_to_num(np.abs(np.diff(d, axis=1)) / d[:, 1:]) > 0.05
    jump[1:, :] |= np.nan_to_num(np.abs(np.diff(d, axis=0)) / d[1:, :]) > 0.05
    return float(np.minimum(dist[jump], 8.0).mean())


def test_sevenscenes_colour_model_aligns_colour_edges_with_depth_edges():
    """The 7-Scenes colour camera model halves the distance between depth discontinuities and colour edges."""
    seq = open_sequence(shared_sequence("7scenes_redkitchen_0000_0499"), DatasetOptions(start=3, stride=83))
    cam = seq.colour_camera
    assert cam is not None and not seq.colour_registered
    raw, reg = [], []
    for i in range(len(seq)):
        f = seq[i]
        raw.append(_edge_distance_px(f.rgb, f.depth_m))
        reg.append(_edge_distance_px(colour_at_depth_pixels(f.rgb, f.depth_m, seq.intrinsics, cam, 2.0), f.depth_m))
    assert len(raw) == 6
    assert np.mean(reg) < 0.65 * np.mean(raw)
    assert max(r / w for r, w in zip(reg, raw, strict=True)) < 0.7  # every frame, not only on average


def _wider_camera_frames(n: int):
    """A short synthetic sequence (registered colour) and the same frames as a wider colour camera at the same
    centre would have taken them (a depth-independent resampling when ``t = 0``)."""
    from dataclasses import replace

    from surfelslam.synth.scenes import make_scene
    from surfelslam.synth.trajectories import make_trajectory
    from surfelslam.synth.writer import default_intrinsics, iter_frames, noise_config

    scene = make_scene("room")
    intr = default_intrinsics(160, 120)
    traj = make_trajectory("handheld", n, scene)
    frames = list(iter_frames(scene, traj, intr, noise_config("kinect"), 0))
    cam = ColourCamera(Intrinsics(0.9 * intr.fx, 0.9 * intr.fy, intr.cx + 1.5, intr.cy - 1.0, intr.width, intr.height))
    uc, vc = pixel_grid(cam.intrinsics)
    map_u = ((uc - cam.intrinsics.cx) * intr.fx / cam.intrinsics.fx + intr.cx).astype(np.float32)
    map_v = ((vc - cam.intrinsics.cy) * intr.fy / cam.intrinsics.fy + intr.cy).astype(np.float32)
    wide = [replace(f, rgb=cv2.remap(f.rgb, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))
            for f in frames]
    return intr, cam, frames, wide


def _run(intr, tracker, frames, camera, enabled=True):
    from dataclasses import replace

    from surfelslam.slam import SlamConfig, build_slam

    cfg = SlamConfig()
    if not enabled:
        cfg = replace(cfg, colour_registration=replace(cfg.colour_registration, enabled=False))
    slam = build_slam(intr, cfg, tracker, colour_registered=False, colour_camera=camera)
    poses = np.stack([slam.process(f).T_world_cam for f in frames])
    res = slam.finish()
    traj = poses if res.trajectory_override is None else res.trajectory_override.T_world_cam
    return traj, res.map_arrays()


def test_dense_map_colours_are_sampled_through_the_colour_camera():
    """Unregistered colour + its camera model gives the map of the registered sequence (same geometry, colours
    within resampling error); without the model the colours are off. Tracking never changes."""
    intr, cam, frames, wide = _wider_camera_frames(12)
    T_ref, m_ref = _run(intr, "dense", frames, None)
    T_model, m_model = _run(intr, "dense", wide, cam)
    T_naive, m_naive = _run(intr, "dense", wide, None)
    T_off, m_off = _run(intr, "dense", wide, cam, enabled=False)
    for T, m in ((T_model, m_model), (T_naive, m_naive), (T_off, m_off)):
        assert np.array_equal(T, T_ref) and np.array_equal(m["position"], m_ref["position"])
    assert np.array_equal(m_off["colour"], m_naive["colour"])
    # two bilinear resamplings of a fine texture at 160x120 blur it by ~5 grey levels; unregistered: ~34
    err_model = np.abs(m_model["colour"].astype(np.float64) - m_ref["colour"]).mean()
    err_naive = np.abs(m_naive["colour"].astype(np.float64) - m_ref["colour"]).mean()
    assert err_model < 8.0 and err_naive > 4 * err_model, (err_model, err_naive)


def test_orb_keyframe_cloud_colours_use_the_colour_camera():
    """The orb tracker's map: same points, colours sampled through the model (tracking sees the raw colour)."""
    intr, cam, _, wide = _wider_camera_frames(12)
    T_model, m_model = _run(intr, "orb", wide, cam)
    T_naive, m_naive = _run(intr, "orb", wide, None)
    assert np.array_equal(T_model, T_naive) and np.array_equal(m_model["position"], m_naive["position"])
    assert np.abs(m_model["colour"] - m_naive["colour"]).mean() > 10.0


def _separate_colour_camera_frames(cam: ColourCamera, n: int = 6, noise: str = "kinect"):
    """Synthetic room frames whose colour is rendered by ``cam`` (its own intrinsics and position)."""
    from dataclasses import replace

    from surfelslam.synth.scenes import make_scene
    from surfelslam.synth.trajectories import make_trajectory
    from surfelslam.synth.writer import default_intrinsics, iter_frames, noise_config
    from surfelslam.types import Trajectory

    scene = make_scene("room")
    intr = default_intrinsics(320, 240)
    traj = make_trajectory("handheld", 8 * n, scene)
    traj = Trajectory(traj.timestamps[::8], traj.T_world_cam[::8])
    T_depth_colour = np.eye(4)
    T_depth_colour[:3, 3] = -np.asarray(cam.t_colour_depth_m)  # X_colour = X_depth + t
    traj_colour = Trajectory(traj.timestamps, traj.T_world_cam @ T_depth_colour)
    depth_frames = iter_frames(scene, traj, intr, noise_config(noise), 0)
    colour_frames = iter_frames(scene, traj_colour, cam.intrinsics, noise_config(noise), 0)
    return intr, [replace(d, rgb=c.rgb) for d, c in zip(depth_frames, colour_frames, strict=True)]


def test_fit_recovers_a_separate_colour_camera():
    """Colour rendered by a wider camera 3 cm to the side, with its own principal point: the edge fit recovers it,
    and colour sampled through the fit lands on the depth edges."""
    from surfelslam.geometry.colour_fit import fit_colour_camera
    from surfelslam.synth.writer import default_intrinsics

    d = default_intrinsics(320, 240)
    truth = ColourCamera(Intrinsics(0.9 * d.fx, 0.92 * d.fy, d.cx + 3.0, d.cy - 2.0, d.width, d.height),
                         (-0.03, 0.0, 0.0))
    intr, frames = _separate_colour_camera_frames(truth)
    fit = fit_colour_camera(frames, intr)
    ci, ti = fit.camera.intrinsics, truth.intrinsics
    assert abs(ci.fx / ti.fx - 1) < 0.01 and abs(ci.fy / ti.fy - 1) < 0.01, (ci, ti)
    assert abs(ci.cx - ti.cx) < 1.5 and abs(ci.cy - ti.cy) < 1.5, (ci, ti)
    assert abs(fit.camera.t_colour_depth_m[0] - truth.t_colour_depth_m[0]) < 0.01, fit.camera
    assert fit.edge_distance_px < 0.6 * fit.edge_distance_same_pixel_px


def test_fit_of_registered_colour_stays_at_the_depth_camera():
    from surfelslam.geometry.colour_fit import fit_colour_camera
    from surfelslam.synth.writer import default_intrinsics

    d = default_intrinsics(320, 240)
    intr, frames = _separate_colour_camera_frames(ColourCamera(d))
    fit = fit_colour_camera(frames, intr)
    ci = fit.camera.intrinsics
    assert abs(ci.fx / d.fx - 1) < 0.01 and abs(ci.cx - d.cx) < 1.5 and abs(ci.cy - d.cy) < 1.5, ci
    assert abs(fit.camera.t_colour_depth_m[0]) < 0.01
    assert fit.edge_distance_px <= fit.edge_distance_same_pixel_px


def test_fit_without_depth_edges_is_a_clear_error():
    from surfelslam.geometry.colour_fit import fit_colour_camera
    from surfelslam.types import RGBDFrame

    flat = RGBDFrame(0, 0.0, np.zeros((*DEPTH.shape, 3), np.uint8), np.full(DEPTH.shape, 1.5, np.float32))
    with pytest.raises(ConfigError, match="no depth discontinuities"):
        fit_colour_camera([flat], DEPTH)


def test_calibrate_colour_command_on_7scenes(tmp_path):
    """`surfelslam calibrate-colour` finds the built-in 7-Scenes model again (within 1 % / 2 px / 1 cm) and prints
    the INFO.txt lines; a copy with those lines in its INFO.txt gets that colour camera."""
    import json
    import shutil

    from typer.testing import CliRunner

    from surfelslam.cli import app
    from surfelslam.datasets.sevenscenes import SEVENSCENES_COLOUR_CAMERA

    src = shared_sequence("7scenes_redkitchen_0000_0499")
    res = CliRunner().invoke(app, ["calibrate-colour", str(src), "--downsample", "2", "--frames", "12", "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.output)
    ref = SEVENSCENES_COLOUR_CAMERA.intrinsics
    got = out["colour_intrinsics_full_resolution"]
    assert abs(got["fx"] / ref.fx - 1) < 0.01 and abs(got["fy"] / ref.fy - 1) < 0.01, got
    assert abs(got["cx"] - ref.cx) < 2.0 and abs(got["cy"] - ref.cy) < 2.0, got
    assert abs(out["t_colour_depth_m"][0] - SEVENSCENES_COLOUR_CAMERA.t_colour_depth_m[0]) < 0.01, out
    assert out["edge_distance_px"] < 0.65 * out["edge_distance_same_pixel_px"]
    # the printed lines, put in a plain folder's INFO.txt, make that colour camera
    rig = tmp_path / "rig"
    rig.mkdir()
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        shutil.copy(src / name, rig / name)
    for name in ("rgb", "depth"):
        (rig / name).symlink_to(src / name)
    (rig / "INFO.txt").write_text("intrinsics : fx=585 fy=585 cx=320 cy=240\ndepth scale : 1000\n"
                                  + "\n".join(out["info_lines"]) + "\n")
    seq = open_sequence(rig)
    assert seq.layout == "tum" and not seq.colour_registered
    assert abs(seq.full_colour_camera.intrinsics.fx - got["fx"]) < 0.01


def test_calibrate_colour_empty_selection_is_one_clear_line(tmp_path):
    from typer.testing import CliRunner

    from surfelslam.cli import app

    src = shared_sequence("7scenes_redkitchen_0000_0499")
    res = CliRunner().invoke(app, ["calibrate-colour", str(src), "--start", "600"])
    assert res.exit_code != 0 and "keeps no frame" in res.output and "Traceback" not in res.output
