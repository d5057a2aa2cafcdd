"""Fuzzing the ROS bag and MCAP reader: byte mutations of a ROS 1 bag, an MCAP file, a ROS 2 SQLite bag and its
``metadata.yaml``; and valid bags holding strange messages (NaN / infinite / negative depth, unsorted and repeated
stamps, colour and depth of different sizes, a broken camera matrix), written with the project's own writers."""

from __future__ import annotations

import types
from pathlib import Path

import numpy as np
import pytest
from fuzzkit import (
    SEED_H,
    SEED_W,
    check_trajectory,
    copy_seed,
    example_dir,
    is_error,
    make_tum_seed,
    mutated_bytes,
    open_and_check,
    outcome,
    text_or_bytes,
    unchanged,
)
from hypothesis import example, given
from hypothesis import strategies as st

from surfelslam.datasets import open_sequence
from surfelslam.datasets.rosbag import POSE_TYPES
from surfelslam.datasets.rosbag.decode import pose_matrix
from surfelslam.datasets.rosbag.write import BagRecorder, write_bag


@pytest.fixture(scope="module")
def bag_seeds(tmp_path_factory) -> dict[str, Path]:
    """The seed sequence as a ROS 1 bag, a plain MCAP file and a ROS 2 SQLite bag folder."""
    base = tmp_path_factory.mktemp("bags")
    folder = make_tum_seed(base / "seq")
    mcap_dir = write_bag(open_sequence(folder), base / "mcap", "mcap")
    return {"ros1": write_bag(open_sequence(folder), base / "seq.bag", "ros1"),
            "mcap": next(mcap_dir.glob("*.mcap")),
            "ros2": write_bag(open_sequence(folder), base / "db3", "ros2")}


def test_seeds_are_valid(bag_seeds):
    for path in bag_seeds.values():
        seq = open_and_check(path)
        assert not is_error(seq), seq
        assert len(seq) == 4 and seq.ground_truth is not None


@given(data=st.data(), fmt=st.sampled_from(("ros1", "mcap")))
def test_mutated_bag_file(bag_seeds, tmp_path, data, fmt):
    path = copy_seed(bag_seeds[fmt], tmp_path)
    path.write_bytes(data.draw(mutated_bytes(path.read_bytes(), max_ops=3)))
    with unchanged(path.parent):
        open_and_check(path)


@given(data=st.data(), which=st.sampled_from(("metadata.yaml", "db3")))
def test_mutated_ros2_bag_folder(bag_seeds, tmp_path, data, which):
    root = copy_seed(bag_seeds["ros2"], tmp_path)
    if which == "metadata.yaml":
        path = root / which
        path.write_bytes(data.draw(text_or_bytes(path.read_text())))
    else:
        path = next(root.glob("*.db3"))
        path.write_bytes(data.draw(mutated_bytes(path.read_bytes(), max_ops=3)))
    with unchanged(root):
        open_and_check(root)


@given(content=st.binary(max_size=300), suffix=st.sampled_from((".bag", ".mcap", ".db3")))
def test_random_bag_file(tmp_path, content, suffix):
    path = example_dir(tmp_path) / f"random{suffix}"
    path.write_bytes(content)
    with unchanged(path.parent):
        open_and_check(path)


_STAMP = st.floats(0.0, 2e9, allow_nan=False).map(lambda t: round(t, 6))
_DEPTH_VALUE = st.sampled_from((np.nan, np.inf, -np.inf, -1.0, 0.0, 1e-30, 1.5, 1e30))
_INTRINSIC = st.sampled_from((np.nan, np.inf, -np.inf, 0.0, -14.0, 14.0, 7.5, 1e12))


@st.composite
def recorded_frames(draw: st.DrawFn) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """2-5 frames ``(rgb, depth_m, stamp)``: stamps anywhere (repeated, unsorted), depth with special values,
    sometimes a frame of another size."""
    n = draw(st.integers(2, 5))
    first = draw(_STAMP)
    stamps = draw(st.lists(st.one_of(st.just(first), _STAMP, st.integers(0, 4).map(lambda k: first + k / 30)),
                           min_size=n, max_size=n))
    frames = []
    for t in stamps:
        h, w = draw(st.sampled_from(((SEED_H, SEED_W), (SEED_H, SEED_W), (SEED_H, SEED_W), (SEED_H + 1, SEED_W),
                                     (1, 1))))
        depth = np.full((h, w), 1.5, np.float32)
        for _ in range(draw(st.integers(0, 3))):
            depth[draw(st.integers(0, h - 1)), draw(st.integers(0, w - 1))] = draw(_DEPTH_VALUE)
        if draw(st.booleans()):
            depth[:] = draw(_DEPTH_VALUE)
        frames.append((np.full((h, w, 3), 99, np.uint8), depth, t))
    return frames


@given(frames=recorded_frames(), camera=st.tuples(_INTRINSIC, _INTRINSIC, _INTRINSIC, _INTRINSIC),
       size=st.sampled_from(((SEED_W, SEED_H), (0, 0), (SEED_W + 3, SEED_H))), fmt=st.sampled_from(("ros1", "mcap")))
def test_strange_messages(tmp_path, frames, camera, size, fmt):
    """A bag as a camera driver might write it on a bad day: the reader gives valid frames or one line."""
    out = example_dir(tmp_path) / ("rec.bag" if fmt == "ros1" else "rec")
    intr = types.SimpleNamespace(fx=camera[0], fy=camera[1], cx=camera[2], cy=camera[3], width=size[0],
                                 height=size[1])
    rec = BagRecorder(out, intr, fmt)
    for rgb, depth, t in frames:
        rec(rgb, depth, t)
    rec.close()
    with unchanged(out.parent):
        open_and_check(out)


_POSE_VALUE = st.one_of(st.sampled_from((0.0, -0.0, 1.0, np.nan, np.inf, -np.inf, 1e200, -1e200, 1e-320, 1e155)),
                        st.floats())


@given(position=st.tuples(_POSE_VALUE, _POSE_VALUE, _POSE_VALUE),
       quaternion=st.tuples(_POSE_VALUE, _POSE_VALUE, _POSE_VALUE, _POSE_VALUE),
       msgtype=st.sampled_from(POSE_TYPES))
@example(position=(0.0, 0.0, 0.0), quaternion=(0.0, 0.0, 0.0, 0.0), msgtype=POSE_TYPES[0])  # found: NaN pose
@example(position=(0.0, 0.0, 0.0), quaternion=(1e200, 0.0, 0.0, 1e200), msgtype=POSE_TYPES[0])  # found: overflow
def test_ground_truth_pose_messages(position, quaternion, msgtype):
    """A bag's ground-truth pose message with any values: a rigid pose, or all NaN (a zero or non-finite pose, which
    the indexer leaves out and counts), or a ValueError (which opening the bag turns into one line naming the
    message)."""
    p = types.SimpleNamespace(x=position[0], y=position[1], z=position[2])
    q = types.SimpleNamespace(x=quaternion[0], y=quaternion[1], z=quaternion[2], w=quaternion[3])
    pose = types.SimpleNamespace(position=p, orientation=q)
    msg = types.SimpleNamespace(pose=types.SimpleNamespace(pose=pose, position=p, orientation=q),
                                transform=types.SimpleNamespace(translation=p, rotation=q))
    try:
        T = outcome(lambda: pose_matrix(msg, msgtype))
    except ValueError as exc:
        assert "\n" not in str(exc)
        return
    if np.isnan(T).all():
        return
    check_trajectory(types.SimpleNamespace(timestamps=np.zeros(1), T_world_cam=T[None]))


@pytest.mark.parametrize("name", ["123", "[1, 2]", "null", "{a: 1}"])
def test_topic_name_that_is_not_text(bag_seeds, tmp_path, name):
    """Found: a ROS 2 metadata.yaml whose topic name reads as a number gave an AttributeError (int.rstrip)."""
    root = copy_seed(bag_seeds["ros2"], tmp_path)
    meta = root / "metadata.yaml"
    text = meta.read_text()
    assert "name: /camera/color/image_raw" in text
    meta.write_text(text.replace("name: /camera/color/image_raw", f"name: {name}"))
    with unchanged(root):
        open_and_check(root)
