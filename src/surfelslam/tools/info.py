"""``surfelslam info SEQ``: what was detected in a sequence folder or bag (layout, frames, camera, ground truth; a bag's
topics)."""

from __future__ import annotations

import json
from typing import Annotated

import typer
from rich.markup import escape
from rich.table import Table

from surfelslam.tools.common import DatasetOptionsArgs, SeqArg, console, handle_errors, with_dataset_options


def _colour_row(d: dict) -> str:
    cam = d.get("colour_camera")
    if cam is not None:
        t = ", ".join(f"{c:g}" for c in cam["t_colour_depth_m"])
        return (f"separate camera fx={cam['fx']:g} fy={cam['fy']:g} cx={cam['cx']:g} cy={cam['cy']:g}, "
                f"t_colour_depth=({t}) m: the maps' colours are sampled through it")
    return "registered to depth" if d.get("colour_registered", True) else "not registered to depth (no model)"


def info_table(d: dict) -> Table:
    """The ``describe()`` dict as a two-column rich table."""
    table = Table(title=f"sequence {escape(d['root'])}", show_header=False)
    table.add_column("field", style="bold")
    table.add_column("value")
    intr = d["intrinsics"]
    med = d["first_frame_median_depth_m"]
    seconds = d.get("seconds_per_stamp", 1.0) == 1.0  # else frame numbers (ICL-NUIM)
    rows = [
        ("layout", d["layout"]),
        ("frames", f"{d['frames']} selected of {d['frames_total']}"),
        ("resolution", f"{d['resolution'][0]}x{d['resolution'][1]} (files {d['full_resolution'][0]}x"
                       f"{d['full_resolution'][1]}, downsample {d['downsample']})"),
        ("intrinsics", f"fx={intr['fx']:g} fy={intr['fy']:g} cx={intr['cx']:g} cy={intr['cy']:g}"
                       f"  (from {d['intrinsics_source']})"),
        ("depth scale", f"{d['depth_scale']:g} units/m  (from {d['depth_scale_source']})"),
        ("ground truth", f"{d['ground_truth_poses']} poses; {d['frames_with_ground_truth']} of {d['frames']} "
                         f"frames have one within 0.02 {'s' if seconds else 'of a frame'}"),
        ("colour", _colour_row(d)),
        ("timestamps", "seconds" if seconds else
         f"frame numbers, {1 / d['seconds_per_stamp']:g} Hz for motion checks (kept in the trajectory)"),
        ("first frame depth", "no valid pixel" if med is None else
         f"median {med:.3f} m, {100 * d['first_frame_valid_depth_fraction']:.1f}% valid"),
    ]
    if "topics" in d:  # a bag
        rows.insert(1, ("bag", d["bag_format"]))
        for t in d["topics"]:
            rate = "" if t["rate_hz"] is None else f", {t['rate_hz']:g} Hz"
            role = f"  <- {t['role']}" if t["role"] else ""
            rows.append(("topic", f"{t['topic']}  {t['type'].replace('/msg/', '/')}  ({t['count']} messages{rate})"
                                  f"{role}"))
        if d.get("ground_truth_source"):
            rows.append(("ground truth from", d["ground_truth_source"]))
    for w in d.get("warnings", []) if "topics" in d else []:
        rows.append(("warning", w))
    if d["depth_scale_warning"]:
        rows.append(("warning", d["depth_scale_warning"]))
    for k, v in rows:
        table.add_row(k, escape(str(v)), style="yellow" if k == "warning" else None)
    return table


def register(app: typer.Typer) -> None:
    @app.command("info")
    @handle_errors
    @with_dataset_options
    def info(
        seq: SeqArg,
        dataset: DatasetOptionsArgs,
        json_out: Annotated[bool, typer.Option("--json", help="Print the information as JSON.")] = False,
    ) -> None:
        """Show the detected layout, frames, resolution, intrinsics, depth scale and ground-truth coverage.

        For a ROS bag or MCAP file, also its topics with message counts and rates, and which are read.
        """
        from surfelslam.datasets import describe, open_sequence

        # info diagnoses: it warns (run refuses)
        d = describe(open_sequence(seq, dataset.resolve(), plausibility="warn"))
        if json_out:
            typer.echo(json.dumps(d, indent=2))
        else:
            console.print(info_table(d))
