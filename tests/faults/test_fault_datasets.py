"""Dataset faults: frames that vanish or do not pair, disagreeing stamps, corrupt and truncated frames, a wrong
depth scale or impossible intrinsics. Each is either refused in one line naming the file or option (exit 2), or
skipped and listed with its reason; never silently dropped."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from faultkit import assert_one_line, cli, index_rows

from surfelslam.datasets import DatasetOptions, open_sequence
from surfelslam.errors import FrameError


def _rewrite(path: Path, rows: list[str]) -> None:
    path.write_text("".join(r + "\n" for r in rows))


def _plain_folder(seq: Path, dest: Path) -> Path:
    """The synthetic frames as a plain numbered folder: rgb/<i>.png, depth/<i>.png."""
    (dest / "rgb").mkdir(parents=True)
    (dest / "depth").mkdir()
    for i, row in enumerate(index_rows(seq / "rgb.txt")):
        shutil.copy(seq / row.split()[1], dest / "rgb" / f"{i}.png")
    for i, row in enumerate(index_rows(seq / "depth.txt")):
        shutil.copy(seq / row.split()[1], dest / "depth" / f"{i}.png")
    return dest


FOLDER_CAMERA = ("--intrinsics", "131.25,131.25,79.5,59.5", "--depth-scale", "5000")


# ----------------------------------------------------------------------------------------- frames that vanish
def test_rows_removed_from_depth_txt_are_listed_not_dropped(seq):
    rows = index_rows(seq / "depth.txt")
    _rewrite(seq / "depth.txt", rows[:2] + rows[5:])  # 3 of 10 depth rows gone
    s = open_sequence(seq)
    assert len(s) == 7 and len(s.unpaired) == 3
    names = {u.file.name for u in s.unpaired}
    assert names == {Path(r.split()[1]).name for r in index_rows(seq / "rgb.txt")[2:5]}
    assert all("no depth image within 0.02 s in depth.txt" in u.reason for u in s.unpaired)
    res = cli("info", seq, "--json")
    assert res.exit_code == 0 and json.loads(res.stdout)["images_unpaired"] == 3


def test_rows_removed_from_rgb_txt_list_the_depth_images(seq):
    rows = index_rows(seq / "rgb.txt")
    _rewrite(seq / "rgb.txt", rows[:8])
    s = open_sequence(seq)
    assert len(s) == 8 and [u.file.parent.name for u in s.unpaired] == ["depth", "depth"]
    assert "no colour image within 0.02 s in rgb.txt" in s.unpaired[0].reason
    assert s.unpaired[0].timestamp == pytest.approx(8 / 30, abs=1e-6)


def test_stamps_that_pair_nothing_much_are_refused(seq):
    """depth.txt in milliseconds: 1 of 10 frames would pair."""
    rows = [r.split() for r in index_rows(seq / "depth.txt")]
    _rewrite(seq / "depth.txt", [f"{float(t) * 1000:.6f} {f}" for t, f in rows])
    assert_one_line(cli("info", seq), 2, str(seq), "only 1 rgb/depth pair within 0.02 s", "rgb.txt (10 lines)",
                    "depth.txt (10 lines)", "unpaired: rgb/", "(t=0.033333)")


def test_plain_folder_with_two_depth_files_removed(seq, tmp_path):
    root = _plain_folder(seq, tmp_path / "plain")
    (root / "depth" / "3.png").unlink()
    (root / "depth" / "7.png").unlink()
    s = open_sequence(root, DatasetOptions(intrinsics=(131.25, 131.25, 79.5, 59.5), depth_scale=5000.0))
    assert len(s) == 8
    assert [(u.file.name, u.reason) for u in s.unpaired] == [("3.png", "no image numbered 3 in depth/"),
                                                             ("7.png", "no image numbered 7 in depth/")]


def test_plain_folder_with_most_depth_files_missing_is_refused(seq, tmp_path):
    root = _plain_folder(seq, tmp_path / "plain")
    for i in range(6):
        (root / "depth" / f"{i}.png").unlink()
    assert_one_line(cli("info", root, *FOLDER_CAMERA), 2, str(root), "rgb/ (10 images)", "depth/ (4 images)",
                    "fewer than 50%")


def test_sevenscenes_frame_without_colour_is_listed(seq, tmp_path):
    folder = tmp_path / "chess" / "seq-01"
    folder.mkdir(parents=True)
    for i, (r, d) in enumerate(zip(index_rows(seq / "rgb.txt"), index_rows(seq / "depth.txt"), strict=True)):
        shutil.copy(seq / r.split()[1], folder / f"frame-{i:06d}.color.png")
        shutil.copy(seq / d.split()[1], folder / f"frame-{i:06d}.depth.png")
    (folder / "frame-000004.color.png").unlink()
    (folder / "frame-000009.depth.png").unlink()
    s = open_sequence(folder)
    assert s.layout == "7scenes" and len(s) == 8
    assert sorted(u.file.name for u in s.unpaired) == ["frame-000004.depth.png", "frame-000009.color.png"]
    assert any("--intrinsics" in w for w in s.warnings)  # 7-Scenes' 640x480 default camera on 160x120 images


# ------------------------------------------------------------------------------------------------ timestamps
def test_unsorted_index_is_sorted(seq):
    rows = index_rows(seq / "rgb.txt")
    _rewrite(seq / "rgb.txt", rows[::-1])
    s = open_sequence(seq)
    assert len(s) == 10 and np.all(np.diff(s.timestamps) > 0) and not s.unpaired


def test_duplicate_ground_truth_stamp_names_the_lines(seq):
    gt = (seq / "groundtruth.txt").read_text().splitlines()
    gt.append(gt[3])
    (seq / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    assert_one_line(cli("info", seq), 2, str(seq / "groundtruth.txt"), "duplicate timestamp",
                    f"(lines 4 and {len(gt)})")


def test_duplicate_index_stamp_names_the_lines(seq):
    rows = index_rows(seq / "depth.txt")
    _rewrite(seq / "depth.txt", [*rows, rows[2]])
    assert_one_line(cli("info", seq), 2, str(seq / "depth.txt"), "duplicate timestamp", "lines 3 and 11")


# ----------------------------------------------------------------------------------------- corrupt frames
def test_corrupt_first_frame_does_not_abort_the_open(seq):
    first = seq / index_rows(seq / "depth.txt")[0].split()[1]
    first.write_bytes(b"")
    s = open_sequence(seq)
    assert (s.intrinsics.width, s.intrinsics.height) == (160, 120)
    with pytest.raises(FrameError, match="empty file") as err:
        s[0]
    assert err.value.path == first and err.value.index == 0
    assert s[1].depth_m.shape == (120, 160)
    res = cli("info", seq, "--start", "1", "--json")  # the case: aborted even with --start 1
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["frames"] == 9


def test_truncated_jpeg_frame_is_a_frame_error(seq):
    rows = index_rows(seq / "rgb.txt")
    t, name = rows[4].split()
    jpg = seq / name.replace(".png", ".jpg")
    cv2.imwrite(str(jpg), cv2.imread(str(seq / name)))
    data = jpg.read_bytes()
    jpg.write_bytes(data[: len(data) // 3])
    rows[4] = f"{t} {jpg.relative_to(seq)}"
    _rewrite(seq / "rgb.txt", rows)
    s = open_sequence(seq)
    with pytest.raises(FrameError, match="truncated colour JPEG") as err:
        s[4]
    assert err.value.path == jpg and err.value.index == 4
    assert s[5].rgb.shape == (120, 160, 3)


def test_no_readable_depth_image_at_all(seq):
    for row in index_rows(seq / "depth.txt"):
        (seq / row.split()[1]).write_bytes(b"\x89PNG\r\n\x1a\n broken")
    first = seq / index_rows(seq / "depth.txt")[0].split()[1]
    assert_one_line(cli("info", seq), 2, str(first), "none of the 10 depth images tried")


def test_depth_file_listed_but_missing_is_a_frame_error(seq):
    rows = index_rows(seq / "depth.txt")
    (seq / rows[6].split()[1]).unlink()
    s = open_sequence(seq)
    with pytest.raises(FrameError, match="depth image not found"):
        s[6]


# ------------------------------------------------------------------------------------------ plausibility
# `run` refuses an implausible camera or depth scale (one line naming the option); `info` only warns (below).
def run_cli(seq, *args):
    return cli("run", seq, "--out", str(seq.parent / "run_out"), *args)


@pytest.mark.parametrize("scale, median", [("1", "is 1.2e+04 m"), ("1000000", "is 0.012 m")])
def test_depth_scale_far_off_names_the_option(seq, scale, median):
    line = assert_one_line(run_cli(seq, "--depth-scale", scale), 2, str(seq),
                           f"--depth-scale {scale} units per metre (from --depth-scale)", "outside 0.1-20 m")
    assert "median valid depth" in line and median in line


def test_depth_scale_from_info_txt_is_named_too(seq):
    info = (seq / "INFO.txt").read_text().replace("depth scale     : 5000", "depth scale     : 5")
    (seq / "INFO.txt").write_text(info)
    assert_one_line(run_cli(seq), 2, "--depth-scale 5 units per metre (from INFO.txt)")


def test_empty_depth_everywhere_is_refused(seq):
    for row in index_rows(seq / "depth.txt"):
        cv2.imwrite(str(seq / row.split()[1]), np.zeros((120, 160), np.uint16))
    assert_one_line(run_cli(seq), 2, str(seq), "no valid depth pixel", "--depth-scale 5000")


@pytest.mark.parametrize("intr, what", [
    ("585,585,5000,240", "the principal point (5000, 240) is outside the 160x120 image"),
    ("131,131,-3,60", "the principal point (-3, 60) is outside"),
    ("0.5,131,80,60", "fx = 0.5 px is outside 0.1-100 image widths"),
    ("131,1e9,80,60", "fy = 1000000000 px is outside"),
])
def test_impossible_intrinsics_name_the_option(seq, intr, what):
    assert_one_line(run_cli(seq, "--intrinsics", intr), 2,
                    f"--intrinsics {intr.replace('1e9', '1000000000')}", what)


def test_impossible_intrinsics_in_info_txt_name_the_file(seq):
    info = (seq / "INFO.txt").read_text().replace("cx=79.5", "cx=795")
    (seq / "INFO.txt").write_text(info)
    assert_one_line(run_cli(seq), 2, str(seq / "INFO.txt"), "principal point (795, 59.5)",
                    "override it with --intrinsics")


def test_layout_default_intrinsics_that_do_not_fit_only_warn(seq):
    info = "\n".join(ln for ln in (seq / "INFO.txt").read_text().splitlines() if not ln.startswith("intrinsics"))
    (seq / "INFO.txt").write_text(info + "\n")
    s = open_sequence(seq)
    assert s.intrinsics_kind == "default"
    assert len(s.warnings) == 1 and "give --intrinsics" in s.warnings[0] and "160x120" in s.warnings[0]


def test_info_warns_where_run_refuses(seq):
    res = cli("info", seq, "--depth-scale", "1")
    assert res.exit_code == 0 and "1 units per metre" in res.output, res.output


def test_warn_policy_records_instead_of_refusing(seq):
    s = open_sequence(seq, DatasetOptions(depth_scale=1.0), plausibility="warn")
    assert len(s.warnings) == 1 and "--depth-scale 1 units per metre" in s.warnings[0]


# ---------------------------------------------------------------------------------- unreadable index files
def test_missing_index_file(seq):
    (seq / "depth.txt").unlink()
    (seq / "associations.txt").unlink()
    assert_one_line(cli("info", seq), 2, str(seq / "depth.txt"), "not found")


def test_index_that_is_a_folder(seq):
    (seq / "rgb.txt").unlink()
    (seq / "rgb.txt").mkdir()
    (seq / "associations.txt").unlink()  # else it gives the frames
    assert_one_line(cli("info", seq), 2, str(seq / "rgb.txt"), "is not a file")


def test_index_that_is_not_text(seq):
    (seq / "rgb.txt").write_bytes(b"\xff\xfe\x00garbage\x81")
    assert_one_line(cli("info", seq), 2, str(seq / "rgb.txt"), "cannot read index file")


def test_sequence_path_that_is_a_file(seq):
    assert_one_line(cli("info", seq / "rgb.txt"), 2, str(seq / "rgb.txt"), "not a folder")
