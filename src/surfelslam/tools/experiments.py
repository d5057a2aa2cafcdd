"""``surfelslam experiments SEQ --out DIR``: the reference assignment's experiments on one sequence, as
``DIR/report.md`` + PNGs + ``results.json``. The sections live in :mod:`surfelslam.experiments`."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer

from surfelslam.errors import ConfigError
from surfelslam.tools.common import (
    DatasetOptionsArgs,
    SeqArg,
    console,
    handle_errors,
    with_dataset_options,
)


def parse_gaps(text: str) -> tuple[int, ...]:
    try:
        gaps = tuple(int(x) for x in text.replace(" ", "").split(",") if x)
    except ValueError:
        raise ConfigError(f"--pair-gaps must be a comma list of frame gaps, got {text!r}") from None
    if not gaps:
        raise ConfigError(f"--pair-gaps must be a comma list of frame gaps, got {text!r}")
    return gaps


def register(app: typer.Typer) -> None:
    @app.command("experiments")
    @handle_errors
    @with_dataset_options
    def experiments_cmd(
        seq_path: SeqArg,
        dataset: DatasetOptionsArgs,
        out: Annotated[Path, typer.Option("--out", "-o", help="Output folder (report.md, PNGs, runs/).")] = Path(
            "out/experiments"),
        config: Annotated[Path | None, typer.Option("--config", help="TOML configuration file.")] = None,
        frames: Annotated[int, typer.Option("--frames", help="Frames used by the fusion and trajectory "
                                                             "sections.")] = 200,
        pair_start: Annotated[int, typer.Option("--pair-start", help="Source frame of the ICP/feature pairs.")] = 10,
        pair_gaps: Annotated[str, typer.Option("--pair-gaps", help="Frame gaps of the pairs, comma list.")] = "40,90",
        progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Show progress bars.")] = True,
    ) -> None:
        """The reference assignment's experiments (ICP pairs, solvers, fusion, dormant rule, features, trackers) ->
        report.md."""
        from surfelslam.datasets import open_sequence
        from surfelslam.experiments import ExperimentOptions, run_experiments
        from surfelslam.slam.runner import load_config

        opts = ExperimentOptions(frames=frames, pair_start=pair_start, pair_gaps=parse_gaps(pair_gaps),
                                 progress=progress)
        cfg = load_config(config)
        dopts = dataset.resolve()
        seq = open_sequence(seq_path, dopts)
        if len(seq) == 0:
            raise ConfigError(f"{seq_path}: the selection has no frames (check --start/--end/--stride)")
        run_end = dopts.start + frames * dopts.stride
        seq_runs = open_sequence(seq_path, replace(dopts, end=run_end if dopts.end is None else min(dopts.end,
                                                                                                   run_end)))
        t0 = time.perf_counter()
        res = run_experiments(seq, seq_runs, out, cfg, opts)
        console.print(f"wrote {out / 'report.md'} in {time.perf_counter() - t0:.0f} s "
                      f"({res['frames_run']} frames run, pairs {res['pairs']})", highlight=False, markup=False)
