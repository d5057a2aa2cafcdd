"""``surfelslam run``: the whole pipeline on a sequence, writing trajectory, map, config, metrics and figures."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.table import Table

from surfelslam.datasets import open_sequence
from surfelslam.errors import ConfigError
from surfelslam.slam import TRACKERS
from surfelslam.slam.runner import load_config, run_sequence
from surfelslam.slam.segments import Segment
from surfelslam.tools.common import (
    DatasetOptionsArgs,
    SeqArg,
    console,
    handle_errors,
    with_dataset_options,
)

TRACKER_HELP = ("dense: frame-to-model ICP; orb: sparse ORB/PnP odometry + loop-closing pose graph (map = "
                "keyframe cloud); hybrid: dense ICP + PnP initial guesses, relocalisation and loop-corrected "
                "trajectory and surfel map. One of " + ", ".join(TRACKERS) + ". Default: the --config file's, "
                "else dense.")
#: Skipped frames quoted under the summary (``metrics.json`` lists them all).
SUMMARY_EXAMPLES = 5


SEGMENT_MIN_FRAMES_SHOWN = 5  # weak stretches shorter than this (frames) are only in metrics.json


def print_summary(metrics: dict, out_dir: Path) -> None:
    t = Table(title=f"surfelslam run -> {escape(str(out_dir))}", show_header=False)
    frames = f"{metrics['frames_processed']} processed, {metrics['frames_skipped']} skipped"
    if metrics.get("frames_unpaired"):
        frames += f", {metrics['frames_unpaired']} unpaired images left out"
    t.add_row("frames", frames)
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
    for s in metrics["skipped"][:SUMMARY_EXAMPLES]:
        console.print(f"[yellow]skipped frame {s['position']}:[/] {escape(s['reason'])}", highlight=False,
                      soft_wrap=True)
    if metrics.get("frames_unpaired"):
        u = metrics["unpaired"][0]
        more = metrics["frames_unpaired"] - 1
        console.print(f"[yellow]unpaired:[/] {metrics['frames_unpaired']} listed images without a partner, e.g. "
                      f"{escape(u['file'])}: {escape(u['reason'])}" + (f" (and {more} more, see metrics.json)"
                                                                        if more else ""),
                      highlight=False, soft_wrap=True)
    for w in metrics.get("warnings", []):
        console.print(f"[yellow]warning:[/] {escape(w)}", highlight=False, soft_wrap=True)
    segs = metrics.get("tracking_segments", [])
    shown = [s for s in segs if s["kind"] == "lost" or s["frames"] >= SEGMENT_MIN_FRAMES_SHOWN]
    for s in shown[:SUMMARY_EXAMPLES]:
        console.print(f"[yellow]{escape(Segment(**s).describe())}[/]", highlight=False, soft_wrap=True)
    if len(shown) > SUMMARY_EXAMPLES:
        console.print(f"[yellow]... and {len(shown) - SUMMARY_EXAMPLES} more segments (metrics.json)[/]")
    if metrics.get("lost_at_end"):
        last = [s for s in segs if s["kind"] == "lost"][-1]
        console.print(f"[bold red]the run ended lost[/] (from frame {last['first_frame']}): the poses after it are "
                      "predictions, not measurements", highlight=False, soft_wrap=True)


def resolve_run_config(config: str | None, sets: list[str] | None, tracker: str | None,
                       dataset: DatasetOptionsArgs):
    """The run's settings: the command-line flags, over ``--set``, over the ``--config`` file (or preset), over
    the defaults."""
    if tracker is not None and tracker not in TRACKERS:
        raise ConfigError(f"--tracker must be one of {', '.join(TRACKERS)}, got {tracker!r}")
    cfg = load_config(config, sets or ())
    return replace(cfg, tracker=cfg.tracker if tracker is None else tracker, dataset=dataset.resolve(cfg.dataset))


def register(app: typer.Typer) -> None:
    @app.command("run")
    @handle_errors
    @with_dataset_options
    def run_cmd(
        seq_path: SeqArg,
        dataset: DatasetOptionsArgs,
        out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")] = Path("out/run"),
        overwrite: Annotated[bool, typer.Option(
            "--overwrite", help="Replace the previous run in --out (only the run's own files are removed).")] = False,
        config: Annotated[str | None, typer.Option(
            "--config", help="TOML configuration file (e.g. a previous run's config.toml: the whole recipe), or a "
                             "preset name (configs/NAME.toml: fast, accurate).")] = None,
        sets: Annotated[list[str] | None, typer.Option(
            "--set", metavar="KEY=VALUE", help="Override one setting, e.g. --set icp.min_inliers=300 --set "
                                               "tracking.photometric=off (repeatable; a TOML value or a bare "
                                               "string).")] = None,
        tracker: Annotated[str | None, typer.Option("--tracker", help=TRACKER_HELP)] = None,
        poses: Annotated[str | None, typer.Option(
            "--poses", help="Map with given poses and skip tracking: 'gt' or a TUM trajectory file.")] = None,
        figures: Annotated[bool, typer.Option("--figures/--no-figures", help="Write PNG figures.")] = True,
        progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Show a progress bar.")] = True,
        rerun: Annotated[bool, typer.Option(
            "--rerun", help="Also write OUT/run.rrd, a Rerun recording (needs rerun-sdk; see `surfelslam rerun`)."
        )] = False,
        viewer: Annotated[str | None, typer.Option(
            "--viewer", metavar="spawn|connect[=ADDR]|serve|save=FILE",
            help="Show the run live in Rerun (needs rerun-sdk): spawn a viewer, connect to one (HOST:PORT), serve "
                 "a web viewer, or save a recording while running.")] = None,
        viewer_images_every: Annotated[int, typer.Option(
            "--viewer-images-every", help="Live viewer: log the images every N frames.")] = 5,
        viewer_map_every: Annotated[int, typer.Option(
            "--viewer-map-every", help="Live viewer: log the map (subsampled) every N frames.")] = 30,
        record: Annotated[Path | None, typer.Option(
            "--record", help="With the live camera (SEQ = realsense): also write the frames to this bag (.bag: "
                             "ROS 1, else a ROS 2 MCAP bag folder).")] = None,
    ) -> None:
        """Track and fuse a sequence; writes trajectory.txt, map.ply, config.toml, metrics.json and figures.

        Settings come from the command-line flags, then --set, then the --config file, then the defaults.
        config.toml records all of them (tracker and dataset options too): `surfelslam run SEQ --config
        OUT/config.toml` repeats the run. A --out folder that holds a previous run needs --overwrite; the run
        writes into OUT/.partial-PID/ and moves its files into OUT when complete.
        """
        cfg = resolve_run_config(config, sets, tracker, dataset)
        if rerun:
            from surfelslam.viz.rerun_export import require_rerun

            require_rerun()  # before the run, not after it
        if record is not None:
            from surfelslam.datasets.realsense import open_realsense

            seq = open_realsense(cfg.dataset, record=record, path=seq_path)
        else:
            seq = open_sequence(seq_path, cfg.dataset)
        exported = []
        from surfelslam.viz.live import finish_viewer, viewer_for_run

        def note(text: str) -> None:
            console.print(escape(text), style="yellow", highlight=False, soft_wrap=True)

        live = viewer_for_run(viewer, seq, viewer_images_every, viewer_map_every, warn=note)

        def started(stage: Path) -> None:
            console.print(f"run -> {escape(str(out))} (writing into {escape(str(stage))} until complete)",
                          highlight=False)

        def export(stage: Path) -> None:
            from surfelslam.tools.export_rerun import export_run

            exported.append(export_run(stage, seq=seq))

        try:
            metrics = run_sequence(seq, out, cfg, poses=poses, progress=progress, figures=figures,
                                   overwrite=overwrite, on_start=started, before_commit=export if rerun else None,
                                   on_frame=live)
        except BaseException:
            finish_viewer(live, None, warn=note, wait_when_serving=False)
            raise
        finally:
            if hasattr(seq, "close"):  # a bag, a live camera (and its recording)
                seq.close()
        print_summary(metrics, out)
        finish_viewer(live, out, warn=note)
        if exported:
            from surfelslam.tools.export_rerun import print_export

            summary, notes = exported[0]
            print_export(replace(summary, path=out / Path(summary.path).name), notes)
