"""Corrupt image files: a truncated or damaged JPEG / PNG is a FrameError naming the file with the decoder's reason,
and libjpeg / libpng print nothing of their own on stderr."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from surfelslam.errors import FrameError
from surfelslam.io.images import decoder_messages, read_depth_raw, read_rgb


def _rgb() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 255, (60, 80, 3), dtype=np.uint8)


def _jpeg(path: Path) -> bytes:
    cv2.imwrite(str(path), _rgb())
    return path.read_bytes()


def _png(path: Path, img: np.ndarray | None = None) -> bytes:
    cv2.imwrite(str(path), _rgb() if img is None else img)
    return path.read_bytes()


def test_truncated_jpeg_is_not_a_good_frame(tmp_path, capfd):
    path = tmp_path / "000010.jpg"
    data = _jpeg(path)
    path.write_bytes(data[: len(data) // 3])
    with pytest.raises(FrameError, match="truncated colour JPEG: the file ends without the end-of-image marker"
                       ) as err:
        read_rgb(path)
    assert err.value.path == path and str(path) in str(err.value)
    assert capfd.readouterr().err == ""  # no 'Premature end of JPEG file' beside our message


def test_jpeg_cut_in_its_header_has_no_image_data(tmp_path):
    path = tmp_path / "head.jpg"
    path.write_bytes(_jpeg(path)[:40])
    with pytest.raises(FrameError, match="truncated colour JPEG: no image data"):
        read_rgb(path)


def test_damaged_jpeg_data_reports_the_decoder_warning(tmp_path, capfd):
    path = tmp_path / "bad.jpg"
    data = bytearray(_jpeg(path))
    mid = len(data) // 2
    data[mid: mid + 64] = bytes(64)  # complete file, garbage inside: libjpeg warns and fills in grey
    path.write_bytes(bytes(data))
    with pytest.raises(FrameError, match="colour image is corrupt .decoder: Corrupt JPEG data"):
        read_rgb(path)
    assert capfd.readouterr().err == ""


def test_truncated_png_depth(tmp_path, capfd):
    path = tmp_path / "d.png"
    data = _png(path, np.full((60, 80), 5000, np.uint16))
    path.write_bytes(data[:-20])
    with pytest.raises(FrameError, match="truncated depth PNG: no IEND chunk"):
        read_depth_raw(path)
    assert capfd.readouterr().err == ""


def test_png_with_a_bad_crc_reports_libpng(tmp_path, capfd):
    path = tmp_path / "c.png"
    data = bytearray(_png(path))
    mid = len(data) // 2
    data[mid: mid + 32] = bytes(32)
    path.write_bytes(bytes(data))
    with pytest.raises(FrameError, match="cannot decode colour image .corrupt or not an image; decoder: libpng"):
        read_rgb(path)
    assert capfd.readouterr().err == ""


@pytest.mark.parametrize("content, message", [
    (b"", "empty file"),
    (b"\x89PNG\r\n\x1a\n" + bytes(20), "truncated depth PNG"),
    (b"not an image at all", "cannot decode depth image"),
])
def test_other_broken_depth_files(tmp_path, content, message):
    path = tmp_path / "x.png"
    path.write_bytes(content)
    with pytest.raises(FrameError, match=message) as err:
        read_depth_raw(path)
    assert err.value.path == path


def test_depth_image_that_is_a_folder(tmp_path):
    (tmp_path / "d.png").mkdir()
    with pytest.raises(FrameError, match="depth image not found"):
        read_depth_raw(tmp_path / "d.png")


def test_other_stderr_lines_written_during_a_decode_are_kept(capfd):
    with decoder_messages() as found:
        os.write(2, b"libpng warning: iCCP: known incorrect sRGB profile\n")
        os.write(2, b"error: a line of ours from another thread\n")
        os.write(2, b"\r 40%|####      | 4/10\n")
    assert found == ["libpng warning: iCCP: known incorrect sRGB profile"]
    err = capfd.readouterr().err
    assert "error: a line of ours" in err and "40%" in err and "libpng" not in err


def test_good_images_still_decode(tmp_path):
    rgb = _rgb()
    cv2.imwrite(str(tmp_path / "a.png"), rgb)
    cv2.imwrite(str(tmp_path / "d.png"), np.full((60, 80), 1234, np.uint16))
    assert np.array_equal(read_rgb(tmp_path / "a.png"), rgb[:, :, ::-1])
    assert read_depth_raw(tmp_path / "d.png").dtype == np.uint16
    path = tmp_path / "trailing.jpg"
    path.write_bytes(_jpeg(path) + b"\x00" * 16)  # padding after the end marker is harmless
    assert read_rgb(path).shape == (60, 80, 3)


def test_the_stderr_capture_file_is_closed_at_exit(tmp_path):
    """Python's development mode reports a file left open at exit; decoding must leave none."""
    cv2.imwrite(str(tmp_path / "a.png"), _rgb())
    code = ("import sys; from pathlib import Path; from surfelslam.io.images import read_rgb; "
            "read_rgb(Path(sys.argv[1])); read_rgb(Path(sys.argv[1]))")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONWARNINGS"}
    done = subprocess.run([sys.executable, "-X", "dev", "-c", code, str(tmp_path / "a.png")],
                          capture_output=True, text=True, env=env, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert "ResourceWarning" not in done.stderr
