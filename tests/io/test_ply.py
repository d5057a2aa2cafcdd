"""PLY writer/reader: surfel maps and plain clouds round-trip; header is the standard one."""

from __future__ import annotations

import numpy as np
import pytest

from surfelslam.errors import InputError
from surfelslam.io.ply import read_ply, write_ply, write_points_ply
from surfelslam.mapping import SurfelMap


def _map(n: int = 257) -> SurfelMap:
    rng = np.random.default_rng(0)
    m = SurfelMap()
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    m.append(rng.normal(size=(n, 3)), nrm, rng.uniform(0, 255, (n, 3)), rng.uniform(0, 9, n), 0.01, 3)
    m.hits[:] = rng.integers(1, 50, n)
    m.last_seen[:] = rng.integers(3, 90, n)
    return m


def test_surfel_map_round_trip_skips_dead_surfels(tmp_path):
    m = _map()
    m.mark_dead(np.arange(0, m.size, 10))  # flagged but not compacted: not written
    alive = m.alive_mask()
    path = tmp_path / "map.ply"
    assert write_ply(path, m) == alive.sum()
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    assert "format binary_little_endian 1.0" in header
    assert f"element vertex {alive.sum()}" in header
    for line in ("property float x", "property float nz", "property uchar red", "property float confidence",
                 "property float radius", "property int first_seen", "property int last_seen", "property int hits"):
        assert line in header
    d = read_ply(path)
    np.testing.assert_array_equal(np.column_stack([d["x"], d["y"], d["z"]]), m.position[alive])
    np.testing.assert_array_equal(np.column_stack([d["nx"], d["ny"], d["nz"]]), m.normal[alive])
    np.testing.assert_array_equal(np.column_stack([d["red"], d["green"], d["blue"]]),
                                  np.floor(m.colour[alive] + 0.5).astype(np.uint8))
    np.testing.assert_array_equal(d["confidence"], m.confidence[alive])
    np.testing.assert_array_equal(d["hits"], m.hits[alive])
    np.testing.assert_array_equal(d["last_seen"], m.last_seen[alive])
    assert not list(tmp_path.glob(".*.tmp"))  # the temp file was renamed


def test_points_ply_with_and_without_normals(tmp_path):
    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(100, 3))
    rgb = rng.integers(0, 256, (100, 3)).astype(np.uint8)
    write_points_ply(tmp_path / "a.ply", xyz, rgb)
    d = read_ply(tmp_path / "a.ply")
    assert set(d) == {"x", "y", "z", "red", "green", "blue"}
    np.testing.assert_allclose(d["x"], xyz[:, 0].astype(np.float32))
    np.testing.assert_array_equal(d["blue"], rgb[:, 2])
    nrm = rng.normal(size=(100, 3))
    write_points_ply(tmp_path / "b.ply", xyz, rgb.astype(np.float32), normals=nrm)
    d = read_ply(tmp_path / "b.ply")
    np.testing.assert_allclose(d["ny"], nrm[:, 1].astype(np.float32))
    with pytest.raises(ValueError, match="colours"):
        write_points_ply(tmp_path / "c.ply", xyz, rgb[:5])


def test_read_ply_rejects_bad_files(tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply")
    with pytest.raises(InputError, match="not a PLY"):
        read_ply(bad)
    ascii_ply = tmp_path / "ascii.ply"
    ascii_ply.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    with pytest.raises(InputError, match="binary_little_endian"):
        read_ply(ascii_ply)
    with pytest.raises(InputError, match="cannot read"):
        read_ply(tmp_path / "missing.ply")
    trunc = tmp_path / "t.ply"
    write_points_ply(trunc, np.zeros((10, 3)), np.zeros((10, 3), np.uint8))
    trunc.write_bytes(trunc.read_bytes()[:-5])
    with pytest.raises(InputError, match="truncated"):
        read_ply(trunc)
