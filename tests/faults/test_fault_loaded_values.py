"""Loaded values are checked, not only their structure (issue 71.2): a structurally valid map.npz whose values are
non-finite or out of range is refused with one line naming the file and the array; bag camera info likewise."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from faultkit import assert_one_line, cli

from surfelslam.errors import MapFileError
from surfelslam.slam.map_file import read_map_file, write_map_file
from surfelslam.slam.map_keyframes import MapKeyframes
from surfelslam.slam.saved_map import SavedMap, chain_graph, to_arrays
from surfelslam.tracking.features import Features
from surfelslam.types import Intrinsics

N_SURFELS = 5
N_FEATURES = 4


def _saved_map() -> SavedMap:
    """A small, valid map: 5 surfels facing the camera, two keyframes 0.1 m apart chained in the graph."""
    rng = np.random.default_rng(0)
    surfels = {"position": rng.uniform(-1, 1, (N_SURFELS, 3)).astype(np.float32),
               "normal": np.tile(np.float32([0, 0, -1]), (N_SURFELS, 1)),
               "colour": np.full((N_SURFELS, 3), 128, np.float32),
               "confidence": np.ones(N_SURFELS, np.float32), "radius": np.full(N_SURFELS, 0.01, np.float32),
               "first_seen": np.zeros(N_SURFELS, np.int32), "last_seen": np.ones(N_SURFELS, np.int32),
               "hits": np.ones(N_SURFELS, np.int32)}
    T = np.tile(np.eye(4), (2, 1, 1))
    T[1, 0, 3] = 0.1
    pts = np.ones((N_FEATURES, 3), np.float32)
    pts[0] = np.nan  # an invalid keypoint: NaN is allowed where kf_valid is False
    feats = [Features(np.ones((N_FEATURES, 2), np.float32), np.zeros((N_FEATURES, 32), np.uint8), pts,
                      np.array([False, True, True, True]), np.ones(N_FEATURES, np.float32)) for _ in range(2)]
    kfs = MapKeyframes(T, np.array([0, 5], np.int64), np.array([0.0, 0.2]), np.zeros(2, np.int32), feats,
                       [np.ones((3, 4), np.float32)] * 2, 4)
    edges, rel = chain_graph(T)
    return SavedMap(surfels, kfs, edges, rel, Intrinsics(10.0, 10.0, 8.0, 6.0, 16, 12), "dense")


def _broken(tmp_path: Path, name: str, value, index=(0,)) -> Path:
    """The map with ``arrays[name][index] = value`` (``name == "intrinsics"``: the manifest's fx)."""
    arrays = to_arrays(_saved_map())
    if name == "intrinsics":
        man = json.loads(bytes(arrays["manifest"]).decode())
        man["intrinsics"][0] = value
        arrays["manifest"] = np.frombuffer(json.dumps(man).encode(), np.uint8)
    else:
        arrays[name] = arrays[name].copy()
        arrays[name][index] = value
    path = tmp_path / f"{name}.npz"
    np.savez(path, **arrays)
    return path


def test_a_valid_map_reads_back(tmp_path):
    write_map_file(tmp_path / "map.npz", _saved_map())
    assert read_map_file(tmp_path / "map.npz").n_surfels == N_SURFELS


@pytest.mark.parametrize("name, value, index, fragment", [
    ("surfel_position", np.nan, (2, 1), "array surfel_position: entry 2"),
    ("surfel_position", 1e9, (0, 0), "within"),
    ("surfel_normal", 0.0, (1, 2), "array surfel_normal: entry 1"),
    ("surfel_colour", -3.0, (0, 0), "surfel_colour"),
    ("surfel_radius", -0.01, (4,), "array surfel_radius: entry 4"),
    ("surfel_confidence", np.inf, (0,), "surfel_confidence"),
    ("kf_T_world_kf", np.nan, (1, 0, 3), "array kf_T_world_kf: entry 1"),
    ("kf_T_world_kf", 2.0, (0, 0, 0), "rigid"),
    ("graph_T_i_j", np.inf, (0, 1, 3), "graph_T_i_j"),
    ("kf_timestamp", np.nan, (1,), "kf_timestamp"),
    ("kf_depth_m", np.nan, (3,), "kf_depth_m (keyframe 0)"),
    ("kf_points_cam", np.nan, (5,), "kf_points_cam (keyframe 1)"),
    ("intrinsics", -10.0, None, "manifest intrinsics"),
])
def test_bad_values_are_refused_naming_the_array(tmp_path, name, value, index, fragment):
    path = _broken(tmp_path, name, value, index)
    with pytest.raises(MapFileError) as exc:
        read_map_file(path)
    text = str(exc.value)
    assert "\n" not in text and text.startswith(str(path)) and fragment in text


def test_cli_refuses_a_map_with_nan_positions_in_one_line(seq, tmp_path):
    path = _broken(tmp_path, "surfel_position", np.nan, (0, 0))
    res = cli("run", seq, "--map", path, "--out", tmp_path / "out", "--no-progress")
    assert_one_line(res, 2, str(path), "surfel_position")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(("row", "fragment"), [("2.0 nan 0 0 0 0 0 1", "line 3: non-finite value"),
                                               ("2.0 0 0 inf 0 0 0 1", "line 3: non-finite value"),
                                               ("2.0 0 0 0 0 0 0 0", "line 3: zero quaternion"),
                                               ("1.0 0 0 0 0 0 0 1", "duplicate timestamp 1.000000 (lines 2 and 3)")])
def test_trajectory_values_are_checked(tmp_path, row, fragment):
    from surfelslam.errors import InputError
    from surfelslam.io.trajectory import read_tum

    path = tmp_path / "traj.txt"
    path.write_text(f"# t tx ty tz qx qy qz qw\n1.0 0 0 0 0 0 0 1\n{row}\n")
    with pytest.raises(InputError) as exc:
        read_tum(path)
    assert str(exc.value).startswith(str(path)) and fragment in str(exc.value)
