"""Batch specs: what to run, as a TOML file or as the inline command-line form, expanded into jobs.

A spec file (docs/batch.md)::

    sequences = ["data/fr1_xyz", "data/fr1_desk"]     # relative paths: to the spec file's folder
    trackers = ["dense", "hybrid"]                      # optional (default: each config's tracker)
    base = "fast"                                       # optional: a config file or preset under every config

    [dataset]                                           # optional: DatasetOptions for every sequence
    end = 300

    [[configs]]                                         # optional (default: one config, "default")
    name = "default"

    [[configs]]
    name = "more-inliers"
    set = ["icp.min_inliers=500"]                      # --set items ...

    [[configs]]
    name = "nested"
    icp = { min_inliers = 500 }                         # ... and/or nested settings, as in config.toml

The inline form (``surfelslam batch SEQ... --tracker dense,hybrid --set icp.min_inliers=300,500``): each
``--set`` key with comma-separated values is a sweep axis; several keys form their grid.

One job = sequence x tracker x config (:func:`expand_jobs`).
"""

from __future__ import annotations

import dataclasses
import itertools
import tomllib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from surfelslam.batch.jobs import Job, make_job
from surfelslam.config import from_dict
from surfelslam.datasets.base import DatasetOptions
from surfelslam.errors import ConfigError, one_line
from surfelslam.slam import TRACKERS, SlamConfig
from surfelslam.slam.runner import apply_sets, load_config, parse_set

SPEC_KEYS = ("sequences", "trackers", "base", "dataset", "configs")
DEFAULT_CONFIG_NAME = "default"


@dataclasses.dataclass(frozen=True)
class ConfigVariant:
    """One configuration of a batch: ``settings`` (nested, as in ``config.toml``) then the ``--set`` items."""

    name: str
    sets: tuple[str, ...] = ()
    settings: dict[str, Any] = dataclasses.field(default_factory=dict)

    def build(self, base: SlamConfig) -> SlamConfig:
        cfg = from_dict(SlamConfig, self.settings, where=f"configs.{self.name}", base=base) if self.settings \
            else base
        return apply_sets(cfg, self.sets)


@dataclasses.dataclass(frozen=True)
class BatchSpec:
    """What a batch runs: every sequence x tracker x config. ``trackers`` empty: each config's own tracker.
    ``base`` carries the dataset options of every job."""

    sequences: tuple[str, ...]
    trackers: tuple[str, ...] = ()
    configs: tuple[ConfigVariant, ...] = (ConfigVariant(DEFAULT_CONFIG_NAME),)
    base: SlamConfig = dataclasses.field(default_factory=SlamConfig)


# ------------------------------------------------------------------------------------------------ helpers
def split_values(text: str) -> list[str]:
    """``"1,2"`` -> ``["1", "2"]``; commas inside ``[...]``, ``{...}`` or quotes do not split."""
    out, cur, depth, quote = [], [], 0, ""
    for ch in text:
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append("".join(cur))
            cur = []
            continue
        cur.append(ch)
    out.append("".join(cur))
    return [v.strip() for v in out]


def split_trackers(text: str | Sequence[str] | None) -> tuple[str, ...]:
    """``"dense,hybrid"`` (or a list) -> the checked tracker names."""
    if text is None:
        return ()
    items = split_values(text) if isinstance(text, str) else [str(t).strip() for t in text]
    names = tuple(t for t in items if t)
    for t in names:
        if t not in TRACKERS:
            raise ConfigError(f"tracker must be one of {', '.join(TRACKERS)}, got {t!r}")
    return names


def sweep_variants(sets: Sequence[str]) -> tuple[ConfigVariant, ...]:
    """``--set`` items, a key's comma-separated values a sweep axis -> one config per grid point.

    ``["icp.min_inliers=300,500", "icp.max_iterations=10"]`` -> 2 configs. Keys are checked here.
    """
    axes: dict[str, list[str]] = {}
    for item in sets:
        key, sep, text = item.partition("=")
        key = key.strip()
        parse_set(item.split(",")[0] if sep else item)  # the key (and KEY=VALUE form) checked
        values = [v for v in split_values(text) if v != ""]
        if not values:
            raise ConfigError(f"--set {one_line(item)}: no value")
        axes.setdefault(key, [])
        axes[key] += [v for v in values if v not in axes[key]]
    if not axes:
        return (ConfigVariant(DEFAULT_CONFIG_NAME),)
    keys = list(axes)
    out = []
    for combo in itertools.product(*(axes[k] for k in keys)):
        items = tuple(f"{k}={v}" for k, v in zip(keys, combo, strict=True))
        out.append(ConfigVariant(",".join(items), sets=items))
    return tuple(out)


# ------------------------------------------------------------------------------------------------ specs
def sequence_path(text: str | Path, base: Path, where: str) -> str:
    """``text`` as an absolute path (``~`` expanded, relative to ``base``); ConfigError, prefixed by ``where``, for a
    path no file can have (a NUL character, ``~user`` of an unknown user)."""
    try:
        return str((base / Path(text).expanduser()).resolve())
    except (ValueError, RuntimeError) as exc:
        raise ConfigError(f"{where}sequence path {str(text)!r}: {exc}") from None


def inline_spec(sequences: Sequence[str | Path], trackers: str | Sequence[str] | None = None,
                sets: Sequence[str] = (), base: SlamConfig | None = None) -> BatchSpec:
    """The inline form: ``SEQ... --tracker a,b --set KEY=V1,V2 ...``."""
    if not sequences:
        raise ConfigError("no sequences given (SEQ... or a spec file)")
    return BatchSpec(sequences=tuple(sequence_path(s, Path(), "") for s in sequences),
                     trackers=split_trackers(trackers), configs=sweep_variants(sets),
                     base=SlamConfig() if base is None else base)


def _variant(i: int, table: Any, where: str) -> ConfigVariant:
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: [[configs]] entry {i + 1} must be a table")
    table = dict(table)
    name = table.pop("name", None)
    if name is None:
        name = f"config{i + 1}"
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{where}: [[configs]] entry {i + 1}: name must be a non-empty string")
    sets = table.pop("set", [])
    if isinstance(sets, str):
        sets = [sets]
    if not isinstance(sets, list) or not all(isinstance(s, str) for s in sets):
        raise ConfigError(f"{where}: configs {name!r}: set must be a list of \"KEY=VALUE\" strings")
    for item in sets:
        parse_set(item)
    return ConfigVariant(name, tuple(sets), table)


def load_spec(path: str | Path) -> BatchSpec:
    """Read a spec TOML file (format: the module docstring and docs/batch.md); errors name the file."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: spec file not found") from None
    except (OSError, UnicodeDecodeError) as exc:  # a folder, no permission, not UTF-8
        raise ConfigError(f"{path}: cannot read the spec file ({exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    unknown = sorted(set(data) - set(SPEC_KEYS))
    if unknown:
        raise ConfigError(f"{path}: unknown key(s) {', '.join(unknown)} (a spec has {', '.join(SPEC_KEYS)})")
    seqs = data.get("sequences")
    if isinstance(seqs, str):
        seqs = [seqs]
    if not seqs or not isinstance(seqs, list) or not all(isinstance(s, str) for s in seqs):
        raise ConfigError(f"{path}: sequences must be a non-empty list of paths")
    here = path.resolve().parent
    sequences = tuple(sequence_path(s, here, f"{path}: ") for s in seqs)
    base_name = data.get("base")
    if base_name is not None and not isinstance(base_name, str):
        raise ConfigError(f"{path}: base must be a config file or preset name")
    if base_name is not None and (here / base_name).is_file():
        base_name = str(here / base_name)
    base = load_config(base_name)
    dataset = data.get("dataset", {})
    if not isinstance(dataset, dict):
        raise ConfigError(f"{path}: [dataset] must be a table")
    if dataset:
        base = dataclasses.replace(base, dataset=from_dict(DatasetOptions, dataset, where="dataset",
                                                           base=base.dataset))
    configs = data.get("configs", [])
    if not isinstance(configs, list):
        raise ConfigError(f"{path}: configs must be an array of tables ([[configs]])")
    variants = tuple(_variant(i, t, str(path)) for i, t in enumerate(configs)) or (ConfigVariant(DEFAULT_CONFIG_NAME),)
    names = [v.name for v in variants]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"{path}: config name(s) used twice: {one_line(', '.join(dup))}")
    return BatchSpec(sequences=sequences, trackers=split_trackers(data.get("trackers")), configs=variants,
                     base=base)


def with_dataset(spec: BatchSpec, dataset: DatasetOptions) -> BatchSpec:
    """``spec`` with its base's dataset options replaced (the command line's options over the spec's)."""
    return dataclasses.replace(spec, base=dataclasses.replace(spec.base, dataset=dataset))


def expand_jobs(spec: BatchSpec, out_root: str | Path) -> list[Job]:
    """Every sequence x tracker x config, in that order; configs are built (and checked) here.

    Raises:
        ConfigError: a bad setting in a config, or two jobs that would share a run folder (two sequences with
            the same folder name, or two configs that are the same settings).
    """
    out_root = Path(out_root)
    built = [(v, v.build(spec.base)) for v in spec.configs]
    jobs: list[Job] = []
    seen: dict[str, Job] = {}
    for seq in spec.sequences:
        for variant, cfg in built:
            for tracker in spec.trackers or (cfg.tracker,):
                job = make_job(seq, tracker, cfg, variant.name, variant.sets, out_root)
                other = seen.get(job.name)
                if other is not None:
                    raise ConfigError(one_line(  # paths and config names may hold line breaks
                        f"two jobs share the run folder {job.name}: {other.sequence} [{other.config_name}] and "
                        f"{job.sequence} [{job.config_name}] (same sequence folder name, or the same settings)"))
                seen[job.name] = job
                jobs.append(job)
    return jobs
