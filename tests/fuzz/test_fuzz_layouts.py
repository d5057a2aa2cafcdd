"""Fuzzing the other folder layouts (plain numbered ``rgb/`` + ``depth/``, native ICL-NUIM, native 7-Scenes): their
text files mutated, files renamed, removed or added (the file names are the frame numbers there)."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from fuzzkit import SEED_FRAMES, SEED_INFO, copy_seed, is_error, open_and_check, seed_images, text_or_bytes, unchanged
from hypothesis import given
from hypothesis import strategies as st

from surfelslam.io.images import write_png_depth

#: a frame number as long as a file name can hold (255 bytes): numbered layouts turn frame numbers into stamps
HUGE_NUMBER = "9" * 230


def _write_frames(root: Path, names: list[tuple[str, str]], mm: bool = False) -> None:
    for (rgb_name, depth_name), (rgb, depth) in zip(names, seed_images(), strict=True):
        (root / rgb_name).parent.mkdir(parents=True, exist_ok=True)
        (root / depth_name).parent.mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(root / rgb_name), rgb[:, :, ::-1])
        write_png_depth(root / depth_name, depth // 5 if mm else depth)  # 7-Scenes: millimetres


def _pose_lines(k: int) -> str:
    T = np.eye(4)
    T[:3, 3] = [0.01 * k, 0.02, 0.0]
    return "\n".join(" ".join(f"{x:.6f}" for x in row) for row in T) + "\n"


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("layouts")
    folder = base / "plain"
    _write_frames(folder, [(f"rgb/{k}.png", f"depth/{k}.png") for k in range(SEED_FRAMES)])
    (folder / "INFO.txt").write_text(SEED_INFO)
    (folder / "groundtruth.txt").write_text("".join(f"{k / 30:.6f} {0.01 * k} 0 0 0 0 0 1\n"
                                                    for k in range(SEED_FRAMES)))
    icl = base / "icl_living_room"
    _write_frames(icl, [(f"rgb/{k}.png", f"depth/{k}.png") for k in range(SEED_FRAMES)])
    (icl / "livingRoom0.gt.freiburg").write_text("".join(f"{k + 1} {0.01 * k} 0 0 0 0 0 1\n"
                                                         for k in range(SEED_FRAMES)))
    (icl / "INFO.txt").write_text("intrinsics : fx=14.0 fy=-14.0 cx=7.5 cy=5.5\n")
    seven = base / "7scenes_chess" / "seq-01"
    _write_frames(seven, [(f"frame-{k:06d}.color.png", f"frame-{k:06d}.depth.png") for k in range(SEED_FRAMES)],
                  mm=True)
    for k in range(SEED_FRAMES):
        (seven / f"frame-{k:06d}.pose.txt").write_text(_pose_lines(k))
    (seven / "INFO.txt").write_text("intrinsics : fx=14.0 fy=14.0 cx=7.5 cy=5.5\n")
    return {"folder": folder, "icl": icl, "7scenes": seven}


def test_seeds_are_valid(seeds):
    for layout, root in seeds.items():
        seq = open_and_check(root)
        assert not is_error(seq), seq
        assert seq.layout == layout and len(seq) == SEED_FRAMES and seq.ground_truth is not None


_NEW_NAME = st.one_of(
    st.sampled_from(("rgb/{n}.png", "depth/{n}.png", "frame-{n}.depth.png", "frame-{n}.color.png",
                     "frame-{n}.pose.txt", "rgb/x{n}y.jpg", "depth/{n}.tiff", "seq-{n}/frame-000000.depth.png")),
).flatmap(lambda pattern: st.sampled_from(("0", "000003", "-1", "12345678901234567890", HUGE_NUMBER, "", "1.5",
                                           "١٢")).map(lambda n: pattern.format(n=n)))


@st.composite
def layout_edit(draw: st.DrawFn, root: Path) -> None:
    """Edit the folder ``root`` in place: a text file mutated, a file removed or renamed, a file added."""
    files = sorted(p for p in root.rglob("*") if p.is_file())
    op = draw(st.sampled_from(("text", "text", "remove", "rename", "add_copy", "add_garbage")))
    texts = [p for p in files if p.suffix in (".txt", ".freiburg")]
    if op == "text" and texts:
        path = draw(st.sampled_from(texts))
        path.write_bytes(draw(text_or_bytes(path.read_bytes().decode("utf-8", "replace"))))
        return
    path = draw(st.sampled_from(files))
    if op == "remove":
        path.unlink()
        return
    target = root / draw(_NEW_NAME)
    if target.exists() or target.is_dir():
        return
    target.parent.mkdir(parents=True, exist_ok=True)
    if op == "rename":
        path.rename(target)
    elif op == "add_copy":
        shutil.copy(path, target)
    else:
        target.write_bytes(draw(st.binary(max_size=40)))


@given(data=st.data(), layout=st.sampled_from(("folder", "icl", "7scenes")), edits=st.integers(1, 3))
def test_edited_layouts(seeds, tmp_path, data, layout, edits):
    root = copy_seed(seeds[layout], tmp_path)
    for _ in range(edits):
        data.draw(layout_edit(root))
    with unchanged(root):
        open_and_check(root)


@pytest.mark.parametrize("layout, name", [("folder", f"rgb/{HUGE_NUMBER}.png"), ("icl", f"depth/{HUGE_NUMBER}.png"),
                                          ("7scenes", f"frame-{HUGE_NUMBER}.depth.png")])
def test_huge_frame_number(seeds, tmp_path, layout, name):
    root = copy_seed(seeds[layout], tmp_path)
    shutil.copy(next(root.rglob("*.png")), root / name)
    with unchanged(root):
        open_and_check(root)


@pytest.mark.parametrize("pose", ["", "\n", "1e200 0 0 0\n0 1e200 0 0\n0 0 1 0\n0 0 0 1\n",
                                  "1e155 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"], ids=["empty", "blank", "huge", "big"])
def test_seven_scenes_pose_values(seeds, tmp_path, pose):
    """Found: an empty pose.txt printed numpy's UserWarning; entries like 1e200 overflowed the rotation check."""
    root = copy_seed(seeds["7scenes"], tmp_path)
    (root / "frame-000001.pose.txt").write_text(pose)
    with unchanged(root):
        open_and_check(root)


@pytest.mark.parametrize("layout, pattern", [("folder", "{k}.png"), ("7scenes", "frame-{k}.")])
def test_frame_numbers_too_close_for_a_float(seeds, tmp_path, layout, pattern):
    """Found (ICL, with a ground-truth id of -9e15): frame numbers beyond 2**53 gave frames the same stamp."""
    root = copy_seed(seeds[layout], tmp_path)
    for path in sorted(root.rglob("*")):
        if path.is_file() and path.suffix in (".png", ".txt") and path.name != "INFO.txt" and "ground" not in path.name:
            k = int("".join(c for c in path.name if c.isdigit()))
            old = pattern.format(k=k) if layout == "folder" else f"frame-{k:06d}."
            path.rename(path.with_name(path.name.replace(old, pattern.format(k=2**60 + k))))
    with unchanged(root):
        seq = open_and_check(root)
    assert is_error(seq)



def test_a_seven_scenes_pose_near_a_rotation_is_made_one(tmp_path):
    """Found by make fuzz: a pose.txt rotation within the accepted tolerance but not orthonormal was passed on as it
    was (downstream code assumes rotations); it is replaced by the nearest rotation, and a reflection is refused."""
    from surfelslam.datasets.sevenscenes import _read_pose
    from surfelslam.errors import DatasetError

    T = np.eye(4)
    T[:3, :3] = [[1.0, 0.003, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [0.5, -0.2, 1.0]
    path = tmp_path / "frame-000000.pose.txt"
    np.savetxt(path, T)
    R = _read_pose(path)[:3, :3]
    assert np.abs(R @ R.T - np.eye(3)).max() < 1e-12 and np.linalg.det(R) > 0
    assert np.abs(R - T[:3, :3]).max() < 3e-3
    T[2, 2] = -1.0
    np.savetxt(path, T)
    with pytest.raises(DatasetError, match="reflection"):
        _read_pose(path)
