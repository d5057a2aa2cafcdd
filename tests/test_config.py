import dataclasses
import math
import typing
from dataclasses import dataclass, field, replace
from pathlib import Path

import pytest

from surfelslam.config import (
    Config,
    dumps_toml,
    from_dict,
    iter_tables,
    load_toml,
    validate,
)
from surfelslam.config_reference import reference_markdown
from surfelslam.errors import ConfigError


@dataclass
class Inner:
    dist_thresh_m: float = 0.07
    levels: tuple[int, ...] = (4, 2, 1)


@dataclass
class Outer:
    name: str = "x"
    enabled: bool = True
    inner: Inner = field(default_factory=Inner)
    end: int | None = None


def test_toml_roundtrip(tmp_path):
    cfg = Outer(name='a "q"', inner=Inner(0.05, (2, 1)))
    path = tmp_path / "c.toml"
    path.write_text(dumps_toml(cfg))
    assert load_toml(Outer, path) == cfg


def test_partial_and_strict():
    assert from_dict(Outer, {"inner": {"dist_thresh_m": 1}}).inner.dist_thresh_m == 1.0
    with pytest.raises(ConfigError, match="unknown key.*bogus"):
        from_dict(Outer, {"inner": {"bogus": 1}})
    with pytest.raises(ConfigError, match="must be a number"):
        from_dict(Outer, {"inner": {"dist_thresh_m": "far"}})


@dataclass
class WithFactory:
    coarse: Inner = field(default_factory=lambda: Inner(0.2, (8, 4)))


def test_a_partial_nested_table_keeps_its_parents_defaults():
    """Missing keys of a nested table take the value the parent's ``default_factory`` gives, not the nested
    class's own defaults (``[orb.loop_icp] enabled = false`` once reset the orb tracker's feature weight)."""
    got = from_dict(WithFactory, {"coarse": {"dist_thresh_m": 0.3}}).coarse
    assert got == Inner(0.3, (8, 4))
    from surfelslam.slam import SlamConfig

    cfg = from_dict(SlamConfig, {"orb": {"loop_icp": {"enabled": False}}, "hybrid": {"loop_icp": {
        "sigma_m": 0.004}}})
    assert not cfg.orb.loop_icp.enabled
    assert cfg.orb.loop_icp == type(cfg.orb.loop_icp)(**{**SlamConfig().orb.loop_icp.__dict__, "enabled": False})
    assert cfg.orb.loop_icp.feature_weight == SlamConfig().orb.loop_icp.feature_weight != Inner.dist_thresh_m
    edge = cfg.hybrid.loop_icp
    assert edge.sigma_m == 0.004 and (edge.pnp_refinement, edge.weak_direction_ratio) == (False, 100.0)  # the hybrid's


def test_bad_toml_names_file(tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text("a = = 1")
    with pytest.raises(ConfigError, match="broken.toml"):
        load_toml(Outer, p)


# ------------------------------------------------------------------------------------- the real configuration
BAD_VALUES = [  # (TOML text, the full path and setting the one-line error must name)
    ("[icp]\nphotometric_weight = inf\n", "[icp] photometric_weight must be finite"),
    ("[preprocess]\nbilateral_radius_px = 100000\n", "[preprocess] bilateral_radius_px must be"),
    ("[icp]\nmin_inliers = -5\n", "[icp] min_inliers must be"),
    ("[io]\nprefetch_frames = -1\n", "[io] prefetch_frames must be"),
    ("[hybrid.loop_icp]\nsigma_m = -1\n", "[hybrid.loop_icp] sigma_m must be > 0, got -1"),
    ("[orb.loop_icp]\nsigma_m = -1\n", "[orb.loop_icp] sigma_m must be > 0, got -1"),
    ("[icp]\niterations = [10, 0, 10, 4]\n", "[icp] iterations[1] must be"),
    ("[icp]\ndist_thresh_m = [0.1, 0.2]\n", "[icp] dist_thresh_m needs one value per level"),
    ("[fusion]\ndist_diff_m = nan\n", "[fusion] dist_diff_m must be finite"),
    ("[fusion]\nweight_mode = \"linear\"\n", "[fusion] weight_mode must be one of keller, constant"),
    ("[render]\nmin_depth_m = 5.0\nmax_depth_m = 1.0\n", "[render] min_depth_m (5) must be < max_depth_m (1)"),
    ("[preprocess]\npyramid_levels = 2\n", "[preprocess] pyramid_levels (2) must be >= [icp] levels (4)"),
    ("[sparse.features]\nmin_inliers = -5\n", "[sparse.features] min_inliers must be"),
    ("[sparse.loop.retrieval]\nratio = 2.0\n", "[sparse.loop.retrieval] ratio must be <= 1, got 2"),
    ("[tracking.shape_guess]\nbins = 1\n", "[tracking.shape_guess] bins must be"),
    ("[tracking]\nphotometric = \"yes\"\n", "[tracking] photometric must be one of auto, on, off, got 'yes'"),
    ("[hybrid]\njoint_weight = -inf\n", "[hybrid] joint_weight must be finite"),
    ("[icp]\nphotometric_weight = \"x\"\n", "[icp] photometric_weight must be a number, got 'x'"),
    ("[icp]\niterations = [1, 2.5]\n", "[icp] iterations must be an integer"),
]


@pytest.mark.parametrize(("text", "message"), BAD_VALUES)
def test_a_bad_value_is_one_line_naming_its_full_toml_path(tmp_path, text, message):
    from surfelslam.slam import SlamConfig

    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_toml(SlamConfig, path)
    msg = str(info.value)
    assert message in msg and msg.startswith(f"{path}: config: ") and "\n" not in msg


def test_configs_built_in_python_are_checked_too():
    from surfelslam.backend.dense_edges import DenseEdgeConfig
    from surfelslam.tracking.icp import ICPConfig
    from surfelslam.tracking.preprocess import PreprocessConfig

    with pytest.raises(ConfigError, match=r"\[ICPConfig\] photometric_weight must be finite"):
        ICPConfig(photometric_weight=math.inf)
    with pytest.raises(ConfigError, match="min_inliers"):
        ICPConfig(min_inliers=-5)
    with pytest.raises(ConfigError, match="bilateral_radius_px"):
        PreprocessConfig(bilateral_radius_px=100000)
    with pytest.raises(ConfigError, match="sigma_m"):
        replace(DenseEdgeConfig(), sigma_m=-1.0)
    with pytest.raises(ConfigError, match="iterations must be a list"):
        ICPConfig(iterations=5)  # type: ignore[arg-type]
    assert ICPConfig(iterations=[1, 2, 3, 4]).iterations == (1, 2, 3, 4)  # lists become tuples
    cfg = from_dict(ICPConfig, {"levels": 2, "iterations": [3, 3]}, "hybrid.loop_icp.icp")
    assert cfg.levels == 2 and cfg.iterations == (3, 3)
    with pytest.raises(ConfigError, match=r"\[hybrid.loop_icp.icp\] levels"):
        from_dict(ICPConfig, {"levels": 0}, "hybrid.loop_icp.icp")
    with pytest.raises(ConfigError, match=r"\[icp\] max_rotation_deg must be > 0, got 0"):
        from_dict(ICPConfig, {"max_rotation_deg": 0}, "icp")


def test_every_config_is_frozen_and_round_trips_through_toml(tmp_path):
    from surfelslam.slam import SlamConfig

    cfg = SlamConfig()
    validate(cfg)
    for path, sub in iter_tables(cfg):
        assert type(sub).__dataclass_params__.frozen, path or "SlamConfig"  # type: ignore[attr-defined]
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.icp.levels = 3  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.hybrid.loop_icp.sigma_m = 3  # type: ignore[misc]
    path = tmp_path / "config.toml"
    path.write_text(dumps_toml(cfg))
    assert load_toml(SlamConfig, path) == cfg


def test_every_setting_has_a_meaning_and_every_number_a_bound():
    """Each field of a :class:`Config` is declared with :func:`setting`: a doc line, and numbers with bounds."""
    from surfelslam.slam import SlamConfig

    for path, sub in iter_tables(SlamConfig()):
        if not isinstance(sub, Config):
            continue
        hints = typing.get_type_hints(type(sub))
        for f in dataclasses.fields(sub):
            meta = f.metadata.get("surfelslam")
            where = f"[{path}] {f.name}"
            assert meta is not None and meta.doc, where
            assert "\n" not in meta.doc and len(meta.doc) < 300, where
            tp = hints[f.name]
            args = typing.get_args(tp)
            if float in (tp, *args) or int in (tp, *args):
                assert meta.choices or (meta.ge, meta.gt) != (None, None), where
                assert meta.choices or meta.allow_inf or (meta.le, meta.lt) != (None, None), where


def test_config_docstrings_are_short():
    from surfelslam.slam import SlamConfig

    for path, sub in iter_tables(SlamConfig()):
        if isinstance(sub, Config):
            assert len((type(sub).__doc__ or "").strip().splitlines()) <= 3, path


def test_reference_page_covers_every_setting_and_is_current():
    """The user settings first (``[table] key`` rows), then a section per table with its expert constants."""
    from surfelslam.settings import is_user_setting
    from surfelslam.slam import SlamConfig
    from surfelslam.tools.gen_docs import reference_text

    text = reference_markdown(SlamConfig)
    user_part, _, expert_part = text.partition("\n## Expert constants")
    assert "\n## User settings\n" in user_part and expert_part
    sections = {}
    for block in expert_part.split("\n### ")[1:]:
        head, _, body = block.partition("\n")
        sections[head] = body
    n_user = 0
    for path, sub in iter_tables(SlamConfig()):
        head = f"`[{path}]`" if path else "SlamConfig (the file's top level)"
        assert head in sections, head
        for f in dataclasses.fields(sub):
            if dataclasses.is_dataclass(getattr(sub, f.name)):
                continue
            if is_user_setting(f):
                n_user += 1
                assert (f"| `[{path}] {f.name}` |" if path else f"| `{f.name}` |") in user_part, f"{head} {f.name}"
            else:
                assert f"| `{f.name}` |" in sections[head], f"{head} {f.name}"
    assert 30 <= n_user <= 80
    committed = Path(__file__).resolve().parents[1] / "docs" / "config_reference.md"
    assert committed.read_text() == reference_text(), "docs/config_reference.md is stale: run `make docs`"


@pytest.mark.parametrize("name", ["fast", "accurate", "hybrid-full"])
def test_presets_load(name):
    from surfelslam.settings import presets_dir
    from surfelslam.slam import SlamConfig

    path = presets_dir() / f"{name}.toml"
    lines = path.read_text(encoding="utf-8").splitlines()
    assert lines[0].startswith("#") and lines[1].startswith("#")
    cfg = load_toml(SlamConfig, path)
    assert cfg != SlamConfig()
    if name == "accurate":
        assert cfg.tracking.max_width_px == 0 and cfg.fusion.max_width_px == 0
    elif name == "hybrid-full":
        assert cfg.tracker == "hybrid" and cfg.hybrid.pnp_check and cfg.hybrid.joint_features == "auto"
        assert cfg.hybrid.loop_icp.pnp_refinement and cfg.sparse.keyframe_threshold == 0.1
        # the back end's own keyframe spacing and loop candidates, not the hybrid's profile (3-frame gap, 3 + 1)
        assert cfg.sparse.keyframe_min_gap_frames == 1
        assert (cfg.sparse.loop.n_nearby, cfg.sparse.loop.n_random) == (5, 5)
    else:
        assert cfg.tracker == "dense" and cfg.tracking.photometric == "off"


def test_every_config_class_is_a_frozen_config():
    """Every ``*Config`` dataclass of the library derives from :class:`Config` (checked on construction) and is
    frozen (settings change by ``dataclasses.replace``)."""
    import importlib
    import pkgutil

    found = []
    for sub in ("backend", "geometry", "mapping", "slam", "synth", "tracking"):
        pkg = importlib.import_module(f"surfelslam.{sub}")
        for info in pkgutil.walk_packages(pkg.__path__, f"surfelslam.{sub}."):
            module = importlib.import_module(info.name)
            for name, obj in vars(module).items():
                if (name.endswith("Config") and isinstance(obj, type) and dataclasses.is_dataclass(obj)
                        and obj.__module__ == module.__name__):
                    found.append(obj)
                    assert issubclass(obj, Config) and obj.__dataclass_params__.frozen, obj  # type: ignore[attr-defined]
    assert len(found) >= 27
