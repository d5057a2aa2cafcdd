"""How a command ends: its exit codes, Ctrl-C, and the one line of an unexpected exception.

Shared by the command line's entry point (:mod:`surfelslam.cli`) and the commands' error handling
(:func:`surfelslam.tools.common.handle_errors`); it imports nothing but the standard library, so that the command
line's start-up stays fast.
"""

from __future__ import annotations

import _thread
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

EXIT_INTERNAL_ERROR = 1
EXIT_INTERRUPTED = 130
DEBUG_ENV = "SURFELSLAM_DEBUG"


def _exit_now(signum, frame) -> None:  # noqa: ARG001 - signal handler signature
    os.write(2, b"interrupted\n")
    os._exit(EXIT_INTERRUPTED)


def force_exit_on_interrupt() -> None:
    """From now on Ctrl-C exits at once with 130 (used after the first Ctrl-C was reported, and while the
    interpreter shuts down, where a KeyboardInterrupt would print a traceback from the clean-up code)."""
    try:
        signal.signal(signal.SIGINT, _exit_now)
    except (ValueError, OSError):  # not the main thread
        pass


def debug_enabled() -> bool:
    """``SURFELSLAM_DEBUG`` set (and not 0): unexpected exceptions keep their traceback."""
    return os.environ.get(DEBUG_ENV, "") not in ("", "0")


def internal_error_message(exc: BaseException) -> str:
    """``internal error: <type>: <message> (please report ...)`` on one line."""
    msg = " ".join(str(exc).split()) or "(no message)"
    return f"internal error: {type(exc).__name__}: {msg} (please report; {DEBUG_ENV}=1 shows the traceback)"


_interrupt_requested = False


def _raise_interrupt(signum, frame) -> None:  # noqa: ARG001 - signal handler signature
    """Python's own Ctrl-C handler (raise KeyboardInterrupt), remembering that the user asked to stop."""
    global _interrupt_requested
    _interrupt_requested = True
    raise KeyboardInterrupt


def interrupt_requested() -> bool:
    """Whether Ctrl-C was pressed in this process's command line (:func:`catch_interrupts`)."""
    return _interrupt_requested


#: Seconds before a dropped Ctrl-C is delivered again: long enough for the callback or destructor that dropped it to
#: return to its caller (raised any sooner, it lands in that same callback and is dropped again).
REDELIVER_AFTER_S = 0.05
_redelivering = threading.Lock()


def _redeliver_interrupt() -> None:
    """Raise a dropped Ctrl-C again in the main thread, from a short-lived thread, unless it was reported by then
    (the handler is then :func:`_exit_now`) or a re-delivery is already on its way."""
    if not _redelivering.acquire(blocking=False):
        return

    def later() -> None:
        time.sleep(REDELIVER_AFTER_S)
        try:
            if signal.getsignal(signal.SIGINT) is _raise_interrupt:
                _thread.interrupt_main(signal.SIGINT)
        finally:
            _redelivering.release()

    threading.Thread(target=later, name="surfelslam-redeliver-ctrl-c", daemon=True).start()


def _quiet_unraisable(previous: Callable[[Any], object]) -> Callable[[Any], None]:
    def hook(unraisable) -> None:
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            # Python could not raise it (a callback, a destructor) and the work may go on regardless (llvmlite's
            # object-cache callback): deliver it again, to be raised at the next point that can, until reported
            _redeliver_interrupt()
            return
        if _interrupt_requested:
            return
        previous(unraisable)

    return hook


def catch_interrupts() -> None:
    """For the process's own command line (:func:`main`): a Ctrl-C is remembered, and the errors it causes where
    Python cannot raise them are dropped. During the JIT warm-up a Ctrl-C can land in an llvmlite callback (printed
    as "Exception ignored", then the compilation fails with a RuntimeError) or in a constructor (its object's
    ``__del__`` fails when freed, after the "interrupted" line); the user pressed Ctrl-C and sees only
    "interrupted" (:func:`run_cli` and the commands report any error after a Ctrl-C as the interruption). A Ctrl-C
    Python could only drop is delivered again, so the work stops even where the failed callback did not matter."""
    try:
        signal.signal(signal.SIGINT, _raise_interrupt)
    except (ValueError, OSError):  # not the main thread
        return
    sys.unraisablehook = _quiet_unraisable(sys.unraisablehook)
