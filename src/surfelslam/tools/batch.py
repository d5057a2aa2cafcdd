"""``surfelslam batch``: every sequence x tracker x configuration of a spec, one run folder each, one table."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from surfelslam.errors import ConfigError
from surfelslam.tools.common import DatasetOptionsArgs, console, err_console, handle_errors, with_dataset_options


def _is_spec(inputs: list[str]) -> bool:
    return len(inputs) == 1 and inputs[0].lower().endswith(".toml")


def _fmt_row(i: int, n: int, row: dict) -> str:
    colour = {"done": "green", "skipped": "cyan", "failed": "red"}.get(row["status"], "yellow")
    text = f"[{i}/{n}] [{colour}]{row['status']:<7}[/] {escape(row['job'])}"
    if row.get("ate_rmse_m") is not None:
        text += f"  ATE {row['ate_rmse_m'] * 100:.2f} cm"
    if row.get("wall_s") is not None and row["status"] == "done":
        text += f"  {row['wall_s']:.1f} s"
    if row.get("error"):
        text += f"  {escape(row['error'])}"
    return text


def register(app: typer.Typer) -> None:
    @app.command("batch")
    @handle_errors
    @with_dataset_options
    def batch_cmd(
        inputs: Annotated[list[str] | None, typer.Argument(
            metavar="SPEC.toml | SEQ...", help="A batch spec (docs/batch.md), or sequence folders (the inline "
                                               "form).", show_default=False)] = None,
        dataset: DatasetOptionsArgs = DatasetOptionsArgs(),
        out: Annotated[Path | None, typer.Option("--out", "-o", help="The batch folder: one run folder per job "
                                                                      "(SEQUENCE-TRACKER-HASH8), results.csv/md.")]
        = None,
        tracker: Annotated[str | None, typer.Option(
            "--tracker", help="Inline form: trackers, comma-separated (e.g. dense,hybrid). Default: the "
                              "config's.")] = None,
        sets: Annotated[list[str] | None, typer.Option(
            "--set", metavar="KEY=V1,V2", help="Inline form: a setting; comma-separated values are a sweep axis, "
                                               "several keys their grid (repeatable).")] = None,
        config: Annotated[str | None, typer.Option(
            "--config", help="Inline form: the TOML config file or preset under every job.")] = None,
        executor: Annotated[str | None, typer.Option(
            "--executor", metavar="ray|local", help="Where the jobs run: ray (one task per job; the default when Ray "
                                                    "is installed) or local (here, one by one).")] = None,
        address: Annotated[str | None, typer.Option(
            "--address", metavar="auto|ray://HOST:10001", help="Join a Ray cluster (default: start a local Ray "
                                                               "sized to this machine).")] = None,
        retries: Annotated[int, typer.Option(
            "--retries", min=0, help="Retries of a job that crashes (or whose worker dies).")] = 2,
        report: Annotated[Path | None, typer.Option(
            "--report", metavar="DIR", help="Only rebuild DIR/results.csv and results.md from its run "
                                            "folders.")] = None,
        warmup: Annotated[bool, typer.Option(
            "--warmup/--no-warmup", help="Compile the JIT kernels once before dispatching the jobs.")] = True,
    ) -> None:
        """Run sequences x trackers x configurations (a spec file, or SEQ... with --tracker/--set sweeps) as Ray
        tasks; one results table.

        Each job is a `surfelslam run` into OUT/SEQUENCE-TRACKER-HASH8 (HASH: the sha256 of its config.toml). A job
        whose folder already holds a complete run of the same config is skipped, so rerunning a batch resumes
        it. A job that crashes is retried --retries times, then recorded as failed with its reason; the batch
        goes on. The table: OUT/results.csv, OUT/results.md and OUT/ate-SEQUENCE.png. See docs/batch.md.
        """
        from surfelslam.batch import report as report_mod

        if report is not None:
            if inputs:
                raise ConfigError("--report DIR takes no spec or sequences")
            rows, files = report_mod.rebuild_report(report)
            console.print(f"{len(rows)} rows -> {escape(str(files['csv']))}, {escape(str(files['md']))}",
                          highlight=False)
            return
        if not inputs:
            raise ConfigError("give a spec file (SPEC.toml) or sequence folders, or --report DIR")
        if out is None:
            raise ConfigError("--out DIR is needed (the batch folder)")
        _run(inputs, out, dataset, tracker, sets or [], config, executor, address, retries, warmup)


def _run(inputs, out, dataset, tracker, sets, config, executor, address, retries, warmup) -> None:
    from surfelslam.batch import spec as spec_mod
    from surfelslam.batch.driver import run_batch
    from surfelslam.batch.executors import make_executor, numba_cache_env
    from surfelslam.slam.runner import load_config

    if _is_spec(inputs):
        if tracker is not None or sets or config is not None:
            raise ConfigError("with a spec file, put trackers, settings and the base config in the spec "
                              "(--tracker, --set and --config are for the inline form)")
        spec = spec_mod.load_spec(inputs[0])
    else:
        spec = spec_mod.inline_spec(inputs, tracker, sets, load_config(config))
    spec = spec_mod.with_dataset(spec, dataset.resolve(spec.base.dataset))
    jobs = spec_mod.expand_jobs(spec, out)
    env = numba_cache_env() if executor != "local" else {}
    runner, note = make_executor(executor, address, retries, env)
    if note:
        err_console.print(f"note: {escape(note)}", highlight=False, soft_wrap=True)
    console.print(f"{len(jobs)} jobs ({len(spec.sequences)} sequences x {len(spec.trackers) or 1} trackers x "
                  f"{len(spec.configs)} configs) -> {escape(str(out))} "
                  f"(executor: {runner.name})", highlight=False, soft_wrap=True)
    done = [0]

    def show(job, row) -> None:
        done[0] += 1
        console.print(_fmt_row(done[0], len(jobs), row), highlight=False, soft_wrap=True)

    result = run_batch(jobs, out, runner, on_result=show, warmup=warmup)
    counts = ", ".join(f"{result.count(s)} {s}" for s in ("done", "skipped", "failed") if result.count(s))
    console.print(f"{counts} -> {escape(str(result.files['csv']))}, {escape(str(result.files['md']))}",
                  highlight=False)
