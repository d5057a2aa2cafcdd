"""Dataset adapters: layout detection, metadata precedence, options, and geometric consistency of the real data."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from surfelslam.datasets import (
    LAYOUTS,
    DatasetOptions,
    check_depth_scale,
    detect_layout,
    open_sequence,
    require_ground_truth,
)
from surfelslam.datasets.metadata import parse_depth_scale_text, parse_intrinsics_text, read_info_fields
from surfelslam.datasets.tum import associate
from surfelslam.errors import ConfigError, DatasetError, GroundTruthError
from surfelslam.geometry.camera import backproject, project, round_in_image
from surfelslam.io.images import write_png_depth, write_png_rgb
from surfelslam.types import Intrinsics, RGBDFrame

from helpers import command_app, shared_sequence

W, H = 8, 6


def info_app():
    """A CLI holding only ``info``."""
    return command_app("info")


def run_info(*args: str):
    return CliRunner().invoke(info_app(), ["info", *map(str, args)])


# --------------------------------------------------------------------------------------------- fixtures
def write_frame(root: Path, rgb_name: str, depth_name: str, depth_raw: int = 5000, shape=(H, W)) -> None:
    (root / rgb_name).parent.mkdir(parents=True, exist_ok=True)
    (root / depth_name).parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(len(rgb_name))
    write_png_rgb(root / rgb_name, rng.integers(0, 255, (*shape, 3), dtype=np.uint8))
    write_png_depth(root / depth_name, np.full(shape, depth_raw, dtype=np.uint16))


def make_tum(root: Path, n: int = 10, dt_s: float = 1 / 30, gt: bool = True, info: str | None = None) -> Path:
    """A tiny TUM-layout sequence: n frames of 8x6, depth 1 m (raw 5000), GT moving along x."""
    root.mkdir(parents=True, exist_ok=True)
    t = 100.0 + dt_s * np.arange(n)
    rgb_lines, depth_lines, gt_lines = ["# color images"], ["# depth maps"], ["# timestamp tx ty tz qx qy qz qw"]
    for i, ti in enumerate(t):
        write_frame(root, f"rgb/{ti:.6f}.png", f"depth/{ti:.6f}.png")
        rgb_lines.append(f"{ti:.6f} rgb/{ti:.6f}.png")
        depth_lines.append(f"{ti:.6f} depth/{ti:.6f}.png")
        gt_lines.append(f"{ti:.6f} {0.01 * i} 0 0 0 0 0 1")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if gt:
        (root / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    if info is not None:
        (root / "INFO.txt").write_text(info)
    return root


# --------------------------------------------------------------------------------------------- real data
SHARED_EXPECTED = {
    # folder: (layout, frames, (fx, fy, cx, cy), depth scale) -- values from each folder's INFO.txt
    "7scenes_redkitchen_0000_0499": ("7scenes", 500, (585.0, 585.0, 320.0, 240.0), 1000.0),
    "tum_fr1_xyz_lucassheng_4f": ("tum", 3, (517.3, 516.5, 318.6, 255.3), 5000.0),
    "icl_lr_kt0_slambook2_5f": ("icl", 5, (481.2, -480.0, 319.5, 239.5), 5000.0),
    "redwood_aug_icl_lr1_open3d_5f": ("tum", 5, (525.0, 525.0, 319.5, 239.5), 1000.0),
}


@pytest.mark.shared
@pytest.mark.parametrize("name", sorted(SHARED_EXPECTED))
def test_info_agrees_with_shared_info_txt(name):
    layout, frames, intr, scale = SHARED_EXPECTED[name]
    res = run_info(shared_sequence(name), "--json")
    assert res.exit_code == 0, res.output
    d = json.loads(res.stdout)
    assert d["layout"] == layout
    assert d["frames"] == frames and d["frames_total"] == frames
    assert d["resolution"] == [640, 480]
    assert [d["intrinsics"][k] for k in ("fx", "fy", "cx", "cy")] == pytest.approx(intr)
    assert d["depth_scale"] == scale
    assert d["ground_truth_poses"] >= frames
    assert d["frames_with_ground_truth"] == frames
    assert 0.5 < d["first_frame_median_depth_m"] < 4.0
    assert d["depth_scale_warning"] is None


@pytest.mark.shared
def test_shared_layout_defaults_match_info_txt_values():
    """Without INFO.txt the name-based defaults give the same camera (checked on the parsed INFO values)."""
    from surfelslam.datasets.icl import ICL_DEPTH_SCALE, ICL_INTRINSICS
    from surfelslam.datasets.sevenscenes import SEVENSCENES_DEPTH_SCALE, SEVENSCENES_INTRINSICS
    from surfelslam.datasets.tum import TUM_INTRINSICS

    assert SHARED_EXPECTED["7scenes_redkitchen_0000_0499"][2:] == (SEVENSCENES_INTRINSICS, SEVENSCENES_DEPTH_SCALE)
    assert SHARED_EXPECTED["icl_lr_kt0_slambook2_5f"][2:] == (ICL_INTRINSICS, ICL_DEPTH_SCALE)
    assert SHARED_EXPECTED["tum_fr1_xyz_lucassheng_4f"][2] == TUM_INTRINSICS["1"]


def warp_median_dz_m(seq, i: int, j: int, T_world_cam: np.ndarray | None = None) -> tuple[float, int]:
    """Median |z_warped - z_j| (m) of frame i's depth warped into frame j, nearest-surface z-buffered."""
    fi, fj = seq[i], seq[j]
    intr = seq.intrinsics
    T = seq.gt_poses()[0] if T_world_cam is None else T_world_cam
    T_j_i = np.linalg.inv(T[j]) @ T[i]
    pts = backproject(fi.depth_m, intr)[fi.depth_m > 0].astype(np.float64)
    pts_j = pts @ T_j_i[:3, :3].T + T_j_i[:3, 3]
    u, v, z = project(pts_j, intr)
    ui, vi, inside = round_in_image(u, v, intr)
    inside &= z > 0
    flat = vi[inside] * intr.width + ui[inside]
    zbuf = np.full(intr.width * intr.height, np.inf)
    np.minimum.at(zbuf, flat, z[inside])
    dj = fj.depth_m.reshape(-1).astype(np.float64)
    both = np.isfinite(zbuf) & (dj > 0)
    return float(np.median(np.abs(zbuf[both] - dj[both]))), int(both.sum())


CONSISTENT_PAIRS = [
    ("7scenes_redkitchen_0000_0499", 0, 10),
    ("7scenes_redkitchen_0000_0499", 0, 30),
    ("redwood_aug_icl_lr1_open3d_5f", 0, 1),
    ("redwood_aug_icl_lr1_open3d_5f", 1, 2),
    ("tum_fr1_xyz_lucassheng_4f", 0, 1),
    ("tum_fr1_xyz_lucassheng_4f", 1, 2),
    ("icl_lr_kt0_slambook2_5f", 0, 4),  # GT ids 2 -> 1201
]


@pytest.mark.shared
@pytest.mark.parametrize("name,i,j", CONSISTENT_PAIRS)
def test_gt_poses_and_intrinsics_agree_with_depth(name, i, j):
    seq = open_sequence(shared_sequence(name))
    _, valid = seq.gt_poses()
    assert valid[i] and valid[j]
    med, n = warp_median_dz_m(seq, i, j)
    assert n > 20_000
    assert med < 0.015, f"{name} {i}->{j}: median |dz| {1000 * med:.1f} mm"


@pytest.mark.shared
def test_consistency_check_detects_wrong_pose_or_wrong_fy_sign():
    """The warp test above can fail: identity poses or a positive ICL fy give large residuals."""
    seq = open_sequence(shared_sequence("7scenes_redkitchen_0000_0499"), DatasetOptions(end=31))
    med, _ = warp_median_dz_m(seq, 0, 30, T_world_cam=np.tile(np.eye(4), (len(seq), 1, 1)))
    assert med > 0.03
    icl = open_sequence(
        shared_sequence("icl_lr_kt0_slambook2_5f"), DatasetOptions(intrinsics=(481.2, 480.0, 319.5, 239.5))
    )
    med, _ = warp_median_dz_m(icl, 0, 4)
    assert med > 0.05


@pytest.mark.shared
def test_shared_options_downsample_and_selection():
    seq = open_sequence(shared_sequence("7scenes_redkitchen_0000_0499"), DatasetOptions(start=10, end=50, stride=4,
                                                                                         downsample=2))
    assert len(seq) == 10 and len(seq.all_entries) == 500
    assert seq.timestamps[0] == pytest.approx(10 / 30, abs=1e-5)
    f = seq[1]
    assert f.index == 1 and f.timestamp == pytest.approx(14 / 30, abs=1e-5)
    assert f.depth_m.shape == (240, 320) and f.rgb.shape == (240, 320, 3)
    assert seq.intrinsics.as_tuple() == (292.5, 292.5, 160.0, 120.0)
    assert seq.full_intrinsics.as_tuple() == (585.0, 585.0, 320.0, 240.0)
    T, valid = seq.gt_poses()
    assert valid.all()
    assert np.allclose(T[1], open_sequence(shared_sequence("7scenes_redkitchen_0000_0499")).gt_poses()[0][14])


# --------------------------------------------------------------------------------------------- options
def test_options_start_end_stride_downsample(tmp_path):
    root = make_tum(tmp_path / "seq", n=10)
    full = open_sequence(root)
    assert full.layout == "tum" and len(full) == 10
    seq = open_sequence(root, DatasetOptions(start=2, end=9, stride=3, downsample=2))
    assert len(seq) == 3 and len(seq.all_entries) == 10
    assert np.allclose(seq.timestamps, full.timestamps[[2, 5, 8]])
    f = seq[2]
    assert f.index == 2 and f.timestamp == pytest.approx(full.timestamps[8])
    assert f.depth_m.shape == (3, 4) and f.rgb.shape == (3, 4, 3)
    assert np.allclose(f.depth_m, 1.0)
    assert seq.intrinsics.as_tuple() == pytest.approx((525 / 2, 525 / 2, 319.5 / 2, 239.5 / 2))
    assert (seq.intrinsics.width, seq.intrinsics.height) == (4, 3)
    T, valid = seq.gt_poses()
    assert valid.all() and np.allclose(T[:, 0, 3], [0.02, 0.05, 0.08])
    assert [fr.index for fr in seq] == [0, 1, 2]
    with pytest.raises(IndexError):
        seq[3]


def test_downsampled_frame_is_the_full_frame_subsampled(tmp_path):
    """Downsampling keeps every f-th pixel of the converted frame: depth in metres, invalid raw values (0, and the
    layout's invalid codes) at 0, colour as read; the conversion is done on the kept pixels only, same values."""
    root = make_tum(tmp_path / "seq", n=2)
    rng = np.random.default_rng(5)
    raw = rng.integers(1, 20000, (H, W)).astype(np.uint16)
    raw[0, 0], raw[2, 4], raw[1, 1] = 0, 0, 0  # invalid, two of them kept by a stride of 2
    raw[4, 2] = 65535
    depth_file = sorted((root / "depth").iterdir())[0]
    write_png_depth(depth_file, raw)
    full = open_sequence(root)
    full.depth_invalid_raw = (0, 65535)
    half = open_sequence(root, DatasetOptions(downsample=2))
    half.depth_invalid_raw = (0, 65535)
    f, h = full[0], half[0]
    assert h.depth_m.shape == (3, 4) and h.depth_m.dtype == np.float32 and h.depth_m.flags.c_contiguous
    assert np.array_equal(h.depth_m, f.depth_m[::2, ::2]) and np.array_equal(h.rgb, f.rgb[::2, ::2])
    assert h.depth_m[0, 0] == 0 and h.depth_m[1, 2] == 0 and h.depth_m[2, 1] == 0 and h.rgb.flags.c_contiguous
    assert h.depth_m[0, 1] == np.float32(raw[0, 2]) / np.float32(5000)


def test_selection_with_no_frames_is_a_config_error(tmp_path):
    root = make_tum(tmp_path / "seq", n=3)
    with pytest.raises(ConfigError, match="keeps no frame"):
        open_sequence(root, DatasetOptions(start=5))


def test_intrinsics_and_depth_scale_options_override_everything(tmp_path):
    root = make_tum(tmp_path / "rgbd_dataset_freiburg2_desk", n=2,
                    info="intrinsics : fx=600 fy=601 cx=4 cy=3\ndepth scale : 1000\n")
    seq = open_sequence(root, DatasetOptions(intrinsics=(700.0, 701.0, 3.5, 2.5), depth_scale=2500.0))
    assert seq.full_intrinsics.as_tuple() == (700.0, 701.0, 3.5, 2.5)
    assert seq.depth_scale == 2500.0 and np.allclose(seq[0].depth_m, 2.0)
    assert seq.intrinsics_source == "--intrinsics" and seq.depth_scale_source == "--depth-scale"


# --------------------------------------------------------------------------------------------- metadata
ICL_INFO_TEXT = """short name      : x
intrinsics      : fx=481.2 fy=-480.0 cx=319.5 cy=239.5 (ICL-NUIM convention, NEGATIVE fy). Checked: warping
                  frames gives 7 mm with fy=-480, but 80-470 mm with fy=+480.
depth scale     : 1000 (MILLIMETRES, not the TUM 5000). 0 = invalid
                  although 65535 is also masked.
generator       : surfelslam synth
"""


def test_info_txt_parsing(tmp_path):
    (tmp_path / "INFO.txt").write_text(ICL_INFO_TEXT)
    fields = read_info_fields(tmp_path / "INFO.txt")
    assert parse_intrinsics_text(fields["intrinsics"]) == (481.2, -480.0, 319.5, 239.5)
    assert parse_depth_scale_text(fields["depth scale"]) == 1000.0
    assert fields["generator"] == "surfelslam synth"
    assert parse_intrinsics_text("500 501 320.5 240") == (500.0, 501.0, 320.5, 240.0)
    assert parse_intrinsics_text("unknown") is None


def test_metadata_precedence_over_name_defaults(tmp_path):
    plain = open_sequence(make_tum(tmp_path / "rgbd_dataset_freiburg2_desk", n=2))
    assert plain.full_intrinsics.as_tuple() == (520.9, 521.0, 325.1, 249.7)
    assert plain.depth_scale == 5000.0 and "freiburg2" in plain.intrinsics_source
    fr3 = open_sequence(make_tum(tmp_path / "tum_fr3_office", n=2))
    assert fr3.layout == "tum"  # 'office' of a TUM name is not ICL
    assert fr3.full_intrinsics.as_tuple() == (535.4, 539.2, 320.1, 247.6)
    ros = open_sequence(make_tum(tmp_path / "mystery", n=2))
    assert ros.full_intrinsics.as_tuple() == (525.0, 525.0, 319.5, 239.5)
    meta = open_sequence(make_tum(tmp_path / "rgbd_dataset_freiburg1_x", n=2,
                                  info="intrinsics : fx=600 fy=601 cx=4 cy=3\ndepth scale : 1000 (mm)\n"))
    assert meta.full_intrinsics.as_tuple() == (600.0, 601.0, 4.0, 3.0)
    assert meta.depth_scale == 1000.0 and np.allclose(meta[0].depth_m, 5.0)
    assert meta.intrinsics_source.endswith("INFO.txt")


def test_camera_intrinsics_txt_is_read(tmp_path):
    root = make_tum(tmp_path / "seq", n=2)
    np.savetxt(root / "camera-intrinsics.txt", np.array([[585.0, 0, 3.5], [0, 586.0, 2.5], [0, 0, 1]]))
    assert open_sequence(root).full_intrinsics.as_tuple() == (585.0, 586.0, 3.5, 2.5)


# --------------------------------------------------------------------------------------------- layouts
def test_synthetic_layout_from_generator_line(tmp_path):
    root = make_tum(tmp_path / "synth_room", n=3, info=(
        "generator       : surfelslam synth\nintrinsics      : fx=10 fy=10 cx=3.5 cy=2.5\ndepth scale     : 5000\n"))
    seq = open_sequence(root)
    assert seq.layout == "synthetic" and detect_layout(root) == "synthetic"
    assert seq.full_intrinsics.as_tuple() == (10.0, 10.0, 3.5, 2.5)


def test_icl_by_name_keeps_negative_fy_and_redwood_is_tum(tmp_path):
    icl = open_sequence(make_tum(tmp_path / "living_room_traj0_frei_png", n=2))
    assert icl.layout == "icl" and icl.full_intrinsics.as_tuple() == (481.2, -480.0, 319.5, 239.5)
    assert icl.depth_scale == 5000.0
    assert detect_layout(make_tum(tmp_path / "redwood_aug_icl_lr1", n=2)) == "tum"


def test_sevenscenes_native_layout(tmp_path):
    scene = tmp_path / "chess"
    folder = scene / "seq-01"
    for n in range(3):
        write_frame(folder, f"frame-{n:06d}.color.png", f"frame-{n:06d}.depth.png", depth_raw=1500)
        T = np.eye(4)
        T[0, 3] = 0.01 * n
        np.savetxt(folder / f"frame-{n:06d}.pose.txt", T)
    raw = np.full((H, W), 1500, np.uint16)
    raw[0, 0] = 65535
    write_png_depth(folder / "frame-000001.depth.png", raw)
    for path in (folder, scene):
        seq = open_sequence(path)
        assert seq.layout == "7scenes" and seq.root == folder and len(seq) == 3
        assert np.allclose(seq.timestamps, np.arange(3) / 30)
        assert seq.full_intrinsics.as_tuple() == (585.0, 585.0, 320.0, 240.0) and seq.depth_scale == 1000.0
        d = seq[1].depth_m
        assert d[0, 0] == 0.0 and np.allclose(d.reshape(-1)[1:], 1.5)
        T, valid = seq.gt_poses()
        assert valid.all() and np.allclose(T[:, 0, 3], [0, 0.01, 0.02])
    (scene / "seq-02").mkdir()
    write_frame(scene / "seq-02", "frame-000000.color.png", "frame-000000.depth.png")
    with pytest.raises(DatasetError, match="seq-01, seq-02"):
        open_sequence(scene)


def test_sevenscenes_tum_copy_masks_65535(tmp_path):
    root = make_tum(tmp_path / "7scenes_chess", n=2)
    raw = np.full((H, W), 1000, np.uint16)
    raw[1, 2] = 65535
    seq = open_sequence(root)
    write_png_depth(seq.entries[0].depth_path, raw)
    assert seq.layout == "7scenes"
    d = seq[0].depth_m
    assert d[1, 2] == 0 and (d > 0).sum() == W * H - 1 and np.allclose(d[d > 0], 1.0)


def test_renamed_kitchen_copy_is_known_by_its_info(tmp_path):
    """A TUM-layout copy of 7-Scenes under another name is still 7-Scenes (colour not registered to depth) when its
    INFO.txt says so; a TUM folder whose INFO.txt does not, or a generated one that mentions it, is not."""
    root = make_tum(tmp_path / "kitchen_0500_0999", n=2)
    assert detect_layout(root) == "tum"
    (root / "INFO.txt").write_text("original dataset: Microsoft 7-Scenes, scene redkitchen\n"
                                   "depth scale : 1000\n")
    seq = open_sequence(root)
    assert seq.layout == "7scenes" and not seq.colour_registered
    (root / "INFO.txt").write_text("generator : surfelslam synth\nnote : a room like 7-Scenes\n")
    assert detect_layout(root) != "7scenes"


def test_plain_folder_needs_camera_from_options_or_info(tmp_path):
    root = tmp_path / "capture"
    for n in (2, 10, 1):  # numeric, not lexicographic, order
        write_frame(root, f"rgb/img_{n}.png", f"depth/img_{n}.png", depth_raw=2000)
    with pytest.raises(ConfigError, match="--intrinsics.*--depth-scale"):
        open_sequence(root)
    seq = open_sequence(root, DatasetOptions(intrinsics=(5.0, 5.0, 3.5, 2.5), depth_scale=1000.0))
    assert seq.layout == "folder" and seq.ground_truth is None
    assert [e.rgb_path.name for e in seq.entries] == ["img_1.png", "img_2.png", "img_10.png"]
    assert np.allclose(seq.timestamps, np.array([1, 2, 10]) / 30)
    assert np.allclose(seq[0].depth_m, 2.0)
    (root / "INFO.txt").write_text("intrinsics : fx=5 fy=5 cx=3.5 cy=2.5\ndepth scale : 1000\n")
    assert open_sequence(root).full_intrinsics.as_tuple() == (5.0, 5.0, 3.5, 2.5)


def test_layouts_registry_order_and_descriptions():
    assert list(LAYOUTS) == ["7scenes", "synthetic", "icl", "tum", "folder", "rosbag"]
    for name, cls in LAYOUTS.items():
        assert cls.layout == name and len(cls.expects) > 10


# --------------------------------------------------------------------------------------------- TUM details
def test_associate_nearest_unique_vectorised():
    t_rgb = np.array([0.0, 0.012, 1.0, 2.0, 3.0])
    t_depth = np.array([0.004, 0.995, 2.5, 3.019])
    ia, ib, gap = associate(t_rgb, t_depth, 0.02)
    # depth 0.004 is nearest to both rgb 0.0 (gap 4 ms) and rgb 0.012 (8 ms): the closer keeps it
    assert ia.tolist() == [0, 2, 4] and ib.tolist() == [0, 1, 3]
    assert gap == pytest.approx(0.004)
    rng = np.random.default_rng(0)
    t_a = np.sort(rng.uniform(0, 100, 3000))
    t_b = np.sort(rng.uniform(0, 100, 2000))
    ia, ib, _ = associate(t_a, t_b, 0.02)
    assert len(np.unique(ib)) == len(ib) and np.all(np.abs(t_a[ia] - t_b[ib]) <= 0.02)
    for a, b in zip(ia[:50], ib[:50], strict=True):  # each pair is the rgb's nearest depth
        assert b == np.argmin(np.abs(t_b - t_a[a]))


def test_tum_unmatched_rgb_dropped_and_unsorted_index_sorted(tmp_path):
    root = make_tum(tmp_path / "seq", n=4)
    lines = (root / "rgb.txt").read_text().splitlines()
    (root / "rgb.txt").write_text("\n".join([lines[0], lines[3], lines[1], lines[4], lines[2]]) + "\n")
    depth_lines = (root / "depth.txt").read_text().splitlines()
    (root / "depth.txt").write_text("\n".join(depth_lines[:-1]) + "\n")  # last rgb has no depth
    seq = open_sequence(root)
    assert len(seq) == 3 and np.all(np.diff(seq.timestamps) > 0)
    assert seq.info()["frames_with_ground_truth"] == 3


def test_associations_used_when_index_files_absent(tmp_path):
    root = make_tum(tmp_path / "seq", n=3)
    rows = [ln.split() for ln in (root / "rgb.txt").read_text().splitlines()[1:]]
    # ICL-NUIM order: the depth pair first
    (root / "associations.txt").write_text("".join(f"{t} {f.replace('rgb', 'depth')} {t} {f}\n" for t, f in rows))
    (root / "depth.txt").unlink()
    seq = open_sequence(root)
    assert len(seq) == 3 and seq.entries[1].depth_path.parent.name == "depth"
    assert seq.entries[1].rgb_path.parent.name == "rgb" and np.allclose(seq[1].depth_m, 1.0)


def test_ground_truth_helpers(tmp_path):
    seq = open_sequence(make_tum(tmp_path / "seq", n=3))
    assert len(require_ground_truth(seq)) == 3
    no_gt = open_sequence(make_tum(tmp_path / "nogt", n=3, gt=False))
    assert no_gt.ground_truth is None and no_gt.info()["frames_with_ground_truth"] == 0
    with pytest.raises(GroundTruthError, match="no ground truth"):
        require_ground_truth(no_gt)


def test_check_depth_scale():
    def frame(z):
        return RGBDFrame(0, 0.0, np.zeros((H, W, 3), np.uint8), np.full((H, W), z, np.float32))

    assert check_depth_scale(frame(1.5)) is None
    msg = check_depth_scale(frame(25.0), depth_scale=1000)
    assert "25" in msg and "1000" in msg
    assert "0.05 m" in check_depth_scale(frame(0.05))
    assert check_depth_scale(frame(0.0)) is not None


def test_intrinsics_downsample_consistency():
    intr = Intrinsics(481.2, -480.0, 319.5, 239.5, 640, 480).scaled(2)
    assert intr.as_tuple() == (240.6, -240.0, 159.75, 119.75) and intr.shape == (240, 320)


def test_trajectory_interpolate_slerp_and_gaps():
    from surfelslam.geometry import se3
    from surfelslam.geometry.interpolation import interpolate_poses
    from surfelslam.types import Trajectory

    R_b = se3.so3_exp(np.array([0.0, 0.0, np.radians(20.0)]))
    T = np.tile(np.eye(4), (3, 1, 1))
    T[1, :3, :3], T[1, :3, 3] = R_b, [0.1, 0.0, 0.0]
    T[2, :3, 3] = [5.0, 0.0, 0.0]
    traj = Trajectory(np.array([0.0, 0.01, 1.0]), T)
    Ti, ok = interpolate_poses(traj, np.array([0.0025, 0.5, 0.985, 2.0, 1.01]), max_gap_s=0.05, max_dt_s=0.02)
    # a quarter of the way: 2.5 cm and 5 degrees about z
    assert ok[0] and np.allclose(Ti[0, :3, 3], [0.025, 0, 0])
    assert np.isclose(se3.rotation_angle_deg(Ti[0, :3, :3]), 5.0) and Ti[0, 1, 0] > 0
    # inside a 0.99 s gap: no pose within 20 ms -> invalid; near its end: the nearest pose, not an interpolation
    assert not ok[1] and np.allclose(Ti[1], np.eye(4))
    assert ok[2] and np.allclose(Ti[2], T[2])
    assert not ok[3] and ok[4] and np.allclose(Ti[4], T[2])  # beyond the end: nearest within 20 ms only


def test_gt_at_depth_time_uses_depth_stamps(tmp_path):
    """TUM colour and depth stamps differ: the depth-time GT is interpolated at the depth stamp."""
    root = make_tum(tmp_path / "seq", n=4, dt_s=0.03)
    t_rgb = 100.0 + 0.03 * np.arange(4)
    # depth captured 12 ms after colour; GT (1 cm per 30 ms along x) interpolates to +4 mm
    (root / "depth.txt").write_text("".join(f"{t + 0.012:.6f} depth/{t:.6f}.png\n" for t in t_rgb))
    seq = open_sequence(root)
    assert np.allclose(seq.depth_timestamps - seq.timestamps, 0.012)
    T_frame, ok_frame = seq.gt_poses()
    T_depth, ok_depth = seq.gt_poses(at_depth_time=True)
    assert ok_frame.all() and ok_depth[:3].all()
    assert np.allclose(T_frame[:, 0, 3], 0.01 * np.arange(4))
    assert np.allclose(T_depth[:3, 0, 3], 0.01 * np.arange(3) + 0.004)
    # the last depth stamp is beyond the ground truth's end: the nearest pose (12 ms away)
    assert ok_depth[3] and np.isclose(T_depth[3, 0, 3], 0.03)
    # associations.txt keeps both stamps too (TUM associate.py order: rgb first)
    rows = [ln.split() for ln in (root / "rgb.txt").read_text().splitlines()[1:]]
    (root / "associations.txt").write_text("".join(
        f"{t} {f} {float(t) + 0.012:.6f} {f.replace('rgb', 'depth')}\n" for t, f in rows))
    (root / "depth.txt").unlink()
    assert np.allclose(open_sequence(root).depth_timestamps - t_rgb, 0.012)


def test_info_colour_camera_makes_a_separate_colour_camera(tmp_path):
    root = make_tum(tmp_path / "rig", n=3, info="intrinsics : fx=10 fy=10 cx=3.5 cy=2.5\n"
                    "colour intrinsics : fx=9 fy=9.5 cx=3.0 cy=2.0\ncolour translation : -0.025 0.001 0\n")
    seq = open_sequence(root)
    assert not seq.colour_registered
    cam = seq.full_colour_camera
    assert cam.intrinsics.as_tuple() == (9.0, 9.5, 3.0, 2.0) and cam.intrinsics.shape == (H, W)
    assert cam.t_colour_depth_m == (-0.025, 0.001, 0.0)
    half = open_sequence(root, DatasetOptions(downsample=2)).colour_camera
    assert half.intrinsics.as_tuple() == (4.5, 4.75, 1.5, 1.0)
    assert seq.info()["colour_camera"]["t_colour_depth_m"] == [-0.025, 0.001, 0.0]
    plain = open_sequence(make_tum(tmp_path / "plain", n=3))
    assert plain.colour_registered and plain.colour_camera is None and plain.info()["colour_camera"] is None


@pytest.mark.parametrize("info, message", [
    ("colour intrinsics : fx=0 fy=9 cx=3 cy=2\n", "colour intrinsics"),
    ("colour intrinsics : fx=9 fy=9 cx=3 cy=2\ncolour translation : 0.02 0\n", "three numbers"),
    ("colour translation : 0.02 0 0\n", "without 'colour intrinsics'"),
])
def test_info_colour_camera_errors_name_the_file(tmp_path, info, message):
    root = make_tum(tmp_path / "rig", n=3, info="intrinsics : fx=10 fy=10 cx=3.5 cy=2.5\n" + info)
    with pytest.raises(DatasetError, match=message) as exc:
        open_sequence(root)
    assert "INFO.txt" in str(exc.value)


def test_sevenscenes_colour_model_only_for_the_recorded_resolution(tmp_path):
    """The Kinect colour model is for 640x480 images; other sizes (e.g. a resized copy) keep their colour as is."""
    folder = tmp_path / "seq-01"
    for n in range(2):
        write_frame(folder, f"frame-{n:06d}.color.png", f"frame-{n:06d}.depth.png", depth_raw=1500)
    seq = open_sequence(folder)
    assert seq.layout == "7scenes" and not seq.colour_registered and seq.colour_camera is None
    seq7 = open_sequence(shared_sequence("7scenes_redkitchen_0000_0499"), DatasetOptions(downsample=2))
    from surfelslam.datasets.sevenscenes import SEVENSCENES_COLOUR_CAMERA
    assert seq7.colour_camera == SEVENSCENES_COLOUR_CAMERA.scaled(2)
