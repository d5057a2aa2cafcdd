"""``surfelslam run``: the whole pipeline on a sequence, writing trajectory, map, config, metrics and figures.

The library (numba, OpenCV, the trackers) is imported inside the command, so that ``surfelslam run --help`` stays
light: at module level only typer, rich and the package's light modules are imported.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.table import Table

from surfelslam.errors import ConfigError
from surfelslam.tools.common import (
    DatasetOptionsArgs,
    SeqArg,
    console,
    handle_errors,
    with_dataset_options,
)

TRACKER_HELP = ("hybrid: dense ICP + ORB back end (PnP guesses, relocalisation, loop-corrected trajectory and "
                "surfel map); dense: frame-to-model ICP alone; orb: sparse ORB/PnP odometry + loop-closing pose graph "
                "(map = keyframe cloud). Default: the --config file's, else hybrid.")
#: Skipped frames quoted under the summary (``metrics.json`` lists them all).
SUMMARY_EXAMPLES = 5


SEGMENT_MIN_FRAMES_SHOWN = 5  # weak stretches shorter than this (frames) are only in metrics.json


def print_summary(metrics: dict, out_dir: Path) -> None:
    from surfelslam.slam.segments import Segment

    t = Table(title=f"surfelslam run -> {escape(str(out_dir))}", show_header=False)
    frames = f"{metrics['frames_processed']} processed, {metrics['frames_skipped']} skipped"
    if metrics.get("frames_unpaired"):
        frames += f", {metrics['frames_unpaired']} unpaired images left out"
    t.add_row("frames", frames)
    t.add_row("tracking failures", str(metrics.get("tracking_failures", 0)))
    t.add_row("FPS", f"{metrics['fps']:.1f}  (JIT warm-up {metrics['warmup_s']:.1f} s excluded)")
    if metrics.get("startup_s") is not None:
        t.add_row("start, end", f"{metrics['startup_s']:.1f} s to the first frame, {metrics['shutdown_s']:.1f} s "
                                "from the last frame to the outputs written")
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
    print_prior_map(metrics.get("prior_map"))
    print_unposed(metrics.get("unposed", []))
    if metrics.get("poses_written") == 0:
        console.print("[bold red]no frame has a pose:[/] trajectory.txt is empty", highlight=False, soft_wrap=True)
    elif metrics.get("lost_at_end"):
        last = [s for s in segs if s["kind"] == "lost"][-1]
        console.print(f"[bold red]the run ended lost[/] (from frame {last['first_frame']}): the poses after it are "
                      "predictions, not measurements", highlight=False, soft_wrap=True)


def print_unposed(unposed: list[dict]) -> None:
    """One line per frame that has no pose (not localised in the loaded map), the first few of them."""
    for u in unposed[:SUMMARY_EXAMPLES]:
        console.print(f"[yellow]unposed frame {u['frame']}[/] (t={u['timestamp']:.3f} s): {escape(str(u['reason']))}",
                      highlight=False, soft_wrap=True)
    if len(unposed) > SUMMARY_EXAMPLES:
        console.print(f"[yellow]... and {len(unposed) - SUMMARY_EXAMPLES} more unposed frames (metrics.json)[/]")


def prior_map_line(rep: dict | None) -> str | None:
    """One line on the loaded map (``--map``): where the run was localised in it, or that it was not."""
    if rep is None:
        return None
    if rep.get("localised"):
        return (f"localised in the loaded map at frame {rep['frame']} (keyframe {rep['keyframe']}, "
                f"{rep['pnp_inliers']} PnP inliers, ICP overlap {rep['icp_inlier_fraction'] * 100:.0f} %, residual "
                f"{rep['icp_rmse_m'] * 1000:.1f} mm)" + ("; map unchanged (--localize-only)"
                                                         if rep.get("localize_only") else ""))
    why = rep.get("last_failure", "no frame tried")
    if rep.get("new_map_frame_at") is not None:
        return (f"not localised in the loaded map in {rep['frames_tried']} frames ({why}): refused; a new map "
                f"frame started at frame {rep['new_map_frame_at']}")
    return f"not localised in the loaded map in {rep['frames_tried']} frames ({why}): no poses written"


def print_prior_map(rep: dict | None) -> None:
    line = prior_map_line(rep)
    if line is not None:
        style = "green" if rep.get("localised") else "bold red"
        console.print(f"[{style}]{escape(line)}[/]", highlight=False, soft_wrap=True)


def resolve_run_config(config: str | None, sets: list[str] | None, tracker: str | None,
                       dataset: DatasetOptionsArgs):
    """The run's settings: the command-line flags, over ``--set``, over the ``--config`` file (or preset), over
    the defaults."""
    from surfelslam.slam import TRACKERS
    from surfelslam.slam.runner import load_config

    if tracker is not None and tracker not in TRACKERS:
        raise ConfigError(f"--tracker must be one of {', '.join(TRACKERS)}, got {tracker!r}")
    cfg = load_config(config, sets or ())
    return replace(cfg, tracker=cfg.tracker if tracker is None else tracker, dataset=dataset.resolve(cfg.dataset))


# the options of `surfelslam run`, one declaration each (the command's signature stays one line per option)
OutOpt = Annotated[Path, typer.Option("--out", "-o", help="Output folder.")]
OverwriteOpt = Annotated[bool, typer.Option(
    "--overwrite", help="Replace the previous run in --out (only the run's own files are removed).")]
ConfigOpt = Annotated[str | None, typer.Option(
    "--config", help="TOML configuration file (e.g. a previous run's config.toml: the whole recipe), or a "
                     "preset name (fast, accurate, hybrid-full: the package's presets).")]
SetOpt = Annotated[list[str] | None, typer.Option(
    "--set", metavar="KEY=VALUE", help="Override one setting, e.g. --set icp.min_inliers=300 --set "
                                       "tracking.photometric=off (repeatable; a TOML value or a bare string).")]
TrackerOpt = Annotated[str | None, typer.Option("--tracker", help=TRACKER_HELP)]
PosesOpt = Annotated[str | None, typer.Option(
    "--poses", help="Map with given poses and skip tracking: 'gt' or a TUM trajectory file.")]
FiguresOpt = Annotated[bool, typer.Option("--figures/--no-figures", help="Write PNG figures.")]
FigureOpt = Annotated[list[str] | None, typer.Option(
    "--figure", metavar="KIND", help="Only these figures: trajectory, ate_errors, map_camera, map_top (repeatable; "
                                     "default: all of them; each map figure costs about a third of a second of CPU).")]
FormatOpt = Annotated[list[str] | None, typer.Option(
    "--format", help="Pose file formats: tum (always: trajectory.txt) and kitti (also trajectory_kitti.txt, the "
                     "3x4 poses row by row); repeatable.")]
ProgressOpt = Annotated[bool, typer.Option("--progress/--no-progress", help="Show a progress bar.")]
RerunOpt = Annotated[bool, typer.Option(
    "--rerun", help="Also write OUT/run.rrd, a Rerun recording (needs rerun-sdk; see `surfelslam rerun`).")]
ViewerOpt = Annotated[str | None, typer.Option(
    "--viewer", metavar="spawn|connect[=ADDR]|serve|save=FILE",
    help="Show the run live in Rerun (needs rerun-sdk): spawn a viewer, connect to one (HOST:PORT), serve a web "
         "viewer, or save a recording while running.")]
ViewerImagesOpt = Annotated[int, typer.Option(
    "--viewer-images-every", help="Live viewer: log the images every N frames.")]
ViewerMapOpt = Annotated[int, typer.Option(
    "--viewer-map-every", help="Live viewer: log the map (subsampled) every N frames.")]
MapOpt = Annotated[Path | None, typer.Option(
    "--map", help="Continue from the map a previous run saved (its --out folder, or its map.npz): the first frames "
                  "are localised in it, then tracking and mapping go on in its frame (dense, hybrid).")]
LocalizeOnlyOpt = Annotated[bool, typer.Option(
    "--localize-only", help="With --map: track against the loaded map without changing it.")]
MeshOpt = Annotated[bool, typer.Option(
    "--mesh", help="Also write OUT/mesh.ply at the end, as `surfelslam mesh OUT` does (TSDF, default settings).")]
RecordOpt = Annotated[Path | None, typer.Option(
    "--record", help="With the live camera (SEQ = realsense): also write the frames to this bag (.bag: ROS 1, else "
                     "a ROS 2 MCAP bag folder).")]


def note(text: str) -> None:
    """A yellow line on the console (the live viewer's remarks)."""
    console.print(escape(text), style="yellow", highlight=False, soft_wrap=True)


def print_run(made, out: Path) -> None:
    """The summary of a run, then what ``--mesh`` and ``--rerun`` wrote."""
    print_summary(made.metrics, out)
    if made.mesh is not None:
        res = made.mesh
        console.print(f"wrote {out / res.path.name} ({res.vertices:,} vertices, {res.faces:,} triangles; "
                      f"{res.seconds:.1f} s)", highlight=False, markup=False, soft_wrap=True)


def print_export_of_run(made, out: Path) -> None:
    if made.export is not None:
        from surfelslam.tools.export_rerun import print_export

        summary, notes = made.export
        print_export(replace(summary, path=out / Path(summary.path).name), notes)


def figures_asked(figures: bool, kinds: list[str] | None) -> bool | tuple[str, ...]:
    """``--figures/--no-figures`` and ``--figure KIND``: none, every figure, or the kinds named (checked here, so
    that a wrong name is refused before the run)."""
    if not figures or not kinds:
        return figures
    from surfelslam.viz.run_report import RUN_FIGURES

    unknown = sorted(set(kinds) - RUN_FIGURES)
    if unknown:
        raise ConfigError(f"--figure: unknown {', '.join(unknown)}; known: {', '.join(sorted(RUN_FIGURES))}")
    return tuple(kinds)


def run_cmd(seq_path: SeqArg, dataset: DatasetOptionsArgs, out: OutOpt = Path("out/run"),
            overwrite: OverwriteOpt = False, config: ConfigOpt = None, sets: SetOpt = None,
            tracker: TrackerOpt = None, poses: PosesOpt = None, figures: FiguresOpt = True,
            progress: ProgressOpt = True, rerun: RerunOpt = False, viewer: ViewerOpt = None,
            viewer_images_every: ViewerImagesOpt = 5, viewer_map_every: ViewerMapOpt = 30, map_dir: MapOpt = None,
            localize_only: LocalizeOnlyOpt = False, mesh: MeshOpt = False, record: RecordOpt = None,
            formats: FormatOpt = None, figure_kinds: FigureOpt = None) -> None:
    """Track and fuse a sequence; writes trajectory.txt, map.ply, config.toml, metrics.json and figures.

    Settings come from the command-line flags, then --set, then the --config file, then the defaults.
    config.toml records all of them (tracker and dataset options too): `surfelslam run SEQ --config
    OUT/config.toml` repeats the run. A --out folder that holds a previous run needs --overwrite; the run
    writes into OUT/.partial-PID/ and moves its files into OUT when complete.
    """
    from surfelslam import IMPORTED_PERF_S
    from surfelslam.api import run_folder
    from surfelslam.viz.live import finish_viewer, viewer_for_run

    cfg = resolve_run_config(config, sets, tracker, dataset)
    wanted = figures_asked(figures, figure_kinds)
    live = []  # the live viewer, once the sequence is open

    def start_viewer(seq):
        live.append(viewer_for_run(viewer, seq, viewer_images_every, viewer_map_every, warn=note))
        return live[0]

    def started(stage: Path) -> None:
        console.print(f"run -> {escape(str(out))} (writing into {escape(str(stage))} until complete)",
                      highlight=False)

    try:
        made = run_folder(seq_path, out, cfg, poses=poses, map_dir=map_dir, localize_only=localize_only,
                          record=record, mesh=mesh, rerun=rerun, viewer=start_viewer, overwrite=overwrite,
                          progress=progress, figures=wanted, on_start=started, formats=formats or ("tum",),
                          started_perf_s=IMPORTED_PERF_S)
    except BaseException:
        finish_viewer(live[0] if live else None, None, warn=note, wait_when_serving=False)
        raise
    print_run(made, out)
    finish_viewer(live[0], out, warn=note)
    print_export_of_run(made, out)


def register(app: typer.Typer) -> None:
    app.command("run")(handle_errors(with_dataset_options(run_cmd)))
