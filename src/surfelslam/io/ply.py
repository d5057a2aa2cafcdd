"""PLY point clouds: binary little-endian writer (surfel maps, plain clouds) and a reader for tests/tools.

Files open in MeshLab and CloudCompare: standard header, one ``vertex`` element, ``float``/``uchar``/``int``
properties. Writes go through a temp file + rename (:mod:`surfelslam.io.atomic`).
"""

from __future__ import annotations

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


def _write_vertices(path: str | Path, fields: list[tuple[str, np.ndarray]], comment: str) -> None:
    n = len(fields[0][1])
    dtype = np.dtype([(name, arr.dtype.newbyteorder("<") if arr.dtype.itemsize > 1 else arr.dtype)
                      for name, arr in fields])
    rec = np.empty(n, dtype)
    for name, arr in fields:
        rec[name] = arr
    lines = ["ply", "format binary_little_endian 1.0", f"comment {comment}", f"element vertex {n}"]
    for name in dtype.names:
        lines.append(f"property {_NP_TO_PLY[dtype[name].str]} {name}")
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode("ascii")
    with atomic_open(path, "wb") as fh:
        fh.write(header)
        fh.write(rec.tobytes())


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


def read_ply(path: str | Path) -> dict[str, np.ndarray]:
    """Read the ``vertex`` element of a binary little-endian PLY into ``{property: (N,) array}``."""
    path = Path(path)
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
                n = int(parts[2])
        elif parts[:1] == ["property"] and in_vertex:
            if parts[1] == "list" or parts[1] not in _PLY_TYPES:
                raise InputError(path, f"unsupported vertex property: {line!r}")
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    if n is None:
        raise InputError(path, "no 'element vertex' in the header")
    dtype = np.dtype(props)
    body = data[end + len(b"end_header\n") :]
    if len(body) < n * dtype.itemsize:
        raise InputError(path, f"truncated PLY: {n} vertices need {n * dtype.itemsize} bytes, got {len(body)}")
    rec = np.frombuffer(body, dtype, count=n)
    return {name: rec[name].copy() for name in dtype.names}
