"""Fuzzing the PLY readers (a run's ``map.ply`` and ``mesh.ply``, read back by ``rerun`` and the mesh tools):
mutated headers and bodies of files written by the project's own writers, and random files."""

from __future__ import annotations

import numpy as np
from fuzzkit import example_dir, is_error, mutated_bytes, mutated_text, outcome
from hypothesis import example, given
from hypothesis import strategies as st

from surfelslam.io.ply import read_mesh_ply, read_ply, write_mesh_ply, write_points_ply

_RNG = np.random.default_rng(5)
_XYZ = _RNG.random((6, 3)).astype(np.float32)


def _seed(tmp, mesh: bool) -> bytes:
    path = tmp / "seed.ply"
    if mesh:
        write_mesh_ply(path, _XYZ, np.array([[0, 1, 2], [3, 4, 5]]), normals=_XYZ, colours=(_XYZ * 255))
    else:
        write_points_ply(path, _XYZ, (_XYZ * 255).astype(np.uint8), normals=_XYZ)
    return path.read_bytes()


def _check(path, mesh: bool) -> None:
    result = outcome(lambda: read_mesh_ply(path) if mesh else read_ply(path))
    if is_error(result):
        return
    vertices, faces = result if mesh else (result, np.zeros((0, 3), np.int32))
    lengths = {len(v) for v in vertices.values()}
    assert len(lengths) <= 1, f"vertex properties of different lengths {lengths}"
    n = lengths.pop() if lengths else 0
    assert faces.ndim == 2 and faces.shape[1] == 3
    assert len(faces) == 0 or (faces.min() >= 0 and faces.max() < n)


def _split(data: bytes) -> tuple[str, bytes]:
    end = data.index(b"end_header\n") + len(b"end_header\n")
    return data[:end].decode("ascii"), data[end:]


@given(data=st.data(), mesh=st.booleans(), where=st.sampled_from(("header", "bytes")))
@example(data=None, mesh=False, where="element vertex x")  # found: ValueError from int()
def test_mutated_ply(tmp_path, data, mesh, where):
    folder = example_dir(tmp_path)
    seed = _seed(folder, mesh)
    if data is None:  # the explicit example: a header line replaced
        header, body = _split(seed)
        content = header.replace("element vertex 6", where).encode() + body
    elif where == "header":
        header, body = _split(seed)
        content = data.draw(mutated_text(header)).encode("utf-8", "surrogatepass") + b"end_header\n" + body
    else:
        content = data.draw(mutated_bytes(seed))
    path = folder / "x.ply"
    path.write_bytes(content)
    _check(path, mesh)


@given(header=st.lists(st.sampled_from((
    "element vertex 3", "element vertex -1", "element vertex 99999999999", "element vertex", "element", "property",
    "property float x", "property float x", "property float", "property list uchar int vertex_indices",
    "property double y", "property uchar red", "element face 1", "element face -2", "element edge 1",
    "property list uchar uint vertex_indices", "comment x", "format binary_little_endian 1.0", "property quux z")),
    max_size=8), body=st.binary(max_size=64), mesh=st.booleans())
def test_generated_headers(tmp_path, header, body, mesh):
    path = example_dir(tmp_path) / "x.ply"
    path.write_bytes(("ply\nformat binary_little_endian 1.0\n" + "\n".join(header) + "\nend_header\n").encode() + body)
    _check(path, mesh)
