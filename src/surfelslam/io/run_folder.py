"""The run folder policy: one run per ``--out`` folder, replaced only on request, never mixed, never torn.

A run writes into ``OUT`` like this (:class:`RunFolder`):

1. **Check** (:meth:`RunFolder.check`, writes nothing). ``OUT`` must be a folder or not exist yet. When it holds a
   previous run (any of the run's own output names, :func:`is_run_output`, or an unfinished hand-over
   ``.commit-*``), the run is refused unless ``overwrite`` is set (``--overwrite``). A live lock is refused too.
2. **Lock** (:meth:`RunFolder.open`). ``OUT/.lock`` is created with ``O_CREAT | O_EXCL`` and holds the PID. A second
   run into the same folder stops with one line naming the PID; a lock whose process is gone (killed run) is taken
   over.
3. **Stage.** The run writes everything into a fresh ``OUT/.partial-<pid>/``: ``config.toml`` first, then the
   trajectory line by line (a killed run leaves a valid partial trajectory there), ``metrics.json``, ``map.ply``,
   the figures. Earlier ``.partial-*`` folders (killed runs) are deleted once the lock is held.
4. **Hand over** (:meth:`RunFolder.commit`). The staging folder is renamed to ``OUT/.commit-<pid>/`` (from here on the
   new run is complete and the hand-over is finished by whichever run takes the lock next, should this one be
   killed), then in ``OUT``: the old ``metrics.json`` is deleted first, then every other file of the run's own
   names that the new run does not have (an older ``eval.json``, figures a ``--no-figures`` run does not write),
   then the new files are renamed in, ``metrics.json`` last. Files of other names in ``OUT`` are never touched.

So at any moment ``OUT`` holds the previous complete run, or the new complete run, and ``metrics.json`` (with
``"complete": true``) is present only when every file beside it belongs to its run. The hand-over is a handful of
renames; a run killed inside it leaves ``OUT`` without ``metrics.json`` and the rest in ``.commit-<pid>/``,
which the next run into ``OUT`` completes before anything else.
"""

from __future__ import annotations

import contextlib
import fnmatch
import json
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path

from surfelslam.errors import ConfigError, InputError, OutputError
from surfelslam.io.atomic import os_error_text

#: The files a run (and ``surfelslam eval`` / ``surfelslam rerun`` beside it) writes into its folder.
RUN_OUTPUT_NAMES = ("trajectory.txt", "map.ply", "config.toml", "metrics.json", "trajectory.png", "ate_errors.png",
                    "run.rrd", "mesh.ply", "map.npz", "keyframes.txt", "trajectory_kitti.txt")
#: Patterns of the same (map figures; evaluation results and plots of ``surfelslam eval``, older names too).
RUN_OUTPUT_PATTERNS = ("map_*.png", "eval*.json", "eval*.png")
#: The file that marks a complete run; handed over last, deleted first.
COMPLETE_MARKER = "metrics.json"
LOCK_NAME = ".lock"
#: Tries to take over a stale lock before giving up (another process keeps taking it in between).
LOCK_TAKEOVER_ATTEMPTS = 3
STAGING_PREFIX = ".partial-"
COMMIT_PREFIX = ".commit-"
#: inside ``.commit-<pid>/``: the names of the new run's files, one a line
MANIFEST_NAME = ".manifest"
#: A lock file still empty after this many seconds is stale (its process died between creating and writing it).
EMPTY_LOCK_STALE_S = 10.0
#: Previous-run files named in the refusal message.
NAMED_FILES = 3


def is_run_output(name: str) -> bool:
    """True for the names a run (or ``eval`` / ``rerun`` of it) writes into its folder."""
    return name in RUN_OUTPUT_NAMES or any(fnmatch.fnmatchcase(name, p) for p in RUN_OUTPUT_PATTERNS)


def previous_run_files(out: Path) -> list[Path]:
    """The run's own output files (and unfinished hand-overs) present in ``out``, sorted."""
    if not out.is_dir():
        return []
    found = [p for p in out.iterdir()
             if (p.is_file() and is_run_output(p.name)) or (p.is_dir() and p.name.startswith(COMMIT_PREFIX))]
    return sorted(found)


def staging_path(out: Path, pid: int | None = None) -> Path:
    """``OUT/.partial-<pid>``: where the run of process ``pid`` (default: this one) writes until it is complete."""
    return Path(out) / f"{STAGING_PREFIX}{os.getpid() if pid is None else pid}"


def pid_alive(pid: int) -> bool:
    """True when a process ``pid`` exists (also one of another user)."""
    if pid <= 0:
        return False
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return False
    return True


def lock_holder(path: Path) -> int | None:
    """The PID in a lock file, ``None`` when it is empty or unreadable."""
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    try:
        return int(text.split()[0]) if text else None
    except ValueError:
        return -1  # garbage: no process of ours wrote it


def lock_is_stale(path: Path, holder: int | None) -> bool:
    """Whether the lock file ``path`` (held by ``holder``: :func:`lock_holder`) is left by a process that died: its PID
    is gone, or it stayed empty longer than a writer takes to fill it."""
    if holder is None:  # being written right now, or its writer died before writing
        try:
            return time.time() - path.stat().st_mtime > EMPTY_LOCK_STALE_S
        except FileNotFoundError:
            return True
    return not pid_alive(holder)


def take_lock(path: Path, what: str, owner: str, held_message: Callable[[int | None], str]) -> None:
    """Create the lock file ``path`` holding this process's PID (``O_EXCL``: one holder), taking over a stale one (a
    dead holder's: :func:`lock_is_stale`). ``what`` names the file and ``owner`` the kind of holder in messages.

    Raises:
        OutputError: a live holder has it (``held_message(holder_pid)``), or it cannot be created or written.
    """
    for _ in range(LOCK_TAKEOVER_ATTEMPTS):
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            holder = lock_holder(path)
            if not lock_is_stale(path, holder):
                raise OutputError(path, held_message(holder)) from None
            if lock_holder(path) == holder:  # still the same stale lock: take it over
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()
            continue
        except OSError as exc:
            raise OutputError(path, f"cannot create the {what} ({os_error_text(exc)})") from None
        try:
            os.write(fd, f"{os.getpid()}\n".encode())
        except OSError as exc:
            os.close(fd)
            with contextlib.suppress(OSError):
                path.unlink()
            raise OutputError(path, f"cannot write the {what} ({os_error_text(exc)})") from None
        os.close(fd)
        return
    raise OutputError(path, f"cannot take over the stale {what} (another {owner} keeps taking it)")


def release_lock(path: Path) -> None:
    """Remove the lock file ``path`` if this process holds it."""
    if lock_holder(path) == os.getpid():
        with contextlib.suppress(OSError):
            path.unlink()


def _held_message(out: Path, holder: int | None) -> str:
    who = "another run" if holder is None else f"another run (process {holder})"
    return (f"{who} is writing into {out}; wait for it to end, or choose another --out "
            f"(delete {out / LOCK_NAME} only if no run is going)")


class RunFolder:
    """One run's hand-over into ``out`` (see the module docstring for the policy).

    Use: ``check()`` before anything is written, then ``with folder: stage = folder.open(); ...;
    folder.commit()``. Leaving the ``with`` block without :meth:`commit` releases the lock and keeps the staging
    folder (with its partial trajectory) for inspection; the next run deletes it.
    """

    def __init__(self, out: str | Path, overwrite: bool = False):
        self.out = Path(out)
        self.overwrite = overwrite
        self.stage: Path | None = None
        self._lock: Path | None = None

    # ---------------------------------------------------------------------------------------------- checks
    def check(self) -> None:
        """Refuse what cannot or may not be done; writes nothing.

        Raises:
            OutputError: ``out`` (or a part of its path) is a file, or another live run holds its lock.
            ConfigError: ``out`` holds a previous run and ``overwrite`` is not set.
        """
        out = self.out
        for part in (out, *out.parents):
            if part.exists():
                if not part.is_dir():
                    where = "is a file" if part == out else f"is below a file ({part})"
                    raise OutputError(out, f"cannot be the output folder: it {where}")
                break
        lock = out / LOCK_NAME
        if lock.exists():
            holder = lock_holder(lock)
            if not lock_is_stale(lock, holder):
                raise OutputError(lock, _held_message(out, holder))
        self._refuse_previous_run()

    def _refuse_previous_run(self) -> None:
        if self.overwrite:
            return
        old = previous_run_files(self.out)
        if old:
            names = ", ".join(p.name for p in old[:NAMED_FILES]) + (", ..." if len(old) > NAMED_FILES else "")
            raise ConfigError(f"{self.out} holds a previous run ({names}); pass --overwrite to replace it "
                              f"(only the run's own files are removed), or choose another --out")

    # ---------------------------------------------------------------------------------------------- lock
    def _acquire(self) -> None:
        path = self.out / LOCK_NAME
        take_lock(path, "lock file", "run", lambda holder: _held_message(self.out, holder))
        self._lock = path

    def _release(self) -> None:
        path, self._lock = self._lock, None
        if path is not None:
            release_lock(path)

    # ---------------------------------------------------------------------------------------------- the run
    def open(self) -> Path:
        """Create ``out``, take its lock, finish or clear what killed runs left, and make the staging folder.

        Returns the staging folder ``out/.partial-<pid>``, where the run writes every file.
        """
        self.check()
        try:
            self.out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(self.out, f"cannot create the output folder ({os_error_text(exc)})") from None
        self._acquire()
        try:
            for journal in sorted(self.out.glob(f"{COMMIT_PREFIX}*")):
                if journal.is_dir():
                    _hand_over(journal, self.out)  # a run killed while handing over: finish its hand-over
            self._refuse_previous_run()  # again, under the lock (a run may have finished in between)
            for old in self.out.glob(f"{STAGING_PREFIX}*"):
                if old.is_dir():
                    shutil.rmtree(old, ignore_errors=True)  # killed runs' partial outputs
            stage = staging_path(self.out)
            stage.mkdir()
        except OSError as exc:
            self._release()
            raise OutputError(exc.filename or self.out, f"cannot prepare the output folder "
                                                        f"({os_error_text(exc)})") from None
        except BaseException:
            self._release()
            raise
        self.stage = stage
        return stage

    def commit(self) -> None:
        """Move the staged files into ``out`` (the hand-over of the module docstring), then drop the lock."""
        if self.stage is None:
            raise RuntimeError("RunFolder.commit() before open()")
        stage, self.stage = self.stage, None
        names = sorted(p.name for p in stage.iterdir() if p.is_file() and not p.name.startswith("."))
        journal = self.out / f"{COMMIT_PREFIX}{os.getpid()}"
        try:
            (stage / MANIFEST_NAME).write_text("".join(n + "\n" for n in names))
            if journal.exists():
                shutil.rmtree(journal)
            os.rename(stage, journal)
        except OSError as exc:
            raise OutputError(exc.filename or stage, f"cannot hand the run over ({os_error_text(exc)}); the "
                                                     f"complete run is in {stage}") from None
        _hand_over(journal, self.out)
        self._release()

    def close(self) -> None:
        """Release the lock (a staging folder not committed stays, with what the run wrote)."""
        self._release()

    def __enter__(self) -> RunFolder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _hand_over(journal: Path, out: Path) -> None:
    """Finish the hand-over of ``journal`` (``.commit-<pid>/``) into ``out``; safe to repeat after a kill."""
    try:
        names = [n for n in (journal / MANIFEST_NAME).read_text().splitlines() if n]
    except FileNotFoundError:
        names = sorted(p.name for p in journal.iterdir() if p.is_file() and not p.name.startswith("."))
    try:
        if (journal / COMPLETE_MARKER).exists():
            with contextlib.suppress(FileNotFoundError):
                (out / COMPLETE_MARKER).unlink()  # from here on `out` holds no complete run until the new marker
        keep = set(names)
        for p in out.iterdir():
            if p.is_file() and is_run_output(p.name) and p.name not in keep:
                p.unlink()
        for name in sorted(names, key=lambda n: n == COMPLETE_MARKER):  # the marker last
            src = journal / name
            if src.exists():
                os.replace(src, out / name)
        shutil.rmtree(journal)
    except OSError as exc:
        raise OutputError(exc.filename or out, f"cannot move the run's files into {out} "
                                               f"({os_error_text(exc)}); the rest is in {journal}") from None


def read_run_trajectory(run_dir: Path):
    """A finished run's ``trajectory.txt`` as a :class:`~surfelslam.types.Trajectory`; one line naming the file
    when it is missing (not a run folder) or holds no pose."""
    from surfelslam.io.trajectory import read_tum

    path = Path(run_dir) / "trajectory.txt"
    if not path.is_file():
        raise InputError(path, "missing: not the output folder of `surfelslam run`")
    est = read_tum(path)
    if len(est) == 0:
        raise InputError(path, "has no poses")
    return est


def read_run_metrics(run_dir: Path) -> dict:
    """A run folder's ``metrics.json`` as a dict (``{}`` when there is none); one line naming the file if unreadable."""
    path = Path(run_dir) / COMPLETE_MARKER
    if not path.is_file():
        return {}
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(path, f"cannot read the run's metrics ({exc})") from None
