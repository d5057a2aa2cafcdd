"""``surfelslam run``: the whole pipeline on a sequence, writing trajectory, map, config, metrics and figures."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.table import Table

from surfelslam.api import run_sequence
from surfelslam.datasets import open_sequence
from surfelslam.errors import ConfigError
from surfelslam.slam import TRACKERS
from surfelslam.slam.runner import load_config
from surfelslam.slam.saved_map import check_map_options
from surfelslam.slam.segments import Segment
from surfelslam.tools.common import (
    DatasetOptionsArgs,
    SeqArg,
    console,
    handle_errors,
    with_dataset_options,
)

TRACKER_HELP = ("hybrid: dense ICP + ORB back end (PnP guesses, relocalisation, loop-corrected trajectory and "
                "surfel map); dense: frame-to-model ICP alone; orb: sparse ORB/PnP odometry + loop-closing pose graph "
                "(map = keyframe cloud). One of " + ", ".join(TRACKERS) + ". Default: the --config file's, else "
                "hybrid.")
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
    print_prior_map(metrics.get("prior_map"))
    if metrics.get("poses_written") == 0:
        console.print("[bold red]no frame has a pose:[/] trajectory.txt is empty", highlight=False, soft_wrap=True)
    elif metrics.get("lost_at_end"):
        last = [s for s in segs if s["kind"] == "lost"][-1]
        console.print(f"[bold red]the run ended lost[/] (from frame {last['first_frame']}): the poses after it are "
                      "predictions, not measurements", highlight=False, soft_wrap=True)


def read_prior_map(map_dir: Path | None, tracker: str, localize_only: bool, poses: str | None):
    """The map ``--map`` names (``None`` without it), after checking the options (before reading a large file)."""
    check_map_options(tracker, map_dir, localize_only, poses)
    if map_dir is None:
        return None
    from surfelslam.io.map_file import read_map_file

    return read_map_file(map_dir)


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
                             "preset name (configs/NAME.toml: fast, accurate, hybrid-full).")] = None,
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
        map_dir: Annotated[Path | None, typer.Option(
            "--map", help="Continue from the map a previous run saved (its --out folder, or its map.npz): the first "
                          "frames are localised in it, then tracking and mapping go on in its frame (dense, hybrid)."
        )] = None,
        localize_only: Annotated[bool, typer.Option(
            "--localize-only", help="With --map: track against the loaded map without changing it.")] = False,
        mesh: Annotated[bool, typer.Option(
            "--mesh", help="Also write OUT/mesh.ply at the end, as `surfelslam mesh OUT` does (TSDF, default "
                           "settings).")] = False,
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
        prior = read_prior_map(map_dir, cfg.tracker, localize_only, poses)
        if rerun:
            from surfelslam.viz.rerun_export import require_rerun

            require_rerun()  # before the run, not after it
        if record is not None:
            from surfelslam.datasets.realsense import open_realsense

            seq = open_realsense(cfg.dataset, record=record, path=seq_path)
        else:
            seq = open_sequence(seq_path, cfg.dataset)
        exported = []
        meshed = []
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

        def before_commit(stage: Path) -> None:
            if mesh:  # in the staging folder: an interrupted run leaves no half mesh in OUT
                from surfelslam.tools.mesh import mesh_config, mesh_run

                meshed.append(mesh_run(stage, mesh_config(), sequence=Path(str(seq.root)), progress=progress,
                                       run_depth_range=True))
            if rerun:
                export(stage)

        try:
            metrics = run_sequence(seq, out, cfg, poses=poses, progress=progress, figures=figures,
                                   overwrite=overwrite, on_start=started,
                                   before_commit=before_commit if rerun or mesh else None, on_frame=live,
                                   prior_map=prior, localize_only=localize_only)
        except BaseException:
            finish_viewer(live, None, warn=note, wait_when_serving=False)
            raise
        finally:
            if hasattr(seq, "close"):  # a bag, a live camera (and its recording)
                seq.close()
        print_summary(metrics, out)
        if meshed:
            res = meshed[0]
            console.print(f"wrote {out / res.path.name} ({res.vertices:,} vertices, {res.faces:,} triangles; "
                          f"{res.seconds:.1f} s)", highlight=False, markup=False, soft_wrap=True)
        finish_viewer(live, out, warn=note)
        if exported:
            from surfelslam.tools.export_rerun import print_export

            summary, notes = exported[0]
            print_export(replace(summary, path=out / Path(summary.path).name), notes)
