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


def test_bad_toml_names_file(tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text("a = = 1")
    with pytest.raises(ConfigError, match="broken.toml"):
        load_toml(Outer, p)
