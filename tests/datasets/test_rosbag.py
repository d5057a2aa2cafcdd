"""ROS bags and MCAP files as sequences: written from a synthetic folder with rosbags' own writers, they give the
folder's frames and trajectory bit for bit; broken bags, missing topics and unsupported encodings are one line."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from surfelslam.api import run_sequence
from surfelslam.cli import app
from surfelslam.datasets import DatasetOptions, open_sequence
from surfelslam.datasets.rosbag import (
    COMPRESSED,
    IMAGE,
    choose_topics,
    decode_depth,
    seconds_to_stamp,
    stamp_seconds,
)
from surfelslam.datasets.rosbag.write import write_bag
from surfelslam.errors import DatasetError
from surfelslam.slam import SlamConfig
from surfelslam.synth.writer import generate_sequence

runner = CliRunner()


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    """10 frames of the synthetic room at 160x120."""
    return generate_sequence(tmp_path_factory.mktemp("bag") / "seq", "room", "slow", 10, "kinect", 0, 160, 120)


@pytest.fixture(scope="module")
def bags(folder) -> dict[str, Path]:
    base = folder.parent
    out = {fmt: write_bag(open_sequence(folder), base / name, fmt)
           for fmt, name in (("ros1", "rec.bag"), ("ros2", "rec_db3"), ("mcap", "rec_mcap"))}
    out["plain_mcap"] = base / "rec_mcap" / "rec_mcap.mcap"  # the MCAP file alone, without metadata.yaml
    return out


def _frames_equal(a, b) -> None:
    assert len(a) == len(b)
    for i in range(len(a)):
        fa, fb = a[i], b[i]
        assert fa.timestamp == fb.timestamp and fa.depth_timestamp == fb.depth_timestamp
        assert np.array_equal(fa.rgb, fb.rgb) and np.array_equal(fa.depth_m, fb.depth_m)


@pytest.mark.slow
def test_bag_trajectories_are_the_folders(folder, bags, tmp_path):
    """ROS 1, ROS 2 (SQLite), ROS 2 (MCAP) and the plain MCAP file: same frames, same camera, same ground truth
    and a trajectory byte-identical to the folder run's."""
    ref = open_sequence(folder)
    run_sequence(ref, tmp_path / "folder", SlamConfig(), "dense", progress=False, figures=False)
    expected = (tmp_path / "folder" / "trajectory.txt").read_bytes()
    for fmt, path in bags.items():
        seq = open_sequence(path)
        assert seq.layout == "rosbag" and seq.intrinsics == ref.intrinsics, fmt
        assert seq.rgb_topic == "/camera/color/image_raw"
        assert seq.depth_topic == "/camera/aligned_depth_to_color/image_raw"
        assert seq.camera_info_topic == "/camera/color/camera_info"
        assert np.allclose(seq.ground_truth.T_world_cam, ref.ground_truth.T_world_cam, atol=1e-12)
        assert np.array_equal(seq.ground_truth.timestamps, ref.ground_truth.timestamps)
        if fmt == "ros1":
            _frames_equal(ref, seq)
        run_sequence(seq, tmp_path / fmt, SlamConfig(), "dense", progress=False, figures=False)
        assert (tmp_path / fmt / "trajectory.txt").read_bytes() == expected, fmt


@pytest.mark.slow
@pytest.mark.parametrize("colour, depth, scale", [("bgr8", "16UC1", 5000.0), ("png", "compressedDepth", 5000.0)])
def test_encodings_give_the_same_frames(folder, tmp_path, colour, depth, scale):
    """bgr8 and PNG colour, 16-bit depth in raw units (read with the folder's --depth-scale), and compressedDepth
    PNG behind its 12-byte header."""
    path = write_bag(open_sequence(folder, DatasetOptions(end=3)), tmp_path / "x.bag", "ros1", colour_encoding=colour,
                     depth_encoding=depth)
    _frames_equal(open_sequence(folder, DatasetOptions(end=3)), open_sequence(path, DatasetOptions(depth_scale=scale)))


@pytest.mark.slow
def test_jpeg_colour_and_millimetre_default(folder, tmp_path):
    path = write_bag(open_sequence(folder, DatasetOptions(end=2)), tmp_path / "j", "mcap", colour_encoding="jpeg",
                     depth_encoding="16UC1")
    seq = open_sequence(path)
    ref = open_sequence(folder)
    assert seq.depth_scale == 1000.0  # 16-bit depth without --depth-scale: millimetres
    f, g = seq[1], ref[1]
    assert f.rgb.shape == g.rgb.shape and np.corrcoef(f.rgb.ravel(), g.rgb.ravel())[0, 1] > 0.95  # lossy
    assert np.allclose(f.depth_m * 1000 / 5000, g.depth_m, atol=1e-6)


@pytest.mark.slow
def test_info_lists_topics_rates_and_camera(bags):
    res = runner.invoke(app, ["info", str(bags["ros2"]), "--json"])
    assert res.exit_code == 0, res.output
    d = json.loads(res.output)
    assert d["layout"] == "rosbag" and d["bag_format"] == "ROS 2 bag (sqlite3)" and d["frames"] == 10
    topics = {t["topic"]: t for t in d["topics"]}
    assert topics["/camera/color/image_raw"]["role"] == "colour"
    assert topics["/camera/aligned_depth_to_color/image_raw"]["count"] == 10
    assert topics["/camera/color/camera_info"]["rate_hz"] == pytest.approx(30.0, rel=1e-3)
    assert topics["/ground_truth/pose"]["role"] == "ground_truth"
    assert d["intrinsics_source"] == "camera info topic /camera/color/camera_info"
    res = runner.invoke(app, ["info", str(bags["ros1"])])
    assert res.exit_code == 0 and "/camera/color/image_raw" in res.output


@pytest.mark.slow
def test_cli_run_on_a_bag_with_a_selection(bags, tmp_path):
    out = tmp_path / "run"
    res = runner.invoke(app, ["run", str(bags["ros1"]), "--out", str(out), "--no-progress", "--no-figures",
                              "--end", "4", "--rgb-topic", "/camera/color/image_raw"])
    assert res.exit_code == 0, res.output
    assert len([ln for ln in (out / "trajectory.txt").read_text().splitlines() if not ln.startswith("#")]) == 4
    assert 'rgb_topic = "/camera/color/image_raw"' in (out / "config.toml").read_text()


# --- errors: one line naming the file and topic ---------------------------------------------------------------------

def _one_line_error(args: list[str]) -> str:
    res = runner.invoke(app, args)
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), res.output
    return lines[0]


@pytest.mark.slow
@pytest.mark.parametrize("which", ["ros1", "ros2", "plain_mcap"])
def test_truncated_bag_is_one_line(bags, tmp_path, which):
    src = bags[which] if which != "ros2" else next(bags["ros2"].glob("*.db3"))
    data = src.read_bytes()
    cut = tmp_path / f"cut{src.suffix}"
    cut.write_bytes(data[: len(data) * 2 // 3])
    line = _one_line_error(["info", str(cut)])
    assert str(cut) in line and "truncated" in line


@pytest.mark.slow
def test_missing_topic_is_one_line(bags):
    line = _one_line_error(["info", str(bags["ros1"]), "--depth-topic", "/camera/depth/nope"])
    assert "/camera/depth/nope" in line and "no such topic" in line and "/camera/color/image_raw" in line


@pytest.mark.slow
def test_no_depth_topic_names_the_option(folder, tmp_path):
    path = write_bag(open_sequence(folder, DatasetOptions(end=2)), tmp_path / "nd.bag", "ros1",
                     depth_topic="/camera/aligned/image_raw")
    line = _one_line_error(["info", str(path)])
    assert "no depth image topic" in line and "--depth-topic" in line
    seq = open_sequence(path, DatasetOptions(depth_topic="/camera/aligned/image_raw"))
    assert len(seq) == 2


def _bag_with_colour_encoding(path: Path, encoding: str) -> Path:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types

    def header(t: float):
        sec, nsec = seconds_to_stamp(t)
        return T["std_msgs/msg/Header"](seq=0, stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec),
                                        frame_id="cam")

    def image(t, enc, data, step):
        return T[IMAGE](header=header(t), height=4, width=4, encoding=enc, is_bigendian=0, step=step,
                        data=np.frombuffer(data, np.uint8))

    with Writer(path) as w:
        c = w.add_connection("/camera/color/image_raw", IMAGE, typestore=ts)
        d = w.add_connection("/camera/depth/image_raw", IMAGE, typestore=ts)
        for k in range(3):
            t = 1.0 + k / 30
            w.write(c, int(t * 1e9), ts.serialize_ros1(image(t, encoding, bytes(32), 8), IMAGE))
            w.write(d, int(t * 1e9), ts.serialize_ros1(image(t, "16UC1", np.full(16, 1000, "<u2").tobytes(), 8),
                                                       IMAGE))
    return path


def test_unsupported_encoding_is_one_line(tmp_path):
    path = _bag_with_colour_encoding(tmp_path / "yuv.bag", "yuv422")
    line = _one_line_error(["info", str(path), "--intrinsics", "4,4,2,2"])
    assert "/camera/color/image_raw" in line and "yuv422" in line and str(path) in line


def test_no_camera_info_asks_for_intrinsics(tmp_path):
    path = _bag_with_colour_encoding(tmp_path / "noinfo.bag", "mono8")
    line = _one_line_error(["info", str(path)])
    assert "--intrinsics" in line and "camera info" in line
    seq = open_sequence(path, DatasetOptions(intrinsics=(4, 4, 2, 2)), plausibility="warn")
    assert seq[0].rgb.shape == (4, 4, 3) and float(seq[0].depth_m[0, 0]) == 1.0  # mono8 colour, 16UC1 in mm


@pytest.mark.slow
def test_gt_file_replaces_ground_truth(folder, tmp_path):
    gt = tmp_path / "gt.txt"
    gt.write_text("0.0 1 2 3 0 0 0 1\n0.033333 1 2 3 0 0 0 1\n")
    seq = open_sequence(folder, DatasetOptions(gt=str(gt)))
    assert len(seq.ground_truth) == 2 and seq.ground_truth.T_world_cam[0, 0, 3] == 1.0
    with pytest.raises(DatasetError, match="--gt"):
        open_sequence(folder, DatasetOptions(gt=str(tmp_path / "none.txt")))


# --- units ----------------------------------------------------------------------------------------------------------

def test_stamps_round_trip_exactly():
    for t in (0.0, 0.033333, 1305031102.175304, 1700000000.123456789, 12.5):
        assert stamp_seconds(*seconds_to_stamp(t)) == t


def test_topic_choice_on_realsense_names(tmp_path):
    types = {"/camera/color/image_raw": IMAGE, "/camera/color/image_raw/compressed": COMPRESSED,
             "/camera/depth/image_rect_raw": IMAGE, "/camera/aligned_depth_to_color/image_raw": IMAGE,
             "/camera/infra1/image_rect_raw": IMAGE, "/camera/color/camera_info": "sensor_msgs/msg/CameraInfo",
             "/camera/aligned_depth_to_color/camera_info": "sensor_msgs/msg/CameraInfo",
             "/camera/depth/camera_info": "sensor_msgs/msg/CameraInfo"}
    rgb, depth, info, notes = choose_topics(types, DatasetOptions(), tmp_path)
    assert (rgb, depth, info) == ("/camera/color/image_raw", "/camera/aligned_depth_to_color/image_raw",
                                  "/camera/aligned_depth_to_color/camera_info")
    assert any("--depth-topic" in n for n in notes)
    rgb, depth, info, _ = choose_topics(types, DatasetOptions(depth_topic="/camera/depth/image_rect_raw"), tmp_path)
    assert info == "/camera/depth/camera_info"


def test_compressed_depth_32fc1_inverse_quantisation():
    """compressedDepth of float depth: PNG of v = A / d + B behind the header (A, B: its two floats)."""
    A, B = 100.0, 0.5
    d = np.array([[1.0, 2.0], [0.0, 4.0]], np.float32)
    v = np.where(d > 0, A / np.where(d > 0, d, 1) + B, 0).round().astype(np.uint16)
    ok, png = cv2.imencode(".png", v)
    head = np.array([0], "<i4").tobytes() + np.array([A, B], "<f4").tobytes()
    msg = SimpleNamespace(format="32FC1; compressedDepth png", data=np.frombuffer(head + png.tobytes(), np.uint8))
    out = decode_depth(msg, COMPRESSED)
    assert out.dtype == np.float32 and out[1, 0] == 0
    assert np.allclose(out[d > 0], A / (v[d > 0] - B), rtol=1e-6)
