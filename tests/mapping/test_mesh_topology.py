"""Mesh topology: our checker on hand-made meshes, the clean-up, and marching cubes meshes that mesh tools accept."""

from __future__ import annotations

import numpy as np
import pytest

from surfelslam.kernels import mesh_topology as kmt
from surfelslam.kernels import tsdf as kt
from surfelslam.mapping.mesh import TsdfVolume, compact
from surfelslam.mapping.mesh_topology import (
    MAX_FAN_ROUNDS,
    clean_faces,
    clean_faces_reference,
    topology_report,
)

# a unit square of two triangles, counter-clockwise seen from +z
SQUARE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
SQUARE_F = np.array([[0, 1, 2], [0, 2, 3]])


def test_report_of_a_clean_square():
    r = topology_report(SQUARE_V, SQUARE_F)
    assert r["manifold"] and r["components"] == 1 and r["border_edges"] == 4
    assert r["non_manifold_edges"] == r["misoriented_edges"] == r["non_manifold_vertices"] == 0


def test_report_counts_each_defect():
    flipped = topology_report(SQUARE_V, np.array([[0, 1, 2], [0, 3, 2]]))
    assert flipped["misoriented_edges"] == 1 and not flipped["manifold"]
    dup = topology_report(SQUARE_V, np.array([[0, 1, 2], [0, 2, 3], [2, 1, 0]]))
    assert dup["duplicated_triangles"] == 1 and dup["non_manifold_edges"] == 1  # edges 0-1, 1-2 have 2; 0-2 has 3
    v = np.vstack([SQUARE_V, [[0, 0, 1], [1, 0, 1]]])
    fin = topology_report(v, np.array([[0, 1, 2], [0, 2, 3], [0, 4, 2]]))  # a third triangle on the diagonal
    assert fin["non_manifold_edges"] == 1
    bowtie_v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], float)
    bowtie = topology_report(bowtie_v, np.array([[0, 1, 2], [0, 3, 4]]))  # two triangles touching at vertex 0
    assert bowtie["non_manifold_vertices"] == 1 and bowtie["components"] == 2
    degenerate = topology_report(np.vstack([SQUARE_V, SQUARE_V[:1]]), np.array([[0, 1, 2], [0, 2, 4]]))
    assert degenerate["duplicated_vertices"] == 1 and degenerate["degenerate_triangles"] == 1


def test_clean_keeps_the_largest_fan_and_drops_small_pieces():
    # a fan of 4 triangles around vertex 0 and one more triangle touching it at vertex 0 only
    ring = np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], float)
    v = np.vstack([[0, 0, 0], ring, [[2, -2, 0.5], [3, -1, 0.5]], [[5, 5, 0], [6, 5, 0], [5, 6, 0]]])
    fan = [[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 1]]
    f = np.array([*fan, [0, 5, 6], [7, 8, 9]])  # the touching triangle; a separate triangle far off
    assert topology_report(v, f)["non_manifold_vertices"] == 1
    keep = clean_faces(v, f, min_component=0)
    np.testing.assert_array_equal(keep, [True] * 4 + [False, True])
    keep = clean_faces(v, f, min_component=2)
    np.testing.assert_array_equal(keep, [True] * 4 + [False, False])
    assert topology_report(v, f[keep])["manifold"]


def test_triangle_table_has_no_diagonal_in_a_cube_face():
    """A diagonal between two cut edges of one face lies in that face, which the neighbouring cube shares."""
    faces_of = [{(b, (c >> b) & 1) for b in range(3) if b != a} for c, a in zip(kt.EDGE_CORNER, kt.EDGE_AXIS,
                                                                                 strict=True)]
    for case in range(256):
        tris = kt.TRI_TABLE[case, : 3 * kt.TRI_COUNT[case]].reshape(-1, 3)
        uses: dict[frozenset, int] = {}
        for t in tris:
            for a, b in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0])):
                uses[frozenset((a, b))] = uses.get(frozenset((a, b)), 0) + 1
        for edge, n in uses.items():
            a, b = tuple(edge)
            assert n in (1, 2), case
            if n == 2:  # an inner diagonal of a loop
                assert not faces_of[a] & faces_of[b], (case, a, b)


def _random_volume(seed: int, blocks: int = 3) -> TsdfVolume:
    """A volume of ``blocks^3`` blocks, every voxel observed, holding a random field: every cube configuration,
    ambiguous faces included, many times over (values within +-0.6: no jump that marching cubes refuses)."""
    vol = TsdfVolume(0.01, 0.04, initial_blocks=blocks**3)
    coords = np.stack(np.meshgrid(*[np.arange(blocks)] * 3, indexing="ij"), -1).reshape(-1, 3)
    n = len(coords)
    vol.coords[:n] = coords
    vol.n_blocks = n
    kt.rehash(vol.coords, n, vol.keys, vol.vals)
    rng = np.random.default_rng(seed)
    vol.tsdf[:n] = rng.uniform(-0.6, 0.6, (n, kt.BLOCK_VOXELS)).astype(np.float32)
    vol.weight[:n] = 1.0
    vol.count[:n] = 1
    return vol


@pytest.mark.parametrize("seed", [0, 1])
def test_marching_cubes_of_any_field_is_edge_manifold_and_oriented(seed):
    vol = _random_volume(seed)
    raw = vol.marching_cubes()
    assert raw.n_faces > 10_000
    r = topology_report(raw.vertices, raw.faces)
    assert r["duplicated_triangles"] == r["duplicated_vertices"] == r["degenerate_triangles"] == 0
    assert r["non_manifold_edges"] == 0 and r["misoriented_edges"] == 0
    assert r["unreferenced_vertices"] == 0
    # each triangle joins points on the edges of one cube (vertex indices = block start + index within the block)
    tri = raw.vertices[raw.faces]
    assert np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max() <= np.sqrt(3) * vol.voxel_m + 1e-6
    # borders only where the volume ends: every vertex of a border edge lies on the volume's outer faces
    mesh = vol.extract_mesh(min_component=0)
    r = topology_report(mesh.vertices, mesh.faces)
    assert r["manifold"] and r["unreferenced_vertices"] == 0
    assert mesh.n_faces >= 0.99 * raw.n_faces  # the clean-up removes a few fans at the border, no more


def test_compact_keeps_the_used_vertices_in_order():
    vol = _random_volume(2, blocks=1)
    raw = vol.marching_cubes()
    keep = np.zeros(raw.n_faces, bool)
    keep[::3] = True
    small = compact(raw, keep)
    np.testing.assert_array_equal(small.vertices[small.faces], raw.vertices[raw.faces[keep]])
    assert small.n_vertices == len(np.unique(raw.faces[keep]))


@pytest.mark.parametrize(("step", "surface"), [(0.2, True), (1.0, False)])
def test_a_truncation_jump_is_no_surface(step, surface):
    """A sign change from +step to -step along x: a surface when small, the truncation band's edge (free space
    next to the back of another surface's band) when it jumps by more than MAX_CROSSING_JUMP."""
    vol = _random_volume(0, blocks=2)
    x = np.arange(kt.BLOCK_VOXELS) & 7
    for b in range(vol.n_blocks):
        gx = vol.coords[b, 0] * kt.BLOCK + x
        vol.tsdf[b] = np.where(gx < 8, step, -step)
    assert 2 * step > kt.MAX_CROSSING_JUMP or surface
    mesh = vol.marching_cubes()
    assert (mesh.n_faces > 0) == surface
    if surface:
        np.testing.assert_allclose(mesh.vertices[:, 0], 0.075, atol=1e-6)  # halfway between x = 7 and 8 voxels


# ------------------------------------------------------------------------------------------ kernels vs reference
def _grid_mesh(n: int, rng):
    """A bumpy ``n`` x ``n`` height field of ``2 (n - 1)^2`` triangles (one piece, edge- and vertex-manifold)."""
    y, x = np.mgrid[0:n, 0:n]
    v = np.c_[x.reshape(-1), y.reshape(-1), rng.uniform(0, 0.3, n * n)].astype(np.float32)
    i = (y[:-1, :-1] * n + x[:-1, :-1]).reshape(-1)
    f = np.vstack([np.c_[i, i + 1, i + n + 1], np.c_[i, i + n + 1, i + n]]).astype(np.int32)
    return v, f


def _random_soup(rng, n: int, n_random: int):
    """A height field of ``n`` x ``n`` vertices on two levels (collinear triples: zero-area triangles) and
    ``n_random`` random triangles over its vertices: shared edges of 3+ triangles, both orientations, repeated
    vertices, duplicated triangles, touching fans."""
    v, f = _grid_mesh(n, rng)
    v[:, 2] = rng.integers(0, 2, len(v)) * 0.5
    return v, np.vstack([f, rng.integers(0, len(v), (n_random, 3))]).astype(np.int32)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("min_component", [0, 2, 5])
def test_clean_kernels_match_the_reference_on_random_soups(seed, min_component):
    rng = np.random.default_rng(seed)
    v, f = _random_soup(rng, 8 + 2 * seed, 20 + 20 * seed)
    keep = clean_faces(v, f, min_component)
    np.testing.assert_array_equal(keep, clean_faces_reference(v, f, min_component))
    assert len(f) // 4 < keep.sum() < len(f)  # the soup has defects to remove and much to keep


def test_clean_kernels_match_the_reference_on_a_grid_with_planted_defects():
    rng = np.random.default_rng(3)
    v, f = _grid_mesh(30, rng)
    assert clean_faces(v, f, 0).all()  # nothing to remove
    fins = np.c_[f[:40, :2], rng.integers(0, len(v), 40)]  # third triangles on existing edges
    flipped = f[40:60, ::-1]  # duplicated triangles, opposite orientation
    touching = np.c_[f[100:130, 0], rng.integers(0, len(v), (30, 2))]  # fans touching at one vertex
    island = np.array([[0, 31, 62], [0, 62, 93]]) + 400  # a separate small piece
    degenerate = np.c_[f[200:210, 0], f[200:210, 0], f[200:210, 1]]
    faces = np.vstack([f, fins, flipped, touching, island, degenerate]).astype(np.int32)
    for mc in (0, 100):
        keep = clean_faces(v, faces, mc)
        np.testing.assert_array_equal(keep, clean_faces_reference(v, faces, mc))
        assert topology_report(v, faces[keep])["non_manifold_vertices"] == 0
        assert not keep[-10:].any()  # the degenerate ones are gone
    assert keep[: len(f)].sum() > 0.9 * len(f)  # most of the grid stays


@pytest.mark.parametrize("dtype", [np.int32, np.int64])
def test_clean_kernels_with_either_index_width(dtype):
    """The work arrays are int32 below 2^31 half-edges, int64 above: both give the reference's mask."""
    rng = np.random.default_rng(11)
    v, f = _random_soup(rng, 16, 100)
    keep = np.ones(len(f), bool)
    kmt.nondegenerate(v, f, keep)
    offsets, halfedges = np.empty(len(v) + 1, np.int64), np.empty(3 * len(f), dtype)
    kmt.edge_buckets(f, len(v), offsets, halfedges)
    parent = np.empty(3 * len(f), dtype)
    fans, best, best_size = np.empty(len(v), np.int32), np.empty(len(v), dtype), np.empty(len(v), dtype)
    rounds = 0
    while kmt.drop_extra_fans(f, keep, offsets, halfedges, parent, fans, best, best_size) and rounds < MAX_FAN_ROUNDS:
        rounds += 1
    kmt.drop_small_pieces(f, keep, offsets, halfedges, parent[: len(f)], 3)
    np.testing.assert_array_equal(keep, clean_faces_reference(v, f, 3))
    assert rounds >= 1 and len(f) // 4 < keep.sum() < len(f)
