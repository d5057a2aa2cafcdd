"""Dataset-scale batch runs: sequences x trackers x configurations, one run folder per job, one results table.

* :mod:`.spec`: a spec TOML file or the inline command-line form -> a list of :class:`~.jobs.Job`;
* :mod:`.jobs`: one job (its folder name, config hash, the "already complete" check, and running it through
  :func:`surfelslam.slam.runner.run_sequence`);
* :mod:`.executors`: where the jobs run: :class:`~.executors.LocalExecutor` (in-process, serial) or
  :class:`~.executors.RayExecutor` (a Ray task per job, local or on a cluster);
* :mod:`.report`: ``results.csv``, ``results.md`` and per-sequence ATE plots, also rebuilt from run folders.

:func:`run_batch` ties them together (what ``surfelslam batch`` calls). See docs/batch.md.
"""

from surfelslam.batch.driver import BatchResult, run_batch
from surfelslam.batch.jobs import Job, run_job
from surfelslam.batch.spec import BatchSpec, expand_jobs, inline_spec, load_spec

__all__ = ["BatchResult", "BatchSpec", "Job", "expand_jobs", "inline_spec", "load_spec", "run_batch", "run_job"]
