"""TSDF meshes: marching cubes topology, surfaces from exact depth, the mesh PLY, `surfelslam mesh`."""

from __future__ import annotations

import json
import shutil
from collections import Counter

import numpy as np
import pytest
from typer.testing import CliRunner

from surfelslam.errors import ConfigError, InputError
from surfelslam.eval.mesh_quality import distance_to_mesh, sample_surface
from surfelslam.io.ply import read_mesh_ply, write_mesh_ply
from surfelslam.kernels import tsdf as kt
from surfelslam.mapping.mesh import MeshConfig, TsdfVolume
from surfelslam.mapping.mesh_topology import topology_report, triangle_components
from surfelslam.types import Intrinsics

VOXEL = 0.01
INTR = Intrinsics(160.0, 160.0, 79.5, 59.5, 160, 120)


def _look_at(eye, target) -> np.ndarray:
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, -1.0, 0.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    T[:3, 3] = eye
    return T


# a wall z = 2 and an axis-aligned box in front of it
BOX_LO, BOX_HI, WALL_Z = np.array([-0.3, -0.25, 1.4]), np.array([0.3, 0.25, 1.8]), 2.0


def _raycast(T: np.ndarray) -> np.ndarray:
    """Exact depth of the wall + box scene seen from ``T``."""
    v, u = np.mgrid[0 : INTR.height, 0 : INTR.width].astype(np.float64)
    rays = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u)], -1)
    d = rays @ T[:3, :3].T
    o = T[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_wall = (WALL_Z - o[2]) / d[..., 2]
        t1, t2 = (BOX_LO - o) / d, (BOX_HI - o) / d
        t_near = np.nanmax(np.minimum(t1, t2), -1)
        t_far = np.nanmin(np.maximum(t1, t2), -1)
    t = np.where((t_near <= t_far) & (t_near > 0), np.minimum(t_near, t_wall), t_wall)
    return (t * rays[..., 2]).astype(np.float32)  # depth = z in the camera


def _surface_distance(p: np.ndarray) -> np.ndarray:
    """Distance to the wall or to the box's surface."""
    q = np.maximum(BOX_LO - p, p - BOX_HI)
    outside = np.linalg.norm(np.maximum(q, 0), axis=1)
    box = np.abs(outside + np.minimum(q.max(1), 0))
    return np.minimum(box, np.abs(p[:, 2] - WALL_Z))


def _views() -> list[np.ndarray]:
    return [_look_at(np.array([x, y, 0.3]), [0.0, 0.0, 1.7]) for x, y in ((0, 0), (0.5, 0.1), (-0.5, -0.1),
                                                                          (0.1, -0.4))]


@pytest.fixture(scope="module")
def box_mesh():
    vol = TsdfVolume(VOXEL, 4 * VOXEL, max_depth_m=3.0)
    rgb = np.full((INTR.height, INTR.width, 3), (200, 120, 40), np.uint8)
    for T in _views():
        assert vol.integrate(_raycast(T), rgb, INTR, T) > 0
    return vol, vol.extract_mesh(1.0)


def test_mesh_of_exact_depth_lies_on_the_surface(box_mesh):
    _, mesh = box_mesh
    assert mesh.n_faces > 10_000
    d = _surface_distance(mesh.vertices.astype(np.float64))
    assert np.median(d) < 0.1 * VOXEL
    # the tail: the projective distance's 'ears' beside the box's edges (a few voxels along its silhouettes), whose
    # share depends on how the views are weighted
    assert np.percentile(d, 98) < VOXEL / 2
    # normals: unit, and where the surface is the flat wall they point at the cameras (-z)
    lens = np.linalg.norm(mesh.normals, axis=1)
    assert np.mean(np.abs(lens - 1) < 1e-4) > 0.999
    wall = np.abs(mesh.vertices[:, 2] - WALL_Z) < 0.003
    wall &= (np.abs(mesh.vertices[:, 0]) > 0.5) | (np.abs(mesh.vertices[:, 1]) > 0.45)
    assert np.median(mesh.normals[wall, 2]) < -0.99
    # faces wound counter-clockwise seen from the side the normals point to
    v = mesh.vertices[mesh.faces].astype(np.float64)
    fn = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    assert np.mean((fn * mesh.normals[mesh.faces].sum(1)).sum(1) > 0) > 0.99
    assert np.all(mesh.colours == (200, 120, 40))


def test_mesh_covers_the_seen_surface(box_mesh):
    _, mesh = box_mesh
    T = _views()[0]
    z = _raycast(T)[::4, ::4].reshape(-1)
    v, u = np.mgrid[0 : INTR.height : 4, 0 : INTR.width : 4]
    rays = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones(u.shape)], -1).reshape(-1, 3)
    truth = (rays * z[:, None]) @ T[:3, :3].T + T[:3, 3]
    assert np.mean(distance_to_mesh(truth, mesh.vertices, mesh.faces) < VOXEL) > 0.97


def _sphere_volume(radius: float, centre) -> TsdfVolume:
    """A volume whose voxels hold the exact truncated distance to a sphere (every block of its bounding box)."""
    vol = TsdfVolume(VOXEL, 3 * VOXEL)
    lo = np.floor((np.asarray(centre) - radius - 0.05) / vol.block_m).astype(int)
    hi = np.floor((np.asarray(centre) + radius + 0.05) / vol.block_m).astype(int)
    coords = np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(lo, hi, strict=True)], indexing="ij"),
                      -1).reshape(-1, 3)
    while vol.coords.shape[0] < len(coords):
        vol._grow()
    n = len(coords)
    vol.coords[:n] = coords
    vol.n_blocks = n
    vol.keys[:] = kt.EMPTY
    kt.rehash(vol.coords, n, vol.keys, vol.vals)
    k = np.arange(kt.BLOCK_VOXELS)
    local = np.stack([k & 7, (k >> 3) & 7, k >> 6], 1)
    p = ((coords[:, None, :] * kt.BLOCK + local[None]) * VOXEL).reshape(-1, 3)
    sdf = np.linalg.norm(p - centre, axis=1) - radius
    vol.tsdf[:n] = np.clip(sdf / vol.trunc_m, -1, 1).reshape(n, -1)
    vol.weight[:n] = 1.0
    vol.count[:n] = 1
    return vol


def test_marching_cubes_gives_a_closed_oriented_surface():
    centre = np.array([0.013, -0.021, 0.5])
    mesh = _sphere_volume(0.2, centre).extract_mesh()
    faces = mesh.faces
    assert len(np.unique(faces)) == mesh.n_vertices  # welded: every vertex used
    directed = Counter(map(tuple, np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])))
    assert max(directed.values()) == 1  # consistently oriented ...
    assert all((b, a) in directed for a, b in directed)  # ... and closed (every edge has its twin)
    r = np.linalg.norm(mesh.vertices - centre, axis=1)
    assert np.abs(r - 0.2).max() < 0.1 * VOXEL
    outward = (mesh.vertices - centre) / r[:, None]
    assert np.min((outward * mesh.normals).sum(1)) > 0.95
    v = mesh.vertices[faces].astype(np.float64)
    fn = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    assert np.all((fn * (v.mean(1) - centre)).sum(1) > 0)  # counter-clockwise from outside


def test_triangle_table_is_complementary_and_bounded():
    assert kt.TRI_COUNT[0] == kt.TRI_COUNT[255] == 0
    assert kt.TRI_COUNT.max() <= 5
    for case in range(1, 255):  # every cut edge is used, and only cut edges
        inside = [(case >> c) & 1 for c in range(8)]
        cut = {e for e, (c, a) in enumerate(zip(kt.EDGE_CORNER, kt.EDGE_AXIS, strict=True))
               if inside[c] != inside[c | (1 << a)]}
        used = set(kt.TRI_TABLE[case, : 3 * kt.TRI_COUNT[case]].tolist())
        assert used == cut, case


def test_volume_grows_and_refuses_past_its_memory_limit():
    T = _views()[0]
    rgb = np.zeros((INTR.height, INTR.width, 3), np.uint8)
    big = TsdfVolume(VOXEL, 4 * VOXEL, max_depth_m=3.0)
    big.integrate(_raycast(T), rgb, INTR, T)
    small = TsdfVolume(VOXEL, 4 * VOXEL, max_depth_m=3.0, initial_blocks=16)
    small.integrate(_raycast(T), rgb, INTR, T)
    assert small.n_blocks == big.n_blocks > 16 * 8  # grown (and rehashed) several times
    np.testing.assert_array_equal(small.extract_mesh().faces, big.extract_mesh().faces)
    limited = TsdfVolume(VOXEL, 4 * VOXEL, max_depth_m=3.0, max_memory_mb=small.memory_mb(small.n_blocks) / 2,
                         initial_blocks=16)
    with pytest.raises(Exception, match="max_memory_mb") as err:
        limited.integrate(_raycast(T), rgb, INTR, T)
    assert "--voxel" in str(err.value)


def test_released_extraction_gives_the_same_mesh_and_leaves_the_volume_whole():
    """``extract_mesh(release=True)`` (surfelslam mesh: the fusion arrays freed before marching cubes, the rest
    after) gives the mesh to the last bit, and leaves an empty volume that fuses again, also when it fails."""
    T = _views()[0]
    rgb = np.full((INTR.height, INTR.width, 3), 90, np.uint8)

    def fused() -> TsdfVolume:
        vol = TsdfVolume(VOXEL, 4 * VOXEL, max_depth_m=3.0)
        vol.integrate(_raycast(T), rgb, INTR, T)
        return vol

    kept, vol = fused().extract_mesh(), fused()
    released = vol.extract_mesh(release=True)
    for a, b in zip((kept.vertices, kept.normals, kept.colours, kept.faces),
                    (released.vertices, released.normals, released.colours, released.faces), strict=True):
        np.testing.assert_array_equal(a, b)
    assert kept.n_faces > 1000 and vol.n_blocks == 0 and vol.extract_mesh().n_faces == 0
    vol.integrate(_raycast(T), rgb, INTR, T)
    np.testing.assert_array_equal(vol.extract_mesh().faces, kept.faces)
    vol.max_memory_mb = 1e-3  # the extraction's own arrays are refused
    with pytest.raises(ConfigError, match="extracting the mesh needs"):
        vol.extract_mesh(release=True)
    assert vol.n_blocks == 0
    vol.max_memory_mb = 4096.0
    vol.integrate(_raycast(T), rgb, INTR, T)
    np.testing.assert_array_equal(vol.extract_mesh().faces, kept.faces)


def test_mesh_config_bounds():
    assert MeshConfig().truncation_m == pytest.approx(0.04)
    assert MeshConfig(voxel_m=0.02, trunc_m=0.05).truncation_m == 0.05
    with pytest.raises(ValueError, match="voxel_m"):
        MeshConfig(voxel_m=0.0)


# ---------------------------------------------------------------------------------------------- PLY
def test_mesh_ply_round_trip(tmp_path, box_mesh):
    _, mesh = box_mesh
    path = tmp_path / "m.ply"
    assert write_mesh_ply(path, mesh.vertices, mesh.faces, mesh.normals, mesh.colours) == (mesh.n_vertices,
                                                                                          mesh.n_faces)
    head = path.read_bytes()[:400].decode("ascii", "replace")
    assert "element face" in head and "property list uchar int vertex_indices" in head
    v, f = read_mesh_ply(path)
    np.testing.assert_array_equal(f, mesh.faces)
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], 1), mesh.vertices)
    np.testing.assert_array_equal(np.stack([v["nx"], v["ny"], v["nz"]], 1), mesh.normals)
    np.testing.assert_array_equal(np.stack([v["red"], v["green"], v["blue"]], 1), mesh.colours)
    # bare geometry; an empty mesh
    write_mesh_ply(path, mesh.vertices[:3], [[0, 1, 2]])
    v, f = read_mesh_ply(path)
    assert sorted(v) == ["x", "y", "z"] and f.tolist() == [[0, 1, 2]]
    write_mesh_ply(path, np.zeros((0, 3)), np.zeros((0, 3), int))
    assert read_mesh_ply(path)[1].shape == (0, 3)


def test_mesh_ply_refuses_bad_meshes(tmp_path):
    path = tmp_path / "m.ply"
    with pytest.raises(ValueError, match="face indices"):
        write_mesh_ply(path, np.zeros((3, 3)), [[0, 1, 3]])
    write_mesh_ply(path, np.eye(3), [[0, 1, 2]])
    data = path.read_bytes()
    path.write_bytes(data[:-5])
    with pytest.raises(InputError, match="truncated"):
        read_mesh_ply(path)


def test_sample_surface_is_on_the_mesh(box_mesh):
    _, mesh = box_mesh
    pts = sample_surface(mesh.vertices, mesh.faces, 2000, seed=1)
    assert pts.shape == (2000, 3)
    assert np.max(distance_to_mesh(pts, mesh.vertices, mesh.faces)) < 1e-6


# ---------------------------------------------------------------------------------------------- the command
runner = CliRunner()


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """8 exact frames of the room at 160x120, mapped at the ground-truth poses."""
    from surfelslam.api import run_sequence
    from surfelslam.datasets import open_sequence
    from surfelslam.slam import SlamConfig
    from surfelslam.synth.writer import generate_sequence

    base = tmp_path_factory.mktemp("mesh")
    seq_dir = generate_sequence(base / "seq", scene="room", n_frames=8, noise="none", seed=2, width=160, height=120)
    run_sequence(open_sequence(seq_dir), base / "run", SlamConfig(), poses="gt", progress=False, figures=False)
    return seq_dir, base / "run"


def _one_error_line(res, *fragments: str) -> None:
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), res.stderr
    for frag in fragments:
        assert frag in lines[0], lines[0]


def test_mesh_command_writes_the_runs_mesh(tiny_run, tmp_path):
    from surfelslam.cli import app
    from surfelslam.synth.scenes import make_scene

    seq_dir, run = tiny_run
    res = runner.invoke(app, ["mesh", str(run), "--no-progress", "--voxel", "0.02"])
    assert res.exit_code == 0, res.output
    assert "8 frames fused" in res.stdout
    v, f = read_mesh_ply(run / "mesh.ply")
    assert len(f) > 1000 and {"nx", "red"} <= v.keys()
    xyz = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    d = make_scene("room", seed=2).distance_to_surface(xyz)  # GT poses: the mesh is in the scene's frame
    assert np.median(d) < 0.005

    # the sequence moved: metrics.json's path is gone, --sequence points at it
    moved = tmp_path / "elsewhere"
    shutil.copytree(seq_dir, moved)
    run2 = tmp_path / "run2"
    shutil.copytree(run, run2)
    metrics = json.loads((run2 / "metrics.json").read_text())
    metrics["sequence"] = str(tmp_path / "gone")
    (run2 / "metrics.json").write_text(json.dumps(metrics))
    res = runner.invoke(app, ["mesh", str(run2), "--no-progress"])
    _one_error_line(res, "gone", "--sequence PATH")
    out = tmp_path / "m.ply"
    res = runner.invoke(app, ["mesh", str(run2), "--no-progress", "--sequence", str(moved), "--stride", "4",
                              "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "2 frames fused" in res.stdout and out.is_file()


def test_mesh_command_bad_inputs(tiny_run, tmp_path):
    from surfelslam.cli import app

    _, run = tiny_run
    _one_error_line(runner.invoke(app, ["mesh", str(tmp_path / "nope")]), "nope", "not a folder")
    empty = tmp_path / "empty"
    empty.mkdir()
    _one_error_line(runner.invoke(app, ["mesh", str(empty)]), "trajectory.txt", "missing")
    _one_error_line(runner.invoke(app, ["mesh", str(run), "--voxel", "0"]), "--voxel")
    _one_error_line(runner.invoke(app, ["mesh", str(run), "--method", "marching"]), "--method")
    nameless = tmp_path / "nameless"
    nameless.mkdir()
    shutil.copy(run / "trajectory.txt", nameless)
    _one_error_line(runner.invoke(app, ["mesh", str(nameless)]), "names no sequence", "--sequence")
    try:
        import open3d  # noqa: F401
    except ImportError:
        _one_error_line(runner.invoke(app, ["mesh", str(run), "--method", "poisson"]), "surfelslam[bench]")


# ---------------------------------------------------------------------------------------------- noise-aware fusion
def test_noise_model_weights_and_truncation():
    vol = TsdfVolume(VOXEL, 4 * VOXEL)
    sigma = lambda z: 0.0012 + 0.0019 * (z - 0.4) ** 2  # noqa: E731 (the Kinect-like model of MeshConfig's doc)
    assert kt.measurement_weight(1.0, vol.noise) == pytest.approx(1.0)
    assert kt.measurement_weight(4.5, vol.noise) == pytest.approx((sigma(1.0) / sigma(4.5)) ** 2)
    assert kt.measurement_weight(0.5, vol.noise) > 2.0
    assert kt.truncation(1.0, vol.trunc_m, vol.noise) == pytest.approx(0.04)  # 3 sigma = 5.6 mm: trunc_m
    assert kt.truncation(4.5, vol.trunc_m, vol.noise) == pytest.approx(3 * sigma(4.5))  # 9.9 cm
    assert kt.truncation(9.0, vol.trunc_m, vol.noise) == pytest.approx(0.12)  # at most 3 trunc_m


def _plane_mesh(flat_weights: bool) -> np.ndarray:
    """Vertices of the mesh of the wall z = WALL_Z fused from one exact frame 1 m away and three frames 4.5 m away
    with Kinect-like noise (sigma 3.3 cm); ``flat_weights``: every frame weighs the same (no noise model)."""
    vol = TsdfVolume(VOXEL, 4 * VOXEL)
    if flat_weights:
        vol.noise[kt.NOISE_QUAD] = 0.0
    rgb = np.zeros((INTR.height, INTR.width, 3), np.uint8)
    rng = np.random.default_rng(3)
    near = np.eye(4)
    near[2, 3] = WALL_Z - 1.0
    vol.integrate(np.full((INTR.height, INTR.width), 1.0, np.float32), rgb, INTR, near)
    far = np.eye(4)
    far[2, 3] = WALL_Z - 4.5
    sigma = 0.0012 + 0.0019 * (4.5 - 0.4) ** 2
    window = np.zeros((INTR.height, INTR.width), bool)
    window[40:80, 60:100] = True  # the far frames' centre: the wall where the near frame saw it, and some more
    for _ in range(3):
        noisy = 4.5 + sigma * rng.standard_normal((INTR.height, INTR.width))
        vol.integrate(np.where(window, noisy, 0.0).astype(np.float32), rgb, INTR, far)
    v = vol.extract_mesh(min_component=0).vertices.astype(np.float64)
    return v[(np.abs(v[:, 0]) < 0.3) & (np.abs(v[:, 1]) < 0.2)]  # what all frames saw


def test_far_noisy_depth_does_not_blur_what_near_depth_saw():
    weighted = np.abs(_plane_mesh(False)[:, 2] - WALL_Z)
    flat = np.abs(_plane_mesh(True)[:, 2] - WALL_Z)
    assert len(weighted) > 1000
    assert np.median(weighted) < 0.001
    assert np.median(flat) > 0.005  # the same frames, averaged with equal weights


# ---------------------------------------------------------------------------------------------- meshes tools accept
def test_mesh_of_exact_scene_is_manifold_oriented_outward(box_mesh):
    _, mesh = box_mesh
    r = topology_report(mesh.vertices, mesh.faces)
    assert r["manifold"], r
    assert r["unreferenced_vertices"] == 0
    sizes = np.bincount(triangle_components(mesh.faces))
    assert sizes.max() > 0.8 * mesh.n_faces and sizes.min() >= MeshConfig().min_component  # the wall is one piece
    # outward: the faces' winding points out of the box and, on the wall, towards the cameras (-z)
    v = mesh.vertices[mesh.faces].astype(np.float64)
    centres = v.mean(1)
    fn = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    area = np.linalg.norm(fn, axis=1)
    on_wall = np.abs(centres[:, 2] - WALL_Z) < 0.005
    out = np.where(on_wall, -fn[:, 2], (fn * (centres - (BOX_LO + BOX_HI) / 2)).sum(1)) > 0
    assert area[out].sum() > 0.99 * area.sum()


def test_open3d_accepts_the_mesh(box_mesh):
    try:
        import open3d as o3d
    except ImportError as exc:  # not installed (the optional bench extra), or a system library it needs is missing
        pytest.skip(f"open3d does not import: {exc}")
    _, mesh = box_mesh
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices.astype(np.float64)),
                                  o3d.utility.Vector3iVector(mesh.faces.astype(np.int32)))
    assert m.is_edge_manifold(allow_boundary_edges=True)
    assert m.is_vertex_manifold()
    assert m.is_orientable()
    assert len(np.asarray(m.get_non_manifold_edges(allow_boundary_edges=True))) == 0
    n = len(m.triangles)
    m.remove_duplicated_triangles()
    assert len(m.triangles) == n


def test_mesh_command_writes_a_manifold_mesh(tiny_run, tmp_path):
    from surfelslam.cli import app

    _, run = tiny_run
    res = runner.invoke(app, ["mesh", str(run), "--no-progress", "--voxel", "0.02", "--out", str(tmp_path / "a.ply")])
    assert res.exit_code == 0, res.output
    v, f = read_mesh_ply(tmp_path / "a.ply")
    xyz = np.stack([v["x"], v["y"], v["z"]], 1)
    report = topology_report(xyz, f)
    assert report["manifold"], report
    assert report["unreferenced_vertices"] == 0
    assert np.bincount(triangle_components(f)).min() >= MeshConfig().min_component
    res = runner.invoke(app, ["mesh", str(run), "--no-progress", "--voxel", "0.02", "--min-component", "0",
                              "--out", str(tmp_path / "b.ply")])
    assert res.exit_code == 0, res.output
    _, f_all = read_mesh_ply(tmp_path / "b.ply")
    assert len(f_all) > len(f)  # the small pieces are back
    assert topology_report(*_xyz_faces(tmp_path / "b.ply"))["components"] > report["components"]
    _one_error_line(runner.invoke(app, ["mesh", str(run), "--min-component", "-1"]), "--min-component")


def _xyz_faces(path):
    v, f = read_mesh_ply(path)
    return np.stack([v["x"], v["y"], v["z"]], 1), f
