"""``surfelslam run``: the whole pipeline on a sequence, writing trajectory, map, config, metrics and figures."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.table import Table

from surfelslam.datasets import open_sequence
from surfelslam.errors import ConfigError
from surfelslam.slam import TRACKERS
from surfelslam.slam.runner import load_config, run_sequence
from surfelslam.tools.common import (
    DepthScaleOpt,
    DownsampleOpt,
    EndOpt,
    IntrinsicsOpt,
    SeqArg,
    StartOpt,
    StrideOpt,
    console,
    dataset_options,
    handle_errors,
)

TRACKER_HELP = ("dense: frame-to-model ICP; orb: sparse ORB/PnP odometry + loop-closing pose graph (map = "
                "keyframe cloud); hybrid: dense ICP + PnP initial guesses, relocalisation and loop-corrected "
                "trajectory and surfel map. One of " + ", ".join(TRACKERS) + ".")


def print_summary(metrics: dict, out_dir: Path) -> None:
    t = Table(title=f"surfelslam run -> {escape(str(out_dir))}", show_header=False)
    t.add_row("frames", f"{metrics['frames_processed']} processed, {metrics['frames_skipped']} skipped")
    t.add_row("tracking failures", str(metrics.get("tracking_failures", 0)))
    t.add_row("FPS", f"{metrics['fps']:.1f}  (JIT warm-up {metrics['warmup_s']:.1f} s excluded)")
    stages = "  ".join(f"{k} {v['mean']:.1f}" for k, v in metrics["stage_ms"].items())
    t.add_row("ms per stage", stages)
    t.add_row("map points", f"{metrics['map_points']:,}  (compression {metrics['compression_ratio'] * 100:.2f}%)")
    if "eval" in metrics:
        e = metrics["eval"]
        t.add_row("ATE RMSE", f"{e['ate_rmse_m'] * 100:.2f} cm")
        t.add_row("RPE / frame", f"{e['rpe_trans_rmse_m_per_frame'] * 1000:.2f} mm, "
                                 f"{e['rpe_rot_rmse_deg_per_frame']:.3f} deg")
    elif "eval_error" in metrics:
        t.add_row("ATE", f"not computed: {escape(str(metrics['eval_error']))}")
    for k in ("relocalisations", "loops_found", "loops_accepted"):
        if k in metrics:
            t.add_row(k.replace("_", " "), str(metrics[k]))
    console.print(t)
    for s in metrics["skipped"][:5]:
        console.print(f"[yellow]skipped frame {s['position']}:[/] {escape(s['reason'])}", highlight=False,
                      soft_wrap=True)


def register(app: typer.Typer) -> None:
    @app.command("run")
    @handle_errors
    def run_cmd(
        seq_path: SeqArg,
        out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")] = Path("out/run"),
        config: Annotated[Path | None, typer.Option("--config", help="TOML configuration file.")] = None,
        tracker: Annotated[str, typer.Option("--tracker", help=TRACKER_HELP)] = "dense",
        poses: Annotated[str | None, typer.Option(
            "--poses", help="Map with given poses and skip tracking: 'gt' or a TUM trajectory file.")] = None,
        figures: Annotated[bool, typer.Option("--figures/--no-figures", help="Write PNG figures.")] = True,
        progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Show a progress bar.")] = True,
        intrinsics: IntrinsicsOpt = None,
        depth_scale: DepthScaleOpt = None,
        start: StartOpt = 0,
        end: EndOpt = None,
        stride: StrideOpt = 1,
        downsample: DownsampleOpt = 1,
        rerun: Annotated[bool, typer.Option(
            "--rerun", help="Also write OUT/run.rrd, a Rerun recording (needs rerun-sdk; see `surfelslam rerun`)."
        )] = False,
    ) -> None:
        """Track and fuse a sequence; writes trajectory.txt, map.ply, config.toml, metrics.json and figures."""
        if tracker not in TRACKERS:
            raise ConfigError(f"--tracker must be one of {', '.join(TRACKERS)}, got {tracker!r}")
        if rerun:
            from surfelslam.viz.rerun_export import require_rerun

            require_rerun()  # before the run, not after it
        cfg = load_config(config)
        seq = open_sequence(seq_path, dataset_options(intrinsics, depth_scale, start, end, stride, downsample))
        metrics = run_sequence(seq, out, cfg, tracker, poses=poses, progress=progress, figures=figures)
        print_summary(metrics, out)
        if rerun:
            from surfelslam.tools.export_rerun import export_run, print_export

            print_export(*export_run(out, seq=seq))
