"""``surfelslam eval EST GT``: ATE / RPE of a TUM trajectory against ground truth, with plots and JSON.

Its files carry their own names (:data:`EVAL_FILES`: ``eval.json``, ``eval_trajectory.png``,
``eval_ate_errors.png``), none of which ``surfelslam run`` writes: evaluating a run in its own folder (the
default ``--out``) never replaces the run's outputs. The plots cover the estimate's time span.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.markup import escape
from rich.table import Table

from surfelslam.errors import ConfigError, EvaluationError, GroundTruthError, InputError
from surfelslam.tools.common import console, handle_errors

if TYPE_CHECKING:  # the library (numpy, evo) is imported when the command runs, not for its --help
    from surfelslam.types import Trajectory

#: --max-diff's default [s]: the TUM association window, :data:`surfelslam.eval.metrics.DEFAULT_MAX_DIFF_S` (a test
#: keeps the two equal; written out here so that ``eval --help`` does not import evo)
MAX_DIFF_DEFAULT_S = 0.02
GT_FILENAME = "groundtruth.txt"
#: what ``eval`` writes into its output folder (key -> file name); ``run`` writes none of these names
EVAL_FILES = {"json": "eval.json", "trajectory_png": "eval_trajectory.png", "ate_errors_png": "eval_ate_errors.png"}


def load_ground_truth(path: Path) -> Trajectory:
    """GT from a TUM file, or from a sequence folder (its ``ground_truth``)."""
    from surfelslam.io.trajectory import read_tum

    if not path.exists():
        raise InputError(path, "ground truth not found (expected a TUM trajectory file or a sequence folder)")
    if path.is_file():
        return read_tum(path)
    try:
        from surfelslam.datasets import open_sequence
    except ImportError:  # datasets adapters not available: plain TUM layout only
        open_sequence = None
    if open_sequence is not None:
        gt = open_sequence(path, plausibility="warn").ground_truth  # only its ground truth is used
    else:
        gt = read_tum(path / GT_FILENAME) if (path / GT_FILENAME).is_file() else None
    if gt is None:
        raise GroundTruthError(path, f"sequence has no ground truth ({GT_FILENAME} not found)")
    return gt


def load_estimate(path: Path) -> Trajectory:
    """The estimate: a TUM file, or a run folder's trajectory (:func:`~surfelslam.slam.run_reader.open_run`)."""
    from surfelslam.io.trajectory import read_tum
    from surfelslam.slam.run_reader import open_run

    if path.is_dir():
        return open_run(path).trajectory()
    return read_tum(path)


def check_max_diff(max_diff_s: float) -> float:
    if not (math.isfinite(max_diff_s) and max_diff_s >= 0):
        raise ConfigError(f"--max-diff must be a finite number of seconds >= 0, got {max_diff_s}")
    return max_diff_s


def within_span(gt: Trajectory, est: Trajectory, margin_s: float) -> Trajectory:
    """The ground-truth poses within the estimate's time span (plus ``margin_s`` each side); all of them when
    fewer than two fall inside."""
    t0, t1 = est.timestamps[0] - margin_s, est.timestamps[-1] + margin_s
    keep = (gt.timestamps >= t0) & (gt.timestamps <= t1)
    return gt.subset(keep) if keep.sum() >= 2 else gt


def _fmt(value: float | None, digits: int = 4) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def results_table(res: dict, title: str) -> Table:
    table = Table(title=escape(title), show_header=True, header_style="bold")
    table.add_column("metric")
    table.add_column("value", justify="right")
    table.add_column("unit")
    rows = [
        ("ATE RMSE", _fmt(res["ate_rmse_m"]), "m"),
        ("ATE mean", _fmt(res["ate_mean_m"]), "m"),
        ("ATE median", _fmt(res["ate_median_m"]), "m"),
        ("ATE max", _fmt(res["ate_max_m"]), "m"),
        ("RPE trans RMSE / frame", _fmt(res["rpe_trans_rmse_m_per_frame"]), "m"),
        ("RPE rot RMSE / frame", _fmt(res["rpe_rot_rmse_deg_per_frame"], 3), "deg"),
        ("RPE trans RMSE / second", _fmt(res["rpe_trans_rmse_m_per_s"]), "m/s"),
        ("RPE rot RMSE / second", _fmt(res["rpe_rot_rmse_deg_per_s"], 3), "deg/s"),
        ("associated poses", f"{res['n_pairs']}", f"of {res['n_est']} est / {res['n_gt']} gt"),
    ]
    for r in rows:
        table.add_row(*r)
    return table


def run_eval(est_path: Path, gt_path: Path, out_dir: Path | None, max_diff_s: float, plots: bool) -> dict:
    from surfelslam.eval import metrics
    from surfelslam.io.atomic import write_text_atomic
    from surfelslam.types import Trajectory

    check_max_diff(max_diff_s)
    est = load_estimate(est_path)
    gt = load_ground_truth(gt_path)
    base = est_path.resolve() if est_path.is_dir() else est_path.resolve().parent
    out_dir = base if out_dir is None else out_dir
    try:
        a, rf, rs = metrics.evaluate_all(est, gt, max_diff_s)
    except GroundTruthError as exc:
        raise GroundTruthError(None, f"{est_path} vs {gt_path}: {exc.problem}") from None
    except EvaluationError as exc:
        raise EvaluationError(f"{est_path} vs {gt_path}: {exc}") from None
    summary = metrics.summary(a, rf, rs, len(est), len(gt), max_diff_s)
    res = {"est": str(est_path), "gt": str(gt_path), **summary}
    files = {"json": str(out_dir / EVAL_FILES["json"])}
    if plots:
        from surfelslam.viz.trajectory_plots import plot_errors, plot_trajectory

        est_full_aligned = Trajectory(est.timestamps, a.T_align @ est.T_world_cam)
        gt_span = within_span(gt, est, max_diff_s)
        title = f"{est_path.name} vs {gt_path.name}: ATE RMSE {a.rmse_m:.4f} m ({a.n_pairs} poses)"
        files["trajectory_png"] = str(plot_trajectory(out_dir / EVAL_FILES["trajectory_png"], est_full_aligned,
                                                      gt_span, title))
        files["ate_errors_png"] = str(plot_errors(out_dir / EVAL_FILES["ate_errors_png"], a, rf))
    res["files"] = files
    write_text_atomic(out_dir / EVAL_FILES["json"], json.dumps(res, indent=2) + "\n")
    return res


def register(app: typer.Typer) -> None:
    @app.command("eval")
    @handle_errors
    def eval_cmd(
        est: Annotated[Path, typer.Argument(help="Estimated trajectory (TUM file, or a run folder).")],
        gt: Annotated[Path, typer.Argument(help="Ground truth: TUM file or sequence folder.")],
        out: Annotated[
            Path | None, typer.Option("--out", help="Output folder for eval.json, eval_trajectory.png and "
                                                    "eval_ate_errors.png (default: the folder of EST).")
        ] = None,
        max_diff: Annotated[
            float, typer.Option("--max-diff", help="Max timestamp difference for association [s].")
        ] = MAX_DIFF_DEFAULT_S,
        figures: Annotated[bool, typer.Option("--figures/--no-figures", help="Write PNG figures.")] = True,
        no_plots: Annotated[bool, typer.Option("--no-plots", hidden=True, help="Old name of --no-figures.")] = False,
    ) -> None:
        """ATE (SE(3)-aligned, TUM protocol) and RPE per frame and per second, computed with evo."""
        res = run_eval(est, gt, out, max_diff, plots=figures and not no_plots)
        console.print(results_table(res, f"{est.name} vs {gt}"))
        for f in res["files"].values():
            console.print(f"wrote {f}", highlight=False, markup=False)
