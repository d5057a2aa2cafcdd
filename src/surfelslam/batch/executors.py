"""Where batch jobs run. Every executor calls the same :func:`~surfelslam.batch.jobs.run_job`.

* :class:`LocalExecutor`: in this process, one job after the other (the reference, and the fallback without Ray);
* :class:`RayExecutor`: one Ray task per job (``num_cpus=2``, ``memory=<estimate>``, ``max_retries=N``), on a
  local Ray started in-process (sized to the machine, shut down after the batch) or on a cluster
  (``address="auto"`` or ``"ray://host:10001"``).

A job that raises (a crash) or whose worker dies (killed, out of memory) is run again, ``retries`` times; after
that it is a ``failed`` row with its reason, and the batch goes on. Ctrl-C (KeyboardInterrupt) cancels what has
not finished and propagates; the finished runs stay (run folders are handed over atomically).
"""

from __future__ import annotations

import logging
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
#: a task never declares more than this share of the cluster's memory (else Ray could never schedule it)
_MAX_MEMORY_SHARE = 0.9
#: ``ray.init(address=...)`` for a new Ray in this process; the variable a Ray job's driver finds its cluster by
LOCAL_RAY, RAY_ADDRESS_ENV = "local", "RAY_ADDRESS"
#: the Ray logger's level in this process: Ray's warnings, not its start-up chatter
_RAY_LOG_LEVEL = logging.WARNING
#: the logger of Ray's notice that a cluster it starts uses token authentication (its secure default): no warning
_RAY_TOKEN_LOGGER = "ray._private.authentication.authentication_token_setup"

OnResult = Callable[[Job, dict[str, Any]], None]
#: what a task runs for one job: :func:`run_job` (tests wrap it to inject faults or to look inside a worker)
TaskFn = Callable[[Job], dict[str, Any]]


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


def failed_row(job: Job, reason: BaseException | str, attempts: int = 1) -> dict[str, Any]:
    """A ``failed`` row; ``attempts`` > 1 is said in the reason."""
    text = reason if isinstance(reason, str) else one_line(reason)
    if attempts > 1:
        text += f" (after {attempts} attempts)"
    return summary(job.describe(), None, "failed", text)


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
                    row = failed_row(job, exc, self.retries + 1)
                break
            on_result(job, row)


def ray_failure_reason(exc: BaseException) -> str:
    """One line for a Ray task's final error: the job's own exception (a ``RayTaskError``'s cause), or what
    happened to its worker (Ray's messages for those run over several lines and name log files)."""
    import ray.exceptions as rex

    if isinstance(exc, rex.RayTaskError):
        cause = getattr(exc, "cause", None)
        return one_line(cause) if isinstance(cause, BaseException) else one_line(exc)
    if isinstance(exc, rex.OutOfMemoryError):
        return f"the worker was killed for using too much memory ({type(exc).__name__})"
    if isinstance(exc, rex.WorkerCrashedError | rex.NodeDiedError | rex.LocalRayletDiedError):
        return f"the worker died while running the job ({type(exc).__name__})"
    return one_line(exc)


def local_or(address: str | None) -> str | None:
    """The ``ray.init`` address for ``--address``: as given; without one, ``RAY_ADDRESS`` when set (a ``ray job
    submit`` entry point has it), else a new local Ray (:data:`LOCAL_RAY`), even when ``ray start`` left a
    cluster running on this machine (``--address auto`` joins that one)."""
    if address is not None:
        return address
    return None if os.environ.get(RAY_ADDRESS_ENV) else LOCAL_RAY


class RayExecutor:
    """One Ray task per job. ``address``: ``None`` starts a local Ray in this process (all the machine's CPUs;
    see :func:`local_or`) unless Ray is already initialised, ``"auto"`` joins the cluster this node belongs to,
    ``"ray://host:10001"`` connects a Ray client. A Ray this executor started is shut down after the batch.
    ``env_vars`` are set in the workers (e.g. ``NUMBA_CACHE_DIR``); ``task`` is what a task runs for a job
    (:func:`run_job`)."""

    name = "ray"

    def __init__(self, address: str | None = None, retries: int = DEFAULT_RETRIES, env_vars: dict | None = None,
                 init_kwargs: dict | None = None, task: TaskFn = run_job):
        require_ray()
        self.address = address
        self.retries = max(int(retries), 0)
        self.env_vars = dict(env_vars or {})
        self.init_kwargs = dict(init_kwargs or {})
        self.task = task

    def _init(self) -> tuple[Any, bool]:
        """``(ray, started)``: Ray connected (started here when it was not initialised)."""
        import ray

        if ray.is_initialized():
            return ray, False
        kwargs: dict[str, Any] = {"address": local_or(self.address), "log_to_driver": False,
                                  "logging_level": _RAY_LOG_LEVEL}
        if kwargs["address"] == LOCAL_RAY:
            kwargs["include_dashboard"] = False  # a local Ray for this batch: nobody to look at it
            logging.getLogger(_RAY_TOKEN_LOGGER).setLevel(logging.ERROR)
        kwargs.update(self.init_kwargs)
        try:
            ray.init(**kwargs)
        except (ConnectionError, TimeoutError, ValueError, RuntimeError) as exc:  # no cluster there, bad address
            where = f" at {self.address}" if self.address else ""
            raise ConfigError(f"cannot start or join Ray{where}: {' '.join(str(exc).split()) or type(exc).__name__}"
                              ) from exc
        return ray, True

    def task_options(self, job: Job, resources: dict[str, float]) -> dict[str, Any]:
        """The Ray options of ``job``'s task: its CPUs and memory (capped by what the cluster has, so that it
        can be scheduled), its retries, the workers' environment."""
        cpus = min(CPUS_PER_JOB, max(resources.get("CPU", CPUS_PER_JOB), 1))
        mem = memory_estimate(job)
        if resources.get("memory"):
            mem = min(mem, int(resources["memory"] * _MAX_MEMORY_SHARE))
        opts: dict[str, Any] = {"num_cpus": cpus, "memory": mem, "max_retries": self.retries,
                                "retry_exceptions": True}
        if self.env_vars:
            opts["runtime_env"] = {"env_vars": dict(self.env_vars)}
        return opts

    def run(self, jobs: Sequence[Job], on_result: OnResult) -> None:
        if not jobs:
            return
        ray, started = self._init()
        try:
            self._run(ray, jobs, on_result)
        finally:
            if started:
                ray.shutdown()

    def _run(self, ray: Any, jobs: Sequence[Job], on_result: OnResult) -> None:
        resources = ray.cluster_resources()
        remote = ray.remote(self.task)
        refs = {remote.options(**self.task_options(job, resources)).remote(job): job for job in jobs}
        pending = list(refs)
        try:
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                for ref in ready:
                    job = refs[ref]
                    try:
                        row = ray.get(ref)
                    except ray.exceptions.RayError as exc:  # the job's exception, a dead worker, ...
                        row = failed_row(job, ray_failure_reason(exc), self.retries + 1)
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
    """``{"NUMBA_CACHE_DIR": ...}`` for the workers, or ``{}`` when numba's in-tree cache (next to the kernels'
    sources, which every worker of this install reads) is used.

    The folder is the one this process uses: the user's ``NUMBA_CACHE_DIR``, else the CLI's fallback when the
    in-tree cache is not writable (:func:`surfelslam.numba_cache.numba_cache_fallback`, one folder for every
    worker). It is set here too, so that this process's warm-up fills the cache the workers then load.
    """
    from surfelslam.numba_cache import NUMBA_CACHE_ENV, numba_cache_fallback

    chosen = os.environ.get(NUMBA_CACHE_ENV) or numba_cache_fallback()
    if not chosen:
        return {}
    os.environ[NUMBA_CACHE_ENV] = chosen
    return {NUMBA_CACHE_ENV: chosen}
