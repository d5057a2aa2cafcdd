"""Serial / parallel twins of the per-pixel kernels, chosen at run time.

Every hot kernel written with ``prange`` is compiled twice (lazily, on first use): ``parallel=True`` and
serial (``prange`` runs as ``range``). Both release the GIL (``nogil``), so a frame-reading thread keeps
running while a kernel works. :func:`set_parallel` switches all kernels at once; the pipelines apply
``SlamConfig.compute.parallel_kernels`` (serial by default: on 2 cores the frame reader thread needs the
second core). Idle OpenMP workers sleep (``OMP_WAIT_POLICY=PASSIVE``, below): spinning workers would starve the
reader thread and other jobs.

Results do not depend on the choice: the parallel kernels write disjoint outputs per row or reduce fixed
chunks in a fixed order, which the serial twin reproduces exactly.
"""

from __future__ import annotations

import functools
import os
import sys
import threading
import types

from numba import njit

_STATE = {"parallel": False}

# If parallel kernels are switched on, let idle OpenMP workers sleep instead of spinning (the spinning
# starves the reader thread and other processes on a small machine). Read by libgomp when numba loads its
# OpenMP threading layer, i.e. at the first parallel kernel call, after this import; a user setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


#: the least priority a thread can be given (Linux nice values run from -20 to 19)
_LOWEST_NICE = 19


def lower_thread_priority(nice_increment: int) -> None:
    """Lower the calling thread's CPU priority by ``nice_increment`` nice levels (Linux, where nice is per thread;
    elsewhere nothing: a process-wide call would slow the tracking thread too). For worker threads whose results
    are wanted later than their inputs arrive (a thread pool's ``initializer``): on two cores, four busy threads
    share them, and the tracking thread waits each frame for the one that works on its path; the others then
    take the cores it leaves idle instead of slowing it. Scheduling only: no result changes."""
    if sys.platform != "linux" or nice_increment <= 0:
        return
    tid = threading.get_native_id()
    try:
        nice = os.getpriority(os.PRIO_PROCESS, tid)
        os.setpriority(os.PRIO_PROCESS, tid, min(nice + nice_increment, _LOWEST_NICE))
    except OSError:  # a system that refuses the hint runs the thread at its priority
        pass


def set_parallel(on: bool) -> None:
    """Use the ``parallel=True`` twins (True) or the serial ones (False, the default)."""
    _STATE["parallel"] = bool(on)


def parallel_enabled() -> bool:
    return _STATE["parallel"]


# numba threading layers that accept parallel kernels launched from two Python threads at once
_CONCURRENT_LAYERS = ("omp", "tbb")


def concurrent_launch_safe() -> bool:
    """Whether kernels may run in two Python threads at once (the reader thread preparing frames while the main
    thread tracks): always with the serial twins; with the parallel ones only on the OpenMP or TBB threading
    layer (numba's fallback ``workqueue`` layer does not support concurrent parallel launches). Call after a
    parallel kernel has run (the layer is chosen then); before that it answers False when parallel is on."""
    if not _STATE["parallel"]:
        return True
    import numba

    try:
        return numba.threading_layer() in _CONCURRENT_LAYERS
    except ValueError:  # no parallel kernel has run yet: the layer is unknown
        return False


def _renamed(f, suffix: str):
    """A copy of ``f`` with its own name: numba's on-disk cache keys by qualified name, not by flags."""
    g = types.FunctionType(f.__code__, f.__globals__, f.__name__ + suffix, f.__defaults__, f.__closure__)
    g.__qualname__ = f.__qualname__ + suffix
    g.__kwdefaults__ = f.__kwdefaults__
    g.__doc__ = f.__doc__
    g.__module__ = f.__module__
    return g


class DualKernel:
    """Callable that dispatches to the serial or the parallel compilation of one kernel."""

    def __init__(self, py_func, opts: dict):
        self.py_func = py_func
        self.serial = njit(nogil=True, cache=True, **opts)(py_func)
        self.parallel = njit(nogil=True, cache=True, parallel=True, **opts)(_renamed(py_func, "__parallel"))
        functools.update_wrapper(self, py_func)

    def __call__(self, *args, **kwargs):
        return (self.parallel if _STATE["parallel"] else self.serial)(*args, **kwargs)


def dual_njit(**opts):
    """Decorator: like ``njit(cache=True, nogil=True, **opts)``, compiled serially and in parallel."""
    return lambda f: DualKernel(f, opts)
