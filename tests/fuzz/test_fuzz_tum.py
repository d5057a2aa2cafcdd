"""Fuzzing the TUM layout's text files (``rgb.txt``, ``depth.txt``, ``associations.txt``, ``groundtruth.txt``) and the
folder metadata (``INFO.txt``, ``camera-intrinsics.txt``): ``open_sequence`` and every frame, on mutated and random
files. The property: a valid sequence or one line of error (fuzzkit)."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from fuzzkit import copy_seed, is_error, make_tum_seed, open_and_check, text_or_bytes, unchanged

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
    from surfelslam.datasets import DatasetOptions

    from fuzzkit import outcome

    options = outcome(lambda: DatasetOptions(intrinsics=intrinsics, depth_scale=depth_scale, start=start, end=end,
                                             stride=stride, downsample=downsample))
    if is_error(options):
        return
    with unchanged(tum_seed):
        open_and_check(tum_seed, options=options)
