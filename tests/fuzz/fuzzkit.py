"""The fuzz tests' property and mutations (imported as ``from fuzzkit import ...``).

The property every reader must hold, whatever its input: it returns a valid result, or it raises a
:class:`~surfelslam.errors.SurfelSlamError` whose message is one non-empty line; never another exception, never a
hang, and it writes nothing (the tests compare the folder tree before and after).
"""

from __future__ import annotations

import contextlib
import shutil
import signal
import tempfile
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

from hypothesis import currently_in_test_context, event
from hypothesis import strategies as st

from surfelslam.errors import SurfelSlamError

T = TypeVar("T")

#: one call of a reader taking longer than this is a hang [s] (they take milliseconds on the fuzz inputs)
HANG_LIMIT_S = 60.0
#: longest run of random bytes inserted or written over a file [bytes]
MAX_SPLICE_BYTES = 64
#: values that break number parsing and checks: not numbers, not finite, negative, huge, empty
NASTY_TOKENS = ("nan", "NaN", "inf", "-inf", "+inf", "-1", "-0", "0", "1e309", "-1e309", "1e-320", "1e308", "-1e308",
                "99999999999999999999", "0x10", "1_0", "abc", "", "#", "\x00", "é", "1,5", "--", "\\", "'", "\"", "[",
                "{", "=")


#: warning categories Python does not show by default (not on a user's stderr)
QUIET = (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning)


class Hang(AssertionError):
    """A reader call ran longer than :data:`HANG_LIMIT_S`."""


@contextlib.contextmanager
def hang_guard(limit_s: float = HANG_LIMIT_S) -> Iterator[None]:
    """Raise :class:`Hang` in the block when it runs longer than ``limit_s`` (a SIGALRM timer; main thread only,
    where pytest runs tests; elsewhere the block runs unguarded)."""
    def _alarm(signum, frame):  # noqa: ARG001 - signal handler signature
        raise Hang(f"the call did not return within {limit_s} s")

    try:
        previous = signal.signal(signal.SIGALRM, _alarm)
    except ValueError:  # not the main thread
        yield
        return
    signal.setitimer(signal.ITIMER_REAL, limit_s)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def assert_one_line(exc: SurfelSlamError) -> str:
    """The error's message, checked to be one non-empty line."""
    text = str(exc)
    assert text.strip(), f"{type(exc).__name__} with an empty message"
    assert "\n" not in text and "\r" not in text, f"{type(exc).__name__} message is not one line: {text!r}"
    return text


def _count(what: str) -> None:
    """Count the outcome for ``--hypothesis-show-statistics`` (how many inputs were valid, which errors)."""
    if currently_in_test_context():
        event(what)


def outcome(call: Callable[[], T]) -> T | SurfelSlamError:
    """``call()``'s result, or the SurfelSlamError it raised (checked: one line). Any other exception propagates
    (a find), and so does a hang. A Python warning is a find too: the command line would print it on stderr beside
    its one line of error."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            with hang_guard():
                result = call()
            _count(f"{getattr(call, '__name__', 'call')}: valid")
            return result
        except SurfelSlamError as exc:
            assert_one_line(exc)
            _count(f"{getattr(call, '__name__', 'call')}: {type(exc).__name__}")
            return exc
        finally:
            shown = [f"{w.category.__name__}: {w.message}" for w in caught if not issubclass(w.category, QUIET)]
            assert not shown, f"warning(s) on stderr: {shown}"


# ------------------------------------------------------------------------------------------------ folders
def example_dir(base: Path) -> Path:
    """A fresh folder for one example below ``base`` (the test's tmp_path)."""
    return Path(tempfile.mkdtemp(prefix="ex-", dir=base))


def tree(root: Path) -> dict[str, tuple[int, int]]:
    """``{relative path: (size, mtime_ns)}`` of every file and folder below ``root``."""
    out = {}
    for p in sorted(root.rglob("*")):
        with contextlib.suppress(OSError):
            s = p.lstat()
            out[str(p.relative_to(root))] = (s.st_size if p.is_file() else 0, s.st_mtime_ns)
    return out


@contextlib.contextmanager
def unchanged(root: Path) -> Iterator[None]:
    """Assert that nothing below ``root`` is created, changed or removed in the block (a reader writes nothing)."""
    before = tree(root)
    yield
    after = tree(root)
    assert after == before, f"files changed below {root}: " \
                            f"{sorted(set(after.items()) ^ set(before.items()))[:6]}"


def copy_seed(seed: Path, base: Path) -> Path:
    """A private copy of the seed file or folder ``seed`` in a fresh example folder below ``base``."""
    dst = example_dir(base) / seed.name
    if seed.is_dir():
        shutil.copytree(seed, dst)
    else:
        shutil.copy2(seed, dst)
    return dst


# ------------------------------------------------------------------------------------------------ mutations
@st.composite
def mutated_bytes(draw: st.DrawFn, data: bytes, max_ops: int = 4) -> bytes:
    """``data`` after 1 to ``max_ops`` byte-level edits: bit flips, truncation, insertion, deletion, overwriting
    with random bytes, a duplicated block."""
    out = bytearray(data)
    for _ in range(draw(st.integers(1, max_ops))):
        n = len(out)
        op = draw(st.sampled_from(("flip", "truncate", "insert", "delete", "overwrite", "duplicate")))
        pos = draw(st.integers(0, max(n - 1, 0)))
        if op == "flip" and n:
            out[pos] ^= 1 << draw(st.integers(0, 7))
        elif op == "truncate":
            del out[pos:]
        elif op == "insert":
            out[pos:pos] = draw(st.binary(min_size=1, max_size=MAX_SPLICE_BYTES))
        elif op == "delete":
            del out[pos:pos + draw(st.integers(1, MAX_SPLICE_BYTES))]
        elif op == "overwrite":
            chunk = draw(st.binary(min_size=1, max_size=MAX_SPLICE_BYTES))
            out[pos:pos + len(chunk)] = chunk
        elif op == "duplicate":
            end = pos + draw(st.integers(1, MAX_SPLICE_BYTES))
            out[end:end] = out[pos:end]
    return bytes(out)


def _token_edit(draw: st.DrawFn, line: str) -> str:
    parts = line.split(" ")
    k = draw(st.integers(0, len(parts) - 1))
    parts[k] = draw(st.one_of(st.sampled_from(NASTY_TOKENS), st.text(max_size=12),
                              st.floats(allow_nan=True, allow_infinity=True).map(repr)))
    return " ".join(parts)


@st.composite
def mutated_text(draw: st.DrawFn, text: str, max_ops: int = 4) -> str:
    """``text`` after 1 to ``max_ops`` line-level edits: a token replaced by a nasty value, a line deleted,
    repeated, moved or replaced by random text, the lines shuffled or reversed (unsorted, repeated stamps), a field
    dropped, the text cut."""
    lines = text.splitlines()
    for _ in range(draw(st.integers(1, max_ops))):
        op = draw(st.sampled_from(("token", "token", "delete", "repeat", "move", "random", "shuffle", "reverse",
                                   "drop_field", "cut", "blank")))
        if not lines:
            lines = [draw(st.text(max_size=40))]
            continue
        i = draw(st.integers(0, len(lines) - 1))
        if op == "token":
            lines[i] = _token_edit(draw, lines[i])
        elif op == "delete":
            del lines[i]
        elif op == "repeat":
            lines.insert(i, lines[i])
        elif op == "move":
            lines.insert(draw(st.integers(0, len(lines) - 1)), lines.pop(i))
        elif op == "random":
            lines[i] = draw(st.text(max_size=60))
        elif op == "shuffle":
            lines = draw(st.permutations(lines))
        elif op == "reverse":
            lines.reverse()
        elif op == "drop_field":
            parts = lines[i].split()
            if parts:
                del parts[draw(st.integers(0, len(parts) - 1))]
            lines[i] = " ".join(parts)
        elif op == "cut":
            joined = "\n".join(lines)
            lines = joined[: draw(st.integers(0, len(joined)))].split("\n")
        elif op == "blank":
            lines[i] = ""
    return "\n".join(lines) + draw(st.sampled_from(("\n", "", "\r\n")))


def text_or_bytes(text: str) -> st.SearchStrategy[bytes]:
    """Mutations of a text file's content: line-level (:func:`mutated_text`) or byte-level (:func:`mutated_bytes`,
    which may leave invalid UTF-8)."""
    return st.one_of(mutated_text(text).map(lambda s: s.encode("utf-8", "surrogatepass")),
                     mutated_bytes(text.encode()))


def is_error(result: Any) -> bool:
    return isinstance(result, SurfelSlamError)


# ------------------------------------------------------------------------------------------------ seeds
#: size of the seed sequences' images [px]: small, so that a fuzz example reads its frames in milliseconds
SEED_W, SEED_H = 16, 12
#: frames of the seed sequences, their first stamp and frame period [s]
SEED_FRAMES = 4
SEED_T0_S = 1305031102.175304
SEED_DT_S = 1 / 30
SEED_INFO = "intrinsics : fx=14.0 fy=14.0 cx=7.5 cy=5.5\ndepth scale : 5000\n"


def seed_images(n: int = SEED_FRAMES, seed: int = 1) -> list[tuple[Any, Any]]:
    """``n`` pairs ``(rgb (H, W, 3) uint8, raw depth (H, W) uint16 at 5000 units per metre, about 1-2 m)``."""
    import numpy as np

    rng = np.random.default_rng(seed)
    return [(rng.integers(0, 256, (SEED_H, SEED_W, 3), dtype=np.uint8),
             rng.integers(5000, 10000, (SEED_H, SEED_W)).astype(np.uint16)) for _ in range(n)]


def make_tum_seed(root: Path, associations: bool = False, colour_ext: str = ".png") -> Path:
    """A valid TUM folder: ``SEED_FRAMES`` frames, ``rgb.txt`` + ``depth.txt`` (or ``associations.txt`` alone),
    ``groundtruth.txt`` at twice the frame rate, an ``INFO.txt`` camera."""
    import cv2
    import numpy as np

    from surfelslam.io.images import write_png_depth

    root.mkdir(parents=True)
    (root / "rgb").mkdir()
    (root / "depth").mkdir()
    stamps = SEED_T0_S + SEED_DT_S * np.arange(SEED_FRAMES)
    rgb_lines, depth_lines, assoc_lines = [], [], []
    for t, (rgb, depth) in zip(stamps, seed_images(), strict=True):
        td = t + 0.004  # depth captured a little after colour, as on the TUM Kinect
        rgb_name, depth_name = f"rgb/{t:.6f}{colour_ext}", f"depth/{td:.6f}.png"
        assert cv2.imwrite(str(root / rgb_name), rgb[:, :, ::-1])
        write_png_depth(root / depth_name, depth)
        rgb_lines.append(f"{t:.6f} {rgb_name}")
        depth_lines.append(f"{td:.6f} {depth_name}")
        assoc_lines.append(f"{t:.6f} {rgb_name} {td:.6f} {depth_name}")
    if associations:
        (root / "associations.txt").write_text("\n".join(assoc_lines) + "\n")
    else:
        (root / "rgb.txt").write_text("# colour images\n# timestamp filename\n" + "\n".join(rgb_lines) + "\n")
        (root / "depth.txt").write_text("# depth images\n# timestamp filename\n" + "\n".join(depth_lines) + "\n")
    gt_t = SEED_T0_S - 0.01 + np.arange(2 * SEED_FRAMES + 2) * SEED_DT_S / 2
    (root / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "".join(
        f"{t:.4f} {0.01 * k:.4f} 0.0200 {-0.003 * k:.4f} 0.0 0.0 {0.01 * k:.4f} 1.0\n" for k, t in enumerate(gt_t)))
    (root / "INFO.txt").write_text(SEED_INFO)
    return root


# ------------------------------------------------------------------------------------------------ validity
def check_trajectory(traj: Any) -> None:
    """A valid trajectory: ``(N,)`` finite strictly increasing stamps, ``(N, 4, 4)`` finite rigid poses."""
    import numpy as np

    t, T = traj.timestamps, traj.T_world_cam
    assert len(t) >= 1 and t.shape == (len(t),) and T.shape == (len(t), 4, 4)
    assert np.all(np.isfinite(t)) and np.all(np.diff(t) > 0), "stamps not finite and increasing"
    assert np.all(np.isfinite(T)), "non-finite pose"
    R = T[:, :3, :3]
    assert np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max() < 1e-6, "pose is not a rotation"
    assert np.allclose(T[:, 3], [0, 0, 0, 1])


def check_sequence(seq: Any) -> None:
    """A valid opened sequence: a camera, frames in time order, and each frame either valid (shapes, dtypes, finite
    non-negative depth) or a one-line FrameError (which a run skips and counts)."""
    import json

    import numpy as np

    from surfelslam.errors import FrameError

    intr = seq.intrinsics
    assert len(seq) >= 1
    assert intr.width >= 1 and intr.height >= 1
    camera_ok = np.all(np.isfinite([intr.fx, intr.fy, intr.cx, intr.cy])) and intr.fx != 0 and intr.fy != 0
    assert camera_ok or seq.warnings, "an unusable camera, and no warning saying so"  # opened for `info` (warn)
    assert np.isfinite(seq.depth_scale) and seq.depth_scale > 0
    stamps = seq.timestamps
    assert np.all(np.isfinite(stamps)) and np.all(np.diff(stamps) > 0), f"frame stamps {stamps}"
    assert np.all(np.isfinite(seq.depth_timestamps))
    if seq.ground_truth is not None:
        check_trajectory(seq.ground_truth)
    T, valid = seq.gt_poses()
    assert T.shape == (len(seq), 4, 4) and valid.shape == (len(seq),) and np.all(np.isfinite(T))
    json.dumps(seq.info(), allow_nan=not camera_ok)  # NaN only where the camera is warned about
    for i in range(len(seq)):
        frame = outcome(lambda i=i: seq[i])
        if is_error(frame):
            assert isinstance(frame, FrameError), f"frame {i}: {type(frame).__name__}: {frame}"
            continue
        assert frame.rgb.shape == (intr.height, intr.width, 3) and frame.rgb.dtype == np.uint8
        assert frame.depth_m.shape == (intr.height, intr.width) and frame.depth_m.dtype == np.float32
        assert np.all(np.isfinite(frame.depth_m)) and np.all(frame.depth_m >= 0)
        assert frame.timestamp == stamps[i]


def open_and_check(root: Path, **kwargs: Any) -> Any:
    """``open_sequence(root)`` under the property, as ``run`` opens it (implausible cameras refused) and as ``info``
    does (only warned about; then every frame is read and checked, :func:`check_sequence`, and ``describe``d).
    Returns the ``run`` outcome: the sequence or the error."""
    from surfelslam.datasets import describe, open_sequence

    for policy in ("warn", "refuse"):
        result = outcome(lambda policy=policy: open_sequence(root, plausibility=policy, **kwargs))
        if is_error(result):
            continue
        try:
            if policy == "warn":
                check_sequence(result)
                outcome(lambda result=result: describe(result))
        finally:
            close = getattr(result, "close", None)
            if close is not None:
                close()
    return result
