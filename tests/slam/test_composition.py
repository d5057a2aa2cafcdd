"""The trackers are composed, not subclassed: no class reaches into another object's private members, no tracker
inherits from another, and every tracker has what the run loop calls (the :class:`Tracker` protocol)."""

from __future__ import annotations

import ast
import inspect
from pathlib import Path

import numpy as np
import pytest

import surfelslam
from surfelslam.errors import ConfigError
from surfelslam.slam import SlamConfig, build_slam, registered
from surfelslam.slam.protocol import Tracker
from surfelslam.types import Intrinsics, RGBDFrame

PACKAGE = Path(surfelslam.__file__).parent
INTR = Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)


def private_accesses(source: str) -> list[str]:
    """``obj._name`` accesses in ``source`` whose object is not ``self`` or ``cls`` (dunders are not private)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Attribute) or not node.attr.startswith("_") or node.attr.startswith("__"):
            continue
        if isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"):
            continue
        found.append(f"{node.lineno}: {ast.unparse(node)}")
    return found


def test_the_private_access_check_finds_what_it_should():
    src = "a._x\nself._y\ncls._z\nself.front._w\nb.__class__\nf()._v\n"
    assert private_accesses(src) == ["1: a._x", "4: self.front._w", "6: f()._v"]


@pytest.mark.parametrize("package", ["slam", "tracking"])
def test_no_private_member_of_another_object_is_touched(package):
    offenders = {str(p.relative_to(PACKAGE)): hits for p in sorted((PACKAGE / package).rglob("*.py"))
                 if (hits := private_accesses(p.read_text(encoding="utf-8")))}
    assert offenders == {}


def test_no_tracker_inherits_from_another():
    classes = registered()
    assert set(classes) == {"dense", "orb", "hybrid", "given"}
    for name, cls in classes.items():
        assert cls.__bases__ == (object,), name
        assert cls.name == name


def test_every_tracker_has_what_the_run_loop_calls():
    """The protocol's methods with the protocol's parameter names (the run loop passes them by keyword)."""
    wanted = {n: list(inspect.signature(getattr(Tracker, n)).parameters)
              for n in ("warmup", "use_prior_map", "prepare", "discard", "process", "finish")}
    assert wanted["process"] == ["self", "frame", "prepared", "T_world_cam"]
    for name, cls in registered().items():
        for method, params in wanted.items():
            assert list(inspect.signature(getattr(cls, method)).parameters) == params, (name, method)
        assert isinstance(build_slam(INTR, SlamConfig(), name), Tracker)


def _frame() -> RGBDFrame:
    return RGBDFrame(0, 0.0, np.zeros((48, 64, 3), np.uint8), np.full((48, 64), 1.5, np.float32))


@pytest.mark.parametrize("tracker", ["dense", "hybrid", "orb"])
def test_a_tracker_refuses_a_given_pose(tracker):
    with pytest.raises(ValueError, match="computes its own poses"):
        build_slam(INTR, SlamConfig(), tracker).process(_frame(), T_world_cam=np.eye(4))


def test_the_given_mapper_needs_a_pose_and_fuses_at_it():
    mapper = build_slam(INTR, SlamConfig(), "given")
    with pytest.raises(ValueError, match="needs each frame's pose"):
        mapper.process(_frame())
    T = np.eye(4)
    T[0, 3] = 0.25
    res = mapper.process(_frame(), T_world_cam=T)
    assert res.tracked and res.fused and np.array_equal(res.T_world_cam, T)
    assert res.map_points == mapper.map.n_alive > 0


def test_orb_refuses_a_saved_map():
    with pytest.raises(ConfigError, match="--tracker orb"):
        build_slam(INTR, SlamConfig(), "orb").use_prior_map(None)
