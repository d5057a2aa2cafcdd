"""Bad input gives one clear line naming the file and the problem, exit code 2, no traceback."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from surfelslam.datasets import LAYOUTS, DatasetOptions, open_sequence, require_ground_truth
from surfelslam.errors import ConfigError, DatasetError, FrameError, GroundTruthError
from surfelslam.io.images import write_png_depth, write_png_rgb

from helpers import command_app

W, H = 8, 6


def info_app():
    """A CLI holding only ``info``."""
    return command_app("info")


def run_info(*args):
    return CliRunner().invoke(info_app(), ["info", *map(str, args)])


def assert_one_line_error(res, *fragments: str) -> str:
    """Exit 2, exactly one non-empty line on stderr containing every fragment, no traceback."""
    assert res.exit_code == 2, f"exit {res.exit_code}: {res.output}"
    assert isinstance(res.exception, SystemExit)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    assert "Traceback" not in res.output
    for frag in fragments:
        assert frag in lines[0], f"{frag!r} not in {lines[0]!r}"
    return lines[0]


def make_tum(root: Path, n: int = 3, gt: bool = True, dt_s: float = 1 / 30) -> Path:
    root.mkdir(parents=True)
    (root / "rgb").mkdir()
    (root / "depth").mkdir()
    rng = np.random.default_rng(1)
    t = 10.0 + dt_s * np.arange(n)
    for ti in t:
        write_png_rgb(root / f"rgb/{ti:.6f}.png", rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        write_png_depth(root / f"depth/{ti:.6f}.png", np.full((H, W), 5000, np.uint16))
    (root / "rgb.txt").write_text("# rgb\n" + "".join(f"{ti:.6f} rgb/{ti:.6f}.png\n" for ti in t))
    (root / "depth.txt").write_text("# depth\n" + "".join(f"{ti:.6f} depth/{ti:.6f}.png\n" for ti in t))
    if gt:
        (root / "groundtruth.txt").write_text("".join(f"{ti:.6f} 0 0 0 0 0 0 1\n" for ti in t))
    return root


def test_missing_rgb_txt(tmp_path):
    root = make_tum(tmp_path / "seq")
    (root / "rgb.txt").unlink()
    assert_one_line_error(run_info(root), str(root / "rgb.txt"), "rgb.txt not found")


def test_missing_depth_txt(tmp_path):
    root = make_tum(tmp_path / "seq")
    (root / "depth.txt").unlink()
    assert_one_line_error(run_info(root), str(root / "depth.txt"), "not found")


def test_empty_folder(tmp_path):
    (tmp_path / "empty").mkdir()
    assert_one_line_error(run_info(tmp_path / "empty"), str(tmp_path / "empty"), "empty")


def test_missing_folder(tmp_path):
    assert_one_line_error(run_info(tmp_path / "nope"), str(tmp_path / "nope"), "not found")


def test_empty_index_file(tmp_path):
    root = make_tum(tmp_path / "seq")
    (root / "depth.txt").write_text("# depth maps\n# nothing here\n")
    assert_one_line_error(run_info(root), str(root / "depth.txt"), "no frames")


def test_malformed_line_reports_line_number(tmp_path):
    root = make_tum(tmp_path / "seq")
    lines = (root / "rgb.txt").read_text().splitlines()
    lines[2] = "ten rgb/x.png"
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    assert_one_line_error(run_info(root), str(root / "rgb.txt"), "line 3", "not a number")
    lines[2] = "10.5"
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    assert_one_line_error(run_info(root), str(root / "rgb.txt"), "line 3", "expected 'timestamp filename'")


def test_duplicate_timestamp(tmp_path):
    root = make_tum(tmp_path / "seq")
    lines = (root / "depth.txt").read_text().splitlines()
    (root / "depth.txt").write_text("\n".join([*lines, lines[1]]) + "\n")
    assert_one_line_error(run_info(root), str(root / "depth.txt"), "duplicate timestamp", "lines 2 and 5")


def test_timestamps_with_no_match(tmp_path):
    root = make_tum(tmp_path / "seq")
    rows = [ln.split() for ln in (root / "depth.txt").read_text().splitlines()[1:]]
    (root / "depth.txt").write_text("".join(f"{float(t) + 0.5:.6f} {f}\n" for t, f in rows))
    line = assert_one_line_error(run_info(root), str(root), "no rgb/depth pair within 0.02 s", "nearest gap")
    assert "0.4" in line  # 0.5 s shift minus the 2 frame spacings of 1/30 s: nearest gap 0.433 s


def test_corrupt_png_at_frame_load(tmp_path):
    root = make_tum(tmp_path / "seq")
    seq = open_sequence(root)
    bad = seq.entries[1].depth_path
    bad.write_bytes(b"\x89PNG garbage, not an image" * 3)
    assert seq[0].depth_m.shape == (H, W)
    with pytest.raises(FrameError, match="cannot decode depth image") as exc:
        seq[1]
    assert exc.value.path == bad and exc.value.index == 1 and str(bad) in str(exc.value)
    bad_rgb = seq.entries[2].rgb_path
    bad_rgb.write_bytes(np.random.default_rng(0).bytes(64))
    with pytest.raises(FrameError, match="cannot decode colour image"):
        seq[2]


def test_corrupt_png_via_cli(tmp_path):
    root = make_tum(tmp_path / "seq")
    first_rgb = root / "rgb" / sorted(p.name for p in (root / "rgb").iterdir())[0]
    first_rgb.write_bytes(b"garbage")
    assert_one_line_error(run_info(root), str(first_rgb), "cannot decode colour image")
    first_depth = root / "depth" / sorted(p.name for p in (root / "depth").iterdir())[0]
    first_depth.write_bytes(b"garbage")
    assert_one_line_error(run_info(root), str(first_depth), "cannot decode depth image")


def test_depth_of_wrong_size(tmp_path):
    root = make_tum(tmp_path / "seq")
    seq = open_sequence(root)
    bad = seq.entries[1].depth_path
    write_png_depth(bad, np.full((H + 2, W), 5000, np.uint16))
    with pytest.raises(FrameError, match=f"image is {W}x{H + 2}, expected {W}x{H}"):
        seq[1]
    assert_one_line_error(run_info(root, "--start", "1"), str(bad), f"expected {W}x{H}")


def test_missing_ground_truth(tmp_path):
    root = make_tum(tmp_path / "seq", gt=False)
    res = run_info(root, "--json")
    assert res.exit_code == 0, res.output
    d = json.loads(res.stdout)
    assert d["ground_truth_poses"] == 0 and d["frames_with_ground_truth"] == 0
    seq = open_sequence(root)
    assert seq.ground_truth is None
    with pytest.raises(GroundTruthError, match=str(root)):
        require_ground_truth(seq)


def test_ground_truth_not_overlapping_frames(tmp_path):
    root = make_tum(tmp_path / "seq")
    (root / "groundtruth.txt").write_text("500.0 0 0 0 0 0 0 1\n501.0 0 0 0 0 0 0 1\n")
    seq = open_sequence(root)
    assert seq.info()["frames_with_ground_truth"] == 0
    with pytest.raises(GroundTruthError, match="no frame has a ground-truth pose"):
        require_ground_truth(seq)


def test_malformed_ground_truth(tmp_path):
    root = make_tum(tmp_path / "seq")
    (root / "groundtruth.txt").write_text("# c\n10.0 0 0 0 0 0 0 1\n10.1 0 0 0\n")
    assert_one_line_error(run_info(root), str(root / "groundtruth.txt"), "line 3")


def test_unknown_layout_lists_known_layouts(tmp_path):
    root = tmp_path / "photos"
    root.mkdir()
    (root / "notes.txt").write_text("hello")
    line = assert_one_line_error(run_info(root), str(root), "not a known RGB-D sequence layout")
    for name, cls in LAYOUTS.items():
        assert f"{name}: {cls.expects}" in line
    with pytest.raises(DatasetError):
        open_sequence(root)


def test_plain_folder_without_camera_names_the_flags(tmp_path):
    root = tmp_path / "capture"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    write_png_rgb(root / "rgb/0.png", np.zeros((H, W, 3), np.uint8))
    write_png_depth(root / "depth/0.png", np.full((H, W), 1000, np.uint16))
    assert_one_line_error(run_info(root), str(root), "--intrinsics fx,fy,cx,cy", "--depth-scale")
    res = run_info(root, "--intrinsics", "5,5,3.5,2.5", "--depth-scale", "1000", "--json")
    assert res.exit_code == 0 and json.loads(res.stdout)["layout"] == "folder"


def test_folder_without_common_numbers(tmp_path):
    root = tmp_path / "capture"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    write_png_rgb(root / "rgb/0.png", np.zeros((H, W, 3), np.uint8))
    write_png_depth(root / "depth/7.png", np.full((H, W), 1000, np.uint16))
    assert_one_line_error(run_info(root, "--intrinsics", "5,5,3.5,2.5", "--depth-scale", "1000"),
                          str(root), "share no image number")


def test_bad_options(tmp_path):
    root = make_tum(tmp_path / "seq")
    assert_one_line_error(run_info(root, "--intrinsics", "1,2,3"), "--intrinsics", "four numbers")
    assert_one_line_error(run_info(root, "--stride", "0"), "--stride")
    assert_one_line_error(run_info(root, "--start", "7"), "keeps no frame")
    with pytest.raises(ConfigError):
        DatasetOptions(downsample=0)


def test_wrong_depth_scale_is_visible(tmp_path):
    root = make_tum(tmp_path / "seq")  # raw 5000 = 1 m at the TUM scale
    res = run_info(root, "--depth-scale", "100", "--json")
    d = json.loads(res.stdout)
    assert d["first_frame_median_depth_m"] == pytest.approx(50.0)
    assert "is the depth scale right" in d["depth_scale_warning"]
    res = run_info(root)
    assert res.exit_code == 0 and "median 1.000 m" in res.stdout
