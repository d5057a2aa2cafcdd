"""PLY point clouds and meshes: binary little-endian writers (surfel maps, plain clouds, triangle meshes) and
readers for tests/tools.

Files open in MeshLab, CloudCompare and Blender: standard header, a ``vertex`` element with ``float``/``uchar``/
``int`` properties (and for meshes a ``face`` element, ``property list uchar int vertex_indices``). Writes go
through a temp file + rename (:mod:`surfelslam.io.atomic`).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from surfelslam.errors import InputError
from surfelslam.io.atomic import atomic_open

if TYPE_CHECKING:
    from surfelslam.mapping.surfel_map import SurfelMap

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2", "int16": "<i2",
    "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
}
_NP_TO_PLY = {"<f4": "float", "|u1": "uchar", "<i4": "int", "<f8": "double"}


#: a triangle in the ``face`` element: the vertex count (3, uchar) and the vertex indices (int)
_FACE_DTYPE = np.dtype([("n", "u1"), ("v", "<i4", (3,))])


def _write_vertices(path: str | Path, fields: list[tuple[str, np.ndarray]], comment: str,
                    faces: np.ndarray | None = None) -> None:
    n = len(fields[0][1])
    dtype = np.dtype([(name, arr.dtype.newbyteorder("<") if arr.dtype.itemsize > 1 else arr.dtype)
                      for name, arr in fields])
    rec = np.empty(n, dtype)
    for name, arr in fields:
        rec[name] = arr
    lines = ["ply", "format binary_little_endian 1.0", f"comment {comment}", f"element vertex {n}"]
    for name in dtype.names:
        lines.append(f"property {_NP_TO_PLY[dtype[name].str]} {name}")
    face_rec = None
    if faces is not None:
        face_rec = np.empty(len(faces), _FACE_DTYPE)
        face_rec["n"] = 3
        face_rec["v"] = faces
        lines += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode("ascii")
    with atomic_open(path, "wb") as fh:
        fh.write(header)
        fh.write(rec.tobytes())
        if face_rec is not None:
            fh.write(face_rec.tobytes())


def _colour_u8(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.dtype == np.uint8:
        return rgb
    return np.clip(np.floor(rgb.astype(np.float64) + 0.5), 0, 255).astype(np.uint8)


def write_ply(path: str | Path, smap: SurfelMap) -> int:
    """Write the live surfels of ``smap``: x y z nx ny nz (float) red green blue (uchar) confidence radius
    (float) first_seen last_seen hits (int). Returns the number of vertices written."""
    alive = smap.alive_mask()
    pos = smap.position[alive].astype("<f4")
    nrm = smap.normal[alive].astype("<f4")
    col = _colour_u8(smap.colour[alive])
    fields = [
        ("x", pos[:, 0]), ("y", pos[:, 1]), ("z", pos[:, 2]),
        ("nx", nrm[:, 0]), ("ny", nrm[:, 1]), ("nz", nrm[:, 2]),
        ("red", col[:, 0]), ("green", col[:, 1]), ("blue", col[:, 2]),
        ("confidence", smap.confidence[alive].astype("<f4")), ("radius", smap.radius[alive].astype("<f4")),
        ("first_seen", smap.first_seen[alive].astype("<i4")), ("last_seen", smap.last_seen[alive].astype("<i4")),
        ("hits", smap.hits[alive].astype("<i4")),
    ]
    _write_vertices(path, fields, "surfelslam surfel map")
    return len(pos)


def write_points_ply(path: str | Path, xyz: np.ndarray, rgb: np.ndarray, normals: np.ndarray | None = None) -> int:
    """Write a plain coloured cloud: ``xyz`` ``(N, 3)`` metres, ``rgb`` ``(N, 3)`` (uint8, or float in
    [0, 255]), optional ``normals`` ``(N, 3)``. Returns N."""
    xyz = np.asarray(xyz, "<f4").reshape(-1, 3)
    col = _colour_u8(np.asarray(rgb).reshape(-1, 3))
    if len(col) != len(xyz):
        raise ValueError(f"write_points_ply: {len(xyz)} points but {len(col)} colours")
    fields = [("x", xyz[:, 0]), ("y", xyz[:, 1]), ("z", xyz[:, 2])]
    if normals is not None:
        nrm = np.asarray(normals, "<f4").reshape(-1, 3)
        if len(nrm) != len(xyz):
            raise ValueError(f"write_points_ply: {len(xyz)} points but {len(nrm)} normals")
        fields += [("nx", nrm[:, 0]), ("ny", nrm[:, 1]), ("nz", nrm[:, 2])]
    fields += [("red", col[:, 0]), ("green", col[:, 1]), ("blue", col[:, 2])]
    _write_vertices(path, fields, "surfelslam point cloud")
    return len(xyz)


def write_mesh_ply(path: str | Path, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None,
                   colours: np.ndarray | None = None) -> tuple[int, int]:
    """Write a triangle mesh: vertices x y z [nx ny nz] (float) [red green blue] (uchar), faces as
    ``vertex_indices`` lists (uchar count 3, int indices). ``vertices`` ``(V, 3)`` metres, ``faces`` ``(F, 3)``
    indices, ``normals`` ``(V, 3)``, ``colours`` ``(V, 3)`` (uint8, or float in [0, 255]). Returns ``(V, F)``."""
    xyz = np.asarray(vertices, "<f4").reshape(-1, 3)
    tri = np.asarray(faces).reshape(-1, 3)
    if len(tri) and (tri.min() < 0 or tri.max() >= len(xyz)):
        raise ValueError(f"write_mesh_ply: face indices outside [0, {len(xyz)})")
    fields = [("x", xyz[:, 0]), ("y", xyz[:, 1]), ("z", xyz[:, 2])]
    if normals is not None:
        nrm = np.asarray(normals, "<f4").reshape(-1, 3)
        if len(nrm) != len(xyz):
            raise ValueError(f"write_mesh_ply: {len(xyz)} vertices but {len(nrm)} normals")
        fields += [("nx", nrm[:, 0]), ("ny", nrm[:, 1]), ("nz", nrm[:, 2])]
    if colours is not None:
        col = _colour_u8(np.asarray(colours).reshape(-1, 3))
        if len(col) != len(xyz):
            raise ValueError(f"write_mesh_ply: {len(xyz)} vertices but {len(col)} colours")
        fields += [("red", col[:, 0]), ("green", col[:, 1]), ("blue", col[:, 2])]
    _write_vertices(path, fields, "surfelslam mesh", faces=tri.astype("<i4"))
    return len(xyz), len(tri)


def _read_header(path: Path) -> tuple[list[str], bytes]:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(path, f"cannot read PLY ({exc.strerror or exc})") from None
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise InputError(path, "not a PLY file (missing 'ply' magic or 'end_header')")
    header = data[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise InputError(path, "only binary_little_endian 1.0 PLY files are supported")
    return header, data[end + len(b"end_header\n") :]


def _malformed(read):
    """``read(path)`` with the errors of a malformed header (a count that is no number, a property without a name,
    the same property twice, no property) as one-line InputErrors naming the file."""
    @functools.wraps(read)
    def wrapper(path: str | Path):
        path = Path(path)
        try:
            return read(path)
        except (ValueError, IndexError, TypeError) as exc:
            raise InputError(path, f"malformed PLY ({exc})") from None

    return wrapper


def _count(path: Path, text: str) -> int:
    n = int(text)
    if n < 0:
        raise InputError(path, f"negative element count {n}")
    return n


@_malformed
def read_mesh_ply(path: Path) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Read a binary little-endian triangle mesh: ``({vertex property: (V,) array}, faces (F, 3) int32)``.
    The ``face`` element must hold one ``list uchar int|uint`` property of triangles; other elements are refused."""
    header, body = _read_header(path)
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in header:
        parts = line.split()
        if parts[:1] == ["element"] and len(parts) == 3:
            elements.append((parts[1], _count(path, parts[2]), []))
        elif parts[:1] == ["property"] and elements:
            if parts[1] == "list":
                if len(parts) != 5 or parts[2] not in ("uchar", "uint8") or parts[3] not in ("int", "int32", "uint",
                                                                                             "uint32"):
                    raise InputError(path, f"unsupported list property: {line!r}")
                elements[-1][2].append((parts[4], "list"))
            elif parts[1] in _PLY_TYPES:
                elements[-1][2].append((parts[2], _PLY_TYPES[parts[1]]))
            else:
                raise InputError(path, f"unsupported property: {line!r}")
    names = [e[0] for e in elements]
    if names[:1] != ["vertex"] or any(n not in ("vertex", "face") for n in names):
        raise InputError(path, f"expected a vertex element then a face element, got {names}")
    _, n_v, vprops = elements[0]
    if any(t == "list" for _, t in vprops):
        raise InputError(path, "list properties in the vertex element are not supported")
    vdtype = np.dtype(vprops)
    if len(body) < n_v * vdtype.itemsize:
        raise InputError(path, f"truncated PLY: {n_v} vertices need {n_v * vdtype.itemsize} bytes, got {len(body)}")
    rec = np.frombuffer(body, vdtype, count=n_v)
    vertices = {name: rec[name].copy() for name in vdtype.names}
    faces = np.zeros((0, 3), np.int32)
    if len(elements) > 1:
        _, n_f, fprops = elements[1]
        if [t for _, t in fprops] != ["list"]:
            raise InputError(path, "the face element must hold exactly one list property (vertex_indices)")
        off = n_v * vdtype.itemsize
        need = n_f * _FACE_DTYPE.itemsize
        if len(body) - off < need:
            raise InputError(path, f"truncated PLY: {n_f} triangles need {need} bytes, got {len(body) - off}")
        frec = np.frombuffer(body, _FACE_DTYPE, count=n_f, offset=off)
        if n_f and not np.all(frec["n"] == 3):
            raise InputError(path, "only triangle faces are supported (a face has another vertex count)")
        faces = frec["v"].astype(np.int32)
        if n_f and (faces.min() < 0 or faces.max() >= n_v):
            raise InputError(path, f"face indices outside [0, {n_v})")
    return vertices, faces


@_malformed
def read_ply(path: Path) -> dict[str, np.ndarray]:
    """Read the ``vertex`` element of a binary little-endian PLY into ``{property: (N,) array}``."""
    header, body = _read_header(path)
    n = None
    props: list[tuple[str, str]] = []
    in_vertex = False
    for line in header:
        parts = line.split()
        if parts[:1] == ["element"]:
            if in_vertex:
                break  # other elements after the vertices are ignored
            in_vertex = parts[1] == "vertex"
            if in_vertex:
                n = _count(path, parts[2])
        elif parts[:1] == ["property"] and in_vertex:
            if parts[1] == "list" or parts[1] not in _PLY_TYPES:
                raise InputError(path, f"unsupported vertex property: {line!r}")
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    if n is None:
        raise InputError(path, "no 'element vertex' in the header")
    dtype = np.dtype(props)
    if len(body) < n * dtype.itemsize:
        raise InputError(path, f"truncated PLY: {n} vertices need {n * dtype.itemsize} bytes, got {len(body)}")
    rec = np.frombuffer(body, dtype, count=n)
    return {name: rec[name].copy() for name in dtype.names}
