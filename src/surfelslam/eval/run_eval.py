"""The evaluation step of a run's report: ATE / RPE of the written trajectory against the sequence's ground truth."""

from __future__ import annotations

from surfelslam.eval.metrics import evaluate
from surfelslam.slam.writer import RunRecord

#: Fewer processed frames than this: no evaluation (ATE and RPE need a few poses to mean anything).
EVAL_MIN_FRAMES = 3


def evaluate_run(record: RunRecord) -> None:
    """Add ``eval`` (:func:`~surfelslam.eval.metrics.evaluate`) to the run's metrics, or ``eval_error`` saying why
    there is none; nothing without ground truth or with fewer than :data:`EVAL_MIN_FRAMES` processed frames."""
    metrics = record.metrics
    if record.ground_truth is None or metrics["frames_processed"] < EVAL_MIN_FRAMES:
        return
    if len(record.trajectory) == 0:
        metrics["eval_error"] = "no frame has a pose (trajectory.txt is empty)"
        return
    try:
        metrics["eval"] = evaluate(record.trajectory, record.ground_truth)
    except Exception as exc:  # noqa: BLE001 - evaluation problems must not lose the run's outputs
        metrics["eval_error"] = str(exc)
