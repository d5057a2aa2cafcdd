"""Bag header stamps a driver did not set, repeated or going backwards: counted and reported as warnings, never
silently dropped; unusable stamps are replaced by the bag's record times."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from surfelslam.datasets import DatasetOptions, open_sequence
from surfelslam.datasets.rosbag import CAMERA_INFO, IMAGE, seconds_to_stamp
from surfelslam.datasets.rosbag.stamps import stamp_faults, usable_mask
from surfelslam.errors import DatasetError

N_FRAMES = 30
RATE_HZ = 30.0
T0_S = 100.0
SIDE_PX = 4
OPTIONS = DatasetOptions(intrinsics=(4.0, 4.0, 2.0, 2.0))


def _bag(path: Path, header_s, K: list[float] | None = None, gt_s: list[float] | None = None,
         gt_x: list[float] | None = None) -> Path:
    """A ROS 1 bag of ``N_FRAMES`` 4x4 colour + depth pairs recorded at 30 Hz; ``header_s(k)``: the header stamp of
    pair ``k`` (depth value ``k + 1`` mm tells the frames apart); ``K``: a camera info message with this matrix;
    ``gt_s``: identity ground-truth poses at these header stamps (``gt_x``: their x, default 0)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types

    def image(t: float, enc: str, data: bytes, step: int):
        sec, nsec = seconds_to_stamp(t)
        header = T["std_msgs/msg/Header"](seq=0, stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec),
                                          frame_id="cam")
        return T[IMAGE](header=header, height=SIDE_PX, width=SIDE_PX, encoding=enc, is_bigendian=0, step=step,
                        data=np.frombuffer(data, np.uint8))

    with Writer(path) as w:
        c = w.add_connection("/camera/color/image_raw", IMAGE, typestore=ts)
        d = w.add_connection("/camera/depth/image_raw", IMAGE, typestore=ts)
        for k in range(N_FRAMES):
            log_ns = int(round((T0_S + k / RATE_HZ) * 1e9))
            t = header_s(k)
            w.write(c, log_ns, ts.serialize_ros1(image(t, "mono8", bytes(16), 4), IMAGE))
            depth = np.full(16, k + 1, "<u2").tobytes()
            w.write(d, log_ns, ts.serialize_ros1(image(t, "16UC1", depth, 8), IMAGE))
        if K is not None:
            i = w.add_connection("/camera/depth/camera_info", CAMERA_INFO, typestore=ts)
            roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
            header = image(T0_S, "mono8", bytes(16), 4).header
            msg = T[CAMERA_INFO](header=header, height=SIDE_PX, width=SIDE_PX, distortion_model="plumb_bob",
                                 D=np.zeros(5), K=np.asarray(K, np.float64), R=np.eye(3).reshape(-1),
                                 P=np.zeros(12), binning_x=0, binning_y=0, roi=roi)
            w.write(i, int(T0_S * 1e9), ts.serialize_ros1(msg, CAMERA_INFO))
        if gt_s is not None:
            pose_type = "geometry_msgs/msg/PoseStamped"
            g = w.add_connection("/ground_truth/pose", pose_type, typestore=ts)
            for k, t in enumerate(gt_s):
                x = 0.0 if gt_x is None else gt_x[k]
                pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=0.0, z=0.0),
                                                   orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0,
                                                                                               w=1.0))
                msg = T[pose_type](header=image(t, "mono8", bytes(16), 4).header, pose=pose)
                w.write(g, int((T0_S + k / RATE_HZ) * 1e9), ts.serialize_ros1(msg, pose_type))
    return path


def _depth_mm(seq, i: int) -> float:
    return float(seq[i].depth_m[0, 0]) * 1000.0


def test_zero_stamps_take_record_times(tmp_path):
    """A driver that leaves every header stamp at zero: 30 frames at the record times, and a warning (it was
    '1 processed, 0 skipped' before: 29 frames vanished as repeated stamps)."""
    seq = open_sequence(_bag(tmp_path / "zero.bag", lambda k: 0.0), OPTIONS, plausibility="warn")
    assert len(seq) == N_FRAMES
    assert seq.timestamps[0] == pytest.approx(T0_S) and seq.timestamps[-1] == pytest.approx(T0_S + 29 / RATE_HZ)
    assert [_depth_mm(seq, i) for i in (0, 7, 29)] == pytest.approx([1.0, 8.0, 30.0])
    note = [w for w in seq.warnings if "record times" in w]
    assert len(note) == 1 and "zero.bag" in note[0]
    assert f"{N_FRAMES - 1} of {N_FRAMES} repeat an earlier stamp, {N_FRAMES} of {N_FRAMES} stamps zero" in note[0]


def test_repeated_stamps_are_counted(tmp_path):
    """Two of 30 colour/depth pairs repeat the previous stamp (below the unusable fraction): left out, counted."""
    stamps = [T0_S + k / RATE_HZ for k in range(N_FRAMES)]
    stamps[5], stamps[20] = stamps[4], stamps[19]
    seq = open_sequence(_bag(tmp_path / "rep.bag", lambda k: stamps[k]), OPTIONS, plausibility="warn")
    assert len(seq) == N_FRAMES - 2
    left = [w for w in seq.warnings if "left out" in w]
    assert len(left) == 2 and all("2 of 30 messages left out" in w and "repeat an earlier stamp" in w for w in left)
    assert _depth_mm(seq, 5) == pytest.approx(7.0)  # frame 5 (depth 6) left out: the 6th frame is pair 6


def test_backwards_stamps_are_reported(tmp_path):
    """Pairs 10 and 11 recorded in swapped stamp order: every frame kept, in stamp order, and a warning."""
    stamps = [T0_S + k / RATE_HZ for k in range(N_FRAMES)]
    stamps[10], stamps[11] = stamps[11], stamps[10]
    seq = open_sequence(_bag(tmp_path / "back.bag", lambda k: stamps[k]), OPTIONS, plausibility="warn")
    assert len(seq) == N_FRAMES and np.all(np.diff(seq.timestamps) > 0)
    assert [_depth_mm(seq, i) for i in (10, 11)] == pytest.approx([12.0, 11.0])
    back = [w for w in seq.warnings if "earlier than" in w]
    assert len(back) == 2 and all("1 of 30 messages" in w for w in back)
    assert not [w for w in seq.warnings if "left out" in w or "record times" in w]


def test_stamp_fault_counts():
    assert stamp_faults([0.0, 0.0, 1.0, 1.0, 0.5, 2.0]) == {"zero": 2, "repeated": 2, "backwards": 1}
    assert stamp_faults([0.0, 1.0, 2.0]) == {"zero": 0, "repeated": 0, "backwards": 0}  # a sequence starting at 0
    assert usable_mask([0.0, 1.0, 1.0, 0.5]).tolist() == [True, True, False, True]


@pytest.mark.parametrize("K", [[np.nan, 0, 2, 0, 4, 2, 0, 0, 1], [-4, 0, 2, 0, 4, 2, 0, 0, 1],
                               [4, 0, np.inf, 0, 4, 2, 0, 0, 1]])
def test_camera_info_must_be_a_finite_camera(tmp_path, K):
    path = _bag(tmp_path / "info.bag", lambda k: T0_S + k / RATE_HZ, K)
    with pytest.raises(DatasetError, match="camera info topic /camera/depth/camera_info: K = .* --intrinsics"):
        open_sequence(path, DatasetOptions(), plausibility="warn")
    good = _bag(tmp_path / "good.bag", lambda k: T0_S + k / RATE_HZ, [4, 0, 2, 0, 4, 2, 0, 0, 1])
    assert open_sequence(good, DatasetOptions(), plausibility="warn").intrinsics.fx == 4.0


def test_repeated_ground_truth_stamps_are_counted(tmp_path):
    gt = [T0_S + k / RATE_HZ for k in range(N_FRAMES)]
    gt[3] = gt[2]
    seq = open_sequence(_bag(tmp_path / "gt.bag", lambda k: T0_S + k / RATE_HZ, gt_s=gt), OPTIONS,
                        plausibility="warn")
    assert len(seq.ground_truth) == N_FRAMES - 1
    assert [w for w in seq.warnings if "/ground_truth/pose: 1 of 30 poses repeat an earlier header stamp" in w]


def test_non_finite_ground_truth_poses_are_left_out_and_counted(tmp_path):
    gt = [T0_S + k / RATE_HZ for k in range(N_FRAMES)]
    x = [0.0] * N_FRAMES
    x[4] = x[9] = float("nan")
    seq = open_sequence(_bag(tmp_path / "nan.bag", lambda k: T0_S + k / RATE_HZ, gt_s=gt, gt_x=x), OPTIONS,
                        plausibility="warn")
    assert len(seq.ground_truth) == N_FRAMES - 2 and np.isfinite(seq.ground_truth.T_world_cam).all()
    assert [w for w in seq.warnings if "/ground_truth/pose: 2 of 30 poses are not finite" in w]
