"""The standard report of a run: its evaluation and its figures, written beside its other outputs.

:func:`run_report` is what ``surfelslam run`` and :meth:`surfelslam.SlamRun.save` pass to the run writer
(:class:`~surfelslam.slam.writer.RunWriter`): the writer lives below this layer and calls the report back.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Collection

from surfelslam.errors import ConfigError
from surfelslam.eval.metrics import ate
from surfelslam.eval.run_eval import evaluate_run
from surfelslam.slam.writer import RunRecord, RunReport

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
    """The report step: evaluation against the ground truth (when known), then the ``figures`` wanted."""
    wanted = figures_wanted(figures)

    def report(record: RunRecord) -> None:
        evaluate_run(record)
        if wanted and len(record.trajectory):
            write_trajectory_figures(record, wanted)
            for job in map_figure_jobs(record, wanted):
                job()

    return report


def preload_figure_modules(figures: bool | Collection[str] = True) -> None:
    """Import the modules the ``figures`` need (matplotlib and the plotting modules) and warm the map figures'
    first use (:func:`~surfelslam.viz.map_figures.warm_up_map_figures`) ahead of time: about a second of a run's
    end; a run calls it in a background thread while it tracks."""
    wanted = figures_wanted(figures)
    if wanted & {"map_camera", "map_top"}:
        from surfelslam.viz.map_figures import warm_up_map_figures

        warm_up_map_figures()
    if wanted & {"trajectory", "ate_errors"}:
        import surfelslam.viz.trajectory_plots  # noqa: F401


def write_trajectory_figures(record: RunRecord, wanted: frozenset[str]) -> None:
    """``trajectory.png`` and ``ate_errors.png`` where ``wanted`` and the run has an evaluation."""
    out_dir, metrics, result, est = record.folder, record.metrics, record.outcome.result, record.trajectory
    if "eval" in metrics and wanted & {"trajectory", "ate_errors"}:
        from surfelslam.viz.trajectory_plots import plot_errors, plot_trajectory

        a = ate(est, record.ground_truth)
        if "trajectory" in wanted:
            plot_trajectory(out_dir / "trajectory.png", a.est_aligned, a.gt,
                            title=f"{metrics['tracker']}: ATE RMSE {a.rmse_m * 100:.2f} cm", loops=result.loop_stamps)
        if "ate_errors" in wanted:
            plot_errors(out_dir / "ate_errors.png", a)


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
