"""The standard report of a run: its evaluation and its figures, written beside its other outputs.

:func:`run_report` is what ``surfelslam run`` and :meth:`surfelslam.SlamRun.save` pass to the run writer
(:class:`~surfelslam.slam.writer.RunWriter`): the writer lives below this layer and calls the report back.

The evaluation's and the figures' modules (evo, matplotlib) are imported when the report runs, or ahead of it by
:func:`preload_figure_modules` in a background thread while the run tracks, never when this module is imported: a
run's start does not pay for them. The figures are drawn concurrently, one thread per figure file
(:func:`run_concurrently`): each is its own matplotlib ``Figure`` on its own Agg canvas (no pyplot state), and
their numpy, numba and PNG work runs outside the GIL.
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable, Collection
from typing import TYPE_CHECKING

from surfelslam.errors import ConfigError
from surfelslam.slam.writer import RunRecord, RunReport

if TYPE_CHECKING:
    from surfelslam.eval.metrics import AteResult

#: The PNGs a run writes: the trajectory and its ATE errors (with ground truth), the map's two views.
RUN_FIGURES = frozenset({"trajectory", "ate_errors", "map_camera", "map_top"})


def figures_wanted(figures: bool | Collection[str]) -> frozenset[str]:
    """Every figure of :data:`RUN_FIGURES` (True), none (False), or those named (checked)."""
    if isinstance(figures, bool):
        return RUN_FIGURES if figures else frozenset()
    wanted = frozenset(figures)
    if not wanted <= RUN_FIGURES:
        raise ConfigError(f"figures: unknown {', '.join(sorted(wanted - RUN_FIGURES))}; known: "
                          f"{', '.join(sorted(RUN_FIGURES))}")
    return wanted


def run_report(figures: bool | Collection[str] = True) -> RunReport:
    """The report step: evaluation against the ground truth (when known) and the ``figures`` wanted (drawn
    concurrently, :func:`run_concurrently`)."""
    wanted = figures_wanted(figures)

    def report(record: RunRecord) -> None:
        from surfelslam.eval.run_eval import evaluate_run

        drawn = wanted if len(record.trajectory) else frozenset()
        # the evaluation first, alone: its thousands of small numpy calls each release the GIL, and beside the figure
        # threads each would wait for it again (several times its own time); then every figure side by side
        ate = evaluate_run(record)
        run_concurrently(trajectory_figure_jobs(record, drawn, ate) + map_figure_jobs(record, drawn))

    return report


def run_concurrently(jobs: list[Callable[[], object]]) -> None:
    """Run ``jobs``: the first in the calling thread, each other in a thread of its own; returns once all are done,
    raising the first job's error (in ``jobs`` order) if any failed. The threads are daemons: an interrupted
    caller does not wait for them (each figure is written to a temp file, then renamed)."""
    errors: list[BaseException | None] = [None] * len(jobs)

    def run(k: int) -> None:
        try:
            jobs[k]()
        except BaseException as exc:  # noqa: BLE001 - handed to the caller below
            errors[k] = exc

    threads = [threading.Thread(target=run, args=(k,), name=f"surfelslam-figure-{k}", daemon=True)
               for k in range(1, len(jobs))]
    for t in threads:
        t.start()
    if jobs:
        run(0)
    for t in threads:
        t.join()
    failed = next((e for e in errors if e is not None), None)
    if failed is not None:
        raise failed


def preload_figure_modules(figures: bool | Collection[str] = True) -> None:
    """Import the modules the report needs (evo for the evaluation; matplotlib and the plotting modules for the
    ``figures``) and warm the map figures' first use (:func:`~surfelslam.viz.map_figures.warm_up_map_figures`) ahead
    of time: about a second of a run's end; a run calls it in a background thread while it tracks."""
    import surfelslam.eval.metrics  # noqa: F401

    wanted = figures_wanted(figures)
    if wanted & {"map_camera", "map_top"}:
        from surfelslam.viz.map_figures import warm_up_map_figures

        warm_up_map_figures()
    if wanted & {"trajectory", "ate_errors"}:
        import surfelslam.viz.trajectory_plots  # noqa: F401


def trajectory_figure_jobs(record: RunRecord, wanted: frozenset[str], ate: AteResult | None,
                           ) -> list[Callable[[], object]]:
    """One job per trajectory figure ``wanted`` (``trajectory.png``, ``ate_errors.png``), drawn from the run's
    evaluation ``ate`` (:func:`~surfelslam.eval.run_eval.evaluate_run`'s); none without one."""
    if ate is None or not wanted & {"trajectory", "ate_errors"}:
        return []
    from surfelslam.viz.trajectory_plots import plot_errors, plot_trajectory

    out_dir = record.folder
    jobs: list[Callable[[], object]] = []
    if "trajectory" in wanted:
        jobs.append(functools.partial(plot_trajectory, out_dir / "trajectory.png", ate.est_aligned, ate.gt,
                                      title=f"{record.metrics['tracker']}: ATE RMSE {ate.rmse_m * 100:.2f} cm",
                                      loops=record.outcome.result.loop_stamps))
    if "ate_errors" in wanted:
        jobs.append(functools.partial(plot_errors, out_dir / "ate_errors.png", ate))
    return jobs


def map_figure_jobs(record: RunRecord, wanted: frozenset[str]) -> list[Callable[[], object]]:
    """One job per map view ``wanted`` (``map_camera.png``, ``map_top.png``); none when the map is empty."""
    views = tuple(v for v in ("camera", "top") if f"map_{v}" in wanted)
    cloud = record.outcome.result.map_arrays() if views else None
    if cloud is None or not len(cloud["position"]):
        return []
    from surfelslam.viz.map_figures import save_map_figures

    est = record.trajectory
    return [functools.partial(save_map_figures, record.folder, cloud["position"], cloud["normal"], cloud["colour"],
                              cloud["confidence"], cloud["first_seen"], est.T_world_cam[0],
                              title=f"{record.metrics['tracker']} map", trajectory_T_world_cam=est.T_world_cam,
                              radius=cloud.get("radius"), views=(view,)) for view in views]
