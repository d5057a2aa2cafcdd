"""Fuzzing the saved-map loader (``map.npz``, ``--map``): byte mutations of the archive, and archives whose arrays or
manifest are changed (missing, another dtype or shape, special values, a manifest with wrong counts or types).
The reader promises a :class:`~surfelslam.errors.MapFileError` naming the file, or a map whose arrays agree."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
from fuzzkit import example_dir, is_error, mutated_bytes, mutated_text, outcome, unchanged
from hypothesis import given
from hypothesis import strategies as st

from surfelslam.errors import MapFileError
from surfelslam.slam.map_file import read_map_file, write_map_file
from surfelslam.slam.map_keyframes import MapKeyframes
from surfelslam.slam.saved_map import SURFEL_FIELDS, SavedMap, chain_graph, to_arrays
from surfelslam.tracking.features import Features
from surfelslam.types import Intrinsics

N_SURFELS, N_FEATURES = 5, 3
#: saved keyframe depth images [px] (a 16x12 camera subsampled by 4)
KF_DEPTH_SHAPE = (3, 4)
#: JSON values put into the manifest's fields: wrong types, signs, sizes, non-finite (``json`` writes them as
#: ``NaN`` / ``Infinity``, which it also reads)
NASTY_JSON = (None, -1, 0, 1, 2, 10**12, -(10**12), 1.5, float("nan"), float("inf"), "", "x", [], [1, 2], {},
              [14.0, 14.0, 7.5, 5.5, 16, 12], [0, 0, 0, 0, 0, 0], [14.0, 14.0, 7.5, 5.5, -16, 12],
              ["a", "b", "c", "d", "e", "f"], True)
DTYPES = ("float16", "float32", "float64", "int8", "int32", "int64", "uint8", "bool", "complex64", "<U3")
SPECIAL_VALUES = (np.nan, np.inf, -np.inf, -1, 0, 1e30, -(2**31), 2**40)


def tiny_map() -> SavedMap:
    rng = np.random.default_rng(3)
    surfels = {name: (rng.random((N_SURFELS, *trail)) * 2).astype(dtype) for name, (dtype, trail) in
               SURFEL_FIELDS.items()}
    surfels["normal"] /= np.linalg.norm(surfels["normal"], axis=1, keepdims=True)  # the loader checks unit normals
    surfels["radius"] += np.float32(0.001)  # and positive radii
    T = np.tile(np.eye(4), (2, 1, 1))
    T[1, :3, 3] = [0.1, 0.0, 0.02]
    feats = [Features(rng.random((N_FEATURES, 2)).astype(np.float32) * 10,
                      rng.integers(0, 256, (N_FEATURES, 32), dtype=np.uint8),
                      rng.random((N_FEATURES, 3)).astype(np.float32), np.ones(N_FEATURES, bool),
                      rng.random(N_FEATURES).astype(np.float32)) for _ in range(2)]
    kfs = MapKeyframes(T, np.array([0, 5]), np.array([1.0, 1.2]), np.zeros(2, np.int32), feats,
                       [np.full(KF_DEPTH_SHAPE, 1.5, np.float32)] * 2, 4)
    edges, rel = chain_graph(T)
    return SavedMap(surfels, kfs, edges, rel, Intrinsics(14.0, 14.0, 7.5, 5.5, 16, 12), "dense",
                    "tracker = \"dense\"\n", "seq")


@pytest.fixture(scope="module")
def map_seed(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("map") / "map.npz"
    write_map_file(path, tiny_map())
    return path


def check_map(m: SavedMap) -> None:
    """A loaded map whose arrays agree with each other (what the run continuing from it indexes)."""
    n = m.n_surfels
    for name, (dtype, trail) in SURFEL_FIELDS.items():
        assert m.surfels[name].shape == (n, *trail) and m.surfels[name].dtype == np.dtype(dtype)
    kf = m.keyframes
    k = len(kf)
    assert kf.T_world_kf.shape == (k, 4, 4) and len(kf.depth_m) == k
    assert kf.frame_index.shape == kf.timestamp.shape == kf.session.shape == (k,)
    for f, d in zip(kf.features, kf.depth_m, strict=True):
        assert f.keypoints_uv.shape == (len(f.valid), 2) and f.descriptors.shape == (len(f.valid), 32)
        assert d.ndim == 2
    e = len(m.graph_edges)
    assert m.graph_edges.shape == (e, 2) and m.graph_T_i_j.shape == (e, 4, 4)
    assert e == 0 or (m.graph_edges.min() >= 0 and m.graph_edges.max() < k)
    assert m.intrinsics.width > 0 and m.intrinsics.height > 0


def load_and_check(path: Path) -> None:
    with unchanged(path.parent):
        result = outcome(lambda: read_map_file(path))
    if is_error(result):
        assert isinstance(result, MapFileError), f"{type(result).__name__}: {result}"
        assert str(path) in str(result)
    else:
        check_map(result)


def test_seed_is_valid(map_seed):
    m = read_map_file(map_seed)
    check_map(m)
    assert m.n_surfels == N_SURFELS and len(m.keyframes) == 2


@given(data=st.data())
def test_mutated_archive_bytes(map_seed, tmp_path, data):
    path = example_dir(tmp_path) / "map.npz"
    path.write_bytes(data.draw(mutated_bytes(map_seed.read_bytes(), max_ops=3)))
    load_and_check(path)


def test_archive_needing_another_zip_version(map_seed, tmp_path):
    """Found by make fuzz: a member whose 'version needed to extract' is one zipfile lacks (6.4) raised its
    NotImplementedError."""
    data = bytearray(map_seed.read_bytes())
    central = data.index(b"PK\x01\x02")  # the first member's central directory record
    data[central + 6] = 64  # its version needed to extract: 6.4
    path = tmp_path / "map.npz"
    path.write_bytes(bytes(data))
    load_and_check(path)


@st.composite
def mutated_arrays(draw: st.DrawFn, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``arrays`` (a map's, :func:`to_arrays`) after 1-3 edits of one array or of the manifest each."""
    out = dict(arrays)
    manifest = json.loads(bytes(out["manifest"]).decode())
    for _ in range(draw(st.integers(1, 3))):
        op = draw(st.sampled_from(("drop", "dtype", "shape", "values", "manifest_field", "manifest_text", "extra")))
        name = draw(st.sampled_from(sorted(out)))
        a = out.get(name)
        if op == "drop":
            out.pop(name, None)
        elif op == "dtype" and a is not None:
            with np.errstate(all="ignore"):  # the test's own cast (e.g. 1e30 to float16)
                out[name] = a.astype(draw(st.sampled_from(DTYPES)))
        elif op == "shape" and a is not None:
            flat = a.reshape(-1)
            how = draw(st.sampled_from(("cut", "grow", "flat", "axis", "scalar")))
            out[name] = {"cut": flat[: max(len(flat) - 1, 0)], "grow": np.concatenate([flat, flat[:3]]),
                         "flat": flat, "axis": a[None], "scalar": np.asarray(flat[0] if len(flat) else 0)}[how]
        elif op == "values" and a is not None and a.size and name != "manifest":
            b = a.copy().reshape(-1)
            v = draw(st.sampled_from(SPECIAL_VALUES))
            try:
                b[draw(st.integers(0, b.size - 1))] = v
            except (OverflowError, ValueError):
                continue
            out[name] = b.reshape(a.shape)
        elif op == "manifest_field":
            manifest[draw(st.sampled_from(sorted(manifest)))] = draw(st.sampled_from(NASTY_JSON))
            out["manifest"] = np.frombuffer(json.dumps(manifest).encode(), np.uint8)
        elif op == "manifest_text":
            text = draw(mutated_text(json.dumps(manifest, indent=1)))
            out["manifest"] = np.frombuffer(text.encode("utf-8", "surrogatepass"), np.uint8)
        elif op == "extra":
            out[f"extra_{name}"] = np.zeros(3)
    return out


@given(data=st.data())
def test_mutated_arrays(tmp_path, data):
    arrays = data.draw(mutated_arrays(to_arrays(tiny_map())))
    path = example_dir(tmp_path) / "map.npz"
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    path.write_bytes(buf.getvalue())
    load_and_check(path)


MANIFEST_FIELDS = sorted(json.loads(bytes(to_arrays(tiny_map())["manifest"]).decode()))


@pytest.mark.parametrize("value", NASTY_JSON, ids=repr)
@pytest.mark.parametrize("field", MANIFEST_FIELDS)
def test_manifest_field_values(tmp_path, field, value):
    """Every manifest field with every nasty JSON value (all pairs: few enough to try each on every run)."""
    arrays = to_arrays(tiny_map())
    manifest = json.loads(bytes(arrays["manifest"]).decode())
    manifest[field] = value
    arrays["manifest"] = np.frombuffer(json.dumps(manifest).encode(), np.uint8)
    path = example_dir(tmp_path) / "map.npz"
    np.savez(path, **arrays)
    load_and_check(path)


@given(content=st.binary(max_size=400))
def test_random_file(tmp_path, content):
    path = example_dir(tmp_path) / "map.npz"
    path.write_bytes(content)
    load_and_check(path)


@pytest.mark.parametrize("dtype", ["complex64", "float32", "int64", "<U3"])
def test_manifest_of_another_dtype(tmp_path, dtype):
    """Found: a complex manifest array was cast to bytes with a ComplexWarning on stderr."""
    arrays = to_arrays(tiny_map())
    arrays["manifest"] = arrays["manifest"].astype(dtype)
    path = example_dir(tmp_path) / "map.npz"
    np.savez(path, **arrays)
    load_and_check(path)
