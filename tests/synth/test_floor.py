"""The ``floor`` scene (rooms along a corridor, joined by doorways) and the ``walk`` trajectory through it."""

from __future__ import annotations

import numpy as np
import pytest

from surfelslam.errors import ConfigError
from surfelslam.geometry.camera import backproject
from surfelslam.geometry.se3 import make_T, so3_exp
from surfelslam.kernels.raycast import raycast_ref
from surfelslam.synth import make_scene, make_trajectory, render
from surfelslam.synth.builder import T_PLASTER
from surfelslam.synth.floor import CORRIDOR_WIDTH_M, DOOR_HALF_W_M
from surfelslam.synth.trajectories import replay_motion
from surfelslam.synth.writer import default_intrinsics, iter_frames
from surfelslam.types import Trajectory

FPS = 30.0
N_WALK = 5400  # 180 s: more than a lap of every seed's route (130-160 s)


@pytest.fixture(scope="module")
def floors():
    return {seed: make_scene("floor", seed) for seed in (0, 1)}


@pytest.fixture(scope="module")
def walks(floors):
    return {seed: make_trajectory("walk", N_WALK, scene, fps=FPS, seed=seed) for seed, scene in floors.items()}


def _rooms(scene) -> list[str]:
    return [n[: -len("_floor")] for n in scene.prim_names if n.startswith("room") and n.endswith("_floor")]


def _hit_m(scene, origin, direction) -> float:
    t, _, _ = raycast_ref(np.asarray([origin], float), np.asarray([direction], float), scene.prim_type,
                          scene.prim_R, scene.prim_center, scene.prim_size, 1e-3)
    return float(t[0])


def test_floor_has_rooms_of_different_sizes_with_doorways_along_a_corridor(floors):
    for scene in floors.values():
        rooms = _rooms(scene)
        assert 7 <= len(rooms) <= 8, rooms
        assert sum(n.endswith("_door_jamb") for n in scene.prim_names) == 2 * len(rooms)  # one doorway each
        floor_sizes = [tuple(np.round(scene.prim_size[scene.prim_names.index(f"{r}_floor"), :2], 2)) for r in rooms]
        assert len(set(floor_sizes)) == len(rooms)  # all different
        corridor = scene.prim_names.index("corridor_floor")
        assert 20.0 <= 2 * scene.prim_size[corridor, 0] <= 35.0
        walls = {scene.prim_tex[scene.prim_names.index(f"{r}_wall")] for r in rooms}
        assert T_PLASTER in walls and len(walls) >= 2  # plain and patterned rooms
        # looking out of the corridor through a doorway reaches far into the room; beside it, the corridor wall
        jambs = [i for i, n in enumerate(scene.prim_names) if n.endswith("_door_jamb")]
        x_door = 0.5 * (scene.prim_center[jambs[0], 0] + scene.prim_center[jambs[1], 0])
        side = -1.0 if scene.prim_center[jambs[0], 1] < 0 else 1.0
        eye = (x_door, CORRIDOR_WIDTH_M / 2, 1.0)
        assert _hit_m(scene, eye, (0.0, side, 0.0)) > CORRIDOR_WIDTH_M / 2 + 3.5
        beside = (x_door + DOOR_HALF_W_M + 0.3, CORRIDOR_WIDTH_M / 2, 1.0)
        assert _hit_m(scene, beside, (0.0, side, 0.0)) == pytest.approx(CORRIDOR_WIDTH_M / 2, abs=1e-9)
    assert not np.array_equal(floors[0].prim_center[:50], floors[1].prim_center[:50])  # the seed changes it


def test_walk_keeps_clear_of_every_surface_at_walking_speed(floors, walks):
    for seed, scene in floors.items():
        pos = walks[seed].positions
        assert scene.distance_to_surface(pos).min() >= 0.3
        assert scene.signed_distance(pos).min() > 0.0  # never inside furniture or behind a wall
        speed = np.linalg.norm(np.diff(pos, axis=0), axis=1) * FPS
        assert 0.8 <= speed.min() and speed.max() <= 1.6, (speed.min(), speed.max())
        assert 1.1 < speed.mean() < 1.3
        # it walks the whole floor: the corridor end to end, and into rooms on both sides
        corridor = scene.prim_names.index("corridor_floor")
        x_ends = scene.prim_center[corridor, 0] + np.array([-1.0, 1.0]) * scene.prim_size[corridor, 0]
        assert pos[:, 0].min() < x_ends[0] + 2.0 and pos[:, 0].max() > x_ends[1] - 2.0
        assert pos[:, 1].min() < -3.0 and pos[:, 1].max() > CORRIDOR_WIDTH_M + 3.0


def test_walk_revisits_places_after_long_loops(walks):
    for walk in walks.values():
        t, pos = walk.timestamps, walk.positions
        late = np.flatnonzero(t > 60.0)[::15]
        gaps = [np.linalg.norm(pos[: np.searchsorted(t, t[k] - 30.0, "right")] - pos[k], axis=1).min() for k in late]
        assert min(gaps) < 1.0
        assert np.mean(np.array(gaps) < 1.0) > 0.3  # not once: much of the second lap is on the first's path


def test_walk_is_deterministic_extends_with_frames_and_needs_a_route(floors, walks):
    short = make_trajectory("walk", 900, floors[0], fps=FPS, seed=0)
    # a longer sequence is the same walk further on (but for the last 3 s, whose smoothing sees the end)
    assert np.allclose(short.T_world_cam[:-90], walks[0].T_world_cam[:810], atol=1e-9)
    assert np.array_equal(short.T_world_cam, make_trajectory("walk", 900, floors[0], fps=FPS, seed=0).T_world_cam)
    with pytest.raises(ConfigError, match="route"):
        make_trajectory("walk", 10, make_scene("room"))


def test_walk_views_are_exact_and_never_close_for_long(floors, walks):
    scene, walk = floors[0], walks[0]
    intr = default_intrinsics(80, 60)
    medians = []
    for T in walk.T_world_cam[::45]:
        d = render(scene, T, intr).depth_m
        assert (d > 0).all()  # closed everywhere
        medians.append(np.median(d))
    assert min(medians) > 0.8, min(medians)  # half the view beyond the sensor's ~0.5 m minimum range, always
    intr = default_intrinsics(160, 120)
    picks = [0, 1500, 3000]
    for f, T in zip(iter_frames(scene, walk.subset(picks), intr, None, seed=0), walk.T_world_cam[picks], strict=True):
        p_cam = backproject(f.depth_m, intr)[f.depth_m > 0].astype(np.float64)
        assert scene.distance_to_surface(p_cam @ T[:3, :3].T + T[:3, 3]).max() < 1e-4  # exact ground truth


def test_render_kernel_matches_the_reference_on_the_floor(floors, walks):
    """Hundreds of primitives, most of them culled by their pixel bounds: the kernel still finds the nearest."""
    scene = floors[1]
    intr = default_intrinsics(160, 120)
    rng = np.random.default_rng(0)
    for T in walks[1].T_world_cam[[100, 2000]]:
        out = render(scene, T, intr)
        u, v = rng.integers(0, intr.width, 600), rng.integers(0, intr.height, 600)
        d_cam = np.column_stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(len(u))])
        t, pid, _ = raycast_ref(np.tile(T[:3, 3], (len(u), 1)), d_cam @ T[:3, :3].T, scene.prim_type,
                                scene.prim_R, scene.prim_center, scene.prim_size, 1e-3)
        assert np.array_equal(pid, out.prim_id[v, u])
        assert np.allclose(t, out.depth_m[v, u], rtol=1e-6, atol=1e-6)


def test_recorded_motion_replays_on_the_floor(floors, tmp_path):
    """A hand-held recording (a 0.5 m sway with turns of the head) replays in the floor's corridor, clear of its
    walls, through the command line as well."""
    from typer.testing import CliRunner

    from surfelslam.cli import app
    from surfelslam.datasets import open_sequence
    from surfelslam.io.trajectory import write_tum

    stamps = np.arange(301) / 100.0
    T = np.stack([make_T(so3_exp(np.array([0.0, 0.4 * np.sin(2.0 * s), 0.1 * np.sin(3.0 * s)])),
                         np.array([0.25 * np.sin(1.5 * s), 0.05 * np.sin(4.0 * s), 0.2 * s])) for s in stamps])
    rec = Trajectory(stamps, T)
    traj = replay_motion(rec, 80, floors[0], fps=FPS)
    assert floors[0].distance_to_surface(traj.positions).min() >= 0.35
    traj = replay_motion(rec, 12, floors[0], fps=FPS)
    write_tum(rec, tmp_path / "gt.txt")
    res = CliRunner().invoke(app, ["synth", str(tmp_path / "seq"), "--scene", "floor", "--motion",
                                   str(tmp_path / "gt.txt"), "--frames", "12", "--width", "80", "--height", "60",
                                   "--no-progress"])
    assert res.exit_code == 0, res.output
    seq = open_sequence(tmp_path / "seq")
    assert len(seq) == 12 and np.allclose(seq.ground_truth.T_world_cam, traj.T_world_cam[:12], atol=1e-6)
    res = CliRunner().invoke(app, ["synth", str(tmp_path / "walk"), "--scene", "floor", "--trajectory", "walk",
                                   "--frames", "6", "--width", "80", "--height", "60", "--no-progress"])
    assert res.exit_code == 0, res.output
    assert "floor" in (tmp_path / "walk" / "INFO.txt").read_text()
