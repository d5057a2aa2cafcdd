"""Fuzzing the PNG and JPEG frame readers: mutated and random files through the image readers, and a mutated frame
inside a sequence (the opening probes the first depth image; a bad frame is a one-line FrameError)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from fuzzkit import (
    SEED_H,
    SEED_W,
    copy_seed,
    is_error,
    make_tum_seed,
    mutated_bytes,
    open_and_check,
    outcome,
    seed_images,
    unchanged,
)
from hypothesis import given
from hypothesis import strategies as st

from surfelslam.errors import FrameError
from surfelslam.io.images import read_depth_raw, read_rgb

_RGB, _DEPTH = seed_images(1, seed=7)[0]
#: encoded seed images: colour PNG, JPEG, grey PNG, 16-bit depth PNG
SEEDS = {
    "colour.png": cv2.imencode(".png", _RGB)[1].tobytes(),
    "colour.jpg": cv2.imencode(".jpg", _RGB)[1].tobytes(),
    "grey.png": cv2.imencode(".png", _RGB[:, :, 0])[1].tobytes(),
    "depth.png": cv2.imencode(".png", _DEPTH)[1].tobytes(),
}


def _check_rgb(path: Path) -> None:
    img = outcome(lambda: read_rgb(path))
    if is_error(img):
        assert isinstance(img, FrameError), type(img)
        return
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3 and img.size > 0


def _check_depth(path: Path) -> None:
    img = outcome(lambda: read_depth_raw(path))
    if is_error(img):
        assert isinstance(img, FrameError), type(img)
        return
    assert img.ndim == 2 and img.size > 0 and img.dtype != np.uint8


@given(name=st.sampled_from(sorted(SEEDS)), data=st.data())
def test_mutated_image_files(tmp_path, name, data):
    path = tmp_path / f"m-{name}"
    path.write_bytes(data.draw(mutated_bytes(SEEDS[name]), label=name))
    with unchanged(tmp_path):
        _check_rgb(path)
        _check_depth(path)


@given(content=st.binary(max_size=300), ext=st.sampled_from((".png", ".jpg", ".tiff", "")))
def test_random_image_files(tmp_path, content, ext):
    path = tmp_path / f"random{ext}"
    path.write_bytes(content)
    with unchanged(tmp_path):
        _check_rgb(path)
        _check_depth(path)


@pytest.fixture(scope="module")
def tum_seed(tmp_path_factory) -> Path:
    return make_tum_seed(tmp_path_factory.mktemp("seed") / "seq")


@pytest.fixture(scope="module")
def jpeg_seed(tmp_path_factory) -> Path:
    return make_tum_seed(tmp_path_factory.mktemp("seed") / "jpeg", colour_ext=".jpg")


@given(data=st.data(), frame=st.integers(0, 3), which=st.sampled_from(("rgb", "depth")), jpeg=st.booleans())
def test_mutated_frame_in_a_sequence(tum_seed, jpeg_seed, tmp_path, data, frame, which, jpeg):
    root = copy_seed(jpeg_seed if jpeg else tum_seed, tmp_path)
    path = sorted((root / which).iterdir())[frame]
    path.write_bytes(data.draw(mutated_bytes(path.read_bytes())))
    with unchanged(root):
        open_and_check(root)


@given(shape=st.tuples(st.integers(1, 40), st.integers(1, 40)), channels=st.sampled_from((0, 1, 3, 4)),
       dtype=st.sampled_from(("uint8", "uint16", "float32")), which=st.sampled_from(("rgb", "depth")),
       ext=st.sampled_from((".png", ".tiff")))
def test_frame_of_another_size_or_type(tum_seed, tmp_path, shape, channels, dtype, which, ext):
    """A frame whose image is valid but of another size, channel count or pixel type than the sequence's."""
    root = copy_seed(tum_seed, tmp_path)
    path = sorted((root / which).iterdir())[1]
    img = np.full(shape if channels == 0 else (*shape, channels), 7, dtype)
    written = tmp_path / f"frame{ext}"
    if not cv2.imwrite(str(written), img):
        return  # a combination OpenCV does not write
    written.replace(path)  # the index still names the .png
    with unchanged(root):
        seq = open_and_check(root)
    if not is_error(seq) and shape != (SEED_H, SEED_W):
        assert len(seq) == 4
