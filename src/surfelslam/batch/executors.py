"""Where batch jobs run. Every executor calls the same :func:`~surfelslam.batch.jobs.run_job`.

* :class:`LocalExecutor`: in this process, one job after the other (the reference, and the fallback without Ray);
* :class:`RayExecutor`: one Ray task per job (``@ray.remote(num_cpus=2, memory=..., max_retries=N)``), on a
  local Ray started in-process (sized to the machine) or on a cluster (``address="auto"`` or
  ``"ray://host:10001"``).

A job that raises (a crash, a killed worker) is retried ``retries`` times; after that it is a ``failed`` row with
its reason, and the batch goes on. Ctrl-C (KeyboardInterrupt) cancels what has not finished and propagates; the
finished runs stay (run folders are handed over atomically).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from surfelslam.batch.jobs import Job, one_line, run_job, summary
from surfelslam.errors import ConfigError

#: threads of one dense run (the tracking thread and the frame reader): the CPUs a task declares
CPUS_PER_JOB = 2
#: Ray task retries after a crash or a lost worker (``--retries``)
DEFAULT_RETRIES = 2
RAY_EXTRA_HINT = "pip install 'surfelslam[batch]'"
#: memory a run needs besides its frames: the interpreter, numba, the kernels' buffers
_BASE_BYTES = 600 << 20
#: per pixel of the working resolution: pyramids, rendered model, the surfel map growing over a sequence
_BYTES_PER_PIXEL = 2500

OnResult = Callable[[Job, dict[str, Any]], None]


class Executor(Protocol):
    """Runs jobs and reports each job's results row through ``on_result`` as it finishes."""

    name: str

    def run(self, jobs: Sequence[Job], on_result: OnResult) -> None: ...


def memory_estimate(job: Job, width: int = 640, height: int = 480) -> int:
    """Bytes a job is declared to need (Ray packs tasks by it): a base plus a per-pixel share of the working
    resolution (``640x480 / downsample``); about 1.3 GiB for a full-resolution TUM sequence."""
    d = max(job.config.dataset.downsample, 1)
    return _BASE_BYTES + _BYTES_PER_PIXEL * (width // d) * (height // d)


def ray_available() -> bool:
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


def failed_row(job: Job, exc: BaseException) -> dict[str, Any]:
    return summary(job.describe(), None, "failed", one_line(exc))


class LocalExecutor:
    """In-process, serial. A job raising an unexpected exception is run again, up to ``retries`` times."""

    name = "local"

    def __init__(self, retries: int = 0):
        self.retries = max(int(retries), 0)

    def run(self, jobs: Sequence[Job], on_result: OnResult) -> None:
        for job in jobs:
            for attempt in range(self.retries + 1):
                try:
                    row = run_job(job)
                except Exception as exc:  # noqa: BLE001 - a job's crash is its row, the batch goes on
                    if attempt < self.retries:
                        continue
                    row = failed_row(job, exc)
                    row["error"] += f" (after {self.retries + 1} attempts)" if self.retries else ""
                break
            on_result(job, row)


class RayExecutor:
    """One Ray task per job. ``address``: ``None`` starts a local Ray in this process (all the machine's CPUs),
    ``"auto"`` joins the cluster this node belongs to, ``"ray://host:10001"`` connects a Ray client.
    ``env_vars`` are set in the workers (e.g. ``NUMBA_CACHE_DIR``)."""

    name = "ray"

    def __init__(self, address: str | None = None, retries: int = DEFAULT_RETRIES, env_vars: dict | None = None,
                 init_kwargs: dict | None = None):
        require_ray()
        self.address = address
        self.retries = max(int(retries), 0)
        self.env_vars = dict(env_vars or {})
        self.init_kwargs = dict(init_kwargs or {})

    def _init(self):
        import ray

        if not ray.is_initialized():
            kwargs: dict[str, Any] = {"address": self.address, "ignore_reinit_error": True,
                                      "log_to_driver": False}
            if self.address is None:
                kwargs["num_cpus"] = None  # local: sized to the machine
            if self.env_vars:
                kwargs["runtime_env"] = {"env_vars": self.env_vars}
            kwargs.update(self.init_kwargs)
            ray.init(**kwargs)
        return ray

    def run(self, jobs: Sequence[Job], on_result: OnResult) -> None:
        if not jobs:
            return
        ray = self._init()
        resources = ray.cluster_resources()
        cpus = min(CPUS_PER_JOB, max(resources.get("CPU", CPUS_PER_JOB), 1))
        mem_cap = resources.get("memory")
        task = ray.remote(run_job)
        refs: dict[Any, Job] = {}
        for job in jobs:
            mem = memory_estimate(job)
            if mem_cap:
                mem = min(mem, int(mem_cap * 0.9))
            opts: dict[str, Any] = {"num_cpus": cpus, "memory": mem, "max_retries": self.retries,
                                    "retry_exceptions": True}
            if self.env_vars:
                opts["runtime_env"] = {"env_vars": self.env_vars}
            refs[task.options(**opts).remote(job)] = job
        pending = list(refs)
        try:
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                for ref in ready:
                    job = refs[ref]
                    try:
                        row = ray.get(ref)
                    except KeyboardInterrupt:
                        raise
                    except Exception as exc:  # noqa: BLE001 - RayTaskError, WorkerCrashedError, ...
                        cause = getattr(exc, "cause", None)
                        row = failed_row(job, cause if isinstance(cause, BaseException) else exc)
                        row["error"] += f" (after {self.retries + 1} attempts)" if self.retries else ""
                    on_result(job, row)
        except KeyboardInterrupt:
            for ref in pending:
                try:
                    ray.cancel(ref, force=True)
                except Exception:  # noqa: BLE001 - best effort while stopping
                    pass
            raise


def require_ray() -> None:
    """Raise the one-line ConfigError naming the extra when Ray is not importable."""
    if not ray_available():
        raise ConfigError(f"--executor ray needs Ray: {RAY_EXTRA_HINT} (or use --executor local)")


def make_executor(kind: str | None, address: str | None = None, retries: int = DEFAULT_RETRIES,
                  env_vars: dict | None = None) -> tuple[Executor, str | None]:
    """The executor ``kind`` names (``None``: Ray when importable, else local) and a note to print (or None)."""
    if kind is None:
        if ray_available():
            kind = "ray"
        else:
            if address is not None:
                require_ray()
            note = f"Ray is not installed: running the jobs here, one by one ({RAY_EXTRA_HINT} for Ray)"
            return LocalExecutor(retries), note
    if kind == "local":
        if address is not None:
            raise ConfigError("--address needs --executor ray")
        return LocalExecutor(retries), None
    if kind == "ray":
        return RayExecutor(address, retries, env_vars), None
    raise ConfigError(f"--executor must be ray or local, got {kind!r}")


def numba_cache_env() -> dict[str, str]:
    """``{"NUMBA_CACHE_DIR": ...}`` for the workers when the kernels' in-tree cache is not writable (the same
    fallback as :func:`surfelslam.cli.numba_cache_fallback`, one folder for every worker); else ``{}``: numba's
    in-tree cache is shared as it is."""
    from surfelslam.cli import KERNEL_CACHE_DIR, NUMBA_CACHE_ENV, _writable_dir, numba_cache_fallback

    if _writable_dir(KERNEL_CACHE_DIR):
        return {}
    chosen = os.environ.get(NUMBA_CACHE_ENV) or numba_cache_fallback()
    if chosen:
        os.environ[NUMBA_CACHE_ENV] = chosen  # this process's warm-up fills the cache the workers read
        return {NUMBA_CACHE_ENV: chosen}
    return {}
