from dataclasses import dataclass, field

import pytest

from surfelslam.config import dumps_toml, from_dict, load_toml
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

    cfg = from_dict(SlamConfig, {"orb": {"loop_icp": {"enabled": False}}, "hybrid": {"loop_icp": {"icp": {
        "robust_scale_m": 0.03}}}})
    assert not cfg.orb.loop_icp.enabled
    assert cfg.orb.loop_icp == type(cfg.orb.loop_icp)(**{**SlamConfig().orb.loop_icp.__dict__, "enabled": False})
    assert cfg.orb.loop_icp.feature_weight == SlamConfig().orb.loop_icp.feature_weight != Inner.dist_thresh_m
    icp = cfg.hybrid.loop_icp.icp
    assert icp.robust_scale_m == 0.03 and (icp.levels, icp.weak_direction_ratio) == (3, 0.0)  # the edge ICP's own


def test_bad_toml_names_file(tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text("a = = 1")
    with pytest.raises(ConfigError, match="broken.toml"):
        load_toml(Outer, p)
