"""``surfelslam eval EST GT``: ATE / RPE of a TUM trajectory against ground truth, with plots and JSON."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.table import Table

from surfelslam.errors import GroundTruthError, InputError
from surfelslam.eval import metrics
from surfelslam.io.atomic import write_text_atomic
from surfelslam.io.trajectory import read_tum
from surfelslam.tools.common import console, handle_errors
from surfelslam.types import Trajectory

GT_FILENAME = "groundtruth.txt"


def load_ground_truth(path: Path) -> Trajectory:
    """GT from a TUM file, or from a sequence folder (its ``ground_truth``)."""
    if not path.exists():
        raise InputError(path, "ground truth not found (expected a TUM trajectory file or a sequence folder)")
    if path.is_file():
        return read_tum(path)
    try:
        from surfelslam.datasets import open_sequence
    except ImportError:  # datasets adapters not available: plain TUM layout only
        open_sequence = None
    if open_sequence is not None:
        gt = open_sequence(path).ground_truth
    else:
        gt = read_tum(path / GT_FILENAME) if (path / GT_FILENAME).is_file() else None
    if gt is None:
        raise GroundTruthError(path, f"sequence has no ground truth ({GT_FILENAME} not found)")
    return gt


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
    est = read_tum(est_path)
    gt = load_ground_truth(gt_path)
    out_dir = est_path.resolve().parent if out_dir is None else out_dir
    try:
        a, rf, rs = metrics.evaluate_all(est, gt, max_diff_s)
    except GroundTruthError as exc:
        raise GroundTruthError(None, f"{est_path} vs {gt_path}: {exc.problem}") from None
    summary = metrics.summary(a, rf, rs, len(est), len(gt), max_diff_s)
    res = {"est": str(est_path), "gt": str(gt_path), **summary}
    files = {"json": str(out_dir / "eval.json")}
    if plots:
        from surfelslam.viz.trajectory_plots import plot_errors, plot_trajectory

        est_full_aligned = Trajectory(est.timestamps, a.T_align @ est.T_world_cam)
        title = f"{est_path.name} vs {gt_path.name}: ATE RMSE {a.rmse_m:.4f} m ({a.n_pairs} poses)"
        traj_png = plot_trajectory(out_dir / "trajectory.png", est_full_aligned, gt, title)
        files["trajectory_png"] = str(traj_png)
        files["ate_errors_png"] = str(plot_errors(out_dir / "ate_errors.png", a, rf))
    res["files"] = files
    write_text_atomic(out_dir / "eval.json", json.dumps(res, indent=2) + "\n")
    return res


def register(app: typer.Typer) -> None:
    @app.command("eval")
    @handle_errors
    def eval_cmd(
        est: Annotated[Path, typer.Argument(help="Estimated trajectory (TUM file).")],
        gt: Annotated[Path, typer.Argument(help="Ground truth: TUM file or sequence folder.")],
        out: Annotated[
            Path | None, typer.Option("--out", help="Output folder (default: the folder of EST).")
        ] = None,
        max_diff: Annotated[
            float, typer.Option("--max-diff", help="Max timestamp difference for association [s].")
        ] = metrics.DEFAULT_MAX_DIFF_S,
        no_plots: Annotated[bool, typer.Option("--no-plots", help="Skip the PNG figures.")] = False,
    ) -> None:
        """ATE (SE(3)-aligned, TUM protocol) and RPE per frame and per second, computed with evo."""
        res = run_eval(est, gt, out, max_diff, plots=not no_plots)
        console.print(results_table(res, f"{est.name} vs {gt}"))
        for f in res["files"].values():
            console.print(f"wrote {f}", highlight=False, markup=False)
