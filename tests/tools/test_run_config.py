"""`surfelslam run`'s settings: config.toml is the whole recipe (tracker and dataset options too) and repeats a run
byte for byte; flags > --set > --config file > defaults; --set parsing and its one-line errors; presets; the dataset
options declared once for every command; the same --figures/--no-figures flag in run and eval."""

from __future__ import annotations

import json
import shutil

import pytest
import typer
from typer.testing import CliRunner

from surfelslam.cli import app, get_app
from surfelslam.config import load_toml
from surfelslam.datasets.base import DatasetOptions
from surfelslam.errors import ConfigError
from surfelslam.settings import package_version, resolve_config_path
from surfelslam.settings import presets as preset_module
from surfelslam.slam import SlamConfig
from surfelslam.slam.runner import apply_sets, load_config, parse_set
from surfelslam.synth.writer import generate_sequence
from surfelslam.tools.common import DatasetOptionsArgs
from surfelslam.tools.run import resolve_run_config

cli = CliRunner()
QUIET = ("--no-progress", "--no-figures")


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    """12 frames of the 'room' scene at 160x120, slow orbit."""
    return generate_sequence(tmp_path_factory.mktemp("runcfg") / "seq", "room", "slow", 12, "kinect", 3, 160, 120)


def one_error_line(res, code: int = 2) -> str:
    assert res.exit_code == code, res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in res.output, res.output
    return lines[0]


# ------------------------------------------------------------------------------------------------ the recipe
@pytest.mark.slow
@pytest.mark.parametrize("tracker", ["dense", "orb"])
def test_config_toml_alone_repeats_the_run_byte_for_byte(seq, tmp_path, tracker):
    first, again = tmp_path / "first", tmp_path / "again"
    res = cli.invoke(app, ["run", str(seq), "-o", str(first), "--tracker", tracker, "--start", "1", "--end", "11",
                           "--stride", "2", "--set", "icp.min_inliers=300", *QUIET])
    assert res.exit_code == 0, res.output
    recipe = load_toml(SlamConfig, first / "config.toml")
    assert recipe.tracker == tracker and recipe.icp.min_inliers == 300
    assert recipe.dataset == DatasetOptions(start=1, end=11, stride=2)
    text = (first / "config.toml").read_text()
    assert "intrinsics" not in text  # None: left out
    # the user settings, the package version and the one expert constant changed: a short recipe
    keys = [ln for ln in text.splitlines() if "=" in ln]
    assert len(keys) <= 80 and keys[0] == f'version = "{package_version()}"' and "min_inliers = 300" in keys
    assert "max_condition_number" not in text  # an expert constant at its default is left out

    res = cli.invoke(app, ["run", str(seq), "-o", str(again), "--config", str(first / "config.toml"), *QUIET])
    assert res.exit_code == 0, res.output
    assert (again / "trajectory.txt").read_bytes() == (first / "trajectory.txt").read_bytes()
    assert (again / "config.toml").read_bytes() == (first / "config.toml").read_bytes()
    m = json.loads((again / "metrics.json").read_text())
    assert m["tracker"] == tracker and m["frames_processed"] == 5


def test_flags_override_set_which_overrides_the_file(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text('tracker = "orb"\n[dataset]\nend = 6\nstride = 2\ndepth_scale = 1000.0\n[icp]\nmin_inliers = 100\n'
                    '[fusion]\ndist_diff_m = 0.01\n')
    cfg = resolve_run_config(str(path), ["icp.min_inliers=200", "dataset.end=8"], None, DatasetOptionsArgs())
    assert (cfg.tracker, cfg.icp.min_inliers, cfg.fusion.dist_diff_m) == ("orb", 200, 0.01)
    assert cfg.dataset == DatasetOptions(depth_scale=1000.0, end=8, stride=2)
    cfg = resolve_run_config(str(path), ["dataset.end=8"], "hybrid",
                             DatasetOptionsArgs(end=4, intrinsics="100,100,80,60", downsample=2))
    assert cfg.tracker == "hybrid"
    assert cfg.dataset == DatasetOptions(intrinsics=(100.0, 100.0, 80.0, 60.0), depth_scale=1000.0, end=4, stride=2,
                                         downsample=2)
    # nothing given: the defaults, the same in every command
    assert resolve_run_config(None, None, None, DatasetOptionsArgs()) == SlamConfig()
    assert DatasetOptionsArgs().resolve() == DatasetOptions() and DatasetOptions().downsample == 1


def test_config_errors_name_the_file_or_the_option(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text('tracker = "kiss"\n')
    with pytest.raises(ConfigError, match=rf"^{path}: config: tracker must be one of dense, orb, hybrid, got 'kiss'$"):
        load_config(path)
    with pytest.raises(ConfigError, match=r"^--tracker must be one of dense, orb, hybrid, got 'kiss'$"):
        resolve_run_config(None, None, "kiss", DatasetOptionsArgs())
    path.write_text("[dataset]\nstride = 0\n")
    with pytest.raises(ConfigError, match="stride must be >= 1, got 0"):
        load_config(path)


# ------------------------------------------------------------------------------------------------ --set
@pytest.mark.parametrize("item, expected", [
    ("icp.min_inliers=300", {"icp": {"min_inliers": 300}}),
    ("tracking.photometric=off", {"tracking": {"photometric": "off"}}),  # a bare string
    ('tracking.photometric="on"', {"tracking": {"photometric": "on"}}),
    ("icp.photometric_weight=0.5", {"icp": {"photometric_weight": 0.5}}),
    ("io.prepare_in_reader=false", {"io": {"prepare_in_reader": False}}),
    ("dataset.intrinsics=[100, 100, 80, 60]", {"dataset": {"intrinsics": [100, 100, 80, 60]}}),
    ("tracker=orb", {"tracker": "orb"}),
    (" hybrid.loop_icp.sigma_m = 0.004", {"hybrid": {"loop_icp": {"sigma_m": 0.004}}}),
])
def test_set_values_are_toml_values_or_bare_strings(item, expected):
    assert parse_set(item) == expected


@pytest.mark.parametrize("item, message", [
    ("icp.min_inliers", "--set 'icp.min_inliers': expected KEY=VALUE, e.g. --set icp.min_inliers=300"),
    ("=3", "--set '=3': expected KEY=VALUE"),
    ("icp..levels=3", "--set 'icp..levels=3': expected KEY=VALUE"),
    ("icp.min_inlier=3", "--set icp.min_inlier=3: unknown setting icp.min_inlier (did you mean icp.min_inliers, "),
    ("icp.zzz=1", "--set icp.zzz=1: unknown setting icp.zzz ([icp] has levels, iterations, "),
    ("bogus.key=1", "--set bogus.key=1: unknown setting bogus.key (the top level has tracker, dataset, io, "),
    ("icp=3", "--set icp=3: icp is a table, not a setting (set its keys, e.g. icp.levels=...)"),
    ("icp.levels.x=1", "--set icp.levels.x=1: unknown setting icp.levels.x (icp.levels is a setting, not a table)"),
])
def test_set_errors_name_the_full_key(item, message):
    with pytest.raises(ConfigError) as err:
        parse_set(item)
    assert str(err.value).startswith(message), str(err.value)


def test_set_type_and_range_errors_name_the_item():
    with pytest.raises(ConfigError, match=r"^--set icp.min_inliers=abc: .*icp.*min_inliers must be an integer"):
        apply_sets(SlamConfig(), ["tracking.photometric=off", "icp.min_inliers=abc"])
    with pytest.raises(ConfigError, match=r"^--set tracker=kiss: config: tracker must be one of"):
        apply_sets(SlamConfig(), ["tracker=kiss"])


def test_sets_apply_together_and_the_last_wins():
    base = SlamConfig()
    fewer = base.icp.levels - 1
    # a rule relating two settings (enough pyramid levels for ICP) holds only with both overrides applied, so the
    # overrides are applied together
    with pytest.raises(ConfigError, match=rf"^--set preprocess.pyramid_levels={fewer}: .*must be >= \[icp\] levels"):
        apply_sets(base, [f"preprocess.pyramid_levels={fewer}"])
    cfg = apply_sets(base, [f"preprocess.pyramid_levels={fewer}", f"icp.levels={fewer}", "icp.min_inliers=5",
                            "icp.min_inliers=7"])
    assert (cfg.preprocess.pyramid_levels, cfg.icp.levels, cfg.icp.min_inliers) == (fewer, fewer, 7)
    assert cfg.fusion == base.fusion


def test_set_on_the_command_line_is_one_line(seq, tmp_path):
    res = cli.invoke(app, ["run", str(seq), "-o", str(tmp_path / "o"), "--set", "icp.min_inlier=3"])
    assert one_error_line(res).startswith("error: --set icp.min_inlier=3: unknown setting icp.min_inlier")
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------------------------------------ presets
def test_config_presets_by_name(tmp_path, monkeypatch):
    presets = tmp_path / "configs"
    presets.mkdir()
    (presets / "fast.toml").write_text("[icp]\nmin_inliers = 111\n")
    monkeypatch.setattr(preset_module, "presets_dir", lambda: presets)
    assert resolve_config_path("fast") == presets / "fast.toml"
    assert load_config("fast", ["fusion.dist_diff_m=0.02"]).icp.min_inliers == 111
    with pytest.raises(ConfigError, match=r"^--config slow: no such file, and not a preset \(presets: fast\)$"):
        load_config("slow")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "fast").write_text("[icp]\nmin_inliers = 222\n")  # a file of that name comes first
    assert load_config("fast").icp.min_inliers == 222
    monkeypatch.setattr(preset_module, "presets_dir", lambda: tmp_path / "none")
    with pytest.raises(ConfigError, match=r"not a preset \(no presets installed\)"):
        load_config("accurate")
    with pytest.raises(ConfigError, match="missing.toml: config file not found"):
        load_config("missing.toml")


def test_presets_are_package_data():
    """The presets are found with importlib.resources inside the package (so a wheel has them), not in the
    repository's tree."""
    folder = preset_module.presets_dir()
    assert folder.is_dir() and folder.name == "presets"
    assert preset_module.preset_names() == ["accurate", "fast", "hybrid-full"]
    for name in preset_module.preset_names():  # whatever presets exist load cleanly
        assert isinstance(load_config(name), SlamConfig)
    assert load_config("fast").tracker == "dense" and load_config("accurate").tracking.max_width_px == 0


# ------------------------------------------------------------------------------------------------ flags
DATASET_FLAGS = ("--intrinsics", "--depth-scale", "--start", "--end", "--stride", "--downsample")


def _options(command: str) -> dict[str, tuple]:
    group = typer.main.get_command(get_app())
    cmd = group.get_command(group.make_context("surfelslam", [command]), command)
    return {p.opts[0]: (tuple(p.opts), p.help, p.default) for p in cmd.params if p.opts[0] in DATASET_FLAGS}


def test_dataset_options_are_one_definition():
    run, experiments = _options("run"), _options("experiments")
    assert sorted(run) == sorted(DATASET_FLAGS)
    assert run == experiments  # same names, help and defaults (experiments used --downsample 2)
    assert run["--downsample"][2] is None and "Default 1." in run["--downsample"][1]
    for command in ("info", "register", "calibrate-colour", "batch"):  # the same names, help and defaults
        assert _options(command) == run, command


def test_eval_takes_figures_no_figures_like_run(seq, tmp_path):
    est = tmp_path / "est.txt"
    shutil.copy(seq / "groundtruth.txt", est)
    for flag in ("--no-figures", "--no-plots"):  # --no-plots: the old name, still accepted (hidden)
        out = tmp_path / flag.strip("-")
        res = cli.invoke(app, ["eval", str(est), str(seq), "--out", str(out), flag])
        assert res.exit_code == 0, res.output
        assert sorted(p.name for p in out.iterdir()) == ["eval.json"]
    helps = cli.invoke(app, ["eval", "--help"]).stdout
    assert "--figures" in helps and "--no-figures" in helps and "--no-plots" not in helps
