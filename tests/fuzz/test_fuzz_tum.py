"""Fuzzing the TUM layout's text files (``rgb.txt``, ``depth.txt``, ``associations.txt``, ``groundtruth.txt``) and the
folder metadata (``INFO.txt``, ``camera-intrinsics.txt``): ``open_sequence`` and every frame, on mutated and random
files. The property: a valid sequence or one line of error (fuzzkit)."""

from __future__ import annotations

from pathlib import Path

import pytest
from fuzzkit import copy_seed, is_error, make_tum_seed, open_and_check, text_or_bytes, unchanged
from hypothesis import given
from hypothesis import strategies as st

TUM_FILES = ("rgb.txt", "depth.txt", "groundtruth.txt", "INFO.txt")
#: a 7-Scenes style camera matrix (fx 14 px on the 16x12 seed images)
CAMERA_MATRIX = "14.0 0 7.5\n0 14.0 5.5\n0 0 1\n"


@pytest.fixture(scope="module")
def tum_seed(tmp_path_factory) -> Path:
    return make_tum_seed(tmp_path_factory.mktemp("seed") / "rgbd_dataset_freiburg1_fuzz")


@pytest.fixture(scope="module")
def assoc_seed(tmp_path_factory) -> Path:
    return make_tum_seed(tmp_path_factory.mktemp("seed") / "assoc", associations=True)


def test_seed_is_valid(tum_seed, assoc_seed):
    """The seeds themselves open with every frame (else the fuzzing below would only test error paths)."""
    for seed in (tum_seed, assoc_seed):
        seq = open_and_check(seed)
        assert not is_error(seq), seq
        assert len(seq) == 4 and seq.ground_truth is not None and seq.gt_poses()[1].all()


@given(data=st.data(), name=st.sampled_from(TUM_FILES))
def test_mutated_index_files(tum_seed, tmp_path, data, name):
    root = copy_seed(tum_seed, tmp_path)
    (root / name).write_bytes(data.draw(text_or_bytes((root / name).read_text()), label=name))
    with unchanged(root):
        open_and_check(root)


@given(data=st.data(), names=st.sets(st.sampled_from(TUM_FILES), min_size=2, max_size=3))
def test_several_files_mutated_at_once(tum_seed, tmp_path, data, names):
    root = copy_seed(tum_seed, tmp_path)
    for name in sorted(names):
        (root / name).write_bytes(data.draw(text_or_bytes((root / name).read_text()), label=name))
    with unchanged(root):
        open_and_check(root)


@given(data=st.data(), name=st.sampled_from(("associations.txt", "groundtruth.txt")))
def test_mutated_associations(assoc_seed, tmp_path, data, name):
    root = copy_seed(assoc_seed, tmp_path)
    (root / name).write_bytes(data.draw(text_or_bytes((root / name).read_text()), label=name))
    with unchanged(root):
        open_and_check(root)


@given(content=st.one_of(st.binary(max_size=200), st.text(max_size=200).map(str.encode)),
       name=st.sampled_from(("rgb.txt", "depth.txt", "associations.txt", "groundtruth.txt", "INFO.txt")))
def test_random_index_file(tum_seed, tmp_path, content, name):
    root = copy_seed(tum_seed, tmp_path)
    (root / name).write_bytes(content)
    with unchanged(root):
        open_and_check(root)


@given(data=st.data())
def test_mutated_camera_matrix(tum_seed, tmp_path, data):
    """``camera-intrinsics.txt`` gives the camera when ``INFO.txt`` has none."""
    root = copy_seed(tum_seed, tmp_path)
    (root / "INFO.txt").write_text("depth scale : 5000\n")
    (root / "camera-intrinsics.txt").write_bytes(data.draw(text_or_bytes(CAMERA_MATRIX)))
    with unchanged(root):
        open_and_check(root)


@given(start=st.integers(-2, 6), end=st.one_of(st.none(), st.integers(-1, 8)), stride=st.integers(-1, 5),
       downsample=st.integers(-1, 20), depth_scale=st.one_of(st.none(), st.floats()),
       intrinsics=st.one_of(st.none(), st.tuples(st.floats(), st.floats(), st.floats(), st.floats())))
def test_dataset_options(tum_seed, tmp_path, start, end, stride, downsample, depth_scale, intrinsics):
    """The dataset options (``--start``, ``--intrinsics`` ...) with any values: a valid selection or one line."""
    from fuzzkit import outcome

    from surfelslam.datasets import DatasetOptions

    options = outcome(lambda: DatasetOptions(intrinsics=intrinsics, depth_scale=depth_scale, start=start, end=end,
                                             stride=stride, downsample=downsample))
    if is_error(options):
        return
    with unchanged(tum_seed):
        open_and_check(tum_seed, options=options)


_INTR = "intrinsics : fx=14 fy=14 cx=7.5 cy=5.5\n"
#: extreme values, each a find of the fuzzing (a RuntimeWarning on stderr beside the result) or a neighbour of one
EXTREMES = {
    "stamps_overflow_differences": {"rgb.txt": "1e308 rgb/a.png\n-1e308 rgb/b.png\n",
                                    "depth.txt": "1e308 depth/a.png\n-1e308 depth/b.png\n"},
    "gt_stamps_overflow_differences": {"groundtruth.txt": "-1e308 0 0 0 0 0 0 1\n1e308 0 0 0 0 0 0 1\n"},
    "subnormal_depth_scale": {"INFO.txt": _INTR + "depth scale : 1e-320\n"},
    "depth_scale_beyond_float32": {"INFO.txt": _INTR + "depth scale : 1e300\n"},
    "huge_focal_length": {"INFO.txt": "intrinsics : fx=1e308 fy=1e308 cx=7.5 cy=5.5\ndepth scale : 5000\n"},
    "subnormal_focal_length": {"INFO.txt": "intrinsics : fx=1e-320 fy=1e-320 cx=7.5 cy=5.5\ndepth scale : 5000\n"},
    "extreme_colour_camera": {"INFO.txt": _INTR + "depth scale : 5000\ncolour intrinsics : fx=1e-320 fy=1e308 cx=0 "
                                                   "cy=0\ncolour translation : 1e308 -1e308 0\n"},
    "huge_ground_truth_positions": {"groundtruth.txt": "1305031102.17 1e308 1e308 1e308 0 0 0 1\n"
                                                       "1305031102.2 -1e308 0 0 0 0 0 1\n"},
}


@pytest.mark.parametrize("name", sorted(EXTREMES))
def test_extreme_values(tum_seed, tmp_path, name):
    root = copy_seed(tum_seed, tmp_path)
    for file, text in EXTREMES[name].items():
        (root / file).write_text(text)
    with unchanged(root):
        open_and_check(root)


@pytest.mark.parametrize("depth_scale", [1e-320, 1e-38, 1e300])
def test_extreme_depth_scale_option(tum_seed, depth_scale):
    """--depth-scale at the ends of the float range (found: divide-by-zero and cast-overflow warnings)."""
    from surfelslam.datasets import DatasetOptions

    open_and_check(tum_seed, options=DatasetOptions(depth_scale=depth_scale))
