"""The evaluation step of a run's report: ATE / RPE of the written trajectory against the sequence's ground truth."""

from __future__ import annotations

from typing import TYPE_CHECKING

from surfelslam.slam.writer import RunRecord

if TYPE_CHECKING:
    from surfelslam.eval.metrics import AteResult

#: Fewer processed frames than this: no evaluation (ATE and RPE need a few poses to mean anything).
EVAL_MIN_FRAMES = 3


def evaluate_run(record: RunRecord) -> AteResult | None:
    """Add ``eval`` (:func:`~surfelslam.eval.metrics.evaluate`) to the run's metrics, or ``eval_error`` saying why
    there is none; nothing without ground truth or with fewer than :data:`EVAL_MIN_FRAMES` processed frames.

    Returns the ATE (its aligned poses and errors: the trajectory figures draw them), ``None`` without an evaluation.
    """
    from surfelslam.eval.metrics import DEFAULT_MAX_DIFF_S, evaluate_all, summary  # evo: only where it is needed

    metrics = record.metrics
    if record.ground_truth is None or metrics["frames_processed"] < EVAL_MIN_FRAMES:
        return None
    if len(record.trajectory) == 0:
        metrics["eval_error"] = "no frame has a pose (trajectory.txt is empty)"
        return None
    try:
        a, rf, rs = evaluate_all(record.trajectory, record.ground_truth, DEFAULT_MAX_DIFF_S)
    except Exception as exc:  # noqa: BLE001 - evaluation problems must not lose the run's outputs
        metrics["eval_error"] = str(exc)
        return None
    metrics["eval"] = summary(a, rf, rs, len(record.trajectory), len(record.ground_truth), DEFAULT_MAX_DIFF_S)
    return a
