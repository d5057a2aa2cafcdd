"""Image decoding with clear errors (OpenCV). Colour is returned RGB, depth as the raw integer image.

A frame is only good when its file decodes completely. OpenCV hands back a grey-filled image for a truncated
JPEG, and libjpeg / libpng report such problems only as lines on the process's stderr. So:

* JPEG and PNG files are checked for their end first (JPEG: the end-of-image marker after the last scan; PNG:
  the ``IEND`` chunk): a truncated file is a :class:`~surfelslam.errors.FrameError` without being decoded.
* While OpenCV decodes, file descriptor 2 is redirected into a temp file (one decode at a time, under
  :data:`stderr_lock`). What the decoders wrote there is not shown: a corruption report (``Corrupt JPEG data``,
  ``libpng error``, ...) becomes the FrameError's reason, harmless notes are dropped. Lines that are not the
  decoders' (another thread's progress bar or messages) are written back to stderr.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import re
import sys
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from surfelslam.errors import FrameError

JPEG_SOI = b"\xff\xd8"  # start of image
JPEG_SOS = b"\xff\xda"  # start of scan (entropy-coded data follows; 0xFF is byte-stuffed inside it)
JPEG_EOI = b"\xff\xd9"  # end of image
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_IEND = b"IEND"
#: bytes at the end of a PNG searched for the IEND chunk (12 bytes long; some writers pad the file) [bytes]
PNG_END_SEARCH_BYTES = 1024

#: decoder messages that mean the image did not decode completely (anything else they print is dropped)
DECODER_FAILURE = re.compile(
    r"corrupt jpeg data|premature end|libpng error|crc error|incomplete|truncat|invalid jpeg|bogus|"
    r"not a jpeg|unsupported jpeg|huffman|too few|too many|extraneous", re.IGNORECASE)
#: stderr lines written during a decode that are someone else's and go back to stderr: progress bars
#: (carriage returns), our own messages and Python warnings
_NOT_DECODER = re.compile(r"\r|^(error|warning|interrupted|Traceback)\b|^\s+File |^\S+:\d+: \w*Warning: ")
#: OpenCV's own log prefix, e.g. "[ WARN:0@0.034] global grfmt_png.cpp:793 readFromStreamOrBuffer "
_CV_LOG_PREFIX = re.compile(r"^\[\s*\w+:[^\]]*\]\s*(global\s+\S+\s+\S+\s+)?")

#: held while fd 2 is redirected; writers of whole lines to stderr (the CLI's error line) take it too
stderr_lock = threading.Lock()
_capture_file = None
#: how long the exit hook waits for a decode in another thread before leaving the capture file to the OS [s]
_EXIT_LOCK_TIMEOUT_S = 1.0


def _capture_fd() -> int | None:
    global _capture_file
    if _capture_file is None:
        try:
            _capture_file = tempfile.TemporaryFile(prefix="surfelslam-stderr-")
        except OSError:
            return None
        atexit.register(_close_capture_file)
    return _capture_file.fileno()


def _close_capture_file() -> None:
    """Close the process-long capture file at exit (else Python reports it as an unclosed file)."""
    global _capture_file
    if not stderr_lock.acquire(timeout=_EXIT_LOCK_TIMEOUT_S):
        return  # a daemon thread is inside a decode: the OS closes the file
    try:
        if _capture_file is not None:
            _capture_file.close()
            _capture_file = None
    finally:
        stderr_lock.release()


@contextlib.contextmanager
def decoder_messages() -> Iterator[list[str]]:
    """Collect what native code writes to fd 2 inside the block (the list is filled on exit).

    Without a usable temp file or fd 2 the block runs uncaptured and the list stays empty.
    """
    found: list[str] = []
    with stderr_lock:
        cap = _capture_fd()
        saved = None
        if cap is not None:
            with contextlib.suppress(OSError, ValueError, AttributeError):
                sys.stderr.flush()
            try:
                saved = os.dup(2)
                os.lseek(cap, 0, os.SEEK_SET)
                os.ftruncate(cap, 0)
                os.dup2(cap, 2)
            except OSError:
                if saved is not None:
                    os.close(saved)
                saved = None
        try:
            yield found
        finally:
            if saved is not None:
                os.dup2(saved, 2)
                os.close(saved)
                size = os.fstat(cap).st_size
                if size:
                    text = os.pread(cap, size, 0).decode("utf-8", errors="replace")
                    back = []
                    for line in re.findall(r"[^\n]*\n|[^\n]+$", text):  # '\r' stays inside its line
                        if _NOT_DECODER.search(line):
                            back.append(line)
                        elif line.strip():
                            found.append(_CV_LOG_PREFIX.sub("", line.strip()))
                    if back:
                        with contextlib.suppress(OSError):
                            os.write(2, "".join(back).encode("utf-8", errors="replace"))


def _read_bytes(path: Path, what: str) -> bytes:
    if not path.is_file():
        raise FrameError(path, f"{what} image not found")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise FrameError(path, f"cannot read {what} image ({exc.strerror or exc})") from None
    if not data:
        raise FrameError(path, f"{what} image is an empty file (0 bytes)")
    return data


def check_complete(path: Path, data: bytes, what: str) -> None:
    """FrameError when a JPEG or PNG file ends before its end marker (a truncated copy). Other formats pass."""
    if data.startswith(JPEG_SOI):
        sos = data.rfind(JPEG_SOS)
        if sos < 0:
            raise FrameError(path, f"truncated {what} JPEG: no image data ({len(data)} bytes)")
        if data.find(JPEG_EOI, sos) < 0:
            raise FrameError(path, f"truncated {what} JPEG: the file ends without the end-of-image marker "
                                   f"({len(data)} bytes)")
    elif data.startswith(PNG_SIGNATURE):
        if PNG_IEND not in data[-PNG_END_SEARCH_BYTES:]:
            raise FrameError(path, f"truncated {what} PNG: no IEND chunk at the end of the file ({len(data)} bytes)")


def _decode(path: Path, flags: int, what: str) -> np.ndarray:
    data = _read_bytes(path, what)
    check_complete(path, data, what)
    with decoder_messages() as messages:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    failures = [m for m in messages if DECODER_FAILURE.search(m)]
    if img is None:
        said = f"; decoder: {failures[0] if failures else messages[0]}" if messages else ""
        raise FrameError(path, f"cannot decode {what} image (corrupt or not an image{said})")
    if failures:
        raise FrameError(path, f"{what} image is corrupt (decoder: {failures[0]}); not used as a frame")
    return img


def read_rgb(path: str | Path) -> np.ndarray:
    """Colour image -> ``(H, W, 3)`` uint8 RGB. Grey images are replicated to 3 channels."""
    path = Path(path)
    img = _decode(path, cv2.IMREAD_UNCHANGED, "colour")
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.dtype != np.uint8:
        raise FrameError(path, f"unsupported colour image type {img.dtype}")
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth_raw(path: str | Path) -> np.ndarray:
    """Depth image -> ``(H, W)`` array of raw units (uint16 for PNG, float for EXR/TIFF)."""
    path = Path(path)
    img = _decode(path, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_UNCHANGED, "depth")
    if img.ndim != 2:
        raise FrameError(path, f"depth image must have one channel, got {img.shape[2]}")
    if img.dtype == np.uint8:
        raise FrameError(path, "depth image is 8-bit; expected 16-bit PNG (raw units)")
    return img


def write_png_rgb(path: str | Path, rgb: np.ndarray) -> None:
    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise FrameError(path, "cannot write colour image")


def write_png_depth(path: str | Path, depth_raw_u16: np.ndarray) -> None:
    if not cv2.imwrite(str(path), depth_raw_u16.astype(np.uint16)):
        raise FrameError(path, "cannot write depth image")
